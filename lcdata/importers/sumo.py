"""SUMO floating car data (``sumo --fcd-output FILE.xml``) -> corpus episodes.

The file is read as a stream (``xml.parsers.expat``, a megabyte at a time, each ``<timestep>`` made a frame
and dropped once read), so its size does not matter; every value is checked against
:mod:`lcdata.importers.limits` as it is read. What SUMO writes, and what becomes of it:

- ``<timestep time="...">``: seconds, any step (``--step-length``, ``--device.fcd.period``); resampled
  onto the corpus grid (:mod:`lcdata.importers.resample`).
- ``<vehicle id x y angle speed [lane] [type] [length] [width] [acceleration] ...>``: ``x, y`` are the
  centre of the **front bumper** in network coordinates (metres, y north); ``angle`` is a navigation
  heading in degrees, clockwise from north (0 = +y, 90 = +x), so ``yaw = radians(90 - angle)``; the
  written position is the vehicle's centre, ``length / 2`` behind the bumper along the heading
  (``length`` from the element when written with ``--fcd-output.attributes``, else
  :attr:`SumoOptions.vehicle_length_m`). ``lane`` is ``<edge>_<index>`` with SUMO's index 0 the
  rightmost lane, as in the corpus; an internal (junction) lane ``:...`` and a missing lane are -1.
  ``acceleration`` when present, else the change of speed since the vehicle's previous sample (0 at its
  first). Ids are strings: each gets an integer from 1 up in the order vehicles first appear; the
  metadata keeps the SUMO id and type of every vehicle of an episode.
- Dropped: ``<person>`` and ``<container>`` elements, ``z``, ``pos``, ``slope``, ``signals``, ``odometer``
  and any other attribute. Positions stay in network coordinates (no road frame is assumed: a network
  has any shape), so the episodes carry no ``road`` in their config and ``lc-view`` draws none.
"""

from __future__ import annotations

import logging
import math
import os
import pathlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any
from xml.parsers import expat

import numpy as np

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
    HEADING,
    LANE,
    LENGTH,
    MAX_VEHICLES_PER_SAMPLE,
    POSITION,
    SPEED,
    TIME,
    WIDTH,
    Bound,
)
from lcdata.importers.resample import TIME_TOLERANCE_S, Frame, resample
from lckit.fileio import file_sha256

log = logging.getLogger(__name__)

FORMAT = "sumo-fcd"
ROOT_TAG = "fcd-export"


@dataclass(frozen=True, slots=True, kw_only=True)
class SumoOptions:
    """Vehicle size when the FCD file does not say (SUMO's default passenger car: 5.0 x 1.8 m)."""

    vehicle_length_m: float = 5.0
    vehicle_width_m: float = 1.8

    def __post_init__(self) -> None:
        for name, bound in (("vehicle_length_m", LENGTH), ("vehicle_width_m", WIDTH)):
            value = getattr(self, name)
            number = isinstance(value, int | float) and not isinstance(value, bool)
            if problem := bound.problem(value) if number else "is not a number":
                raise ValueError(f"{name} {value!r} {problem}")


def _lane_index(lane: str | None) -> int | None:
    """``edge_2`` -> 2; an internal lane (``:junction_0_0``), a missing or odd id -> -1; an index of more digits
    than any lane count -> None."""
    if not lane or lane.startswith(":"):
        return -1
    _, _, index = lane.rpartition("_")
    if not (index.isascii() and index.isdigit()):
        return -1
    return int(index) if len(index) <= 9 else None


VEHICLE_FIELDS: tuple[tuple[str, Bound], ...] = (
    ("x", POSITION), ("y", POSITION), ("angle", HEADING), ("speed", SPEED), ("length", LENGTH), ("width", WIDTH),
    ("acceleration", ACCELERATION),
)  # fmt: skip
"""The attributes of a ``<vehicle>`` read, in the columns of :meth:`FcdReader._frame`'s table, and their bounds."""
READ_BYTES = 1 << 20
"""The file is parsed this many bytes at a time."""


