"""Fit the human-like traffic's parameters to recorded traffic by moment matching (``lc-calibrate``).

The recorded statistics (:func:`lcsim.stats.summarise` of the recorded tracks) are the targets; the simulator's
traffic is measured by the same code. What the tracks show directly sets the start: the road (lanes, lane width),
the vehicles' size, the density, the desired speeds (free-flow speeds), the desired time gap (the 15th percentile of
the time gaps), the acceleration noise (the acceleration's 5th to 95th percentile, as a normal distribution's sd:
robust to the hard braking of a few), the lane-change duration and its spread, the
lateral wander (the offset from the lane centre). Then a deterministic search: every iteration simulates the same
episodes (fixed seeds: common random numbers), measures them, and moves each parameter towards the statistic it
governs most, a damped Newton step of the moment equations with a diagonal Jacobian, each pair seen in coordinates
where one moves the other about one for one (:data:`COORDINATES`):

======================================  ===========================================================
parameter (coordinate)                  statistic (coordinate)
======================================  ===========================================================
``speed_kmh``                           speed, mean
``speed_spread_kmh`` (squared)          speed, sd (squared)
density (log; ``num_vehicles``)         time gap, median (minus log)
``idm_time_headway_s`` (log)            time gap, 15th percentile (log)
``driver_spread`` (log)                 time gaps under 1 s, share (log of share + 0.01)
``accel_noise_mps2`` (log)              acceleration, p5 to p95 (log; the sd, too, for "close")
``lane_change_duration_s`` (log)        lane-change duration, mean (log)
``lane_change_spread`` (log)            lane-change duration, coefficient of variation (log)
``lane_wander_m`` (log)                 lateral offset, sd (log)
lane-change propensity ``u``            lane changes per vehicle-km (log)
======================================  ===========================================================

The propensity ``u`` is one number that moves the two levers of the lane-change rate in turn: from the base's
spontaneous rate ``r0`` and blocked-leader margin ``m0``, ``random_lane_change_rate_per_min = r0 e^u`` and
``blocked_speed_margin_kmh = m0 + max(0, -u - 1) * 2 * max(speed_spread_kmh, 2)`` (fewer changes: the
spontaneous ones fade first, then a leader must be slower to count as blocking).

The iterate with the smallest cost (:func:`search_cost`: the distance, the sum over :data:`lcsim.stats.COMPARED` of
``((sim - recorded) / tolerance)^2``, plus a penalty for each statistic not well within its tolerance and one if
the traffic collided) is the result. Each step starts from
the best iterate so far and moves every parameter whose statistic is not already close (:data:`DEAD_BAND`); once
that makes things worse, the search goes on one parameter at a time (a coordinate search: passes over the
parameters whose statistics are not close, the worst first), each parameter's step halved after it made things
worse and doubled back (up to the full step) after it helped. Each parameter's slope (how far its statistic moves per unit of it)
is re-estimated from its own steps that improved the distance, so that a statistic that responds weakly gets longer
steps. The search ends after its iterations, or earlier when every statistic is close. The result is measured again
on other seeds for the report.

Vehicles are spawned at least a car-following gap apart (``min_spawn_gap_m``: the minimum gap plus the desired time
gap at the desired speed, as far as the density allows), since they start at their desired speeds. The other
parameters keep the base scenario's values.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from lcsim.config import WANDER_CLIP_SIGMAS, RoadConfig, ScenarioConfig, TrafficConfig
from lcsim.stats import COMPARED, WARMUP_S, TrafficSamples, check_track_bytes, summarise, traffic_statistics

log = logging.getLogger(__name__)

RELATIVE_TOLERANCE = 0.10
"""A simulated statistic matches a recorded one within this share of it ..."""
ABSOLUTE_TOLERANCE: dict[str, float] = {
    "speed_mean_kmh": 0.5, "speed_sd_kmh": 0.2, "accel_sd_mps2": 0.01, "accel_p05_mps2": 0.01, "accel_p95_mps2": 0.01,
    "time_gap_p15_s": 0.05, "time_gap_median_s": 0.05, "time_gap_p85_s": 0.05, "time_gap_under_1s": 0.01,
    "lateral_offset_sd_m": 0.01, "lane_changes_per_vehicle_km": 0.01, "lane_change_duration_mean_s": 0.1,
    "lane_change_duration_sd_s": 0.1,
}  # fmt: skip
"""... or within the half-width of its sampling interval, or within these (the resolution that matters: a
centimetre of offset, a tenth of a second of duration), whichever is widest."""
MAX_SPEED_KMH = 200.0
COLLISION_PENALTY = 100.0
"""Added to the search's cost of an evaluation whose traffic collided (recorded traffic does not)."""
OUTSIDE_PENALTY, SEARCH_MARGIN = 4.0, 0.8
"""Added to the search's cost for each statistic further than ``SEARCH_MARGIN`` tolerances from the recorded one."""


