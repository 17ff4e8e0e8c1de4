"""SUMO floating car data (``sumo --fcd-output FILE.xml``) -> corpus episodes.

The file is read as a stream (``xml.etree.ElementTree.iterparse``, one ``<timestep>`` at a time, each
cleared once read), so its size does not matter. What SUMO writes, and what becomes of it:

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
from xml.etree.ElementTree import Element, ParseError, iterparse

import numpy as np

from lcdata.fileio import file_sha256
from lcdata.importers.episodes import (
    EpisodeFiles,
    ImportedEpisode,
    ImportOptions,
    Progress,
    check_written,
    write_episodes,
)
from lcdata.importers.resample import Frame, resample

log = logging.getLogger(__name__)

FORMAT = "sumo-fcd"
ROOT_TAG = "fcd-export"
PROGRESS_EVERY = 200
"""Timesteps between two progress calls."""


@dataclass(frozen=True, slots=True, kw_only=True)
class SumoOptions:
    """Vehicle size when the FCD file does not say (SUMO's default passenger car: 5.0 x 1.8 m)."""

    vehicle_length_m: float = 5.0
    vehicle_width_m: float = 1.8

    def __post_init__(self) -> None:
        for name in ("vehicle_length_m", "vehicle_width_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")


def _lane_index(lane: str | None) -> int:
    """``edge_2`` -> 2; an internal lane (``:junction_0_0``), a missing or odd id -> -1."""
    if not lane or lane.startswith(":"):
        return -1
    _, _, index = lane.rpartition("_")
    return int(index) if index.isdigit() else -1


class FcdReader:
    """The frames of one FCD file, in file order (:meth:`frames`), and the SUMO ids behind the integers.

    Raises ``ValueError`` naming the file for anything that is not SUMO FCD output: malformed XML, another
    root element, a timestep without a time, a vehicle without ``x``, ``y``, ``angle`` or ``speed``, a
    number that is not one, the same vehicle twice in a timestep.
    """

    def __init__(self, path: pathlib.Path, options: SumoOptions, progress: Progress | None = None) -> None:
        self.path, self.options, self.progress = path, options, progress
        self.ids: dict[str, int] = {}
        self.types: dict[int, str] = {}
        self.sources: dict[int, str] = {}
        self.size = path.stat().st_size
        self.timesteps = 0

    def _error(self, message: str) -> ValueError:
        return ValueError(f"{self.path}: {message}")

    def frames(self) -> Iterator[Frame]:
        if self.size == 0:
            raise self._error("the file is empty")
        prev: Frame | None = None
        with open(self.path, "rb") as raw:
            events = iterparse(raw, events=("start", "end"))
            try:
                _, root = next(events)
                if root.tag != ROOT_TAG:
                    raise self._error(f"not SUMO FCD output: the root element is <{root.tag}>, expected <{ROOT_TAG}>")
                for event, elem in events:
                    if event != "end" or elem.tag != "timestep":
                        continue
                    frame = self._frame(elem, prev)
                    root.clear()  # the timesteps read so far: memory stays flat
                    self.timesteps += 1
                    if self.progress is not None and self.timesteps % PROGRESS_EVERY == 0:
                        self.progress(raw.tell(), self.size)
                    prev = frame
                    yield frame
            except ParseError as exc:
                raise self._error(f"malformed XML ({exc})") from None
        if self.progress is not None:
            self.progress(self.size, self.size)

    def _frame(self, elem: Element, prev: Frame | None) -> Frame:
        time_text = elem.get("time")
        try:
            t = float(time_text)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise self._error(f"timestep {self.timesteps + 1} has no valid time ({time_text!r})") from None
        vehicles = [v for v in elem if v.tag == "vehicle"]
        n = len(vehicles)
        ids = np.empty(n, dtype=np.int64)
        values = np.empty((n, 7))  # x, y, angle, speed, length, width, acceleration (NaN: none)
        lanes = np.empty(n, dtype=np.int64)
        o = self.options
        for i, v in enumerate(vehicles):
            name = v.get("id")
            if name is None:
                raise self._error(f"a vehicle at time {t:g} has no id")
            vid = self.ids.get(name)
            if vid is None:
                vid = self.ids[name] = len(self.ids) + 1
                self.sources[vid] = name
                self.types[vid] = v.get("type", "")
            ids[i] = vid
            try:
                values[i] = (float(v.attrib["x"]), float(v.attrib["y"]), float(v.attrib["angle"]),
                             float(v.attrib["speed"]), float(v.get("length", o.vehicle_length_m)),
                             float(v.get("width", o.vehicle_width_m)), float(v.get("acceleration", "nan")))  # fmt: skip
            except KeyError as exc:
                raise self._error(f"vehicle {name!r} at time {t:g} has no {exc.args[0]!r} attribute") from None
            except ValueError as exc:
                raise self._error(f"vehicle {name!r} at time {t:g}: {exc}") from None
            lanes[i] = _lane_index(v.get("lane"))
        if not np.isfinite(values[:, :6]).all():
            raise self._error(f"a vehicle at time {t:g} has a non-finite position, angle, speed or size")
        order = np.argsort(ids, kind="stable")
        ids, values, lanes = ids[order], values[order], lanes[order]
        if n > 1 and (np.diff(ids) == 0).any():
            dup = self.sources[int(ids[1:][np.diff(ids) == 0][0])]
            raise self._error(f"vehicle {dup!r} appears twice at time {t:g}")
        yaw = np.radians(90.0 - values[:, 2])
        yaw = np.remainder(yaw + math.pi, 2 * math.pi) - math.pi
        half = values[:, 4] / 2
        x = values[:, 0] - half * np.cos(yaw)
        y = values[:, 1] - half * np.sin(yaw)
        speed, accel = values[:, 3], values[:, 6]
        missing = np.isnan(accel)
        if missing.any():
            accel = np.where(missing, 0.0, accel)
            if prev is not None and t > prev.t_s:
                _, i_cur, i_prev = np.intersect1d(ids, prev.ids, assume_unique=True, return_indices=True)
                fill = np.zeros(n)
                fill[i_cur] = (speed[i_cur] - prev.speed[i_prev]) / (t - prev.t_s)
                accel = np.where(missing, fill, accel)
        return Frame(t, ids, x, y, yaw, speed, accel, lanes, values[:, 4], values[:, 5])

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
        written = write_episodes(resample(reader.frames(), options.dt_s), files, stem, meta, options,
                                 reader.vehicle_info)  # fmt: skip
        if not reader.ids:
            raise ValueError(f"{path}: no vehicle in {reader.timesteps} timesteps")
        check_written(path, written, options)
    log.info("%s: %d timesteps, %d vehicles -> %d episodes", path, reader.timesteps, len(reader.ids), len(written))
    return written
