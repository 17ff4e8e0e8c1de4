"""What an import believes of its source, and how much it may write for it.

A recording from elsewhere is untrusted input: a value that is not finite or not plausible for what it names
(a time, a position, a speed, an acceleration, a size, a lane, an id) is refused with the file, the line or
data row and the field, never written; and what an import writes is bounded relative to what it reads, so
that neither a gap in the source nor a small ``--dt`` turns a small file into a full disk:

- the source times span at most :attr:`~lcdata.importers.episodes.ImportOptions.max_duration_s`
  (:data:`DEFAULT_MAX_DURATION_S`, a day; ``lc-import --max-duration``);
- the grid steps written, all episodes together, are at most
  :attr:`~lcdata.importers.episodes.ImportOptions.max_steps` (``lc-import --max-steps``); by default
  :data:`STEPS_PER_SAMPLE` for each source sample (timestep, video frame) read so far, and at most
  :data:`STEPS_PER_SAMPLE` vehicle-rows for each vehicle-row read: what is written is at most about that
  many times what is read, files included (a file holds ``episode_steps`` steps).

The bounds below are those of road traffic, wide enough for any real recording.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lcdata.recorded import MAX_LANES

MAX_ABS_TIME_S = 1e9
"""A source time is at most this far from 0 (about 31 years): the grid keeps microsecond resolution, and every
episode's start time (2024-01-01 plus its source time) stays a valid MCAP time."""
DEFAULT_MAX_DURATION_S = 86_400.0
"""The source time an import may span unless told otherwise (``--max-duration``): a day."""
MIN_DT_S, MAX_DT_S = 0.001, 1.0
"""The step of the written episodes: 1 kHz to 1 Hz (the simulator's own step is at most 1 s)."""
STEPS_PER_SAMPLE = 1000
"""Grid steps an import may write per source sample read (and vehicle-rows per vehicle-row read) unless
``--max-steps`` says otherwise: a source at 1 Hz resampled at 1 kHz."""
MAX_VEHICLES_PER_SAMPLE = 200_000
"""The most vehicles one source sample (a SUMO timestep) may hold: each is kept until its sample is read."""
MAX_VEHICLE_ID = 2**31 - 1
"""The largest source vehicle id (highD's are small integers; 0 is the ego's)."""
MAX_LANE_INDEX = MAX_LANES - 1
"""Lanes of a carriageway are 0 to this (:data:`lcdata.recorded.MAX_LANES` lanes)."""


@dataclass(frozen=True, slots=True)
class Bound:
    """The plausible values of one field: finite, in ``[low, high]`` (``low`` excluded when ``low_open``), an
    integer when ``integer``."""

    what: str
    """What the field holds, plural, for messages (``speeds``, ``vehicle lengths``)."""
    low: float
    high: float
    unit: str = ""
    low_open: bool = False
    integer: bool = False

    def _ok(self, values: np.ndarray) -> np.ndarray:
        v = np.asarray(values, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(v) & (v <= self.high) & ((v > self.low) if self.low_open else (v >= self.low))
            if self.integer:
                ok &= v == np.round(v)
        return ok

    def first_bad(self, values: np.ndarray) -> int | None:
        """The index of the first value out of bounds, or None."""
        bad = np.flatnonzero(~self._ok(values))
        return int(bad[0]) if len(bad) else None

    def problem(self, value: float) -> str:
        """Why ``value`` is refused (``""`` when it is not)."""
        if self._ok(np.array([value]))[0]:
            return ""
        if not math.isfinite(value):
            return "is not a finite number"
        if self.integer and value != round(value):
            return "is not a whole number"
        lo, unit = "(" if self.low_open else "[", f" {self.unit}" if self.unit else ""
        return f"is outside {lo}{shown(self.low)}, {shown(self.high)}]{unit}, the {self.what} an import accepts"


def shown(x: float) -> str:
    """A number for a message: an integer with thousands separators, else ``%g``."""
    return f"{int(x):,}" if float(x).is_integer() and abs(x) < 1e16 else f"{x:g}"


TIME = Bound("times", -MAX_ABS_TIME_S, MAX_ABS_TIME_S, "s")
POSITION = Bound("positions", -1e7, 1e7, "m")
SPEED = Bound("speeds", 0.0, 150.0, "m/s")
VELOCITY = Bound("velocity components", -150.0, 150.0, "m/s")
ACCELERATION = Bound("accelerations", -1000.0, 1000.0, "m/s^2")
"""About 100 g: a collision stop in a SUMO step of 0.04 s, and nothing a vehicle does otherwise."""
LENGTH = Bound("vehicle lengths", 0.0, 200.0, "m", low_open=True)
WIDTH = Bound("vehicle widths", 0.0, 10.0, "m", low_open=True)
HEADING = Bound("headings", -3600.0, 3600.0, "degrees")
LANE = Bound("lane indices", 0, MAX_LANE_INDEX, integer=True)
LANE_ID = Bound("lane ids", 0, 10_000, integer=True)
VEHICLE_ID = Bound("vehicle ids", 1, MAX_VEHICLE_ID, integer=True)
FRAME = Bound("frame numbers", 0, 2**53, integer=True)
