"""Traffic recorded elsewhere, one source sample at a time, onto the corpus's time grid.

An importer turns its source into :class:`Frame` objects (every vehicle seen at one source time, already
in the world frame of docs/INTERFACES.md) and :func:`resample` puts them on the grid ``t0 + k * dt_s``
(``t0``: the first source time), one frame in, a few frames out, so that a file of any length streams
through in constant memory. What it yields is bounded by what it reads (:mod:`lcdata.importers.limits`): the
source times span at most ``max_duration_s``, and the grid steps are at most ``max_steps`` (by default
:data:`~lcdata.importers.limits.STEPS_PER_SAMPLE` per source frame read, and as many vehicle-rows per
vehicle-row read); both are refused with the source position of the frame that would exceed them.

Between two consecutive source frames a vehicle seen in both is interpolated linearly (position, speed,
acceleration; heading along the shorter arc); its lane, length and width are those of the earlier frame
(sample and hold: a lane change shows at the first source sample in the new lane or after it, never
before). A vehicle seen in only one of the two frames exists only at the source time itself: one that
appears or disappears between source samples is not extrapolated, and a vehicle missing from some source
samples has a gap there.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from lcdata.importers.limits import DEFAULT_MAX_DURATION_S, STEPS_PER_SAMPLE

TIME_TOLERANCE_S = 1e-6
"""Two times closer than this are the same instant (source times are printed decimals: 0.1 * 3 != 0.3)."""


@dataclass(frozen=True, slots=True)
class Frame:
    """Every vehicle at one time, world frame (x forward, y left, yaw counter-clockwise from +x).

    All arrays are ``(N,)``, sorted by ``ids`` (unique, >= 1: id 0 is the ego, and recorded traffic has
    none).
    """

    t_s: float
    ids: np.ndarray  # int64
    x: np.ndarray  # float64, m, the vehicle's centre
    y: np.ndarray  # float64, m
    yaw: np.ndarray  # float64, rad
    speed: np.ndarray  # float64, m/s
    accel: np.ndarray  # float64, m/s², along the heading
    lane: np.ndarray  # int64, 0 = rightmost, -1 unknown
    length: np.ndarray  # float64, m
    width: np.ndarray  # float64, m
    where: str = ""
    """Where in the source the frame was read (``FILE: line 12``), for messages."""

    def __post_init__(self) -> None:
        n = len(self.ids)
        for name in ("x", "y", "yaw", "speed", "accel", "lane", "length", "width"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"Frame.{name} has {len(getattr(self, name))} values for {n} vehicles")

    @classmethod
    def empty(cls, t_s: float, where: str = "") -> Frame:
        f, i = np.zeros(0), np.zeros(0, dtype=np.int64)
        return cls(t_s, i, f, f, f, f, f, i, f, f, where)

    def take(self, index: np.ndarray, t_s: float | None = None) -> Frame:
        """The vehicles at ``index`` (into the arrays), at ``t_s`` (default: this frame's time)."""
        return Frame(self.t_s if t_s is None else t_s, self.ids[index], self.x[index], self.y[index],
                     self.yaw[index], self.speed[index], self.accel[index], self.lane[index],
                     self.length[index], self.width[index], self.where)  # fmt: skip


def interpolate(a: Frame, b: Frame, t_s: float) -> Frame:
    """The vehicles seen in both ``a`` and ``b`` at ``a.t_s <= t_s < b.t_s`` (see the module docstring)."""
    common, ia, ib = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
    w = (t_s - a.t_s) / (b.t_s - a.t_s)

    def mix(name: str) -> np.ndarray:
        u, v = getattr(a, name)[ia], getattr(b, name)[ib]
        return u + w * (v - u)

    yaw_a = a.yaw[ia]
    turn = np.remainder(b.yaw[ib] - yaw_a + math.pi, 2 * math.pi) - math.pi
    yaw = np.remainder(yaw_a + w * turn + math.pi, 2 * math.pi) - math.pi
    return Frame(t_s, common, mix("x"), mix("y"), yaw, mix("speed"), mix("accel"), a.lane[ia], a.length[ia],
                 a.width[ia], a.where)  # fmt: skip


def resample(frames: Iterable[Frame], dt_s: float, *, max_duration_s: float = DEFAULT_MAX_DURATION_S,
             max_steps: int | None = None) -> Iterator[tuple[int, Frame]]:  # fmt: skip
    """``(k, frame at t0 + k * dt_s)`` for every grid time from the first source time to the last.

    Grid times between two source frames are interpolated (:func:`interpolate`); one that falls on a
    source time (within :data:`TIME_TOLERANCE_S`) is that frame as it is. Grid frames may be empty.

    Raises:
        ValueError: source times that do not increase; a source time more than ``max_duration_s`` after the
            first; a frame that would take the grid past ``max_steps`` steps (None: past
            :data:`~lcdata.importers.limits.STEPS_PER_SAMPLE` steps per source frame read so far, or as many
            vehicle-rows per vehicle-row read). Each names the source frame (:attr:`Frame.where`), and is raised
            before any grid step it would need is yielded.
    """
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    prev: Frame | None = None
    t0, k = 0.0, 0
    samples = rows_in = rows_out = 0
    for cur in frames:
        samples += 1
        rows_in += len(cur.ids)
        if prev is None:
            t0, prev = cur.t_s, cur
            continue
        if not cur.t_s > prev.t_s + TIME_TOLERANCE_S:
            raise ValueError(f"{_at(cur)}source time does not increase: {cur.t_s:g} s after {prev.t_s:g} s")
        if cur.t_s - t0 > max_duration_s:
            raise ValueError(f"{_at(cur)}time {cur.t_s:g} s is {cur.t_s - t0:g} s after the first ({t0:g} s), more "
                             f"than an import may span ({max_duration_s:g} s; --max-duration raises it)")  # fmt: skip
        end = math.ceil((cur.t_s - TIME_TOLERANCE_S - t0) / dt_s)  # the grid steps before cur: k .. end - 1
        budget = max_steps if max_steps is not None else STEPS_PER_SAMPLE * samples
        if end > budget:
            raise ValueError(f"{_at(cur)}time {cur.t_s:g} s is {end} steps of {dt_s:g} s after the first; an import "
                             f"of {samples} source samples writes at most {budget} steps"
                             + (" (--max-steps raises it)" if max_steps is None else " (--max-steps)"))  # fmt: skip
        if max_steps is None and end > k:
            # the first grid step holds prev's vehicles, the others those of prev and cur (at most the fewer)
            rows_out += len(prev.ids) + (end - k - 1) * min(len(prev.ids), len(cur.ids))
            if rows_out > STEPS_PER_SAMPLE * rows_in:
                raise ValueError(f"{_at(cur)}interpolating up to time {cur.t_s:g} s would write more than "
                                 f"{STEPS_PER_SAMPLE} vehicle-steps per vehicle-step read ({rows_in}); --max-steps "
                                 "lifts the limit")  # fmt: skip
        while (t := t0 + k * dt_s) < cur.t_s - TIME_TOLERANCE_S:
            if t <= prev.t_s + TIME_TOLERANCE_S:
                yield k, prev.take(slice(None), t)
            else:
                yield k, interpolate(prev, cur, t)
            k += 1
        prev = cur
    if prev is not None and abs(t0 + k * dt_s - prev.t_s) <= TIME_TOLERANCE_S:
        yield k, prev.take(slice(None), t0 + k * dt_s)


def _at(frame: Frame) -> str:
    return f"{frame.where}: " if frame.where else ""
