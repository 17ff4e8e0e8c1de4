"""The MCAP message records of a batch of simulation steps, written with one compiled call.

Every simulation step gives two messages, ``/vehicles`` (``lc.VehicleTracks``) and ``/ego/state``
(``lc.EgoState``). Encoding them one Python call at a time cost tens of microseconds per step; here
:class:`SimStepEncoder` lays out the K steps of a batch, message record headers included, in one
buffer, with a compiled function for everything but the vehicle columns. The bytes are those of
:class:`lcdata.encode.VehicleEncoder`, :func:`lcdata.encode.vehicle_head`, :func:`lcdata.encode.encode_ego`
and :func:`lcdata.mcap_write.message_header` (tested against them).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from lcdata import mcap_write
from lcdata.encode import VEHICLE_COLUMNS, VehicleEncoder

# The MCAP message record's header size (opcode, length, channel, sequence, log and publish times), written out here:
# compiled functions keep module constants in numba's cache, which only this file's changes invalidate.
MESSAGE_HEADER_BYTES = 31
assert MESSAGE_HEADER_BYTES == mcap_write.MESSAGE_HEADER_BYTES

EGO_MAX_BYTES = 11 + 9 + 9 + 3 * 11 + 2 + 27
"""Upper bound of an ``lc.EgoState`` message (step varint, t, speed, three sint varints, off_road, controls)."""
HEAD_MAX_BYTES = 11 + 9
"""Upper bound of the ``step`` and ``t`` fields that start an ``lc.VehicleTracks`` message."""


@njit(cache=True)
def _varint(out: np.ndarray, p: int, value: np.uint64) -> int:
    while value >= 0x80:
        out[p] = (value & 0x7F) | 0x80
        value >>= np.uint64(7)
        p += 1
    out[p] = value
    return p + 1


@njit(cache=True)
def _u64(out: np.ndarray, p: int, value: np.uint64, size: int) -> int:
    for i in range(size):
        out[p + i] = (value >> np.uint64(8 * i)) & 0xFF
    return p + size


@njit(cache=True)
def _double(out: np.ndarray, p: int, key: int, value: float, scratch: np.ndarray) -> int:
    out[p] = key
    scratch[0] = value
    return _u64(out, p + 1, scratch.view(np.uint64)[0], 8)


@njit(cache=True)
def _step_field(out: np.ndarray, p: int, step: int) -> int:
    """``int64 step = 1``, omitted when 0 (a negative step as its 64-bit two's complement)."""
    if step == 0:
        return p
    out[p] = 0x08
    return _varint(out, p + 1, np.uint64(step))


@njit(cache=True)
def _sint_field(out: np.ndarray, p: int, key: int, value: int) -> int:
    """A ``sint64`` field (zigzag varint), omitted when 0."""
    if value == 0:
        return p
    out[p] = key
    return _varint(out, p + 1, np.uint64((value << 1) ^ (value >> 63)))


@njit(cache=True)
def _header(out: np.ndarray, p: int, channel: int, time_ns: int, data_size: int) -> int:
    """A message record header: opcode 5, record length, channel, sequence 0, log time = publish time."""
    out[p] = 0x05
    p = _u64(out, p + 1, np.uint64(22 + data_size), 8)
    p = _u64(out, p, np.uint64(channel), 2)
    p = _u64(out, p, np.uint64(0), 4)
    p = _u64(out, p, np.uint64(time_ns), 8)
    return _u64(out, p, np.uint64(time_ns), 8)


@njit(cache=True)
def _step_records(slots: np.ndarray, k: int, body_at: int, body_bytes: int, spans: np.ndarray, times: np.ndarray,
                  sizes: np.ndarray, steps: np.ndarray, ts: np.ndarray, ego: np.ndarray, origin_ns: int,
                  vehicles_id: int, ego_id: int) -> None:  # fmt: skip
    """Complete the records of K steps around their vehicle fields, already in ``slots[i, body_at:]``.

    Row i of ``slots`` (uint8) gets the ``/vehicles`` record header and message head just before its
    vehicle fields and the ``/ego/state`` record right after them; ``spans[i]`` is where the two
    records of step i start and end, ``times`` and ``sizes`` (2 K,) their log times and sizes.
    ``ego``: (K, 8) float64 speed, lane, collision_with, lane_invasion, off_road, steer, throttle,
    brake (the integers truncated toward zero, off_road true when nonzero).
    """
    scratch = np.empty(1, dtype=np.float64)
    message = np.empty(EGO_MAX_BYTES, dtype=np.uint8)
    for i in range(k):
        row = slots[i]
        step, t = steps[i], ts[i]
        time_ns = origin_ns + np.int64(np.rint(t * 1e9))
        m = _step_field(message, 0, step)
        m = _double(message, m, 0x11, t, scratch)
        start = body_at - m - MESSAGE_HEADER_BYTES
        p = _header(row, start, vehicles_id, time_ns, m + body_bytes)
        row[p : p + m] = message[:m]
        p = body_at + body_bytes
        times[2 * i], sizes[2 * i] = time_ns, p - start
        e = ego[i]
        m = _step_field(message, 0, step)
        m = _double(message, m, 0x11, t, scratch)
        m = _double(message, m, 0x19, e[0], scratch)
        m = _sint_field(message, m, 0x20, np.int64(e[1]))
        m = _sint_field(message, m, 0x28, np.int64(e[2]))
        m = _sint_field(message, m, 0x30, np.int64(e[3]))
        if e[4] != 0.0:
            message[m], message[m + 1] = 0x38, 0x01
            m += 2
        m = _double(message, m, 0x41, e[5], scratch)
        m = _double(message, m, 0x49, e[6], scratch)
        m = _double(message, m, 0x51, e[7], scratch)
        q = _header(row, p, ego_id, time_ns, m)
        row[q : q + m] = message[:m]
        times[2 * i + 1], sizes[2 * i + 1] = time_ns, q + m - p
        spans[i, 0], spans[i, 1] = i * row.size + start, i * row.size + q + m


class SimStepEncoder:
    """The ``/vehicles`` and ``/ego/state`` records of batches of simulation steps (one per writer).

    Rows of a buffer kept between calls hold one step each: the vehicle fields at a fixed place (their
    key and length prefixes written once per vehicle count, the values by one cast-and-copy per column
    into a strided view), the rest written around them by a compiled function.
    """

    def __init__(self) -> None:
        self._vehicles = VehicleEncoder()
        self._slots = np.zeros((0, 0), dtype=np.uint8)
        self._views: list[np.ndarray] = []
        self._n = -1

    def _layout(self, k: int, n: int) -> None:
        vehicles = self._vehicles
        vehicles.bodies(0, *([np.zeros(n)] * len(VEHICLE_COLUMNS)))  # lays out the fields for N
        template = vehicles._template
        rows = max(k, 16, len(self._slots) if n == self._n else 0)
        self._slots = np.zeros((rows, _BODY_AT + template.size + MESSAGE_HEADER_BYTES + EGO_MAX_BYTES), np.uint8)
        self._slots[:, _BODY_AT : _BODY_AT + template.size] = template
        self._views = [self._slots[:, _BODY_AT + offset : _BODY_AT + offset + size].view(dtype)
                       for offset, size, dtype in vehicles._fields]  # fmt: skip
        self._n = n

    def encode(self, steps: np.ndarray, ts: np.ndarray, ego: np.ndarray, columns: Sequence[np.ndarray],
               origin_ns: int, vehicles_id: int, ego_id: int) -> tuple[bytes, np.ndarray, np.ndarray]:  # fmt: skip
        """The 2 K records of K steps, in order (``/vehicles`` then ``/ego/state`` of each step).

        Args:
            steps: (K,) int64. ts: (K,) float64, seconds. ego: (K, 8) float64 (see :func:`_step_records`).
            columns: :data:`~lcdata.encode.VEHICLE_COLUMNS`, each (K, N) or (N,), any numeric dtype.
            origin_ns: the time of ``t = 0``. vehicles_id, ego_id: the channels.

        Returns:
            ``(records, log_times, sizes)``: the bytes, and (2 K,) int64 per record.
        """
        if len(columns) != len(VEHICLE_COLUMNS):
            names = ", ".join(VEHICLE_COLUMNS)
            raise ValueError(f"expected {len(VEHICLE_COLUMNS)} columns ({names}), got {len(columns)}")
        k, n = len(steps), np.shape(columns[0])[-1]
        if n != self._n or k > len(self._slots):
            self._layout(k, n)
        whole = k == len(self._slots)
        for view, column in zip(self._views, columns, strict=False):  # no views when N = 0
            (view if whole else view[:k])[...] = column
        spans = np.empty((k, 2), dtype=np.int64)
        times, sizes = np.empty(2 * k, dtype=np.int64), np.empty(2 * k, dtype=np.int64)
        body_bytes = self._vehicles._template.size
        _step_records(self._slots, k, _BODY_AT, body_bytes, spans, times, sizes, steps, ts, ego, origin_ns,
                      vehicles_id, ego_id)  # fmt: skip
        flat = memoryview(self._slots.reshape(-1))
        return b"".join([flat[a:b] for a, b in spans.tolist()]), times, sizes


_BODY_AT = MESSAGE_HEADER_BYTES + HEAD_MAX_BYTES
"""Where the vehicle fields start in a row of :class:`SimStepEncoder`'s buffer."""