@dataclass(frozen=True, slots=True, kw_only=True)
class RecordedRoad:
    """What the recording shows of its road and vehicles (:class:`lcdata.recorded.RecordedTraffic` holds it)."""

    num_lanes: int
    lane_width_m: float
    length_m: float
    width_m: float
    density_per_lane_km: float


@dataclass(frozen=True, slots=True, kw_only=True)
class CalibrationOptions:
    """How hard to search (every evaluation simulates ``episodes`` x ``seconds`` with the same seeds)."""

    iterations: int = 30
    """Simulated evaluations of the search (the first is the start)."""
    episodes: int = 32
    """Environments simulated side by side per evaluation, at most :attr:`MAX_EPISODES` (and what
    :data:`lcsim.stats.MAX_TRACK_BYTES` holds: :func:`check_memory`)."""
    seconds: float | None = None
    """Simulated seconds per episode (the first :data:`lcsim.stats.WARMUP_S` left out); None: the base scenario's
    time limit, the traffic as an episode of it sees it (the traffic's statistics drift as platoons form)."""
    seed: int = 0
    """Seed of the search's episodes; the report measures the result (and the base) on ``seed + 1``."""
    report_episodes: int = 32
    damping: float = 0.8
    """Share of each step taken (1: the full fixed-point step)."""
    keep_road: bool = False
    """Keep the base scenario's road (lanes, lane width) instead of the recording's."""

    MAX_EPISODES: ClassVar[int] = 1024
    """The most environments of one evaluation (``episodes``, ``report_episodes``)."""
    MAX_ITERATIONS: ClassVar[int] = 10_000

    def __post_init__(self) -> None:
        for name, most in (("iterations", self.MAX_ITERATIONS), ("episodes", self.MAX_EPISODES),
                           ("report_episodes", self.MAX_EPISODES)):  # fmt: skip
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= most:
                raise ValueError(f"{name} must be an integer in [1, {most}], got {value!r}")
        if self.seconds is not None and not (math.isfinite(self.seconds) and self.seconds > WARMUP_S + 5.0):
            raise ValueError(f"seconds must be more than {WARMUP_S + 5.0:g} (the first {WARMUP_S:g} are left out), "
                             f"got {self.seconds!r}")  # fmt: skip
        if not 0.0 < self.damping <= 1.0:
            raise ValueError(f"damping must be in (0, 1], got {self.damping!r}")

    def seconds_for(self, base: ScenarioConfig) -> float:
        """The simulated seconds per episode with ``base`` as the base scenario."""
        return self.seconds if self.seconds is not None else max(base.time_limit_s, WARMUP_S + 10.0)


@dataclass(frozen=True, slots=True)
class Params:
    """The searched values: the traffic's fields and the two that are not fields (density factor, propensity)."""

    speed_kmh: float
    speed_spread_kmh: float
    density: float
    """Vehicles per lane-km at spawn."""
    idm_time_headway_s: float
    driver_spread: float
    accel_noise_mps2: float
    lane_change_duration_s: float
    lane_change_spread: float
    lane_wander_m: float
    propensity: float


@dataclass
class CalibrationResult:
    """The calibrated scenario, the statistics side by side (``recorded``, ``default``: the base scenario's,
    ``calibrated``; the last two on the report's seeds), each compared statistic's ``tolerance`` and the recorded
    ``intervals``, and the search's ``history`` (per iteration: the parameters and the distance)."""

    scenario: ScenarioConfig
    recorded: dict[str, float]
    default: dict[str, float]
    calibrated: dict[str, float]
    tolerance: dict[str, float]
    intervals: dict[str, tuple[float, float]]
    history: list[dict[str, float]] = field(default_factory=list)

    def distance(self, stats: dict[str, float]) -> float:
        return distance(stats, self.recorded, self.tolerance)

    def within(self, stats: dict[str, float]) -> dict[str, bool]:
        """Per compared statistic, whether ``stats`` is within its tolerance of the recorded one."""
        return {k: bool(abs(stats[k] - self.recorded[k]) <= self.tolerance[k]) for k in COMPARED}


