"""Encoders: numpy arrays -> serialized protobuf bytes for the per-step topics.

Hot messages (``lc.VehicleTracks``, ``lc.EgoState``, ``foxglove.FrameTransform``, the image and the
scene cubes) are written directly in wire format (see :mod:`lcdata.wire`); tests check every encoder
against the protobuf runtime's decoder. Field numbers come from ``lcdata/proto/lc.proto`` and the
``foxglove`` schemas.
"""

from __future__ import annotations

import math
import struct

import numpy as np

from lcdata.topics import EGO_FRAME, WORLD_FRAME
from lcdata.wire import (
    WIRE_I64,
    WIRE_LEN,
    f_bytes,
    f_double,
    f_packed,
    f_packed_bool,
    f_sint,
    f_string,
    f_varint,
    tag,
    varint,
)

_T_FIELD = struct.Struct("<Bd")  # double t = 2
_T_SPEED = struct.Struct("<BdBd")  # EgoState t (2) and speed (3)
_CONTROLS = struct.Struct("<BdBdBd")  # EgoState steer (8), throttle (9), brake (10)
_VEC3 = struct.Struct("<BdBdBd")
_FIXED32 = struct.Struct("<BI")
_QUAT = struct.Struct("<BdBdBdBd")


VEHICLE_COLUMNS = ("ids", "x", "y", "yaw", "speed", "accel", "lane", "target_lane", "length", "width")
"""The per-vehicle arrays of ``lc.VehicleTracks``, in the order the encoder takes them."""
# VehicleTracks packed fields in wire order (of VEHICLE_COLUMNS): (field number, little-endian wire dtype).
_VEHICLE_FIELDS = ((3, "<i4"), (4, "<f8"), (5, "<f8"), (6, "<f8"), (7, "<f8"), (8, "<f8"), (9, "<i4"),
                   (10, "<i4"), (11, "<f8"), (12, "<f8"))  # fmt: skip


class VehicleEncoder:
    """Encode ``lc.VehicleTracks`` from (N,) arrays, one step or a batch of steps at a time.

    For a given N every packed field has a fixed position after the ``step`` and ``t`` fields, so
    the key and length prefixes are laid out once (a template) and a batch of K steps is one (K, B)
    byte array: the template broadcast into it, then one cast-and-copy per column into a strided
    numpy view (:meth:`bodies`). One instance per writer: the template is kept between calls.
    """

    def __init__(self) -> None:
        self._n = -1
        self._template = np.zeros(0, dtype=np.uint8)
        self._fields: list[tuple[int, int, str]] = []  # (offset, bytes, wire dtype) in the template

    def _layout(self, n: int) -> None:
        template = bytearray()
        fields = []
        for field, dtype in _VEHICLE_FIELDS if n else ():
            size = np.dtype(dtype).itemsize * n
            template += tag(field, WIRE_LEN) + varint(size)
            fields.append((len(template), size, dtype))
            template += bytes(size)
        self._template = np.frombuffer(bytes(template), dtype=np.uint8)
        self._fields = fields
        self._n = n

    def bodies(self, k: int, *columns: np.ndarray) -> np.ndarray:
        """The packed fields of K messages (all but ``step`` and ``t``, which :func:`vehicle_head` makes)
        as a (K, B) uint8 array: row k is the rest of message k.

        ``columns``: :data:`VEHICLE_COLUMNS`, each (K, N) (one row per step) or (N,) (the same at every
        step), any numeric dtype (cast to the wire dtype as numpy assignment casts).
        """
        if len(columns) != len(_VEHICLE_FIELDS):
            names = ", ".join(VEHICLE_COLUMNS)
            raise ValueError(f"expected {len(_VEHICLE_FIELDS)} columns ({names}), got {len(columns)}")
        n = np.shape(columns[0])[-1]
        if n != self._n:
            self._layout(n)
        out = np.empty((k, self._template.size), dtype=np.uint8)
        out[...] = self._template
        for (offset, size, dtype), column in zip(self._fields, columns, strict=False):  # no fields when N = 0
            out[:, offset : offset + size].view(dtype)[...] = column
        return out

    def encode(self, step: int, t_s: float, *columns: np.ndarray) -> bytes:
        """Serialized ``lc.VehicleTracks`` of the (N,) arrays :data:`VEHICLE_COLUMNS`, any numeric dtype."""
        return vehicle_head(step, t_s) + self.bodies(1, *columns).tobytes()


