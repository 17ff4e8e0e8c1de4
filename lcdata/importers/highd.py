"""highD-layout drone tracks (``XX_tracks.csv`` with ``XX_tracksMeta.csv`` beside it) -> corpus episodes.

What the layout holds, and what becomes of it:

- ``XX_tracks.csv``: one row per vehicle per video frame (25 Hz: :attr:`HighdOptions.frame_rate_hz`),
  in image coordinates (metres, origin at the image's upper left, x to the right, **y down**). ``x, y``
  are the upper-left corner of the bounding box, ``width`` its extent along x (the vehicle's length),
  ``height`` along y (its width): the centre is ``(x + width / 2, y + height / 2)``. ``xVelocity,
  yVelocity, xAcceleration, yAcceleration`` in the same axes; ``laneId`` numbers the lanes from the top of
  the image.
- ``XX_tracksMeta.csv``: per vehicle ``id``, ``class`` (Car, Truck) and ``drivingDirection``: 1 drives
  toward -x on the upper carriageway, 2 toward +x on the lower one.

The two carriageways become separate episodes (``..._dir1_...``, ``..._dir2_...``): put together they would
overlap once both are turned to drive +x, and a vehicle of the other carriageway is no neighbour. Each is
*rotated* into the corpus frame (x forward, y to the driver's left, lane 0 the rightmost), never mirrored,
so a lane change to the left stays one: direction 2 takes ``(x, -y)``, direction 1 ``(-x, y)`` (a
half turn of direction 2's frame). Lane ``k`` counts from the carriageway's right edge; the lane width is
fitted to the median lateral position of every lane and ``y`` shifted so that lane ``k``'s centre lies at
``(k + 0.5) * width`` (docs/INTERFACES.md), the road ``lc-view`` draws from the episode's config. Speed is
the norm of the velocity, yaw its direction, acceleration its component along the velocity.

Every value is checked against :mod:`lcdata.importers.limits` (:data:`BOUNDS`) as the table is read, frames
for their span before anything is sized by them, and the lane ids of each carriageway for the lanes they span;
one that fails is refused naming the file, the data row and the column.

Dropped: the surrounding-vehicle ids, ``dhw``, ``thw``, ``ttc``, sight distances (all derivable from the
tracks), ``XX_recordingMeta.csv`` (not read) and the per-vehicle statistics of the meta file.
"""

from __future__ import annotations

import logging
import math
import os
import pathlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from lcdata.importers.episodes import (
    EpisodeFiles,
    ImportedEpisode,
    ImportOptions,
    Progress,
    check_written,
    write_episodes,
)
from lcdata.importers.limits import (
    ACCELERATION,
    FRAME,
    LANE_ID,
    LENGTH,
    MAX_LANE_INDEX,
    POSITION,
    TIME,
    VEHICLE_ID,
    VELOCITY,
    WIDTH,
    Bound,
    shown,
)
from lcdata.importers.resample import Frame, resample
from lckit.fileio import file_sha256
from lcsim.config import RoadConfig

log = logging.getLogger(__name__)

FORMAT = "highd"
TRACK_COLUMNS = ("frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity", "xAcceleration",
                 "yAcceleration", "laneId")  # fmt: skip
"""The columns of ``XX_tracks.csv`` read (the others are dropped)."""
META_COLUMNS = ("id", "class", "drivingDirection")
"""The columns of ``XX_tracksMeta.csv`` read."""
BOUNDS: dict[str, Bound] = {
    "frame": FRAME, "id": VEHICLE_ID, "x": POSITION, "y": POSITION, "width": LENGTH, "height": WIDTH,
    "xVelocity": VELOCITY, "yVelocity": VELOCITY, "xAcceleration": ACCELERATION, "yAcceleration": ACCELERATION,
    "laneId": LANE_ID,
}  # fmt: skip
"""What each numeric column may hold (:mod:`lcdata.importers.limits`; highD's ``width`` is the length)."""
TRACKS_SUFFIX, META_SUFFIX = "_tracks.csv", "_tracksMeta.csv"
DEFAULT_LANE_WIDTH_M = RoadConfig().lane_width_m
LANE_WIDTH_RANGE_M = (2.5, 5.0)
"""A fitted lane width outside this range is not believed (the default is used, with a warning)."""
PROGRESS_EVERY = 500


