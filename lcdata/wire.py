"""Protobuf wire format straight from and to numpy arrays.

The generic protobuf runtime builds a Python object per message and converts repeated fields element
by element, which costs tens of microseconds for a step of 100 vehicles. Packed repeated fields of a
fixed-width type (``double``, ``float``, ``sfixed32``, ...) are, on the wire, just
``tag + varint(byte length) + little-endian array bytes``, so they can be written with
``ndarray.tobytes()`` and read with ``np.frombuffer``. The bytes produced here are ordinary protobuf:
any decoder (the protobuf runtime, Foxglove, Rerun) reads them.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

import numpy as np

WIRE_VARINT = 0
WIRE_I64 = 1
WIRE_LEN = 2
WIRE_I32 = 5

_F64 = struct.Struct("<d")
_F32 = struct.Struct("<f")


def varint(value: int) -> bytes:
    """Encode a non-negative int (or a negative int64 as two's complement) as a varint."""
    if 0 <= value < 0x80:
        return bytes((value,))
    value &= 0xFFFFFFFFFFFFFFFF
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def zigzag(value: int) -> int:
    """Zigzag-map a signed int (``sint32``/``sint64``) to a non-negative one."""
    return (value << 1) ^ (value >> 63)


def tag(field: int, wire_type: int) -> bytes:
    """Field key bytes."""
    return varint((field << 3) | wire_type)


def f_varint(field: int, value: int) -> bytes:
    """A scalar ``int64``/``int32``/``bool``/enum field; zero is omitted as proto3 does."""
    return tag(field, WIRE_VARINT) + varint(int(value)) if value else b""


def f_sint(field: int, value: int) -> bytes:
    """A scalar ``sint32``/``sint64`` field."""
    return tag(field, WIRE_VARINT) + varint(zigzag(int(value))) if value else b""


def f_double(field: int, value: float) -> bytes:
    """A scalar ``double`` field, always written (cheap, keeps the layout fixed)."""
    return tag(field, WIRE_I64) + _F64.pack(value)


def f_float(field: int, value: float) -> bytes:
    """A scalar ``float`` field, always written."""
    return tag(field, WIRE_I32) + _F32.pack(value)


def f_bytes(field: int, data: bytes) -> bytes:
    """A length-delimited field: ``bytes``, ``string`` (already encoded) or an embedded message."""
    return tag(field, WIRE_LEN) + varint(len(data)) + data


def f_string(field: int, text: str) -> bytes:
    """A ``string`` field; empty strings are omitted."""
    return f_bytes(field, text.encode()) if text else b""


def f_packed(field: int, array: np.ndarray, dtype: str) -> bytes:
    """A packed repeated fixed-width field from an array of any shape (flattened row-major).

    ``dtype`` is the little-endian wire type: ``'<f8'`` double, ``'<f4'`` float, ``'<i4'`` sfixed32,
    ``'<u4'`` fixed32, ``'<i8'`` sfixed64, ``'<u8'`` fixed64.
    """
    data = np.ascontiguousarray(array, dtype=dtype).tobytes()
    return tag(field, WIRE_LEN) + varint(len(data)) + data if data else b""


def f_packed_bool(field: int, array: np.ndarray) -> bytes:
    """A packed ``repeated bool`` field (one byte 0/1 per element)."""
    data = np.ascontiguousarray(array, dtype=bool).view(np.uint8).tobytes()
    return tag(field, WIRE_LEN) + varint(len(data)) + data if data else b""


def read_varint(buf: bytes | memoryview, pos: int) -> tuple[int, int]:
    """Decode one varint at ``pos``; return ``(value, next_pos)``."""
    byte = buf[pos]
    if byte < 0x80:
        return byte, pos + 1
    value = byte & 0x7F
    shift = 7
    pos += 1
    while True:
        byte = buf[pos]
        value |= (byte & 0x7F) << shift
        pos += 1
        if byte < 0x80:
            return value, pos
        shift += 7


def to_int64(value: int) -> int:
    """Interpret a decoded ``int64`` varint (two's complement) as signed."""
    return value - (1 << 64) if value >= 1 << 63 else value


def unzigzag(value: int) -> int:
    """Inverse of :func:`zigzag`."""
    return (value >> 1) ^ -(value & 1)


def iter_fields(buf: bytes | memoryview) -> Iterator[tuple[int, int, int | bytes | memoryview]]:
    """Yield ``(field, wire_type, value)`` for each field of a serialized message.

    ``value`` is an int for varints, the raw 8 or 4 bytes for fixed-width scalars and a slice of
    ``buf`` for length-delimited fields. Raises ``ValueError`` on malformed input.
    """
    pos = 0
    end = len(buf)
    try:
        while pos < end:
            key, pos = read_varint(buf, pos)
            field, wire_type = key >> 3, key & 7
            if wire_type == WIRE_VARINT:
                value, pos = read_varint(buf, pos)
                yield field, wire_type, value
            elif wire_type == WIRE_LEN:
                size, pos = read_varint(buf, pos)
                if pos + size > end:
                    raise ValueError("length-delimited field runs past the message end")
                yield field, wire_type, buf[pos : pos + size]
                pos += size
            elif wire_type == WIRE_I64:
                yield field, wire_type, buf[pos : pos + 8]
                pos += 8
            elif wire_type == WIRE_I32:
                yield field, wire_type, buf[pos : pos + 4]
                pos += 4
            else:
                raise ValueError(f"unsupported wire type {wire_type}")
    except IndexError as exc:
        raise ValueError("truncated protobuf message") from exc


def decode_varints(data: np.ndarray) -> np.ndarray:
    """Decode a packed run of varints, vectorised.

    Args:
        data: (B,) uint8, the concatenated varint bytes.
    Returns:
        (M,) uint64 decoded values.
    """
    data = np.asarray(data, dtype=np.uint8)
    if data.size == 0:
        return np.zeros(0, dtype=np.uint64)
    if not (data & 0x80).any():
        return data.astype(np.uint64)
    ends = np.flatnonzero(data < 0x80)
    if ends.size == 0 or ends[-1] != data.size - 1:
        raise ValueError("truncated varint run")
    starts = np.concatenate(([0], ends[:-1] + 1))
    index = np.arange(data.size)
    shift = (index - np.repeat(starts, ends - starts + 1)).astype(np.uint64) * np.uint64(7)
    contrib = (data & 0x7F).astype(np.uint64) << shift
    return np.add.reduceat(contrib, starts)
