"""Vectorised decoding of ``lc.VehicleTracks`` messages written by :class:`lcdata.encode.VehicleEncoder`.

For N vehicles such a message is a small head (``step`` varint, ``t`` double) followed by ten packed
fields at fixed offsets. Messages with the same head length and size are stacked into one
``(M, L)`` byte matrix; the keys and length prefixes are checked column-wise against the expected
layout, and every field is then one strided view of the matrix. Anything else (another writer's field
order, missing fields) returns ``None`` and the caller falls back to the field-by-field decoder.
"""

from __future__ import annotations

import numpy as np

from lcdata.wire import WIRE_LEN, tag, varint

# VehicleTracks packed fields in wire order: (field number, column, wire dtype).
FIELDS = ((3, "vehicle_id", "<i4"), (4, "x", "<f8"), (5, "y", "<f8"), (6, "yaw", "<f8"), (7, "speed", "<f8"),
          (8, "accel", "<f8"), (9, "lane", "<i4"), (10, "target_lane", "<i4"), (11, "length", "<f8"),
          (12, "width", "<f8"))  # fmt: skip
_BYTES_PER_VEHICLE = sum(np.dtype(d).itemsize for _, _, d in FIELDS)


def _head(p: memoryview) -> tuple[int, int, int]:
    """``(step, offset of t or -1, head length)`` of one message."""
    i, step = 0, 0
    n = len(p)
    if n and p[0] == 0x08:
        shift, i = 0, 1
        while True:
            b = p[i]
            step |= (b & 0x7F) << shift
            i += 1
            if b < 0x80:
                break
            shift += 7
    t_at = -1
    if i < n and p[i] == 0x11:
        t_at, i = i + 1, i + 9
    return step, t_at, i


def _layout(body_len: int) -> tuple[int, list[tuple[bytes, int, int]]] | None:
    """``(N, [(key+length prefix, data offset, data size)])`` for a body of ``body_len`` bytes, or None."""
    if body_len == 0:  # no vehicles: proto3 omits the empty packed fields
        return 0, [(b"", 0, 0)] * len(FIELDS)
    n = max(0, (body_len - 10 * 3) // _BYTES_PER_VEHICLE)
    for cand in (n, n + 1):
        out, pos = [], 0
        for field, _, dtype in FIELDS:
            size = np.dtype(dtype).itemsize * cand
            prefix = tag(field, WIRE_LEN) + varint(size)
            out.append((prefix, pos + len(prefix), size))
            pos += len(prefix) + size
        if pos == body_len:
            return cand, out
    return None


def decode_tracks_fast(payloads: list[memoryview]) -> dict[str, np.ndarray] | None:
    """Columns ``step, t`` and :data:`FIELDS` (int64 / float64, R rows), or None to fall back."""
    m = len(payloads)
    steps = np.zeros(m, dtype=np.int64)
    t_at = np.zeros(m, dtype=np.int64)
    heads = np.zeros(m, dtype=np.int64)
    sizes = np.fromiter((len(p) for p in payloads), dtype=np.int64, count=m)
    for i, p in enumerate(payloads):
        steps[i], t_at[i], heads[i] = _head(p)
    if m == 0 or (t_at != heads - 8).any() or (steps >= 1 << 62).any():
        return None
    key = heads * (1 << 32) + sizes
    groups = np.unique(key)
    counts = np.zeros(m, dtype=np.int64)
    t = np.zeros(m, dtype=np.float64)
    parts: dict[str, list[np.ndarray]] = {name: [] for _, name, _ in FIELDS}
    order_parts: list[np.ndarray] = []
    for g in groups:
        idx = np.flatnonzero(key == g)
        head, size = int(heads[idx[0]]), int(sizes[idx[0]])
        layout = _layout(size - head)
        if layout is None:
            return None
        n, fields = layout
        mat = np.frombuffer(b"".join(payloads[i] for i in idx), dtype=np.uint8).reshape(len(idx), size)
        body = mat[:, head:]
        t[idx] = np.ascontiguousarray(mat[:, head - 8 : head]).view("<f8").reshape(-1)
        for (_, name, dtype), (prefix, offset, nbytes) in zip(FIELDS, fields, strict=True):
            pre = np.frombuffer(prefix, dtype=np.uint8)
            if not (body[:, offset - len(pre) : offset] == pre).all():
                return None
            block = np.ascontiguousarray(body[:, offset : offset + nbytes]).view(dtype)
            parts[name].append(block.reshape(-1))
        counts[idx] = n
        order_parts.append(idx)
    cols: dict[str, np.ndarray] = {}
    if len(groups) == 1:
        for _, name, dtype in FIELDS:
            cols[name] = parts[name][0].astype(np.int64 if dtype == "<i4" else np.float64)
    else:  # restore message order: rows of message i follow those of message i - 1
        order = np.concatenate(order_parts)
        starts = np.zeros(m, dtype=np.int64)
        starts[order] = np.concatenate([[0], np.cumsum(counts[order])[:-1]])
        row_src = np.concatenate([np.arange(starts[i], starts[i] + counts[i]) for i in range(m)])
        for _, name, dtype in FIELDS:
            cols[name] = np.concatenate(parts[name])[row_src].astype(np.int64 if dtype == "<i4" else np.float64)
    cols["step"] = np.repeat(steps, counts)
    cols["t"] = np.repeat(t, counts)
    return cols