def vehicle_head(step: int, t_s: float) -> bytes:
    """The ``step`` and ``t`` fields that start an ``lc.VehicleTracks`` message (see :class:`VehicleEncoder`)."""
    if 0 < step < 0x80:
        return _STEP_T_FIELDS.pack(0x08, step, 0x11, t_s)
    return (_step_field(step) if step else b"") + _T_FIELD.pack(0x11, t_s)


_STEP_T_FIELDS = struct.Struct("<BBBd")


def encode_vehicles(step: int, t_s: float, *columns: np.ndarray) -> bytes:
    """``lc.VehicleTracks`` from (N,) arrays ``ids, x, y, yaw, speed, accel, lane, target_lane, length,
    width`` (convenience wrapper around :class:`VehicleEncoder`)."""
    return VehicleEncoder().encode(step, t_s, *columns)


def encode_ego(
    step: int,
    t_s: float,
    speed: float,
    lane: int,
    collision_with: int,
    lane_invasion: int,
    off_road: bool,
    steer: float,
    throttle: float,
    brake: float,
) -> bytes:
    """``lc.EgoState`` from scalars (small ints come from precomputed field bytes: this runs every step)."""
    lane_b = _SINT_4.get(lane)
    collision_b = _SINT_5.get(collision_with)
    invasion_b = _SINT_6.get(lane_invasion)
    return b"".join(
        (
            _step_field(step),
            _T_SPEED.pack(0x11, t_s, 0x19, speed),
            f_sint(4, lane) if lane_b is None else lane_b,
            f_sint(5, collision_with) if collision_b is None else collision_b,
            f_sint(6, lane_invasion) if invasion_b is None else invasion_b,
            b"\x38\x01" if off_road else b"",
            _CONTROLS.pack(0x41, steer, 0x49, throttle, 0x51, brake),
        )
    )


_SINT_4, _SINT_5, _SINT_6 = ({v: f_sint(f, v) for v in range(-1, 1024)} for f in (4, 5, 6))


def _step_field(step: int) -> bytes:
    """``int64 step = 1`` (fast path for steps below 2**14)."""
    if 0 < step < 0x80:
        return bytes((0x08, step))
    if 0x80 <= step < 0x4000:
        return bytes((0x08, (step & 0x7F) | 0x80, step >> 7))
    return f_varint(1, step)


_RL_DOUBLES = struct.Struct("<dddddd")  # t, reward, r_collision, r_off_road, r_forward, r_success
_RL_DOUBLE_KEYS = (0x11, 0x31, 0x39, 0x41, 0x49, 0x51)  # fields 2, 6, 7, 8, 9, 10 (64-bit)
_MASK_BYTES = {(a, b, c): bytes((0x2A, 3, a, b, c)) for a in (0, 1) for b in (0, 1) for c in (0, 1)}


def _varint_field(key: int, value: int) -> bytes:
    """A proto3 ``int64``/``int32``/``bool`` field (zero omitted) with a one-byte key."""
    if not value:
        return b""
    if 0 < value < 0x80:
        return bytes((key, value))
    return bytes((key,)) + varint(value)


def _nonzero_double(value: float) -> bool:
    """Whether proto3 writes a ``double`` (it omits +0.0 only, not -0.0)."""
    return value != 0.0 or math.copysign(1.0, value) < 0


