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
from lcsim.traffic import idm_accel


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


def perceive(sim: HighwaySim, range_m: float) -> None:
    """Reduce every environment to what its ego's sensors tell about the traffic (for an imagined copy).

    Traffic vehicles farther than ``range_m`` from the ego (centre to centre) are moved 100 km behind
    it, spaced apart, where they take no part in anything near the ego. Each vehicle left keeps its
    position, speed, acceleration and any lane change under way (all observable), but its desired
    speed, which no sensor shows, becomes what its motion tells (:func:`estimated_desired_speeds`,
    after the parking, so from the leaders the ego can see); with human-like traffic, its own car-following
    parameters, reaction time and lane-change habits become the median driver's. A planner that imagines futures in a copy
    so reduced, and redrawn (:func:`redraw_future`), knows the traffic's rules but nothing a sensor of
    that range would not show it.
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
    if sim.human:  # each driver's own parameters show in no sensor: the copy's drivers are the median ones,
        # but a lane change under way keeps its pace (its progress shows)
        sim.drivers.set_nominal(traffic, sim.config.traffic, sim.dt)
        sim.drivers.lc_inv_duration[...] = np.where(sim.lc_active, original_durations, sim.drivers.lc_inv_duration)
    sim.v0 = np.where(traffic, estimated_desired_speeds(sim), sim.v0)


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
