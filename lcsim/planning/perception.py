"""What a planner imagines futures in: a copy of the simulator, its random draws redrawn, reduced to what
the ego's sensors show.

:func:`imagined_copy` copies a :class:`~lcsim.core.LaneChangeCore` without hooks or renderer;
:func:`redraw_future` gives a copy other random draws from now on (the planner then knows the traffic's
rules and present state, not its coming random lane changes); :func:`perceive` reduces a copy to the
traffic within sensing range, each vehicle's unseen desired speed read from its motion
(:func:`estimated_desired_speeds`).
"""

from __future__ import annotations

import copy

import numpy as np

from lcsim.core import LaneChangeCore
from lcsim.sim import HighwaySim
from lcsim.traffic import DriverParams, driver_fields, idm_accel


def imagined_copy(core: LaneChangeCore) -> LaneChangeCore:
    """A copy of ``core`` to imagine a future in: it shares no state with ``core`` and has no hooks (a
    recorder must not see the imagined future) and no renderer."""
    return copy.deepcopy(core, {id(core.sim.hooks): [], id(core.sim.log_hooks): [], id(core.renderer): None})


def redraw_future(sim: HighwaySim, salt: int | np.ndarray) -> None:
    """Give every environment's traffic other random draws from now on (``salt`` >= 1 picks which; one per
    environment when an array).

    The traffic's spontaneous lane changes are drawn from a counter-based stream keyed by the episode
    seed, so a copy of the simulator foresees them exactly. A planner that imagines futures in a copy
    it has redrawn knows the traffic's rules and present state but not its coming random choices: what
    an onboard predictor could know.
    """
    if np.any(np.asarray(salt) < 1):
        raise ValueError(f"salt must be >= 1 (0 would keep the episode's own draws), got {salt}")
    sim.rekey(salt)


def perceive(sim: HighwaySim, range_m: float, *, draw_drivers: bool = False,
             known_drivers: tuple[str, ...] = ()) -> None:
    """Reduce every environment to what its ego's sensors tell about the traffic (for an imagined copy).

    Traffic vehicles farther than ``range_m`` from the ego (centre to centre) are moved 100 km behind
    it, spaced apart, where they take no part in anything near the ego. Each vehicle left keeps its
    position, speed, acceleration and any lane change under way (all observable), but its desired
    speed, which no sensor shows, becomes what its motion tells (:func:`estimated_desired_speeds`,
    after the parking, so from the leaders the ego can see); with human-like traffic, its own car-following
    parameters, reaction time and lane-change habits become the median driver's. A planner that imagines futures in a copy
    so reduced, and redrawn (:func:`redraw_future`), knows the traffic's rules but nothing a sensor of
    that range would not show it.

    With ``draw_drivers`` (human-like traffic), each unseen driver's parameters are instead drawn from the
    traffic's distribution, from a generator seeded by the copy's random keys (so each redrawn future of
    :func:`redraw_future` imagines other plausible drivers, and the same state gives the same draws): a
    planner that imagines several futures then weighs the drivers it cannot tell apart, not only the median.

    ``known_drivers`` (names of :class:`~lcsim.traffic.DriverParams` fields) keeps those parameters of every
    driver at their true values: a privileged diagnostic, the ceiling of a planner that would estimate them.
    """
    if not range_m > 0:
        raise ValueError(f"range_m must be > 0, got {range_m!r}")
    far = np.hypot(sim.x - sim.x[:, :1], sim.y - sim.y[:, :1]) > range_m
    original_durations = sim.drivers.lc_inv_duration.copy()
    traffic = sim.is_traffic.copy()
    traffic[:, 0] = False  # the ego knows itself, autopilot or not
    far &= traffic
    sim.x = np.where(far, sim.x[:, :1] - 1.0e5 - 50.0 * sim.ids[None, :], sim.x)  # parked, spaced apart
    sim.rebuild_index()
    true = {name: getattr(sim.drivers, name).copy() for name in driver_fields(known_drivers, "known_drivers")}
    if sim.human:  # each driver's own parameters show in no sensor: the copy's drivers are the median ones
        # (or plausible ones drawn), but a lane change under way keeps its pace (its progress shows)
        if draw_drivers:
            _draw_drivers(sim, traffic)
        else:
            sim.drivers.set_nominal(traffic, sim.config.traffic, sim.dt)
        sim.drivers.lc_inv_duration[...] = np.where(sim.lc_active, original_durations, sim.drivers.lc_inv_duration)
        for name, values in true.items():
            getattr(sim.drivers, name)[...] = values
    sim.v0 = np.where(traffic, estimated_desired_speeds(sim), sim.v0)


def _draw_drivers(sim: HighwaySim, mask: np.ndarray) -> None:
    """Draw the drivers where ``mask`` is set from the traffic's distribution, seeded by the copy's keys."""
    keys = np.concatenate([np.asarray(sim.key, dtype=np.uint64), np.asarray(sim.step, dtype=np.uint64)])
    gen = np.random.default_rng(keys.view(np.uint32))  # the copy's keys (salted per future) and its time
    drawn = DriverParams.nominal(sim.config.traffic, mask.shape, sim.dt)
    for e in range(mask.shape[0]):
        drawn.draw(e, gen, sim.config.traffic, sim.dt, mask.shape[1])
    sim.drivers.set_where(mask, drawn)


def estimated_desired_speeds(sim: HighwaySim) -> np.ndarray:
    """``(E, N)`` each vehicle's desired speed (m/s) as its observed motion tells it under the traffic's car
    following model: the one at which the Intelligent Driver Model gives the acceleration each vehicle had
    in the last step, with the leader it has now in the neighbour index (so only a leader the index holds
    counts). Where that motion does not tell (the acceleration was clipped, or no desired speed fits),
    the top of the traffic's spread; always within the spread (2.5 sigma around the nominal speed).
    """
    tc = sim.config.traffic
    if sim.index is None:
        sim.rebuild_index()
    index = sim.index
    a, v = tc.idm_max_accel_mps2, sim.speed
    # IDM is a * (1 - (v / v0) ** delta - interaction); with v0 infinite only the interaction is left
    free = (idm_accel(v, np.inf, index.gap, v - index.lead_speed, tc) - sim.accel) / a  # = (v / v0) ** delta
    lo = max((tc.speed_kmh - 2.5 * tc.speed_spread_kmh) / 3.6, 1.0)
    hi = max((tc.speed_kmh + 2.5 * tc.speed_spread_kmh) / 3.6, 1.0)
    clipped = (sim.accel <= -tc.max_decel_mps2 + 1e-9) | (sim.accel >= a - 1e-9)
    v0 = np.where(free > 0.0, v / np.maximum(free, 1e-12) ** (1.0 / tc.idm_delta), np.inf)
    return np.clip(np.where(clipped, hi, v0), lo, hi)
