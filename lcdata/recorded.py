"""Recorded traffic (corpus episodes: ``lc-import``'s, ``lc-record``'s) as :class:`lcsim.stats.TrackArrays`, the
arrays the traffic statistics are measured on, with what can be read off the road: lanes, lane width, vehicle size,
density.

The traffic must drive along +x with lane 0 the rightmost (the corpus frame: the highD importer turns both
directions so, and ``tools/sumo_highway.py``'s road runs along +x). Lane centres are not assumed: each lane's is the
median lateral position of the samples in it.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from lcsim.stats import TrackArrays

log = logging.getLogger(__name__)

MAX_CELLS = 50_000_000
"""The most step x vehicle cells one episode may densify into (a 100 s episode of 2000 steps holds 25,000 vehicles
before this)."""
MAX_LANES = 16
REQUIRED = ("step", "t", "vehicle_id", "x", "y", "speed", "accel", "lane", "length", "width")


@dataclass(frozen=True, slots=True)
class RecordedTraffic:
    """Recorded episodes and what their road shows: ``num_lanes`` (the highest lane index + 1), ``lane_width_m``
    (median distance between neighbouring lane centres), ``length_m`` and ``width_m`` (median vehicle),
    ``density_per_lane_km`` (vehicles present per lane and km of the road seen, averaged over steps), ``seconds``
    of traffic."""

    tracks: list[TrackArrays]
    num_lanes: int
    lane_width_m: float
    length_m: float
    width_m: float
    density_per_lane_km: float
    seconds: float


def _lane_centres(y: np.ndarray, lane: np.ndarray, episode: str) -> np.ndarray:
    lanes = int(lane.max()) + 1
    if lanes > MAX_LANES:
        raise ValueError(f"episode {episode}: lane index {lanes - 1} is more than a road has ({MAX_LANES} lanes)")
    centres = np.full(lanes, np.nan)
    for k in range(lanes):
        sel = lane == k
        if sel.any():
            centres[k] = np.median(y[sel])
    known = np.flatnonzero(np.isfinite(centres))
    if len(known) >= 2:  # a lane nobody drove in lies between (or beyond) the others, evenly
        centres = np.interp(np.arange(lanes), known, centres[known], left=np.nan, right=np.nan)
        fit = np.polyfit(known, centres[known], 1)
        centres = np.where(np.isfinite(centres), centres, np.polyval(fit, np.arange(lanes)))
    else:
        centres[np.isnan(centres)] = centres[known[0]] + 3.5 * (np.flatnonzero(np.isnan(centres)) - known[0])
    if lanes > 1 and not (np.diff(centres) > 0).all():
        raise ValueError(f"episode {episode}: the lane centres are not ordered right to left ({np.round(centres, 2)} "
                         "m); the corpus frame has lane 0 the rightmost, y to the left")
    return centres


def track_arrays(tracks: pd.DataFrame, episode: str = "") -> tuple[TrackArrays, np.ndarray]:
    """One episode's long-form tracks (``Episode.tracks``) as dense arrays, and each vehicle's width ``(V,)``.

    ``ValueError`` naming the episode for a missing column, no rows, duplicate rows, non-finite values, more cells
    than :data:`MAX_CELLS`, or traffic that does not drive along +x.
    """
    missing = [c for c in REQUIRED if c not in tracks]
    if missing:
        raise ValueError(f"episode {episode}: the tracks have no column {missing[0]!r}")
    if not len(tracks):
        raise ValueError(f"episode {episode}: no vehicles")
    step = tracks["step"].to_numpy(np.int64)
    first = int(step.min())
    ids, vi = np.unique(tracks["vehicle_id"].to_numpy(np.int64), return_inverse=True)
    t_steps, n = int(step.max()) - first + 1, len(ids)
    if t_steps * n > MAX_CELLS:
        raise ValueError(f"episode {episode}: {t_steps} steps x {n} vehicles is more than {MAX_CELLS} cells")
    ti = step - first
    if np.any(np.bincount(ti * n + vi, minlength=t_steps * n) > 1):
        raise ValueError(f"episode {episode}: duplicate (step, vehicle_id) rows")
    values = {c: tracks[c].to_numpy(np.float64) for c in ("t", "x", "y", "speed", "accel", "length", "width")}
    for c, v in values.items():
        if not np.isfinite(v).all():
            raise ValueError(f"episode {episode}: non-finite {c}")
    times = np.unique(values["t"])
    dt = float(np.median(np.diff(times))) if len(times) > 1 else 0.0
    if not dt > 0:
        raise ValueError(f"episode {episode}: fewer than two time steps")
    lane = tracks["lane"].to_numpy(np.int64)
    if not (lane >= 0).any():
        raise ValueError(f"episode {episode}: no lane index known")
    centres = _lane_centres(values["y"][lane >= 0], lane[lane >= 0], episode)
    dense = {}
    for c in ("x", "y", "speed", "accel"):
        a = np.zeros((t_steps, n))
        a[ti, vi] = values[c]
        dense[c] = a
    lanes = np.full((t_steps, n), -1, dtype=np.int64)
    lanes[ti, vi] = lane
    present = np.zeros((t_steps, n), dtype=bool)
    present[ti, vi] = True
    both = present[1:] & present[:-1]
    if both.any() and np.median((dense["x"][1:] - dense["x"][:-1])[both]) <= 0:
        raise ValueError(f"episode {episode}: the traffic does not drive along +x (the corpus frame); import it "
                         "with lc-import, which turns highD's directions so, or record a road along +x")
    length, width = np.zeros(n), np.zeros(n)
    length[vi], width[vi] = values["length"], values["width"]
    return TrackArrays(dt, dense["x"], dense["y"], dense["speed"], dense["accel"], lanes, present, length,
                       centres), width  # fmt: skip


def recorded_traffic(source: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
                     progress: Callable[[int, int], None] | None = None) -> RecordedTraffic:  # fmt: skip
    """The episodes of a folder (every ``*.mcap`` below it) or a list of files, read (:func:`lcdata.read_episode`)
    and measured. ``ValueError`` (``FileNotFoundError`` for a missing folder) in one line naming the problem."""
    from lcdata.reader import list_episodes, read_episode

    paths = list_episodes(source) if isinstance(source, str | os.PathLike) and os.path.isdir(source) else \
        [source] if isinstance(source, str | os.PathLike) else list(source)  # fmt: skip
    if not paths:
        raise ValueError(f"no .mcap episode files found in {source}")
    tracks, widths, densities, lanes, lane_widths = [], [], [], [], []
    seconds = 0.0
    for i, path in enumerate(paths):
        episode = read_episode(path)
        arrays, width = track_arrays(episode.tracks, str(path))
        tracks.append(arrays)
        widths.append(width)
        counts = arrays.present.sum(axis=1)
        xs = arrays.x[arrays.present]
        extent_km = (xs.max() - xs.min()) / 1000.0
        lanes.append(len(arrays.lane_centres))
        if len(arrays.lane_centres) > 1:
            lane_widths.append(float(np.median(np.diff(arrays.lane_centres))))
        if extent_km > 0:
            densities.append((counts.mean() / (len(arrays.lane_centres) * extent_km), len(counts)))
        seconds += len(counts) * arrays.dt_s
        if progress is not None:
            progress(i + 1, len(paths))
    if not lane_widths:
        raise ValueError(f"{source}: every episode has one lane; lane changes need two")
    weights = np.array([w for _, w in densities], dtype=np.float64)
    density = float(np.average([d for d, _ in densities], weights=weights)) if densities else 0.0
    log.info("read %d episodes, %.0f s of traffic", len(tracks), seconds)
    return RecordedTraffic(tracks, max(lanes), float(np.median(lane_widths)),
                           float(np.median(np.concatenate([t.length for t in tracks]))),
                           float(np.median(np.concatenate(widths))), density, seconds)  # fmt: skip
