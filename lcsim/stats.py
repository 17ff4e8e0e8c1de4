"""Statistics of highway traffic, from tracks: the simulator's (:func:`traffic_statistics`, what
``tools/traffic_stats.py`` prints and docs/simulator.md tabulates) and recorded ones (``lc-calibrate``) measured
by the same code, so that the two compare.

Definitions (:func:`traffic_samples` collects the samples, :func:`summarise` reduces them):

- Samples every :data:`SAMPLE_PERIOD_S` (consecutive steps are strongly correlated) of every vehicle present:
  speed, acceleration, and the **time gap** to the leader (the nearest vehicle ahead in the same lane index,
  bumper to bumper, over the follower's speed) where that gap is under :data:`FOLLOW_GAP_M` and the follower
  drives faster than 2 m/s.
- A **lane change** is a step at which a vehicle's lane index moves to a neighbouring lane. Its **duration** is
  measured on the lateral position: the time between the last moment before the switch at which the vehicle had
  covered 10% of the way between the two lane centres and the first moment after it at which it had covered 90%
  (linear between steps), divided by the share of a minimum-jerk move's time those 80% take (:data:`CORE_SHARE`,
  0.504): the simulator's own profile, so that its lane changes measure their configured durations. A change cut
  off by the track's start or end has no duration. The **rate** is the lane changes that start (cross 10%; where
  that is not seen, switch lanes) after the warm-up per vehicle-km driven after it.
- The **lateral offset** is the distance from the lane centre of every sample outside a lane change (the
  measured duration and :data:`LANE_CHANGE_MARGIN_S` either side).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lcsim.config import ScenarioConfig
from lcsim.sim import HighwaySim

WARMUP_S = 5.0
"""Seconds left out at the start of every simulated episode (the spawn's even spacing settles)."""
SAMPLE_PERIOD_S = 0.5
"""Speeds, accelerations, time gaps and lateral offsets are sampled this often."""
FOLLOW_GAP_M = 60.0
"""A vehicle follows a leader closer than this (bumper to bumper); its time gap counts."""
FREE_GAP_M = 100.0
"""A vehicle drives freely when nothing is ahead of it in its lane within this distance, and at least this much road
is seen ahead of it (recorded traffic ends where the recording does)."""
MIN_FOLLOW_SPEED_MPS = 2.0
LANE_CHANGE_MARGIN_S = 0.5
"""Time either side of a measured lane change whose samples are not lane keeping (the lateral offset)."""


def _min_jerk(tau: np.ndarray | float) -> np.ndarray | float:
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def _core_share(lo: float = 0.1, hi: float = 0.9) -> float:
    tau = np.linspace(0.0, 1.0, 200_001)
    prof = _min_jerk(tau)
    return float(tau[np.searchsorted(prof, hi)] - tau[np.searchsorted(prof, lo)])


CORE_SHARE = _core_share()
"""Share of a minimum-jerk lane change's time spent between 10% and 90% of the lateral move (0.504)."""

COMPARED = (
    "speed_mean_kmh", "speed_sd_kmh", "accel_sd_mps2", "accel_p05_mps2", "accel_p95_mps2", "time_gap_p15_s",
    "time_gap_median_s", "time_gap_p85_s", "time_gap_under_1s", "lateral_offset_sd_m",
    "lane_changes_per_vehicle_km", "lane_change_duration_mean_s", "lane_change_duration_sd_s",
)  # fmt: skip
"""The statistics that describe the traffic's behaviour (the rest are counts and extremes)."""


@dataclass(frozen=True, slots=True)
class TrackArrays:
    """One episode's traffic as dense arrays over ``T`` steps of ``dt_s`` and ``V`` vehicles, along +x.

    ``x``, ``y``, ``speed``, ``accel``: ``(T, V)`` metres, m/s, m/s^2 (any value where absent); ``lane``: ``(T, V)``
    lane index (0 the rightmost, -1 unknown); ``present``: ``(T, V)``; ``length``: ``(V,)`` metres;
    ``lane_centres``: ``(L,)`` y of each lane's centre.
    """

    dt_s: float
    x: np.ndarray
    y: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    lane: np.ndarray
    present: np.ndarray
    length: np.ndarray
    lane_centres: np.ndarray


@dataclass(frozen=True, slots=True)
class TrafficSamples:
    """What :func:`summarise` reduces, each sample with the index of its vehicle (over all episodes, so that a
    bootstrap can resample vehicles): ``speed`` (m/s), ``accel``, ``time_gap`` (s), ``offset`` (m), ``duration``
    (s, one per measured lane change), ``free_speed`` (m/s, samples of vehicles driving freely) and the ``*_vehicle``
    index arrays beside them; per vehicle, ``changes`` and ``distance_m`` (after the warm-up)."""

    speed: np.ndarray
    speed_vehicle: np.ndarray
    accel: np.ndarray
    time_gap: np.ndarray
    time_gap_vehicle: np.ndarray
    offset: np.ndarray
    offset_vehicle: np.ndarray
    duration: np.ndarray
    duration_vehicle: np.ndarray
    free_speed: np.ndarray
    free_speed_vehicle: np.ndarray
    changes: np.ndarray
    distance_m: np.ndarray

    @property
    def vehicles(self) -> int:
        return len(self.changes)


def _lane_changes(track: TrackArrays, first: int) -> tuple[np.ndarray, list[tuple[int, float]], np.ndarray]:
    """Per vehicle, the lane changes that start (cross 10%; where that is not seen, switch lanes) at steps >= ``first``;
    the durations ``(vehicle, seconds)`` of those measured; the ``(T, V)`` mask of samples inside any lane change (with
    its margin; a change cut off by the track's start or end: the vehicle's whole stretch of presence)."""
    lane, present, y, c = track.lane, track.present, track.y, track.lane_centres
    valid = present & (lane >= 0)
    switch = valid[1:] & valid[:-1] & (lane[1:] != lane[:-1])  # (T-1, V): at step t+1
    jumps = np.where(switch, np.abs(lane[1:] - lane[:-1]), 0)
    changes = np.zeros(lane.shape[1], dtype=np.int64)
    inside = np.zeros(lane.shape, dtype=bool)
    durations: list[tuple[int, float]] = []
    margin = LANE_CHANGE_MARGIN_S / track.dt_s
    steps = np.arange(len(lane))[:, None]
    starts = np.maximum.accumulate(np.where(valid, 0, steps + 1), axis=0)  # first step of each stretch of presence
    stops = np.minimum.accumulate(np.where(valid, len(lane), steps)[::-1], axis=0)[::-1]  # ... and past its last
    for t, v in zip(*np.nonzero(switch), strict=True):
        lo, hi = starts[t, v], stops[t + 1, v]  # the vehicle's presence around the switch: [lo, hi)
        a, b = lane[t, v], lane[t + 1, v]
        if jumps[t, v] != 1 or max(a, b) >= len(c):
            inside[lo:hi, v] = True
            changes[v] += jumps[t, v] if t + 1 >= first else 0
            continue
        frac = (y[lo:hi, v] - c[a]) / (c[b] - c[a])
        k = t - lo  # frac[k] is the last step in the old lane
        after = np.flatnonzero(frac[k + 1 :] >= 0.9)
        j = k + 1 + after[0] if after.size else 0
        while j > 0 and frac[j - 1] >= 0.9:
            j -= 1
        before = np.flatnonzero(frac[:j] <= 0.1)
        if j == 0 or before.size == 0:
            inside[lo:hi, v] = True  # cut off by the track's start or end
            changes[v] += t + 1 >= first
            continue
        i = before[-1]  # the crossings: between steps i, i + 1 and j - 1, j (linear in between)
        start = i + (0.1 - frac[i]) / (frac[i + 1] - frac[i])
        end = j - (frac[j] - 0.9) / (frac[j] - frac[j - 1])
        seconds = (end - start) * track.dt_s / CORE_SHARE
        if lo + start >= first:
            changes[v] += 1
            durations.append((int(v), seconds))
        mid, half = lo + 0.5 * (start + end), 0.5 * seconds / track.dt_s + margin
        inside[max(int(np.floor(mid - half)), lo) : min(int(np.ceil(mid + half)) + 1, hi), v] = True
    _mark_excursions(track, inside)
    return changes, durations, inside


def _mark_excursions(track: TrackArrays, inside: np.ndarray) -> None:
    """Mark in ``inside`` every lateral excursion that no lane switch explains (a change under way where the track
    starts or ends, or one given up): a run of samples more than 10% of a lane width from their lane's centre that
    reaches 25% somewhere or touches the start or end of the vehicle's presence."""
    c = track.lane_centres
    if len(c) < 2:
        return
    width = float(np.median(np.diff(c)))
    valid = track.present & (track.lane >= 0) & (track.lane < len(c))
    off = np.where(valid, np.abs(track.y - c[np.clip(track.lane, 0, len(c) - 1)]) / width, 0.0)
    padded = np.pad(track.present, ((1, 1), (0, 0)))
    edge = track.present & ~(padded[:-2] & padded[2:])  # first or last step of a stretch of presence
    flag = ((off > 0.25) | (edge & (off > 0.1))) & ~inside
    for v in np.flatnonzero(flag.any(axis=0)):
        out = off[:, v] > 0.1
        run = np.cumsum(np.diff(np.concatenate(([False], out))) > 0) * out  # the runs of `out`, numbered from 1
        hit = np.unique(run[flag[:, v]])
        inside[:, v] |= np.isin(run, hit[hit > 0])


def traffic_samples(tracks: Sequence[TrackArrays], *, warmup_s: float = 0.0) -> TrafficSamples:
    """The samples of :func:`summarise` from the episodes ``tracks`` (steps before ``warmup_s`` left out)."""
    parts: dict[str, list[np.ndarray]] = {f.name: [] for f in dataclasses.fields(TrafficSamples)}
    offset_v = 0
    for track in tracks:
        t_steps, n = track.present.shape
        first = round(warmup_s / track.dt_s)
        every = max(1, round(SAMPLE_PERIOD_S / track.dt_s))
        changes, durations, inside = _lane_changes(track, first)
        # distance: the telescoped x of each vehicle's steps after the warm-up (present steps, consecutive pairs)
        both = track.present[first + 1 :] & track.present[first:-1]
        dx = np.where(both, track.x[first + 1 :] - track.x[first:-1], 0.0)
        parts["changes"].append(changes)
        parts["distance_m"].append(dx.sum(axis=0))
        parts["duration"].append(np.array([d for _, d in durations]))
        parts["duration_vehicle"].append(np.array([v for v, _ in durations], dtype=np.int64) + offset_v)
        rows = np.arange(first, t_steps, every)
        present = track.present[rows]
        r, v = np.nonzero(present)
        sel = (rows[r], v)
        speed, x, lane = track.speed[sel], track.x[sel], track.lane[sel]
        parts["speed"].append(speed)
        parts["speed_vehicle"].append(v + offset_v)
        parts["accel"].append(track.accel[sel])
        # leaders: sort the samples by (row, lane, x); the next one in the same row and lane is ahead
        order = np.lexsort((x, lane, r))
        rs, ls, xs = r[order], lane[order], x[order]
        same = (rs[1:] == rs[:-1]) & (ls[1:] == ls[:-1]) & (ls[1:] >= 0)
        half = 0.5 * track.length[v[order]]
        gap = np.full(len(order), np.inf)
        gap[:-1] = np.where(same, xs[1:] - xs[:-1] - half[1:] - half[:-1], np.inf)
        sp = speed[order]
        follow = (gap < FOLLOW_GAP_M) & (sp > MIN_FOLLOW_SPEED_MPS)
        parts["time_gap"].append(gap[follow] / sp[follow])
        parts["time_gap_vehicle"].append(v[order][follow] + offset_v)
        # free driving: no leader within FREE_GAP_M, that much road seen ahead, not in a lane change
        front = np.full(len(rows), -np.inf)
        np.maximum.at(front, r, x)
        changing = inside[sel][order]
        free = (gap > FREE_GAP_M) & (front[rs] - xs >= FREE_GAP_M) & ~changing & (ls >= 0)
        parts["free_speed"].append(sp[free])
        parts["free_speed_vehicle"].append(v[order][free] + offset_v)
        keep = (lane >= 0) & (lane < len(track.lane_centres)) & ~inside[sel]
        centre = track.lane_centres[np.clip(lane, 0, len(track.lane_centres) - 1)]
        parts["offset"].append((track.y[sel] - centre)[keep])
        parts["offset_vehicle"].append(v[keep] + offset_v)
        offset_v += n
    out = {}
    for name, arrays in parts.items():
        integer = name.endswith("_vehicle") or name == "changes"
        out[name] = np.concatenate(arrays).astype(np.int64 if integer else np.float64) if arrays else \
            np.zeros(0, dtype=np.int64 if integer else np.float64)  # fmt: skip
    return TrafficSamples(**out)


def _mean_sd(values: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    total = w.sum()
    if total <= 0:
        return float("nan"), float("nan")
    mean = float((values * w).sum() / total)
    return mean, float(np.sqrt(max(((values - mean) ** 2 * w).sum() / total, 0.0)))


def _quantiles(values: np.ndarray, w: np.ndarray, qs: Sequence[float]) -> list[float]:
    """Weighted quantiles (the inverted empirical distribution, as ``np.percentile``'s ``inverted_cdf``)."""
    keep = w > 0
    values, w = values[keep], w[keep]
    if not len(values):
        return [float("nan")] * len(qs)
    order = np.argsort(values, kind="stable")
    values, cum = values[order], np.cumsum(w[order])
    return [float(values[min(np.searchsorted(cum, q * cum[-1]), len(values) - 1)]) for q in qs]


def summarise(samples: TrafficSamples, vehicle_weights: np.ndarray | None = None) -> dict[str, float]:
    """The statistics of ``samples`` (``vehicle_weights`` ``(vehicles,)``: each vehicle's weight, as a bootstrap
    draws them; None: 1 each)."""
    vw = np.ones(samples.vehicles) if vehicle_weights is None else np.asarray(vehicle_weights, dtype=np.float64)
    s = samples
    speed_mean, speed_sd = _mean_sd(s.speed * 3.6, vw[s.speed_vehicle])
    wa = vw[s.speed_vehicle]
    _, accel_sd = _mean_sd(s.accel, wa)
    p05, p95 = _quantiles(s.accel, wa, (0.05, 0.95))
    wg = vw[s.time_gap_vehicle]
    p15, median, p85 = _quantiles(s.time_gap, wg, (0.15, 0.5, 0.85))
    under = float((wg * (s.time_gap < 1.0)).sum() / wg.sum()) if wg.sum() > 0 else float("nan")
    wo = vw[s.offset_vehicle]
    _, offset_sd = _mean_sd(s.offset, wo)
    offset_max = float(np.abs(s.offset[wo > 0]).max()) if (wo > 0).any() else float("nan")
    wd = vw[s.duration_vehicle]
    dur_mean, dur_sd = _mean_sd(s.duration, wd)
    changes, km = float((vw * s.changes).sum()), float((vw * s.distance_m).sum()) / 1000.0
    free_mean, free_sd = _mean_sd(s.free_speed * 3.6, vw[s.free_speed_vehicle])
    return {
        "speed_mean_kmh": speed_mean, "speed_sd_kmh": speed_sd,
        "accel_sd_mps2": accel_sd, "accel_p05_mps2": p05, "accel_p95_mps2": p95,
        "time_gap_p15_s": p15, "time_gap_median_s": median, "time_gap_p85_s": p85, "time_gap_under_1s": under,
        "lateral_offset_sd_m": offset_sd, "lateral_offset_max_m": offset_max,
        "lane_changes_per_vehicle_km": changes / km if km > 0 else float("nan"),
        "lane_change_duration_mean_s": dur_mean, "lane_change_duration_sd_s": dur_sd,
        "free_speed_mean_kmh": free_mean, "free_speed_sd_kmh": free_sd,
        "lane_changes": changes, "lane_change_durations": float(wd.sum()), "vehicle_km": km,
    }  # fmt: skip


MAX_BOOTSTRAP_DRAWS = 10_000
"""The most draws :func:`sampling_intervals` makes: the Monte Carlo error of a 95% interval's ends is long
negligible by then, and each draw summarises every sample once."""
TRACK_BYTES_PER_CELL = 41
"""What :func:`simulate_tracks` holds per step, environment and vehicle: four float64 arrays, one int64, a flag."""
MAX_TRACK_BYTES = 4 << 30
"""The most memory the tracks of one :func:`simulate_tracks` call may take (4 GiB)."""


def track_bytes(episodes: int, seconds: float, dt_s: float, vehicles: int) -> int:
    """The memory :func:`simulate_tracks` takes for ``episodes`` environments of ``vehicles`` vehicles (the ego
    included) over ``seconds`` of ``dt_s`` steps."""
    return (round(seconds / dt_s) + 1) * episodes * vehicles * TRACK_BYTES_PER_CELL


def check_track_bytes(episodes: int, seconds: float, dt_s: float, vehicles: int) -> None:
    """``ValueError`` (one line, with the figures) when those tracks would take more than :data:`MAX_TRACK_BYTES`."""
    need = track_bytes(episodes, seconds, dt_s, vehicles)
    if need > MAX_TRACK_BYTES:
        raise ValueError(f"{episodes} episodes x {seconds:g} s of {vehicles} vehicles at {dt_s:g} s steps would hold "
                         f"{need / 2**30:.1f} GiB of tracks, more than {MAX_TRACK_BYTES / 2**30:g} GiB; simulate fewer "
                         "episodes or seconds")  # fmt: skip


def sampling_intervals(samples: TrafficSamples, reps: int = 200, seed: int = 0,
                       level: float = 0.95) -> dict[str, tuple[float, float]]:  # fmt: skip
    """Percentile-bootstrap intervals of every statistic, resampling vehicles (a vehicle's samples are correlated,
    vehicles nearly independent), from a generator seeded with ``seed``; ``reps`` draws, 1 to
    :data:`MAX_BOOTSTRAP_DRAWS` (``ValueError`` otherwise)."""
    if not (isinstance(reps, int) and 1 <= reps <= MAX_BOOTSTRAP_DRAWS):
        raise ValueError(f"the bootstrap takes 1 to {MAX_BOOTSTRAP_DRAWS} draws, got {reps!r}")
    gen = np.random.default_rng(seed)
    n = samples.vehicles
    fields = {f.name: getattr(samples, f.name) for f in dataclasses.fields(TrafficSamples)}
    for name, vehicle in (("accel", "speed_vehicle"), ("time_gap", "time_gap_vehicle")):  # sorted once: each draw's
        order = np.argsort(fields[name], kind="stable")  # quantiles then sort sorted arrays
        fields[name] = fields[name][order]
        if name == "accel":  # the speed samples share their vehicle index with the accelerations
            fields["speed"] = fields["speed"][order]
        fields[vehicle] = fields[vehicle][order]
    samples = TrafficSamples(**fields)
    draws = [summarise(samples, np.bincount(gen.integers(0, n, n), minlength=n).astype(np.float64))
             for _ in range(reps)]  # fmt: skip
    lo, hi = (1.0 - level) / 2.0, (1.0 + level) / 2.0
    out = {}
    for key in draws[0]:
        values = np.array([d[key] for d in draws])
        values = values[np.isfinite(values)]
        out[key] = (float(np.quantile(values, lo)), float(np.quantile(values, hi))) if len(values) else \
            (float("nan"), float("nan"))  # fmt: skip
    return out


def simulate_tracks(config: ScenarioConfig, episodes: int, seconds: float, seed: int = 0) -> tuple[list[TrackArrays], int]:
    """Tracks of ``episodes`` environments of ``config``'s traffic (all on autopilot, the ego too) over ``seconds``
    (episode seeds ``seed * 100_000 + k``), and the number of collisions among the traffic. ``ValueError`` before
    anything is allocated when they would take more than :data:`MAX_TRACK_BYTES` (:func:`check_track_bytes`)."""
    check_track_bytes(episodes, seconds, config.dt_s, config.traffic.num_vehicles + 1)
    sim = HighwaySim(dataclasses.replace(config, render_image=False), episodes, autopilot_ego=True)
    sim.reset(np.arange(episodes), [seed * 100_000 + k for k in range(episodes)])
    steps = round(seconds / sim.dt)
    shape = (steps + 1, episodes, sim.num_vehicles)
    x, y, speed, accel = (np.empty(shape) for _ in range(4))
    lane = np.empty(shape, dtype=np.int64)
    for k in range(steps + 1):
        if k:
            sim.substep()
        x[k], y[k], speed[k], accel[k], lane[k] = sim.x, sim.y, sim.speed, sim.accel, sim.lane
    road = sim.road
    centres = np.asarray(road.lane_center(np.arange(config.road.num_lanes)), dtype=np.float64)
    length = np.full(sim.num_vehicles, config.traffic.length_m)
    length[0] = config.ego.length_m
    present = np.ones(shape[:1] + shape[2:], dtype=bool)
    tracks = [TrackArrays(sim.dt, x[:, e], y[:, e], speed[:, e], accel[:, e], lane[:, e], present, length, centres)
              for e in range(episodes)]  # fmt: skip
    return tracks, int(sim.traffic_collisions.sum())


def traffic_statistics(config: ScenarioConfig, episodes: int, seconds: float, seed: int = 0) -> dict[str, float]:
    """Run ``episodes`` environments of ``config``'s traffic (all on autopilot) for ``seconds`` and measure it
    (:func:`summarise`, the first :data:`WARMUP_S` left out), with the count of collisions among the traffic."""
    tracks, collisions = simulate_tracks(config, episodes, seconds, seed)
    return {**summarise(traffic_samples(tracks, warmup_s=WARMUP_S)), "traffic_collisions": collisions}
