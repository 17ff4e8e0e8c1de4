"""Trajectory corpus: history/future windows cut on the fly from recorded episodes.

A *window* is one agent (any vehicle, the ego included) at one observed step ``t0``: its ``H`` history
positions ``t0-H+1 .. t0``, its ``F`` future positions ``t0+1 .. t0+F`` and the ``H``-step histories
of the ``K`` vehicles nearest to it at ``t0``. Every array of a window is expressed in one
agent-centric frame fixed at ``t0``: the origin is the agent's position at ``t0`` and the x axis its
heading, estimated from positions only by a backward difference (:func:`heading_from_positions`).
The policy-time predictor API uses exactly the same functions, so training and deployment share one
code path.

Guarantees:

- a window never mixes episodes (windows are cut inside one episode's dense arrays);
- the history part only holds data from steps ``<= t0`` (the frame, the velocities and the
  neighbour selection use nothing later), the future part only steps ``> t0``;
- splits are made by episode (:func:`split_episodes`), never by window.

Nothing is cached on disk: the dense per-episode arrays are rebuilt from the tracks whenever a
:class:`Corpus` is built, so a change of source data or of :class:`WindowOptions` can never be served
stale windows.

Units: metres, steps of the recording (20 Hz for the default corpus).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pandas as pd

__all__ = [
    "Corpus",
    "EpisodeArrays",
    "Split",
    "WindowBatch",
    "WindowOptions",
    "from_frame",
    "heading_from_positions",
    "load_tracks",
    "split_episodes",
    "to_frame",
]

logger = logging.getLogger(__name__)

#: Columns of the long-form tracks DataFrame this module needs (see docs/INTERFACES.md).
REQUIRED_COLUMNS: tuple[str, ...] = ("episode", "step", "vehicle_id", "x", "y")
#: Displacement below which a backward difference is too short to define a heading, metres.
MIN_HEADING_DISPLACEMENT_M = 1e-3


@dataclass(frozen=True, slots=True, kw_only=True)
class WindowOptions:
    """How windows are cut from episodes."""

    history_steps: int = 10
    """H: observed steps, the last one (``t0``) included."""
    future_steps: int = 10
    """F: predicted steps after ``t0``."""
    num_neighbours: int = 8
    """K: nearest other vehicles at ``t0`` given as context."""
    stride: int = 1
    """Steps between consecutive ``t0`` of one agent."""
    include_ego: bool = True
    """Whether the ego (vehicle 0) is also used as an agent (it is always a possible neighbour)."""

    def __post_init__(self) -> None:
        for name in ("history_steps", "future_steps", "num_neighbours", "stride"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"{name} must be an int, got {value!r}")
        if self.history_steps < 2:
            raise ValueError(
                f"history_steps must be >= 2 (velocity needs two points), got {self.history_steps}"
            )
        if self.future_steps < 1:
            raise ValueError(f"future_steps must be >= 1, got {self.future_steps}")
        if self.num_neighbours < 0:
            raise ValueError(f"num_neighbours must be >= 0, got {self.num_neighbours}")
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {self.stride}")

    def to_dict(self) -> dict[str, int | bool]:
        return dataclasses.asdict(self)


# --------------------------------------------------------------------------------------------------
# Frames (shared with the policy-time predictor API)
# --------------------------------------------------------------------------------------------------


def heading_from_positions(
    positions: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    min_displacement_m: float = MIN_HEADING_DISPLACEMENT_M,
) -> np.ndarray:
    """Heading at the last step of a history, from positions only (backward difference).

    The heading is the direction from the most recent earlier valid position that lies at least
    ``min_displacement_m`` away to the last position; with none (a standing vehicle, a single
    point, a missing last step) it is 0, i.e. the input frame's x axis.

    Args:
        positions: ``(..., H, 2)``.
        mask: ``(..., H)`` bool, True where the position is valid; None means all valid.

    Returns:
        ``(...,)`` float64 heading in radians, in the input frame.
    """
    positions = np.asarray(positions, dtype=np.float64)
    h = positions.shape[-2]
    if mask is None:
        mask = np.ones(positions.shape[:-1], dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    last = positions[..., -1:, :]
    disp = last - positions[..., :-1, :]  # (..., H-1, 2): p[H-1] - p[j]
    norm = np.hypot(disp[..., 0], disp[..., 1])
    valid = mask[..., :-1] & mask[..., -1:] & (norm >= min_displacement_m)  # (..., H-1)
    # Most recent valid j: argmax over the reversed axis finds the first True from the end.
    rev = valid[..., ::-1]
    j = (h - 2) - np.argmax(rev, axis=-1)
    any_valid = rev.any(axis=-1)
    chosen = np.take_along_axis(disp, j[..., None, None].repeat(2, axis=-1), axis=-2)[..., 0, :]
    heading = np.arctan2(chosen[..., 1], chosen[..., 0])
    return np.where(any_valid, heading, 0.0)


def to_frame(points: np.ndarray, origin: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Express points in the frame with the given origin and heading.

    Args:
        points: ``(..., P, 2)`` in the parent frame.
        origin: ``(..., 2)`` frame origin in the parent frame.
        heading: ``(...,)`` frame x-axis angle in the parent frame, radians.

    Returns:
        ``(..., P, 2)`` in the new frame.
    """
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    d = points - origin[..., None, :]
    return np.stack((c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]), axis=-1)