class FcdReader:
    """The frames of one FCD file, in file order (:meth:`frames`), and the SUMO ids behind the integers.

    Raises ``ValueError`` naming the file, and the line where there is one, for anything that is not SUMO FCD
    output: malformed XML, another root element, a timestep without a time or one that does not come after
    the one before, a vehicle without ``x``, ``y``, ``angle`` or ``speed``, a value that is not a number or not
    plausible for what it is (:mod:`lcdata.importers.limits`: time, position, heading, speed, acceleration,
    size, lane), the same vehicle twice in a timestep.
    """

    def __init__(self, path: pathlib.Path, options: SumoOptions, progress: Progress | None = None) -> None:
        self.path, self.options, self.progress = path, options, progress
        self.ids: dict[str, int] = {}
        self.types: dict[int, str] = {}
        self.sources: dict[int, str] = {}
        self.size = path.stat().st_size
        self.timesteps = 0

    def _error(self, message: str, line: int | None = None) -> ValueError:
        return ValueError(f"{self.path}: {'' if line is None else f'line {line}: '}{message}")

    def frames(self) -> Iterator[Frame]:
        if self.size == 0:
            raise self._error("the file is empty")
        parser = expat.ParserCreate()
        depth = 0
        root: list[str] = []
        timestep: list[Any] = []  # [time attribute, line, [(vehicle attributes, line), ...]] while inside one
        done: list[tuple[str | None, int, list[tuple[dict[str, str], int]]]] = []

        def start(name: str, attrs: dict[str, str]) -> None:
            nonlocal depth
            depth += 1
            if depth == 1:
                root.append(name)
            elif depth == 2 and name == "timestep" and root[0] == ROOT_TAG:
                timestep[:] = [attrs.get("time"), parser.CurrentLineNumber, []]
            elif depth == 3 and name == "vehicle" and timestep:
                if len(timestep[2]) >= MAX_VEHICLES_PER_SAMPLE:
                    raise self._error(f"the timestep of line {timestep[1]} holds more than {MAX_VEHICLES_PER_SAMPLE} "
                                      "vehicles", parser.CurrentLineNumber)  # fmt: skip
                timestep[2].append((attrs, parser.CurrentLineNumber))

        def end(name: str) -> None:
            nonlocal depth
            if depth == 2 and timestep:
                done.append((timestep[0], timestep[1], timestep[2]))
                timestep.clear()
            depth -= 1

        parser.StartElementHandler, parser.EndElementHandler = start, end
        prev: Frame | None = None
        with open(self.path, "rb") as raw:
            while True:
                chunk = raw.read(READ_BYTES)
                try:
                    parser.Parse(chunk, not chunk)
                except expat.ExpatError as exc:
                    raise self._error(f"malformed XML ({exc})") from None
                if root and root[0] != ROOT_TAG:
                    raise self._error(f"not SUMO FCD output: the root element is <{root[0]}>, expected <{ROOT_TAG}>")
                for time_text, line, vehicles in done:
                    prev = self._frame(time_text, line, vehicles, prev)
                    self.timesteps += 1
                    yield prev
                done.clear()
                if self.progress is not None:
                    self.progress(raw.tell(), self.size)
                if not chunk:
                    break

    def _frame(self, time_text: str | None, line: int, vehicles: list[tuple[dict[str, str], int]],
               prev: Frame | None) -> Frame:  # fmt: skip
        try:
            t = float(time_text)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise self._error(f"timestep {self.timesteps + 1} has no valid time ({time_text!r})", line) from None
        if problem := TIME.problem(t):
            raise self._error(f"timestep time {time_text!r} {problem}", line)
        if prev is not None and not t > prev.t_s + TIME_TOLERANCE_S:
            raise self._error(f"source time does not increase: {t:g} s after {prev.t_s:g} s", line)
        n = len(vehicles)
        ids = np.empty(n, dtype=np.int64)
        values = np.empty((n, len(VEHICLE_FIELDS)))  # NaN: no acceleration attribute
        lanes = np.empty(n, dtype=np.int64)
        o = self.options
        defaults = {"length": o.vehicle_length_m, "width": o.vehicle_width_m, "acceleration": math.nan}
        for i, (attrs, vline) in enumerate(vehicles):
            name = attrs.get("id")
            if name is None:
                raise self._error(f"a vehicle at time {t:g} has no id", vline)
            vid = self.ids.get(name)
            if vid is None:
                vid = self.ids[name] = len(self.ids) + 1
                self.sources[vid] = name
                self.types[vid] = attrs.get("type", "")
            ids[i] = vid
            for j, (field, bound) in enumerate(VEHICLE_FIELDS):
                text = attrs.get(field)
                if text is None:
                    if field not in defaults:
                        raise self._error(f"vehicle {name!r} at time {t:g} has no {field!r} attribute", vline)
                    values[i, j] = defaults[field]
                    continue
                try:
                    values[i, j] = value = float(text)
                except ValueError:
                    raise self._error(f"vehicle {name!r} at time {t:g}: {field} {text[:40]!r} is not a number",
                                      vline) from None  # fmt: skip
                if problem := bound.problem(value):
                    raise self._error(f"vehicle {name!r} at time {t:g}: {field} {text[:40]!r} {problem}", vline)
            lane = _lane_index(attrs.get("lane"))
            if lane is None or (lane >= 0 and (problem := LANE.problem(lane))):
                raise self._error(f"vehicle {name!r} at time {t:g}: lane {attrs['lane'][:60]!r}: its index "
                                  f"{'is more than any road has' if lane is None else problem}", vline)  # fmt: skip
            lanes[i] = lane
        order = np.argsort(ids, kind="stable")
        ids, values, lanes = ids[order], values[order], lanes[order]
        if n > 1 and (np.diff(ids) == 0).any():
            dup = self.sources[int(ids[1:][np.diff(ids) == 0][0])]
            raise self._error(f"vehicle {dup!r} appears twice at time {t:g}", line)
        yaw = np.radians(90.0 - values[:, 2])
        yaw = np.remainder(yaw + math.pi, 2 * math.pi) - math.pi
        half = values[:, 4] / 2
        x = values[:, 0] - half * np.cos(yaw)
        y = values[:, 1] - half * np.sin(yaw)
        speed, accel = values[:, 3], values[:, 6]
        missing = np.isnan(accel)
        if missing.any():
            accel = np.where(missing, 0.0, accel)
            if prev is not None:
                _, i_cur, i_prev = np.intersect1d(ids, prev.ids, assume_unique=True, return_indices=True)
                fill = np.zeros(n)
                fill[i_cur] = (speed[i_cur] - prev.speed[i_prev]) / (t - prev.t_s)
                accel = np.where(missing, fill, accel)
                if (bad := ACCELERATION.first_bad(accel)) is not None:
                    raise self._error(f"vehicle {self.sources[int(ids[bad])]!r}: its speed changes from "
                                      f"{prev.speed[prev.ids == ids[bad]][0]:g} to {speed[bad]:g} m/s between time "
                                      f"{prev.t_s:g} and {t:g} s, an acceleration of {accel[bad]:g} m/s^2, which "
                                      f"{ACCELERATION.problem(accel[bad])}", line)  # fmt: skip
        return Frame(t, ids, x, y, yaw, speed, accel, lanes, values[:, 4], values[:, 5], f"{self.path}: line {line}")

    def vehicle_info(self, ids: np.ndarray) -> dict[str, Any]:
        """``{"<id>": {"source_id": ..., "type": ...}}`` of the given integer ids."""
        return {str(int(i)): {"source_id": self.sources[int(i)], "type": self.types[int(i)]} for i in ids}