@dataclass(frozen=True, slots=True, kw_only=True)
class HighdOptions:
    """The video frame rate (highD: 25 Hz)."""

    frame_rate_hz: float = 25.0

    def __post_init__(self) -> None:
        if not (isinstance(self.frame_rate_hz, int | float) and math.isfinite(self.frame_rate_hz)
                and self.frame_rate_hz > 0):  # fmt: skip
            raise ValueError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz!r}")


def meta_path_for(tracks: pathlib.Path) -> pathlib.Path:
    """``01_tracks.csv`` -> ``01_tracksMeta.csv`` beside it (``ValueError`` for another name)."""
    if not tracks.name.endswith(TRACKS_SUFFIX):
        raise ValueError(f"{tracks}: a highD tracks file is named XX{TRACKS_SUFFIX}; name its meta file explicitly")
    return tracks.with_name(tracks.name.removesuffix(TRACKS_SUFFIX) + META_SUFFIX)


def _read_csv(path: pathlib.Path, columns: tuple[str, ...], what: str) -> pd.DataFrame:
    """The named columns of a CSV file; ``ValueError`` naming the file for an empty file, missing columns
    or values of the wrong kind."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file ({what})" if not path.exists() else f"{path} is not a file")
    try:
        header = pd.read_csv(path, nrows=0).columns
    except pd.errors.EmptyDataError:
        raise ValueError(f"{path}: the file is empty") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a CSV file ({' '.join(str(exc).split())[:120]})") from None
    missing = [c for c in columns if c not in header]
    if missing:
        raise ValueError(f"{path}: no column {', '.join(missing)} (is it a highD {what}?)")
    try:
        frame = pd.read_csv(path, usecols=list(columns))
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a CSV file ({' '.join(str(exc).split())[:120]})") from None
    if frame.empty:
        raise ValueError(f"{path}: no rows")
    for column in columns:
        if column == "class":
            continue
        values = pd.to_numeric(frame[column], errors="coerce")
        bad = values.isna() | ~np.isfinite(values.to_numpy(np.float64, na_value=np.nan))
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            cell = frame[column].iloc[row]
            shown_cell = "nothing" if pd.isna(cell) else repr(str(cell)[:40])
            raise ValueError(f"{path}: column {column} holds {shown_cell} on data row {row + 1}, not a number")
        bound = BOUNDS.get(column)
        if bound is not None and (row := bound.first_bad(values.to_numpy(np.float64))) is not None:
            value = float(values.iloc[row])
            raise ValueError(f"{path}: data row {row + 1}: {column} {shown(value)} {bound.problem(value)}")
        frame[column] = values.astype(np.int64) if bound is not None and bound.integer else values
    return frame


def _check_span(rows: pd.DataFrame, path: pathlib.Path, frame_rate_hz: float, options: ImportOptions) -> None:
    """``ValueError`` naming the data row for a frame whose time is implausible or too far from the first frame's
    (``options.max_duration_s``): checked on the table as read, before anything is sized by the frames."""
    frame = rows["frame"].to_numpy(np.float64)
    time = frame / frame_rate_hz
    if (row := TIME.first_bad(time)) is not None:
        raise ValueError(f"{path}: data row {row + 1}: frame {frame[row]:.0f} at {frame_rate_hz:g} Hz is time "
                         f"{time[row]:g} s, which {TIME.problem(time[row])}")  # fmt: skip
    first, last = int(np.argmin(frame)), int(np.argmax(frame))
    if time[last] - time[first] > options.max_duration_s:
        raise ValueError(f"{path}: data row {last + 1}: frame {frame[last]:.0f} is {time[last] - time[first]:g} s "
                         f"after frame {frame[first]:.0f} at {frame_rate_hz:g} Hz, more than an import may span "
                         f"({options.max_duration_s:g} s; --max-duration raises it)")  # fmt: skip


def _check_lanes(lane_id: np.ndarray, path: pathlib.Path, direction: int, rows: np.ndarray) -> None:
    """``ValueError`` naming the data row (``rows``: each lane id's) of the lane id furthest from the others when
    the lane ids of a driving direction span more lanes than a road has."""
    lo, hi = int(lane_id.min()), int(lane_id.max())
    if hi - lo > MAX_LANE_INDEX:
        i = int(np.argmax(np.abs(lane_id - np.median(lane_id))))
        raise ValueError(f"{path}: data row {rows[i] + 1}: laneId {lane_id[i]} makes the lanes of driving "
                         f"direction {direction} span ids {lo} to {hi}, more than a road has "
                         f"({MAX_LANE_INDEX + 1} lanes)")  # fmt: skip


@dataclass(frozen=True, slots=True)
class Carriageway:
    """One driving direction's rows in the corpus frame, sorted by (frame, id); arrays ``(R,)``."""

    direction: int
    frame: np.ndarray  # int64
    ids: np.ndarray  # int64
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    lane: np.ndarray  # int64, 0 = rightmost
    length: np.ndarray
    width: np.ndarray
    transform: dict[str, float]
    """world ``x = x_sign * centre_x``, ``y = y_sign * centre_y + y_offset_m`` (image centre coordinates)."""
    road: dict[str, float | int]
    """``num_lanes`` and the fitted ``lane_width_m``."""
    row: np.ndarray  # int64, the data row (from 0) of each entry in the tracks file
    source: pathlib.Path

    @classmethod
    def from_rows(cls, rows: pd.DataFrame, direction: int, source: pathlib.Path) -> Carriageway:
        rows = rows.sort_values(["frame", "id"], kind="stable")
        frame, ids = rows["frame"].to_numpy(np.int64), rows["id"].to_numpy(np.int64)
        same = (np.diff(frame) == 0) & (np.diff(ids) == 0)
        if same.any():
            i = int(np.flatnonzero(same)[0])
            raise ValueError(f"{source}: vehicle {ids[i]} has two rows in frame {frame[i]}")
        col = {c: rows[c].to_numpy(np.float64) for c in TRACK_COLUMNS if c not in ("frame", "id", "laneId")}
        # Image (y down) -> a frame where this direction drives +x and +y is the driver's left: a rotation.
        sx, sy = (1.0, -1.0) if direction == 2 else (-1.0, 1.0)
        cx, cy = col["x"] + col["width"] / 2, col["y"] + col["height"] / 2
        vx, vy = sx * col["xVelocity"], sy * col["yVelocity"]
        ax, ay = sx * col["xAcceleration"], sy * col["yAcceleration"]
        speed = np.hypot(vx, vy)
        moving = speed > 1e-6
        accel = np.where(moving, (ax * vx + ay * vy) / np.where(moving, speed, 1.0), ax)
        lane_id = rows["laneId"].to_numpy(np.int64)
        _check_lanes(lane_id, source, direction, rows.index.to_numpy())
        # Lanes are numbered from the top of the image: the rightmost lane of direction 2 (driving +x,
        # y down) has the largest id, that of direction 1 the smallest.
        lane = lane_id.max() - lane_id if direction == 2 else lane_id - lane_id.min()
        y = sy * cy
        width_m, offset = _lane_geometry(y, lane, source, direction)
        return cls(
            direction, frame, ids, sx * cx, y + offset, np.arctan2(vy, vx), speed, accel, lane,
            col["width"], col["height"], {"x_sign": sx, "y_sign": sy, "y_offset_m": round(offset, 6)},
            {"num_lanes": int(lane.max()) + 1, "lane_width_m": round(width_m, 4)}, rows.index.to_numpy(), source,
        )  # fmt: skip

    def frames(self, frame_rate_hz: float, progress: Progress | None = None, done: int = 0,
               total: int = 0) -> Iterator[Frame]:  # fmt: skip
        """One :class:`Frame` per video frame, at ``frame / frame_rate_hz`` seconds."""
        starts = np.flatnonzero(np.diff(self.frame, prepend=self.frame[0] - 1))
        ends = np.append(starts[1:], len(self.frame))
        for i, (a, b) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):
            if progress is not None and i % PROGRESS_EVERY == 0:
                progress(done + i, total)
            yield Frame(self.frame[a] / frame_rate_hz, self.ids[a:b], self.x[a:b], self.y[a:b], self.yaw[a:b],
                        self.speed[a:b], self.accel[a:b], self.lane[a:b], self.length[a:b], self.width[a:b],
                        f"{self.source}: frame {self.frame[a]} (data row {self.row[a] + 1})")  # fmt: skip

    @property
    def frame_count(self) -> int:
        return len(np.unique(self.frame))