def encode_rl_step(
    step: int,
    t_s: float,
    decision: int,
    action: int,
    action_mask: list[bool],
    reward: float,
    r_collision: float,
    r_off_road: float,
    r_forward: float,
    r_success: float,
    terminated: bool,
    truncated: bool,
    outcome: str,
    obs_current: np.ndarray | None,
) -> bytes:
    """``lc.RLStep``, byte for byte what the protobuf runtime serializes (fields in number order,
    proto3 zero values omitted). ``obs_current``: float32 array (any shape) or None."""
    parts = [_varint_field(0x08, step)]
    doubles = (t_s, reward, r_collision, r_off_road, r_forward, r_success)
    packed = _RL_DOUBLES.pack(*doubles)
    for i, (key, value) in enumerate(zip(_RL_DOUBLE_KEYS, doubles, strict=True)):
        if i == 1:  # decision, action and the mask come between t and reward
            parts.append(_varint_field(0x18, decision))
            parts.append(_varint_field(0x20, action))
            mask = _MASK_BYTES.get(tuple(action_mask)) if len(action_mask) == 3 else None
            parts.append(mask if mask is not None else f_packed_bool(5, np.asarray(action_mask, dtype=bool)))
        if _nonzero_double(value):
            parts.append(bytes((key,)) + packed[8 * i : 8 * i + 8])
    parts.append(b"\x58\x01" if terminated else b"")
    parts.append(b"\x60\x01" if truncated else b"")
    parts.append(f_string(13, outcome))
    if obs_current is not None:
        parts.append(f_packed(14, obs_current, "<f4"))
        shape = b"".join(varint(d & 0xFFFFFFFFFFFFFFFF) for d in obs_current.shape)
        parts.append(f_bytes(15, shape) if shape else b"")
    return b"".join(parts)


def encode_timestamp(field: int, time_ns: int) -> bytes:
    """A ``google.protobuf.Timestamp`` field (the last one is cached: /tf, the image and /scene of a
    decision share their time)."""
    global _LAST_TIMESTAMP
    key, data = _LAST_TIMESTAMP
    if key == (field, time_ns):
        return data
    seconds, nanos = divmod(time_ns, 1_000_000_000)
    body = (b"\x08" + varint(seconds) if seconds else b"") + (b"\x10" + varint(nanos) if nanos else b"")
    data = f_bytes(field, body)
    _LAST_TIMESTAMP = ((field, time_ns), data)
    return data


_LAST_TIMESTAMP: tuple[tuple[int, int], bytes] = ((-1, -1), b"")


_TF_FRAMES = f_string(2, WORLD_FRAME) + f_string(3, EGO_FRAME)
_TF_POSITION = tag(4, WIRE_LEN) + varint(_VEC3.size)
_TF_ROTATION = tag(5, WIRE_LEN) + varint(_QUAT.size)
TRANSFORM_HEAD = _TF_FRAMES + _TF_POSITION
"""The bytes of a :func:`encode_transform` message between its timestamp and the position's members."""
TRANSFORM_ROTATION = _TF_ROTATION
"""The bytes of a :func:`encode_transform` message between the position and the rotation's members."""


def encode_image(time_ns: int, chw: np.ndarray, frame_id: str = EGO_FRAME) -> bytes:
    """``foxglove.RawImage`` (rgb8) from a (3, H, W) uint8 array."""
    return ImageEncoder(frame_id).encode(time_ns, chw)


class ImageEncoder:
    """:func:`encode_image` into a buffer kept between calls (one per writer): the fields after the
    timestamp are written once per image size; each call copies the pixels in (channel by channel:
    faster than a transposed copy), puts the timestamp in front and takes the bytes."""

    HEAD_ROOM = 32
    """Bytes before the fixed fields, for the timestamp field (<= 24 bytes)."""

    def __init__(self, frame_id: str = EGO_FRAME) -> None:
        self.frame_id = frame_id
        self._shape: tuple[int, int] | None = None
        self._buffer = bytearray()
        self._hwc = np.zeros((0, 0, 3), dtype=np.uint8)

    def parts(self, h: int, w: int) -> tuple[bytes, bytes]:
        """The bytes of an H x W image message between its timestamp and the pixels (H x W x 3, row-major), and
        after them."""
        head = b"".join(
            (
                _FIXED32.pack(0x15, w),  # width: fixed32, field 2
                _FIXED32.pack(0x1D, h),  # height: fixed32, field 3
                f_string(4, "rgb8"),
                _FIXED32.pack(0x2D, 3 * w),  # step (row stride): fixed32, field 5
                tag(6, WIRE_LEN) + varint(3 * h * w),  # data: bytes, field 6 (filled per call)
            )
        )
        return head, f_string(7, self.frame_id)

    def _layout(self, h: int, w: int) -> None:
        size = 3 * h * w
        head, tail = self.parts(h, w)
        start = self.HEAD_ROOM + len(head)
        self._buffer = bytearray(self.HEAD_ROOM) + head + bytes(size) + tail
        self._hwc = np.frombuffer(self._buffer, dtype=np.uint8)[start : start + size].reshape(h, w, 3)
        self._shape = (h, w)

    def encode(self, time_ns: int, chw: np.ndarray) -> bytes:
        """Serialized ``foxglove.RawImage``; ``chw`` (3, H, W) uint8."""
        if chw.ndim != 3 or chw.shape[0] != 3 or chw.dtype != np.uint8:
            raise ValueError(f"image must be a (3, H, W) uint8 array, got {chw.shape} {chw.dtype}")
        if chw.shape[1:] != self._shape:
            self._layout(chw.shape[1], chw.shape[2])
        hwc = self._hwc
        for c in range(3):
            hwc[..., c] = chw[c]
        stamp = encode_timestamp(1, time_ns)
        start = self.HEAD_ROOM - len(stamp)
        self._buffer[start : self.HEAD_ROOM] = stamp
        return bytes(memoryview(self._buffer)[start:])