def import_sumo_fcd(path: str | os.PathLike[str], out: str | os.PathLike[str],
                    options: ImportOptions | None = None, sumo: SumoOptions | None = None, *,
                    overwrite: bool = False, progress: Progress | None = None) -> list[ImportedEpisode]:  # fmt: skip
    """Import one SUMO FCD file into ``out`` as corpus episodes ``sumo_<stem>_<index:04d>.mcap``.

    Args:
        path: the XML of ``sumo --fcd-output``.
        out: output folder (created if missing).
        options: episode rate and length (:class:`~lcdata.importers.episodes.ImportOptions`).
        sumo: vehicle size where the file does not give one.
        overwrite: replace the episodes of an earlier import of the same file name (refused otherwise).
        progress: ``progress(bytes read, file size)``, called now and then.

    Returns:
        The episodes written, in order.

    Raises:
        FileNotFoundError: no such file. FileExistsError: episodes of this file in ``out`` already.
        ValueError: not a SUMO FCD file, or no vehicle in it (nothing is written then).
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file" if not path.exists() else f"{path} is not a file")
    options = options or ImportOptions()
    reader = FcdReader(path, sumo or SumoOptions(), progress)
    stem = f"sumo_{path.stem}"
    meta: dict[str, Any] = {
        "config": {"dt_s": options.dt_s}, "driver": "recorded", "scenario": FORMAT, "source_format": FORMAT,
        "source_file": path.name,
    }  # fmt: skip
    files = EpisodeFiles(out, stem, overwrite=overwrite)  # refuses before anything is read
    # The hash goes into every episode's metadata, so it is needed before the first one is written: a pass
    # of its own (at disk speed, far faster than the XML is parsed).
    meta["source_sha256"] = file_sha256(path)
    with files:
        grid = resample(reader.frames(), options.dt_s, max_duration_s=options.max_duration_s,
                        max_steps=options.max_steps)
        written = write_episodes(grid, files, stem, meta, options, reader.vehicle_info)
        if not reader.ids:
            raise ValueError(f"{path}: no vehicle in {reader.timesteps} timesteps")
        check_written(path, written, options)
    log.info("%s: %d timesteps, %d vehicles -> %d episodes", path, reader.timesteps, len(reader.ids), len(written))
    return written