def _lane_geometry(y: np.ndarray, lane: np.ndarray, source: pathlib.Path, direction: int) -> tuple[float, float]:
    """``(lane width, y offset)`` that put lane ``k``'s centre at ``(k + 0.5) * width``: the width is the
    slope of the lanes' median positions over their index, the offset from the median over all rows."""
    lanes = np.unique(lane)
    width = DEFAULT_LANE_WIDTH_M
    if len(lanes) >= 2:
        centres = np.array([np.median(y[lane == k]) for k in lanes])
        fitted = float(np.polyfit(lanes.astype(np.float64), centres, 1)[0])
        lo, hi = LANE_WIDTH_RANGE_M
        if lo <= fitted <= hi:
            width = fitted
        else:
            log.warning("%s, direction %d: fitted lane width %.2f m is outside [%g, %g] m; using %g m",
                        source, direction, fitted, lo, hi, width)  # fmt: skip
    return width, width / 2 - float(np.median(y - lane * width))


def import_highd(tracks: str | os.PathLike[str], out: str | os.PathLike[str], options: ImportOptions | None = None,
                 highd: HighdOptions | None = None, *, meta: str | os.PathLike[str] | None = None,
                 overwrite: bool = False, progress: Progress | None = None) -> list[ImportedEpisode]:  # fmt: skip
    """Import one highD recording into ``out`` as corpus episodes ``highd_<XX>_dir<d>_<index:04d>.mcap``.

    Args:
        tracks: ``XX_tracks.csv``.
        out: output folder (created if missing).
        options: episode rate and length (:class:`~lcdata.importers.episodes.ImportOptions`).
        highd: the source frame rate.
        meta: ``XX_tracksMeta.csv`` (default: beside ``tracks``).
        overwrite: replace the episodes of an earlier import of the same recording (refused otherwise).
        progress: ``progress(frames done, frames in all)``, now and then.

    Returns:
        The episodes written: direction 1's, then direction 2's.

    Raises:
        FileNotFoundError: a file is missing. FileExistsError: episodes of this recording in ``out`` already.
        ValueError: a file that does not have the layout (nothing is written then).
    """
    tracks = pathlib.Path(tracks)
    if not tracks.is_file():
        raise FileNotFoundError(f"{tracks}: no such file" if not tracks.exists() else f"{tracks} is not a file")
    meta_path = pathlib.Path(meta) if meta is not None else meta_path_for(tracks)
    options, highd = options or ImportOptions(), highd or HighdOptions()
    stem = f"highd_{tracks.name.removesuffix(TRACKS_SUFFIX).removesuffix('.csv')}"
    files = EpisodeFiles(out, stem, overwrite=overwrite, parts="_dir[12]")  # refuses before anything is read
    rows = _read_csv(tracks, TRACK_COLUMNS, "tracks file")
    _check_span(rows, tracks, highd.frame_rate_hz, options)
    info = _read_csv(meta_path, META_COLUMNS, "tracks meta file").set_index("id")
    if info.index.duplicated().any():
        raise ValueError(f"{meta_path}: vehicle {info.index[info.index.duplicated()][0]} has two rows")
    unknown = np.setdiff1d(rows["id"].unique(), info.index.to_numpy())
    if len(unknown):
        raise ValueError(f"{tracks}: vehicle {unknown[0]} is not in {meta_path.name}")
    direction = info.loc[rows["id"], "drivingDirection"].to_numpy()
    odd = ~np.isin(direction, (1, 2))
    if odd.any():
        raise ValueError(f"{meta_path}: drivingDirection {shown(float(direction[odd][0]))} is neither 1 nor 2")
    classes = info["class"].astype(str)
    ways = [Carriageway.from_rows(rows[direction == d], d, tracks) for d in (1, 2) if (direction == d).any()]
    base: dict[str, Any] = {
        "driver": "recorded", "scenario": FORMAT, "source_format": FORMAT, "source_file": tracks.name,
        "source_sha256": file_sha256(tracks), "source_meta_file": meta_path.name,
        "source_meta_sha256": file_sha256(meta_path), "source_frame_rate_hz": highd.frame_rate_hz,
    }  # fmt: skip

    def vehicle_info(ids: np.ndarray) -> dict[str, Any]:
        return {str(int(i)): {"source_id": str(int(i)), "class": classes.loc[int(i)]} for i in ids}

    total = sum(w.frame_count for w in ways)
    written: list[ImportedEpisode] = []
    done = 0
    with files:
        for way in ways:
            meta_record = {**base, "config": {"dt_s": options.dt_s, "road": way.road},
                           "driving_direction": way.direction, "source_transform": way.transform}  # fmt: skip
            grid = resample(way.frames(highd.frame_rate_hz, progress, done, total), options.dt_s,
                            max_duration_s=options.max_duration_s, max_steps=options.max_steps)
            written += write_episodes(grid, files, f"{stem}_dir{way.direction}", meta_record, options, vehicle_info)
            done += way.frame_count
        check_written(tracks, written, options)
    if progress is not None:
        progress(total, total)
    log.info("%s: %d vehicles, %d frames -> %d episodes", tracks, rows["id"].nunique(), total, len(written))
    return written
