"""The MCAP message records of a batch of simulation steps, written with one compiled call.

Every simulation step gives two messages, ``/vehicles`` (``lc.VehicleTracks``) and ``/ego/state``
(``lc.EgoState``). Encoding them one Python call at a time cost tens of microseconds per step; here
:class:`SimStepEncoder` lays out the K steps of a batch, message record headers included, in one
buffer, with a compiled function for everything but the vehicle columns. The bytes are those of
:class:`lcdata.encode.VehicleEncoder`, :func:`lcdata.encode.vehicle_head`, :func:`lcdata.encode.encode_ego`
and :func:`lcdata.mcap_write.message_header` (tested against them).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit

from lcdata import mcap_write
from lcdata.encode import VEHICLE_COLUMNS, VehicleEncoder
from lcsim import kernel

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
    src, dst = scratch.view(np.uint8), out[p + 1 : p + 9]
    for i in range(8):
        dst[i] = src[i]
    return p + 9


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


# -- a whole decision, straight into the chunk buffer ------------------------------------------------------------------
# The records a recorder writes for one decision (lcdata.writer.EpisodeSink.write_decision), laid out by one compiled
# call in the MCAP writer's chunk buffer: /tf, /scene, the image, /vehicles and /ego/state of every step, /rl/step.
# The bytes are those of the Python encoders (lcdata.encode) and of McapStreamWriter.add_message (tested against them).
# Values that need numpy's or the math module's own functions (the cubes' and the transform's quaternions) come in
# computed, so that the bits are theirs.

# The step log's layout (lcsim.kernel), written out: compiled functions keep module constants in numba's cache.
(LOG_STEP, LOG_T, LOG_SPEED, LOG_LANE, LOG_COLLISION, LOG_INVASION, LOG_OFF_ROAD, LOG_STEER, LOG_THROTTLE, LOG_BRAKE,
 LOG_LC_ACTIVE) = range(11)
LOG_HEAD = 11
assert (LOG_HEAD, LOG_OFF_ROAD, LOG_LC_ACTIVE, LOG_BRAKE) == (kernel.LOG_HEAD, kernel.LOG_OFF_ROAD,
                                                             kernel.LOG_LC_ACTIVE, kernel.LOG_BRAKE)  # fmt: skip
assert kernel.LOG_VEHICLE_ROWS == ("x", "y", "yaw", "speed", "accel", "lane", "target_lane")

RL_FIELDS = ("decision", "action", "mask_right", "mask_keep", "mask_left", "reward", "r_collision", "r_off_road",
             "r_forward", "r_success", "terminated", "truncated", "outcome")
"""The values of ``/rl/step`` :func:`decision_records` takes as one float64 array (``outcome``: its index in
:data:`lcdata.writer.OUTCOMES`)."""
RL_DECISION, RL_ACTION, RL_MASK, RL_REWARD, RL_TERMINATED, RL_TRUNCATED, RL_OUTCOME = 0, 1, 2, 5, 10, 11, 12
assert RL_FIELDS[RL_REWARD] == "reward" and RL_FIELDS[RL_OUTCOME] == "outcome" and len(RL_FIELDS) == 13

SPANS = ("tf_head", "tf_rotation", "vehicles_entity", "lanes_entity", "lanes", "cubes", "image_head", "image_tail",
         "px", "py", "qz", "qw", "sx", "sy")
"""The constant byte strings of :func:`decision_records` (the cube fields: their offsets in a cube record), then one
``/rl/step`` outcome field per outcome."""
(S_TF_HEAD, S_TF_ROTATION, S_VEHICLES_ENTITY, S_LANES_ENTITY, S_LANES, S_CUBES, S_IMAGE_HEAD, S_IMAGE_TAIL,
 S_CUBE_FIELDS) = range(9)
S_OUTCOMES = len(SPANS)
assert SPANS[S_CUBE_FIELDS] == "px" and SPANS[S_IMAGE_TAIL] == "image_tail"


@njit(cache=True)
def _put(out: np.ndarray, p: int, value: float, scratch: np.ndarray) -> None:
    """The 8 bytes of a double at ``out[p:]``."""
    scratch[0] = value
    src, dst = scratch.view(np.uint8), out[p : p + 8]
    for i in range(8):
        dst[i] = src[i]


@njit(cache=True)
def _varint_size(value: np.uint64) -> int:
    size = 1
    while value >= 0x80:
        value >>= np.uint64(7)
        size += 1
    return size


@njit(cache=True)
def _stamp(out: np.ndarray, p: int, time_ns: int) -> int:
    """``google.protobuf.Timestamp`` as field 1 (:func:`lcdata.encode.encode_timestamp`), ``time_ns >= 0``."""
    seconds, nanos = np.uint64(time_ns // 1_000_000_000), np.uint64(time_ns % 1_000_000_000)
    size = (1 + _varint_size(seconds) if seconds else 0) + (1 + _varint_size(nanos) if nanos else 0)
    out[p], out[p + 1] = 0x0A, size
    p += 2
    if seconds:
        out[p] = 0x08
        p = _varint(out, p + 1, seconds)
    if nanos:
        out[p] = 0x10
        p = _varint(out, p + 1, nanos)
    return p


@njit(cache=True)
def copy_into(out: np.ndarray, p: int, src: np.ndarray) -> int:
    """Copy ``src`` (N,) (any layout, cast to ``out``'s dtype) to ``out[p:]``; returns the position after it."""
    # (a loop over a slice: a memcpy once compiled; numba's slice assignment from an array checks for overlap and
    # copies first, and indexing out[p + i] checks for negative indices, which keeps the loop from being vectorised)
    dst = out[p : p + src.size]
    for i in range(src.size):
        dst[i] = src[i]
    return p + src.size


@njit(cache=True)
def _packed_key(out: np.ndarray, p: int, key: int, size: int) -> int:
    out[p] = key
    return _varint(out, p + 1, np.uint64(size))


@njit(cache=True)
def _open(index: np.ndarray, m: int, channel: int, time_ns: int, start: int) -> int:
    """Enter a message record starting at ``start`` in the chunk's index (its header is written by _close)."""
    index[0, m], index[1, m], index[2, m] = channel, time_ns, start
    return m + 1


@njit(cache=True)
def _close(out: np.ndarray, start: int, end: int, channel: int, time_ns: int) -> int:
    _header(out, start, channel, time_ns, end - start - MESSAGE_HEADER_BYTES)
    return end


@njit(cache=True)
def _nonzero_double(value: float) -> bool:
    """Whether proto3 writes a ``double`` (it omits +0.0 only)."""
    return value != 0.0 or math.copysign(1.0, value) < 0.0


@njit(cache=True)
def log_event_row(log: np.ndarray, off_road: bool, lc_active: bool) -> int:
    """The first row of a step log (K, W) where the ego meets an event (a collision, a lane invasion, leaving or
    regaining the road, a lane change starting or ending; ``off_road``, ``lc_active``: its state before the first
    row), or -1."""
    for i in range(log.shape[0]):
        row = log[i]
        off, active = row[LOG_OFF_ROAD] != 0.0, row[LOG_LC_ACTIVE] != 0.0
        if row[LOG_COLLISION] >= 0.0 or row[LOG_INVASION] >= 0.0 or off != off_road or active != lc_active:
            return i
        off_road, lc_active = off, active
    return -1


@njit(cache=True)
def _log_records(out: np.ndarray, p: int, index: np.ndarray, m: int, log: np.ndarray, ids: np.ndarray,
                 length: np.ndarray, width: np.ndarray, origin_ns: int, vehicles_id: int,
                 ego_id: int) -> tuple[int, int]:  # fmt: skip
    """The ``/vehicles`` and ``/ego/state`` records of the steps of a log (K, W); returns the new (p, m)."""
    n = ids.size
    ids32 = np.empty(n, dtype=np.int32)
    lanes32 = np.empty(n, dtype=np.int32)
    for v in range(n):
        ids32[v] = np.int32(ids[v])
    ids_b, length_b, width_b = ids32.view(np.uint8), length.view(np.uint8), width.view(np.uint8)
    lanes_b = lanes32.view(np.uint8)
    scratch = np.empty(1, dtype=np.float64)
    for i in range(log.shape[0]):
        row = log[i]
        row_b = row.view(np.uint8)
        step, t = np.int64(row[LOG_STEP]), row[LOG_T]
        time_ns = origin_ns + np.int64(np.rint(t * 1e9))
        start = p
        m = _open(index, m, vehicles_id, time_ns, start)
        p = _step_field(out, p + MESSAGE_HEADER_BYTES, step)
        p = _double(out, p, 0x11, t, scratch)
        if n:
            p = _packed_key(out, p, 0x1A, 4 * n)
            p = copy_into(out, p, ids_b)
            for j in range(5):  # x, y, yaw, speed, accel: fields 4 .. 8
                at = 8 * (LOG_HEAD + j * n)
                p = _packed_key(out, p, 0x22 + 8 * j, 8 * n)
                p = copy_into(out, p, row_b[at : at + 8 * n])
            for j in range(5, 7):  # lane, target_lane: fields 9, 10 as int32
                lanes = row[LOG_HEAD + j * n : LOG_HEAD + (j + 1) * n]
                for v in range(n):
                    lanes32[v] = np.int32(lanes[v])
                p = _packed_key(out, p, 0x22 + 8 * j, 4 * n)
                p = copy_into(out, p, lanes_b)
            p = _packed_key(out, p, 0x5A, 8 * n)
            p = copy_into(out, p, length_b)
            p = _packed_key(out, p, 0x62, 8 * n)
            p = copy_into(out, p, width_b)
        p = _close(out, start, p, vehicles_id, time_ns)
        start = p
        m = _open(index, m, ego_id, time_ns, start)
        p = _step_field(out, p + MESSAGE_HEADER_BYTES, step)
        p = _double(out, p, 0x11, t, scratch)
        p = _double(out, p, 0x19, row[LOG_SPEED], scratch)
        p = _sint_field(out, p, 0x20, np.int64(row[LOG_LANE]))
        p = _sint_field(out, p, 0x28, np.int64(row[LOG_COLLISION]))
        p = _sint_field(out, p, 0x30, np.int64(row[LOG_INVASION]))
        if row[LOG_OFF_ROAD] != 0.0:
            out[p], out[p + 1] = 0x38, 0x01
            p += 2
        p = _double(out, p, 0x41, row[LOG_STEER], scratch)
        p = _double(out, p, 0x49, row[LOG_THROTTLE], scratch)
        p = _double(out, p, 0x51, row[LOG_BRAKE], scratch)
        p = _close(out, start, p, ego_id, time_ns)
    return p, m


@njit(cache=True)
def log_records(out: np.ndarray, p: int, index: np.ndarray, m: int, log: np.ndarray, ids: np.ndarray,
                length: np.ndarray, width: np.ndarray, origin_ns: int, vehicles_id: int,
                ego_id: int) -> tuple[int, int]:  # fmt: skip
    """The ``/vehicles`` and ``/ego/state`` records of every step of a step log (K, W) written into ``out`` from
    ``p`` on, entered in ``index`` from column ``m`` on (see :meth:`lcdata.mcap_write.McapStreamWriter.records_target`);
    returns the new ``(p, m)``. ``ids`` (N,) int64, ``length``, ``width`` (N,) float64, all contiguous."""
    return _log_records(out, p, index, m, log, ids, length, width, origin_ns, vehicles_id, ego_id)


@njit(cache=True)
def decision_records(out: np.ndarray, p: int, index: np.ndarray, m: int, channels: np.ndarray, consts: np.ndarray,
                     spans: np.ndarray, time_ns: int, origin_ns: int, step: int, t: float, pose: np.ndarray,
                     ids: np.ndarray, length: np.ndarray, width: np.ndarray, x: float, y: float, qz: float, qw: float,
                     quaternions: np.ndarray, image: np.ndarray, log: np.ndarray, off_road: bool, lc_active: bool,
                     rl: np.ndarray, current: np.ndarray) -> tuple[int, int, int]:  # fmt: skip
    """The records of one decision (see the comment above) up to the first step of ``log`` where the ego meets an
    event (:func:`log_event_row`). Returns ``(p, m, row)``: where the records end, the index's length, and that
    step's row in ``log`` (its events, and the rest of the decision, are the caller's: call again with the rest of
    the log, no view) or -1 when the decision is complete.

    ``channels``: ids of /tf, /scene, the image, /vehicles, /ego/state, /rl/step. ``consts`` and ``spans``: the
    constant byte strings (:data:`SPANS`) and their (start, end) in ``consts``. ``pose`` (3, N) x, y, yaw, or
    (0, N) without /tf and /scene; ``x``, ``y``, ``qz``, ``qw``: the ego's position and the sine and cosine (the
    math module's) of half its heading; ``quaternions`` (2, N): numpy's sine and cosine of yaw / 2. ``image``
    (C, H, W), or empty without one. ``rl``: :data:`RL_FIELDS`, or empty without ``/rl/step``; ``current``: the
    observation matrix (stored as float32).
    """
    event = log_event_row(log, off_road, lc_active)
    if event >= 0:
        log = log[: event + 1]
    scratch = np.empty(1, dtype=np.float64)
    n = ids.size
    if pose.shape[0]:
        tf_id, scene_id = channels[0], channels[1]
        start = p
        m = _open(index, m, tf_id, time_ns, start)
        p = _stamp(out, p + MESSAGE_HEADER_BYTES, time_ns)
        p = copy_into(out, p, consts[spans[S_TF_HEAD, 0] : spans[S_TF_HEAD, 1]])
        p = _double(out, p, 0x09, x, scratch)
        p = _double(out, p, 0x11, y, scratch)
        p = _double(out, p, 0x19, 0.0, scratch)
        p = copy_into(out, p, consts[spans[S_TF_ROTATION, 0] : spans[S_TF_ROTATION, 1]])
        p = _double(out, p, 0x09, 0.0, scratch)
        p = _double(out, p, 0x11, 0.0, scratch)
        p = _double(out, p, 0x19, qz, scratch)
        p = _double(out, p, 0x21, qw, scratch)
        p = _close(out, start, p, tf_id, time_ns)
        start = p
        m = _open(index, m, scene_id, time_ns, start)
        p += MESSAGE_HEADER_BYTES
        cubes = consts[spans[S_CUBES, 0] : spans[S_CUBES, 1]]
        record = cubes.size // n if n else 0
        stamp_size = _stamp_size(time_ns)
        for entity in range(2):
            head_at = S_VEHICLES_ENTITY if entity == 0 else S_LANES_ENTITY
            head = consts[spans[head_at, 0] : spans[head_at, 1]]
            body = cubes.size if entity == 0 else spans[S_LANES, 1] - spans[S_LANES, 0]
            if entity == 1 and body == 0:
                break
            p = _packed_key(out, p, 0x12, stamp_size + head.size + body)
            p = _stamp(out, p, time_ns)
            p = copy_into(out, p, head)
            if entity == 1:
                p = copy_into(out, p, consts[spans[S_LANES, 0] : spans[S_LANES, 1]])
                break
            p = copy_into(out, p, cubes)
            base = p - cubes.size
            fields = spans[S_CUBE_FIELDS : S_CUBE_FIELDS + 6, 0]  # px, py, qz, qw, sx, sy in a cube record
            for v in range(n):
                at = base + v * record
                _put(out, at + fields[0], pose[0, v], scratch)
                _put(out, at + fields[1], pose[1, v], scratch)
                _put(out, at + fields[2], quaternions[0, v], scratch)
                _put(out, at + fields[3], quaternions[1, v], scratch)
                _put(out, at + fields[4], length[v], scratch)
                _put(out, at + fields[5], width[v], scratch)
        p = _close(out, start, p, scene_id, time_ns)
    if image.size:
        image_id = channels[2]
        start = p
        m = _open(index, m, image_id, time_ns, start)
        p = _stamp(out, p + MESSAGE_HEADER_BYTES, time_ns)
        p = copy_into(out, p, consts[spans[S_IMAGE_HEAD, 0] : spans[S_IMAGE_HEAD, 1]])
        c, h, w = image.shape
        hw = h * w
        pixels, planes = out[p : p + c * hw], image.ravel()  # (C, H, W) -> (H, W, C)
        if c == 3:  # (the loop the compiler vectorises)
            for i in range(hw):
                pixels[3 * i], pixels[3 * i + 1], pixels[3 * i + 2] = planes[i], planes[hw + i], planes[2 * hw + i]
        else:
            for i in range(hw):
                for k in range(c):
                    pixels[c * i + k] = planes[k * hw + i]
        p += c * hw
        p = copy_into(out, p, consts[spans[S_IMAGE_TAIL, 0] : spans[S_IMAGE_TAIL, 1]])
        p = _close(out, start, p, image_id, time_ns)
    p, m = _log_records(out, p, index, m, log, ids, length, width, origin_ns, channels[3], channels[4])
    if event >= 0:
        return p, m, event
    if rl.size:
        rl_id = channels[5]
        start = p
        m = _open(index, m, rl_id, time_ns, start)
        p += MESSAGE_HEADER_BYTES
        if step:
            out[p] = 0x08
            p = _varint(out, p + 1, np.uint64(step))
        for i in range(6):  # t, then decision, action and the mask, then reward and its components
            value = t if i == 0 else rl[RL_REWARD + i - 1]
            if i == 1:
                decision, action = np.int64(rl[RL_DECISION]), np.int64(rl[RL_ACTION])
                if decision:
                    out[p] = 0x18
                    p = _varint(out, p + 1, np.uint64(decision))
                if action:
                    out[p] = 0x20
                    p = _varint(out, p + 1, np.uint64(action))
                out[p], out[p + 1] = 0x2A, 3
                for j in range(3):
                    out[p + 2 + j] = rl[RL_MASK + j] != 0.0
                p += 5
            if _nonzero_double(value):
                p = _double(out, p, 0x11 if i == 0 else 0x29 + 8 * i, value, scratch)
        if rl[RL_TERMINATED] != 0.0:
            out[p], out[p + 1] = 0x58, 0x01
            p += 2
        if rl[RL_TRUNCATED] != 0.0:
            out[p], out[p + 1] = 0x60, 0x01
            p += 2
        outcome = S_OUTCOMES + np.int64(rl[RL_OUTCOME])
        p = copy_into(out, p, consts[spans[outcome, 0] : spans[outcome, 1]])
        if current.size:
            values = np.empty(current.size, dtype=np.float32)
            for i in range(current.shape[0]):
                for j in range(current.shape[1]):
                    values[i * current.shape[1] + j] = np.float32(current[i, j])
            p = _packed_key(out, p, 0x72, 4 * values.size)
            p = copy_into(out, p, values.view(np.uint8))
        if current.ndim:
            size = 0
            for d in current.shape:
                size += _varint_size(np.uint64(d))
            p = _packed_key(out, p, 0x7A, size)
            for d in current.shape:
                p = _varint(out, p, np.uint64(d))
        p = _close(out, start, p, rl_id, time_ns)
    return p, m, -1


@njit(cache=True)
def _stamp_size(time_ns: int) -> int:
    seconds, nanos = np.uint64(time_ns // 1_000_000_000), np.uint64(time_ns % 1_000_000_000)
    return 2 + (1 + _varint_size(seconds) if seconds else 0) + (1 + _varint_size(nanos) if nanos else 0)