def tolerances(recorded: dict[str, float], intervals: dict[str, tuple[float, float]]) -> dict[str, float]:
    """Per compared statistic: the widest of :data:`RELATIVE_TOLERANCE` of it, its interval's half-width and its
    :data:`ABSOLUTE_TOLERANCE`."""
    out = {}
    for k in COMPARED:
        lo, hi = intervals.get(k, (math.nan, math.nan))
        half = 0.5 * (hi - lo) if math.isfinite(hi - lo) else 0.0
        out[k] = max(RELATIVE_TOLERANCE * abs(recorded[k]), half, ABSOLUTE_TOLERANCE[k])
    return out


def distance(stats: dict[str, float], recorded: dict[str, float], tolerance: dict[str, float]) -> float:
    """Sum over the compared statistics of ``((stats - recorded) / tolerance)^2`` (a statistic the simulation could
    not measure, such as a duration without lane changes, counts 100)."""
    total = 0.0
    for k in COMPARED:
        if not math.isfinite(recorded[k]):
            continue
        z = (stats[k] - recorded[k]) / tolerance[k]
        total += z * z if math.isfinite(z) else 100.0
    return total


def search_cost(stats: dict[str, float], recorded: dict[str, float], tolerance: dict[str, float]) -> float:
    """What the search minimises: the :func:`distance`, plus :data:`OUTSIDE_PENALTY` for every statistic further
    than :data:`SEARCH_MARGIN` of its tolerance from the recorded one (the aim is every statistic within its
    tolerance, also on episodes the search did not see), plus :data:`COLLISION_PENALTY` if the traffic collided."""
    outside = sum(not abs(stats[k] - recorded[k]) <= SEARCH_MARGIN * tolerance[k] for k in COMPARED
                  if math.isfinite(recorded[k]))  # fmt: skip
    crashed = COLLISION_PENALTY if stats.get("traffic_collisions", 0) else 0.0
    return distance(stats, recorded, tolerance) + OUTSIDE_PENALTY * outside + crashed


def max_wander(base: ScenarioConfig, road: RoadConfig, width_m: float) -> float:
    """The largest lane wander the scenario accepts (the clipped wander keeps the widest car inside its lane)."""
    widest = max(width_m, base.ego.width_m)
    return max(0.0, (road.lane_width_m - 1e-3 - widest - 0.2) / (2 * WANDER_CLIP_SIGMAS))


def _spawn_window_km(tc: TrafficConfig) -> float:
    return (tc.spawn_behind_m + tc.spawn_ahead_m - 1.5 * tc.ego_clearance_m) / 1000.0


def max_vehicles(base: ScenarioConfig, road: RoadConfig, size: RecordedRoad) -> int:
    """The most traffic vehicles :func:`scenario_of` puts on ``road`` (as many as its spawn window holds)."""
    window_m = _spawn_window_km(base.traffic) * 1000.0
    per_lane_max = int(window_m / (size.length_m + base.traffic.min_spawn_gap_m))
    return per_lane_max * road.num_lanes - road.num_lanes


