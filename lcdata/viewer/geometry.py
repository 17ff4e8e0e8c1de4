"""Array geometry for the viewer: per-step layout of the long-form tracks, boxes, trails, futures.

Everything here is pure numpy over whole episodes (no per-step or per-vehicle Python loops).
Rerun's 2D views draw y downwards, so the viewer shows the road top-down with x to the right and
the world's y (to the left of the road) upwards: :func:`screen` mirrors y, and a yaw measured
counter-clockwise in the world is clockwise on screen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

TRAIL_LAGS = np.arange(0, 41, 5)
"""Steps behind the current one sampled by a history trail (2 s at 20 Hz, one point every 0.25 s)."""
GRID_CELLS_PER_ROW = 64
MIN_GRID_CELLS = 1 << 22
"""A :class:`TrackGrid` may have :data:`GRID_CELLS_PER_ROW` cells per track row, and always
:data:`MIN_GRID_CELLS` (64 MiB of positions). A simulated episode fills most of its grid, an imported window
where vehicles come and go a smaller part; a file whose every step holds a new vehicle id would make a grid of
rows squared (12,000 rows: 2.3 GB)."""


def check_grid_size(n_steps: int, n_ids: int, rows: int) -> None:
    """Refuse a (step, vehicle) grid far larger than the track rows it holds (a crafted file's, not an episode's).

    Raises:
        ValueError: one line, for a person.
    """
    cells, limit = n_steps * n_ids, max(MIN_GRID_CELLS, GRID_CELLS_PER_ROW * rows)
    if cells > limit:
        raise ValueError(
            f"{n_steps:,} steps x {n_ids:,} vehicle ids would make a track grid of {cells:,} cells for "
            f"{rows:,} track rows, more than the {limit:,} shown ({GRID_CELLS_PER_ROW} per row, at least "
            f"{MIN_GRID_CELLS:,}): not a plausible episode"
        )


def screen(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """World ``(x, y)`` of any shape ``S`` -> screen points ``S + (2,)`` (float32, y mirrored)."""
    return np.stack([np.asarray(x, dtype=np.float32), -np.asarray(y, dtype=np.float32)], axis=-1)


def box_corners(
    x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """Closed outlines of oriented rectangles: arrays ``(R,)`` -> ``(R, 5, 2)`` screen points.

    The fifth point repeats the first so that a line strip draws the whole outline. A short nose line
    is not drawn; the heading is visible from the box's rotation and the trail behind it.
    """
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    u = np.array([0.5, 0.5, -0.5, -0.5, 0.5])[None, :] * np.asarray(length)[:, None]  # along the body
    v = np.array([0.5, -0.5, -0.5, 0.5, 0.5])[None, :] * np.asarray(width)[:, None]  # to its left
    return screen(np.asarray(x)[:, None] + c * u - s * v, np.asarray(y)[:, None] + s * u + c * v)


@dataclass(frozen=True, slots=True)
class TrackGrid:
    """The long-form tracks laid out on a (step, vehicle) grid.

    Attributes:
        steps: ``(T,)`` int64 simulation steps present, ascending.
        t: ``(T,)`` float64 simulation time of each step (s).
        ids: ``(V,)`` int64 vehicle ids present in the episode, ascending.
        row: ``(R,)`` index into ``steps`` of every track row (rows sorted by step, then vehicle id).
        col: ``(R,)`` index into ``ids`` of every track row.
        counts: ``(T,)`` rows per step.
        xy: ``(T, V, 2)`` world positions, NaN where a vehicle has no row at a step.
    """

    steps: np.ndarray
    t: np.ndarray
    ids: np.ndarray
    row: np.ndarray
    col: np.ndarray
    counts: np.ndarray
    xy: np.ndarray

    @classmethod
    def from_tracks(cls, tracks: pd.DataFrame) -> tuple[TrackGrid, pd.DataFrame]:
        """Build the grid; also returns ``tracks`` sorted by (step, vehicle_id) to match ``row``/``col``.

        Raises:
            ValueError: the grid would be far larger than the rows (:func:`check_grid_size`).
        """
        step = tracks["step"].to_numpy()
        vid = tracks["vehicle_id"].to_numpy()
        if len(step) > 1 and (np.any(np.diff(step) < 0) or np.any((np.diff(step) == 0) & (np.diff(vid) < 0))):
            tracks = tracks.iloc[np.lexsort((vid, step))].reset_index(drop=True)
            step, vid = tracks["step"].to_numpy(), tracks["vehicle_id"].to_numpy()
        steps, first, counts = np.unique(step, return_index=True, return_counts=True)
        ids = np.unique(vid)
        check_grid_size(len(steps), len(ids), len(step))
        row = np.repeat(np.arange(len(steps)), counts)
        col = np.searchsorted(ids, vid)
        xy = np.full((len(steps), len(ids), 2), np.nan)
        xy[row, col, 0] = tracks["x"].to_numpy()
        xy[row, col, 1] = tracks["y"].to_numpy()
        t = tracks["t"].to_numpy()[first]
        return cls(steps, t, ids, row, col, counts, xy), tracks

    def trails(self, select: np.ndarray, lags: np.ndarray = TRAIL_LAGS) -> np.ndarray:
        """History trails of the rows ``select`` (bool ``(R,)``): ``(R', len(lags), 2)`` screen points.

        Point ``j`` is the vehicle's position ``lags[j]`` steps earlier (rows of the grid, which are
        simulation steps in a complete recording); before the vehicle's first step the trail holds its
        earliest known position, so young trails are simply shorter.
        """
        row, col = self.row[select], self.col[select]
        back = np.maximum(row[:, None] - lags[None, :], 0)
        pts = self.xy[back, col[:, None]]  # (R', L, 2)
        missing = np.isnan(pts[..., 0])
        if missing.any():  # fill from the nearer (later) sample: walk from the current step backwards
            for j in range(1, pts.shape[1]):
                gap = missing[:, j]
                pts[gap, j] = pts[gap, j - 1]
        return screen(pts[..., 0], pts[..., 1])

    def future(self, step_index: np.ndarray, col: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
        """What vehicles really did: positions ``1..horizon`` steps after ``step_index``.

        Args:
            step_index: ``(S,)`` indices into ``steps``. col: ``(S,)`` indices into ``ids``.

        Returns:
            ``(S, horizon + 1, 2)`` world positions starting at the current one (NaN past the end of the
            recording) and ``(S, horizon + 1)`` bool validity.
        """
        k = np.arange(horizon + 1)
        rows = step_index[:, None] + k[None, :]
        inside = rows < len(self.steps)
        pts = self.xy[np.minimum(rows, len(self.steps) - 1), col[:, None]]
        pts[~inside] = np.nan
        return pts, inside & ~np.isnan(pts[..., 0])