def _quaternion_z(yaw: float) -> bytes:
    return _QUAT.pack(0x09, 0.0, 0x11, 0.0, 0x19, math.sin(yaw / 2), 0x21, math.cos(yaw / 2))


def encode_transform(time_ns: int, x: float, y: float, yaw: float, z: float = 0.0) -> bytes:
    """``foxglove.FrameTransform`` world -> ego for a pose on the road plane."""
    return b"".join(
        (
            encode_timestamp(1, time_ns),
            _TF_FRAMES,
            _TF_POSITION,
            _VEC3.pack(0x09, x, 0x11, y, 0x19, z),
            _TF_ROTATION,
            _quaternion_z(yaw),
        )
    )


def _cube_layout() -> tuple[np.dtype, np.ndarray]:
    """A packed numpy record whose bytes are one ``cubes`` entry of a ``foxglove.SceneEntity``.

    Every double is written (key + 8 bytes), so the entry has a fixed size and the values of all
    vehicles can be filled column by column. Returns the record dtype and its (itemsize,) uint8 template.
    """
    key = tag(1, WIRE_I64)[0]  # member i of Vector3/Quaternion/Color has key `key + 8 * i`
    pose_len = 2 + _VEC3.size + 2 + _QUAT.size
    cube_len = 2 + pose_len + 2 + _VEC3.size + 2 + _QUAT.size
    template = bytearray(tag(8, WIRE_LEN) + varint(cube_len) + tag(1, WIRE_LEN) + varint(pose_len))
    fields: list[tuple[str, int]] = []
    parts = (
        ("p", tag(1, WIRE_LEN) + varint(_VEC3.size), "xyz"),  # pose.position
        ("q", tag(2, WIRE_LEN) + varint(_QUAT.size), "xyzw"),  # pose.orientation
        ("s", tag(2, WIRE_LEN) + varint(_VEC3.size), "xyz"),  # size
        ("c", tag(3, WIRE_LEN) + varint(_QUAT.size), "rgba"),  # color
    )
    for prefix, header, members in parts:
        template += header
        for i, member in enumerate(members):
            template.append(key + 8 * i)
            fields.append((prefix + member, len(template)))
            template += bytes(8)
    dtype = np.dtype(
        {
            "names": [name for name, _ in fields],
            "formats": ["<f8"] * len(fields),
            "offsets": [offset for _, offset in fields],
            "itemsize": len(template),
        }
    )
    return dtype, np.frombuffer(bytes(template), dtype=np.uint8)


_CUBE_DTYPE, _CUBE_TEMPLATE = _cube_layout()


def encode_cubes(
    x: np.ndarray,
    y: np.ndarray,
    yaw: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    height: float,
    rgba: np.ndarray,
) -> bytes:
    """Repeated ``cubes`` entries (field 8 of ``foxglove.SceneEntity``) for N boxes on the road.

    Args:
        x, y, yaw, length, width: (N,) box centres (m), headings (rad) and sizes (m).
        height: box height, m; boxes stand on z = 0.
        rgba: (N, 4) or (4,) colours in [0, 1].
    """
    n = len(x)
    records = np.tile(_CUBE_TEMPLATE, n).view(_CUBE_DTYPE)
    half = np.asarray(yaw, dtype=np.float64) / 2
    records["px"], records["py"], records["pz"] = x, y, height / 2
    records["qz"], records["qw"] = np.sin(half), np.cos(half)
    records["sx"], records["sy"], records["sz"] = length, width, height
    colour = np.broadcast_to(np.asarray(rgba, dtype=np.float64), (n, 4))
    records["cr"], records["cg"], records["cb"], records["ca"] = colour.T
    return records.tobytes()