def scenario_of(params: Params, base: ScenarioConfig, road: RoadConfig, size: RecordedRoad) -> ScenarioConfig:
    """The base scenario with the recording's road and vehicle size and the parameters ``params``."""
    t0 = base.traffic
    spread_margin = 2.0 * max(params.speed_spread_kmh, 2.0)
    window_m = _spawn_window_km(t0) * 1000.0
    per_lane = params.density * window_m / 1000.0
    num = int(np.clip(round(per_lane * road.num_lanes) - 1, 1, max_vehicles(base, road, size)))
    # spawned vehicles start at their desired speeds: space them at least at a car-following gap, or the first
    # seconds brake hard (and collide) wherever two are spawned close
    following = t0.idm_min_gap_m + params.idm_time_headway_s * params.speed_kmh / 3.6
    fits = 0.9 * window_m / math.ceil((num + 1) / road.num_lanes) - size.length_m
    spawn_gap = float(max(t0.min_spawn_gap_m, min(following, fits)))
    traffic = dataclasses.replace(
        t0, num_vehicles=num, length_m=size.length_m, width_m=size.width_m, min_spawn_gap_m=round(spawn_gap, 3),
        speed_kmh=float(np.clip(params.speed_kmh, 5.0, MAX_SPEED_KMH)),
        speed_spread_kmh=float(np.clip(params.speed_spread_kmh, 0.0, 50.0)),
        idm_time_headway_s=float(np.clip(params.idm_time_headway_s, 0.3, 10.0)),
        driver_spread=float(np.clip(params.driver_spread, 0.0, 1.0)),
        accel_noise_mps2=float(np.clip(params.accel_noise_mps2, 0.0, 5.0)),
        lane_change_duration_s=float(np.clip(params.lane_change_duration_s, 1.0, 20.0)),
        lane_change_spread=float(np.clip(params.lane_change_spread, 0.0, 2.0)),
        lane_wander_m=float(np.clip(params.lane_wander_m, 0.0, max_wander(base, road, size.width_m))),
        random_lane_change_rate_per_min=float(min(t0.random_lane_change_rate_per_min * math.exp(params.propensity),
                                                  60.0)),
        blocked_speed_margin_kmh=float(min(t0.blocked_speed_margin_kmh + max(0.0, -params.propensity - 1.0)
                                           * spread_margin, 300.0)),
    )  # fmt: skip
    return dataclasses.replace(base, road=road, traffic=traffic)


def start(recorded: dict[str, float], base: ScenarioConfig, size: RecordedRoad) -> Params:
    """What the tracks show directly (see the module's docstring)."""
    t0 = base.traffic
    speed = recorded["free_speed_mean_kmh"] if math.isfinite(recorded["free_speed_mean_kmh"]) else \
        recorded["speed_mean_kmh"]  # fmt: skip
    spread = recorded["free_speed_sd_kmh"] if math.isfinite(recorded["free_speed_sd_kmh"]) else \
        recorded["speed_sd_kmh"]  # fmt: skip
    mean, sd = recorded["lane_change_duration_mean_s"], recorded["lane_change_duration_sd_s"]
    duration = mean if math.isfinite(mean) and mean > 0 else t0.lane_change_duration_s
    lc_spread = math.sqrt(math.log1p((sd / mean) ** 2)) if math.isfinite(sd) and mean > 0 else t0.lane_change_spread
    gap = recorded["time_gap_p15_s"]
    return Params(
        speed_kmh=speed, speed_spread_kmh=spread, density=max(size.density_per_lane_km, 1.0),
        idm_time_headway_s=gap if math.isfinite(gap) else t0.idm_time_headway_s, driver_spread=t0.driver_spread,
        accel_noise_mps2=(recorded["accel_p95_mps2"] - recorded["accel_p05_mps2"]) / (2 * 1.6449),
        lane_change_duration_s=duration,
        lane_change_spread=max(lc_spread, 1e-3), lane_wander_m=max(recorded["lateral_offset_sd_m"], 1e-4),
        propensity=0.0,
    )  # fmt: skip


def _log(v: float) -> float:
    return math.log(max(v, 1e-9)) if math.isfinite(v) else math.nan


def _cv(stats: dict[str, float]) -> float:
    return max(stats["lane_change_duration_sd_s"], 1e-3) / stats["lane_change_duration_mean_s"]


@dataclass(frozen=True, slots=True)
class Coordinate:
    """How one parameter is searched: the statistics it governs, the parameter and those statistics seen in
    coordinates where one moves the other about one for one (``x`` of the parameter, ``y`` of the statistics), and
    the longest step in ``x``."""

    def off(self, stats: dict[str, float], rec: dict[str, float], tolerance: dict[str, float]) -> float:
        """How far ``stats`` are from the recorded ones, in tolerances (the worst of this parameter's statistics)."""
        return max(abs(stats[k] - rec[k]) / tolerance[k] for k in self.stats)

    stats: tuple[str, ...]
    x: Callable[[float], float]
    from_x: Callable[[float], float]
    y: Callable[[dict[str, float]], float]
    max_step: float