def from_frame(points: np.ndarray, origin: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_frame`: ``(..., P, 2)`` frame points back to the parent frame."""
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    x, y = points[..., 0], points[..., 1]
    return np.stack((c * x - s * y, s * x + c * y), axis=-1) + origin[..., None, :]


def load_tracks(source: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]) -> list[pd.DataFrame]:
    """Tracks of recorded episodes: a directory (every ``*.mcap`` below it) or a list of files.

    Returns:
        One long-form tracks DataFrame per episode file, ready for :meth:`Corpus.from_tracks`.

    Raises:
        ValueError: no episode files found.
    """
    from lcdata.reader import list_episodes, read_episode  # local: keeps this module light

    if isinstance(source, str | os.PathLike):
        paths = list_episodes(source) if os.path.isdir(source) else [source]
    else:
        paths = list(source)
    if not paths:
        raise ValueError(f"no .mcap episode files found in {source}")
    frames = [read_episode(p).tracks for p in paths]
    logger.info("loaded %d episodes, %d track rows", len(frames), sum(len(f) for f in frames))
    return frames


# --------------------------------------------------------------------------------------------------
# Episodes and windows
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class EpisodeArrays:
    """One episode's tracks as dense arrays over ``T`` consecutive steps and ``V`` vehicles."""

    episode: str
    steps: np.ndarray  # (T,) int64, consecutive
    vehicle_ids: np.ndarray  # (V,) int64
    xy: np.ndarray  # (T, V, 2) float64, 0 where absent
    present: np.ndarray  # (T, V) bool
    lane: np.ndarray  # (T, V) int64, -1 where absent or unknown
    accel: np.ndarray  # (T, V) float64, NaN where absent

    @classmethod
    def from_tracks(cls, tracks: pd.DataFrame, episode: str) -> EpisodeArrays:
        """Densify one episode's long-form tracks (rows of a single episode)."""
        steps_col = tracks["step"].to_numpy(np.int64)
        vid_col = tracks["vehicle_id"].to_numpy(np.int64)
        if len(steps_col) == 0:
            raise ValueError(f"episode {episode!r} has no rows")
        first = int(steps_col.min())
        steps = np.arange(first, int(steps_col.max()) + 1, dtype=np.int64)
        vehicle_ids, vi = np.unique(vid_col, return_inverse=True)
        ti = steps_col - first
        t, v = len(steps), len(vehicle_ids)
        present = np.zeros((t, v), dtype=bool)
        if np.any(np.bincount(ti * v + vi, minlength=t * v) > 1):
            raise ValueError(f"episode {episode!r} has duplicate (step, vehicle_id) rows")
        present[ti, vi] = True
        xy = np.zeros((t, v, 2))
        xy[ti, vi, 0] = tracks["x"].to_numpy(np.float64)
        xy[ti, vi, 1] = tracks["y"].to_numpy(np.float64)
        if not np.isfinite(xy).all():
            raise ValueError(f"episode {episode!r} has non-finite positions")
        lane = np.full((t, v), -1, dtype=np.int64)
        if "lane" in tracks:
            lane[ti, vi] = tracks["lane"].to_numpy(np.int64)
        accel = np.full((t, v), np.nan)
        if "accel" in tracks:
            accel[ti, vi] = tracks["accel"].to_numpy(np.float64)
        elif "speed" in tracks and "t" in tracks:
            speed = np.full((t, v), np.nan)
            speed[ti, vi] = tracks["speed"].to_numpy(np.float64)
            dt = float(np.median(np.diff(np.unique(tracks["t"].to_numpy(np.float64))))) if t > 1 else 1.0
            accel[1:] = (speed[1:] - speed[:-1]) / dt  # backward difference
        return cls(episode, steps, vehicle_ids, xy, present, lane, accel)


class WindowBatch(NamedTuple):
    """N windows, each in its agent-centric frame at ``t0`` (metres)."""

    history: np.ndarray  # (N, H, 2) agent positions t0-H+1..t0; history[:, -1] == 0
    future: np.ndarray  # (N, F, 2) agent positions t0+1..t0+F
    neighbours: np.ndarray  # (N, K, H, 2) nearest vehicles at t0, nearest first; 0 where masked
    neighbour_mask: np.ndarray  # (N, K, H) bool, presence of each neighbour at each history step
    origin: np.ndarray  # (N, 2) agent position at t0, world frame
    heading: np.ndarray  # (N,) frame heading, world frame, radians
    lane_change: np.ndarray  # (N,) bool, the agent's lane in the future differs from its lane at t0
    episode_index: np.ndarray  # (N,) int64 index into Corpus.episodes
    vehicle_id: np.ndarray  # (N,) int64
    step: np.ndarray  # (N,) int64, the step t0

    @property
    def size(self) -> int:
        """N, the number of windows (``len()`` of a NamedTuple is its field count)."""
        return int(self.history.shape[0])

    def tokens(self) -> tuple[np.ndarray, np.ndarray]:
        """Agent and neighbours as one token set: ``(N, 1+K, H, 2)`` positions, ``(N, 1+K, H)`` mask."""
        pos = np.concatenate((self.history[:, None], self.neighbours), axis=1)
        agent_mask = np.ones(self.history.shape[:2], dtype=bool)[:, None]
        return pos, np.concatenate((agent_mask, self.neighbour_mask), axis=1)


class Split(NamedTuple):
    """Episode indices (into ``Corpus.episodes``) of each split."""

    train: list[int]
    val: list[int]
    test: list[int]


def split_episodes(
    episodes: Sequence[str], *, val_fraction: float = 0.15, test_fraction: float = 0.15, seed: int = 0
) -> Split:
    """Deterministic train/val/test split by episode.

    Episodes are ordered by a hash of ``(seed, episode id)`` (so the split does not depend on the
    order they were loaded in) and cut by count. With at least 3 episodes, val and test get at least
    one episode each and train keeps at least one. Every episode lands in exactly one split.

    Args:
        episodes: unique episode ids.

    Returns:
        Indices into ``episodes`` for each split, each sorted.
    """
    if len(set(episodes)) != len(episodes):
        raise ValueError("episode ids must be unique")
    if not (0 <= val_fraction < 1 and 0 <= test_fraction < 1 and val_fraction + test_fraction < 1):
        raise ValueError(f"bad split fractions: val_fraction={val_fraction}, test_fraction={test_fraction}")
    n = len(episodes)

    def key(i: int) -> str:
        return hashlib.sha256(f"{seed}:{episodes[i]}".encode()).hexdigest()

    order = sorted(range(n), key=key)
    n_test = round(n * test_fraction)
    n_val = round(n * val_fraction)
    if n >= 3:
        n_test = max(n_test, 1 if test_fraction > 0 else 0)
        n_val = max(n_val, 1 if val_fraction > 0 else 0)
        while n - n_test - n_val < 1:
            if n_val >= n_test and n_val > 0:
                n_val -= 1
            else:
                n_test -= 1
    test = sorted(order[:n_test])
    val = sorted(order[n_test : n_test + n_val])
    train = sorted(order[n_test + n_val :])
    return Split(train=train, val=val, test=test)


class Corpus:
    """Windows over a set of episodes, cut on the fly.

    ``corpus.index`` is an ``(M, 3)`` int64 array of ``(episode_index, vehicle_column, t0_row)``
    rows, one per valid window (the agent is present over all ``H + F`` steps); :meth:`gather` turns
    any subset of it into a :class:`WindowBatch`.
    """

    def __init__(self, episodes: Sequence[EpisodeArrays], options: WindowOptions | None = None) -> None:
        self.options = options or WindowOptions()
        self.episodes: list[EpisodeArrays] = list(episodes)
        names = [e.episode for e in self.episodes]
        if len(set(names)) != len(names):
            raise ValueError("episode ids must be unique across the corpus")
        self.index = self._build_index()
        logger.info("corpus: %d episodes, %d windows (%s)", len(self.episodes), len(self.index), self.options)

    @classmethod
    def from_tracks(
        cls, tracks: pd.DataFrame | Sequence[pd.DataFrame], options: WindowOptions | None = None
    ) -> Corpus:
        """Build from long-form tracks DataFrame(s) (columns per docs/INTERFACES.md).

        Several frames may be given (one per recorded file); episode ids must be unique over all.
        """
        frames = [tracks] if isinstance(tracks, pd.DataFrame) else list(tracks)
        if not frames:
            raise ValueError("no tracks given")
        episodes: list[EpisodeArrays] = []
        for frame in frames:
            missing = [c for c in REQUIRED_COLUMNS if c not in frame.columns]
            if missing:
                raise ValueError(f"tracks lack columns {missing}; see docs/INTERFACES.md")
            for name, group in frame.groupby("episode", sort=True, observed=True):
                episodes.append(EpisodeArrays.from_tracks(group, str(name)))
        return cls(episodes, options)

    @property
    def episode_ids(self) -> list[str]:
        return [e.episode for e in self.episodes]

    def _build_index(self) -> np.ndarray:
        o = self.options
        span = o.history_steps + o.future_steps
        rows: list[np.ndarray] = []
        for ei, ep in enumerate(self.episodes):
            t = len(ep.steps)
            if t < span:
                continue
            cum = np.concatenate(
                (np.zeros((1, ep.present.shape[1]), np.int64), np.cumsum(ep.present, axis=0))
            )
            t0 = np.arange(o.history_steps - 1, t - o.future_steps, o.stride)
            # present on rows t0-H+1 .. t0+F  <=>  cum[t0+F+1] - cum[t0-H+1] == H+F
            full = (cum[t0 + o.future_steps + 1] - cum[t0 - o.history_steps + 1]) == span  # (n_t0, V)
            if not o.include_ego:
                full[:, ep.vehicle_ids == 0] = False
            ti, vi = np.nonzero(full)
            rows.append(np.stack((np.full_like(ti, ei), vi, t0[ti]), axis=1).astype(np.int64))
        return np.concatenate(rows) if rows else np.zeros((0, 3), np.int64)

    def __len__(self) -> int:
        return len(self.index)

    def windows_of(self, episode_indices: Sequence[int]) -> np.ndarray:
        """Row numbers into :attr:`index` of the windows of the given episodes, ``(M,)`` int64."""
        return np.flatnonzero(np.isin(self.index[:, 0], np.asarray(list(episode_indices), dtype=np.int64)))

    def gather(self, rows: np.ndarray | None = None) -> WindowBatch:
        """Materialise windows (all if ``rows`` is None) as one :class:`WindowBatch`, float32 arrays."""
        sel = self.index if rows is None else self.index[np.asarray(rows, dtype=np.int64)]
        parts = [self._gather_episode(int(ei), sel[sel[:, 0] == ei]) for ei in np.unique(sel[:, 0])]
        if not parts:
            return self._empty()
        batch = WindowBatch(*(np.concatenate(field) for field in zip(*parts, strict=True)))
        if rows is not None and len(parts) > 1:  # restore the requested order
            order = np.argsort(np.argsort(sel[:, 0], kind="stable"), kind="stable")
            batch = WindowBatch(*(f[order] for f in batch))
        return batch

    def _empty(self) -> WindowBatch:
        o = self.options
        h, f, k = o.history_steps, o.future_steps, o.num_neighbours
        z = np.zeros
        return WindowBatch(
            z((0, h, 2), np.float32), z((0, f, 2), np.float32), z((0, k, h, 2), np.float32),
            z((0, k, h), bool), z((0, 2)), z((0,)), z((0,), bool), z((0,), np.int64), z((0,), np.int64),
            z((0,), np.int64),
        )  # fmt: skip

    def _gather_episode(self, ei: int, sel: np.ndarray) -> WindowBatch:
        o = self.options
        ep = self.episodes[ei]
        h, f, k = o.history_steps, o.future_steps, o.num_neighbours
        vi, t0 = sel[:, 1], sel[:, 2]
        n = len(sel)
        hist_rows = t0[:, None] + np.arange(-h + 1, 1)  # (n, H)
        fut_rows = t0[:, None] + np.arange(1, f + 1)  # (n, F)
        hist = ep.xy[hist_rows, vi[:, None]]  # (n, H, 2)
        fut = ep.xy[fut_rows, vi[:, None]]  # (n, F, 2)
        origin = hist[:, -1]
        heading = heading_from_positions(hist)
        # Neighbours: K nearest vehicles present at t0 (distance at t0 only: no future data).
        v = ep.xy.shape[1]
        kk = min(k, max(v - 1, 0))
        nb_pos = np.zeros((n, k, h, 2))
        nb_mask = np.zeros((n, k, h), dtype=bool)
        if kk > 0:
            d = np.linalg.norm(ep.xy[t0] - origin[:, None], axis=-1)  # (n, V)
            d[~ep.present[t0]] = np.inf
            d[np.arange(n), vi] = np.inf
            nb = np.argsort(d, axis=1, kind="stable")[:, :kk]  # (n, kk)
            ok = np.isfinite(np.take_along_axis(d, nb, axis=1))  # (n, kk)
            nb_pos[:, :kk] = ep.xy[hist_rows[:, None, :], nb[:, :, None]]  # (n, kk, H, 2)
            nb_mask[:, :kk] = ep.present[hist_rows[:, None, :], nb[:, :, None]] & ok[:, :, None]
        hist_f = to_frame(hist, origin, heading)
        fut_f = to_frame(fut, origin, heading)
        nb_f = to_frame(nb_pos.reshape(n, k * h, 2), origin, heading).reshape(n, k, h, 2)
        nb_f[~nb_mask] = 0.0
        lane_t0 = ep.lane[t0, vi]
        lane_fut = ep.lane[fut_rows, vi[:, None]]
        lane_change = (lane_t0 >= 0) & np.any((lane_fut != lane_t0[:, None]) & (lane_fut >= 0), axis=1)
        return WindowBatch(
            history=hist_f.astype(np.float32),
            future=fut_f.astype(np.float32),
            neighbours=nb_f.astype(np.float32),
            neighbour_mask=nb_mask,
            origin=origin,
            heading=heading,
            lane_change=lane_change,
            episode_index=np.full(n, ei, np.int64),
            vehicle_id=ep.vehicle_ids[vi],
            step=ep.steps[t0],
        )

    def statistics(self, rows: np.ndarray | None = None) -> dict[str, float | int]:
        """Corpus statistics over all windows (or the given rows of :attr:`index`).

        Returns a JSON-ready dict: window and episode counts, the fraction of windows with a lane
        change in their future part, and the spread of the recorded longitudinal accelerations
        (m/s², over every present vehicle-step of the episodes involved).
        """
        sel = self.index if rows is None else self.index[np.asarray(rows, dtype=np.int64)]
        lc = 0
        for ei in np.unique(sel[:, 0]):
            ep = self.episodes[int(ei)]
            s = sel[sel[:, 0] == ei]
            lane_t0 = ep.lane[s[:, 2], s[:, 1]]
            fut_rows = s[:, 2][:, None] + np.arange(1, self.options.future_steps + 1)
            lane_fut = ep.lane[fut_rows, s[:, 1][:, None]]
            lc += int(
                np.sum((lane_t0 >= 0) & np.any((lane_fut != lane_t0[:, None]) & (lane_fut >= 0), axis=1))
            )
        eps = [self.episodes[int(ei)] for ei in np.unique(sel[:, 0])]
        acc = np.concatenate([e.accel[e.present] for e in eps]) if eps else np.zeros(0)
        acc = acc[np.isfinite(acc)]
        stats: dict[str, float | int] = {
            "episodes": len(eps),
            "windows": len(sel),
            "lane_change_fraction": lc / len(sel) if len(sel) else 0.0,
            "history_steps": self.options.history_steps,
            "future_steps": self.options.future_steps,
            "stride": self.options.stride,
        }
        if acc.size:
            p = np.percentile(acc, [1, 5, 50, 95, 99])
            stats |= {"accel_std_mps2": float(acc.std()), "accel_mean_mps2": float(acc.mean())}
            stats |= {f"accel_p{q}_mps2": float(val) for q, val in zip((1, 5, 50, 95, 99), p, strict=True)}
        return stats