class CubeEncoder:
    """:func:`encode_cubes` with the record array and the colours kept between calls (one per writer).

    The per-call work is six column assignments (position, heading, size) and one ``tobytes``.
    """

    def __init__(self) -> None:
        self._records = np.zeros(0, dtype=_CUBE_DTYPE)
        self._key: tuple[int, float, bytes] | None = None

    FIELDS = ("px", "py", "qz", "qw", "sx", "sy")
    """The members each call fills: position, heading (the quaternion's z and w) and size."""

    def template(self, n: int, height: float, rgba: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """The (n,) cube records with the members that do not change between calls filled in (:attr:`FIELDS` are
        filled by the calls), and the offsets of :attr:`FIELDS` in a record."""
        colour = np.broadcast_to(np.asarray(rgba, dtype=np.float64), (n, 4))
        key = (n, float(height), colour.tobytes())
        if key != self._key:
            records = np.tile(_CUBE_TEMPLATE, n).view(_CUBE_DTYPE)
            records["pz"], records["sz"] = height / 2, height
            records["cr"], records["cg"], records["cb"], records["ca"] = colour.T
            self._records, self._key = records, key
        return self._records, [_CUBE_DTYPE.fields[name][1] for name in self.FIELDS]

    def encode(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray,
               height: float, rgba: np.ndarray) -> bytes:  # fmt: skip
        """Same arguments and bytes as :func:`encode_cubes`."""
        records = self.template(len(x), height, rgba)[0]
        half = np.asarray(yaw, dtype=np.float64) / 2
        records["px"], records["py"] = x, y
        records["qz"], records["qw"] = np.sin(half), np.cos(half)
        records["sx"], records["sy"] = length, width
        return records.tobytes()


def encode_entity(time_ns: int, entity_id: str, primitives: bytes, frame_id: str = WORLD_FRAME) -> bytes:
    """A ``foxglove.SceneEntity`` (lifetime 0 = until replaced) holding already-encoded primitives."""
    return b"".join((encode_timestamp(1, time_ns), f_string(2, frame_id), f_string(3, entity_id), primitives))


def encode_scene_update(entities: list[bytes]) -> bytes:
    """A ``foxglove.SceneUpdate`` from encoded entities."""
    return b"".join(part for entity in entities for part in (tag(2, WIRE_LEN), varint(len(entity)), entity))


def encode_scene_entity_update(time_ns: int, entity_id: str, primitives: bytes, frame_id: str = WORLD_FRAME) -> bytes:
    """``encode_scene_update([encode_entity(time_ns, entity_id, primitives, frame_id)])`` with one copy
    of ``primitives`` instead of three."""
    head = b"".join((encode_timestamp(1, time_ns), f_string(2, frame_id), f_string(3, entity_id)))
    return b"".join((tag(2, WIRE_LEN), varint(len(head) + len(primitives)), head, primitives))


def encode_line_strip(points: np.ndarray, thickness: float, rgba: tuple[float, float, float, float]) -> bytes:
    """One ``lines`` entry (field 11 of ``foxglove.SceneEntity``): a LINE_STRIP through (K, 2) points."""
    pts = b"".join(
        f_bytes(5, _VEC3.pack(0x09, px, 0x11, py, 0x19, 0.0)) for px, py in np.asarray(points, float)
    )
    colour = _QUAT.pack(0x09, rgba[0], 0x11, rgba[1], 0x19, rgba[2], 0x21, rgba[3])
    # type LINE_STRIP = 0 (omitted), pose = identity orientation.
    pose = f_bytes(2, _QUAT.pack(0x09, 0.0, 0x11, 0.0, 0x19, 0.0, 0x21, 1.0))
    line = f_bytes(2, pose) + f_double(3, thickness) + pts + f_bytes(6, colour)
    return f_bytes(11, line)


__all__ = [
    "CubeEncoder",
    "ImageEncoder",
    "encode_cubes",
    "encode_ego",
    "encode_entity",
    "encode_image",
    "encode_line_strip",
    "encode_rl_step",
    "encode_scene_entity_update",
    "encode_scene_update",
    "encode_timestamp",
    "encode_transform",
    "encode_vehicles",
]