_LOG3 = math.log(3.0)
COORDINATES: dict[str, Coordinate] = {
    "speed_kmh": Coordinate(("speed_mean_kmh",), float, float, lambda s: s["speed_mean_kmh"], 20.0),
    "speed_spread_kmh": Coordinate(("speed_sd_kmh",), lambda v: v * v, lambda x: math.sqrt(max(x, 0.0)),
                                   lambda s: s["speed_sd_kmh"] ** 2, 400.0),
    "density": Coordinate(("time_gap_median_s",), _log, math.exp, lambda s: -_log(s["time_gap_median_s"]), _LOG3),
    "idm_time_headway_s": Coordinate(("time_gap_p15_s",), _log, math.exp, lambda s: _log(s["time_gap_p15_s"]), _LOG3),
    "driver_spread": Coordinate(("time_gap_under_1s",), _log, math.exp,
                                lambda s: _log(s["time_gap_under_1s"] + 0.01), _LOG3),
    "accel_noise_mps2": Coordinate(("accel_p05_mps2", "accel_p95_mps2", "accel_sd_mps2"), _log, math.exp,
                                   lambda s: _log(s["accel_p95_mps2"] - s["accel_p05_mps2"]), _LOG3),
    "lane_change_duration_s": Coordinate(("lane_change_duration_mean_s",), _log, math.exp,
                                         lambda s: _log(s["lane_change_duration_mean_s"]), _LOG3),
    "lane_change_spread": Coordinate(("lane_change_duration_sd_s",), _log, math.exp, lambda s: _log(_cv(s)), _LOG3),
    "lane_wander_m": Coordinate(("lateral_offset_sd_m",), _log, math.exp, lambda s: _log(s["lateral_offset_sd_m"]), _LOG3),
    "propensity": Coordinate(("lane_changes_per_vehicle_km",), float, float,
                             lambda s: _log(s["lane_changes_per_vehicle_km"]), 1.0),
}  # fmt: skip
"""Each parameter, the statistic it moves towards (the table of the module's docstring), and their coordinates."""
DEAD_BAND = 0.3
"""A parameter whose statistic is within this share of its tolerance stays where it is (the others' steps are then
not undone by noise)."""
SLOPE_RANGE = (0.1, 10.0)


def step(p: Params, sim: dict[str, float], rec: dict[str, float], tolerance: dict[str, float], damping: float,
         slopes: dict[str, float] | None = None, only: str | None = None) -> Params:  # fmt: skip
    """One damped Newton step of every parameter (or ``only`` one) towards its statistic in their
    :data:`COORDINATES`, ``damping`` times ``(y_recorded - y_simulated) / slope`` long (``slopes``: dy/dx, 1 each
    unless given), except those whose statistic is within the :data:`DEAD_BAND` or not measured."""
    out = {}
    for name, c in COORDINATES.items():
        value = getattr(p, name)
        gap = c.y(rec) - c.y(sim)
        if only not in (None, name) or c.off(sim, rec, tolerance) <= DEAD_BAND or \
                not math.isfinite(gap):  # fmt: skip
            out[name] = value
            continue
        dx = float(np.clip(damping * gap / (slopes or {}).get(name, 1.0), -c.max_step, c.max_step))
        out[name] = c.from_x(c.x(value) + dx)
    return Params(**out)


def update_slopes(slopes: dict[str, float], before: tuple[Params, dict[str, float]],
                  after: tuple[Params, dict[str, float]]) -> dict[str, float]:  # fmt: skip
    """Each parameter's slope dy/dx after a step that improved the distance: the geometric mean of the old one and
    the secant of the step (where the parameter moved and its statistic moved the same way), within
    :data:`SLOPE_RANGE`. A statistic that responds weakly to its parameter gets longer steps."""
    out = dict(slopes)
    for name, c in COORDINATES.items():
        dx = c.x(getattr(after[0], name)) - c.x(getattr(before[0], name))
        dy = c.y(after[1]) - c.y(before[1])
        if abs(dx) > 1e-3 and math.isfinite(dy) and dy / dx > 0:
            out[name] = float(np.clip(math.sqrt(out[name] * dy / dx), *SLOPE_RANGE))
    return out


def check_memory(options: CalibrationOptions, base: ScenarioConfig, size: RecordedRoad) -> RoadConfig:
    """The road the search simulates; ``ValueError`` when it cannot be built, or when an evaluation's tracks (the
    most vehicles the road may get, ``episodes`` or ``report_episodes`` environments, ``seconds``) would take more
    than :data:`lcsim.stats.MAX_TRACK_BYTES`: checked before anything is simulated."""
    if options.keep_road:
        road = base.road
    else:
        if not 2 <= size.num_lanes <= 6:
            raise ValueError(f"the recording has {size.num_lanes} lanes; the simulator builds 2 to 6 (keep the base "
                             "scenario's road instead)")  # fmt: skip
        road = dataclasses.replace(base.road, num_lanes=size.num_lanes, lane_width_m=round(size.lane_width_m, 3))
    vehicles = max(max_vehicles(base, road, size), base.traffic.num_vehicles, 1) + 1
    check_track_bytes(max(options.episodes, options.report_episodes), options.seconds_for(base), base.dt_s, vehicles)
    return road


def calibrate(recorded: TrafficSamples | dict[str, float], intervals: dict[str, tuple[float, float]],
              size: RecordedRoad, base: ScenarioConfig, options: CalibrationOptions | None = None,
              progress: Callable[[int, int, float, dict[str, float]], None] | None = None) -> CalibrationResult:  # fmt: skip
    """Fit ``base``'s traffic to the recorded statistics (``recorded``: the samples or their summary, ``intervals``:
    their sampling intervals, :func:`lcsim.stats.sampling_intervals`).

    ``progress(iteration, iterations, cost, stats)`` after each evaluation (:func:`search_cost`). ``ValueError`` when the recording has
    no time gaps, no speeds or no lane changes with a duration to match, or a road the simulator cannot build.
    """
    options = options or CalibrationOptions()
    seconds = options.seconds_for(base)
    rec = summarise(recorded) if isinstance(recorded, TrafficSamples) else dict(recorded)
    for key, what in (("speed_mean_kmh", "speeds"), ("time_gap_median_s", "vehicles following one another")):
        if not math.isfinite(rec[key]):
            raise ValueError(f"the recording has no {what} to match")
    if not math.isfinite(rec["lane_change_duration_mean_s"]):
        raise ValueError("the recording has no complete lane change whose duration could be measured")
    road = check_memory(options, base, size)
    tol = tolerances(rec, intervals)
    params = start(rec, base, size)
    best: tuple[float, Params, dict[str, float]] | None = None
    slopes = dict.fromkeys(COORDINATES, 1.0)
    scale = dict.fromkeys(COORDINATES, 1.0)  # each parameter's step alone, as a share of the damped Newton step
    alone = False  # True once a step of every parameter together made things worse: from then on one at a time
    pending: list[str] = []  # this pass's parameters still to try alone, the one with the worst statistic first
    tried: str | None = None  # the parameter the last evaluation stepped alone
    history: list[dict[str, float]] = []

    def worst_first(stats: dict[str, float]) -> list[str]:
        z = {n: c.off(stats, rec, tol) for n, c in COORDINATES.items()}
        return sorted((n for n in COORDINATES if z[n] > DEAD_BAND), key=lambda n: -z[n])

    for it in range(options.iterations):
        config = scenario_of(params, base, road, size)
        sim = traffic_statistics(config, options.episodes, seconds, options.seed)
        d = search_cost(sim, rec, tol)
        history.append({**dataclasses.asdict(params), "num_vehicles": config.traffic.num_vehicles,
                        "distance": distance(sim, rec, tol), "cost": d})
        log.debug("iteration %d: distance %.3g, %s", it + 1, d, params)
        if progress is not None:
            progress(it + 1, options.iterations, d, sim)
        if best is None or d < best[0]:
            if best is not None and tried is not None:  # (a step of one parameter: its statistic's move is its own)
                slopes = update_slopes(slopes, best[1:], (params, sim))
                scale[tried] = min(1.0, 2.0 * scale[tried])
            best = (d, params, sim)
        elif tried is not None:
            scale[tried] *= 0.5
        else:
            alone = True
        if not alone:
            params, tried = step(best[1], best[2], rec, tol, options.damping, slopes), None
            if params == best[1]:
                break  # every statistic within the dead band: nothing left to move
            continue
        if not pending:
            pending = worst_first(best[2])
            if not pending:
                break
        tried = pending.pop(0)
        params = step(best[1], best[2], rec, tol, options.damping * scale[tried], slopes, only=tried)
    assert best is not None
    scenario = scenario_of(best[1], base, road, size)
    report_seed = options.seed + 1
    default = traffic_statistics(base, options.report_episodes, seconds, report_seed)
    calibrated = traffic_statistics(scenario, options.report_episodes, seconds, report_seed)
    return CalibrationResult(scenario, rec, default, calibrated, tol, intervals, history)
