"""Audit cases for hostile and foreign MCAP recordings: small files that claim huge chunks, many records or
duplicated messages, and valid files from another writer (the ``mcap`` package's, each compression).

Used with :mod:`tools.audit_inputs` (its ``Case`` class is passed in, this module does not import it)::

    from tools.audit_inputs import Case, run_case
    from tools.audit_cases_mcap import build
    for case in build(root, Case):
        print(run_case(case, root).verdict, case.what)

Every case runs ``lc-view FILE --save OUT.rrd`` as a user would. A refusal must write no ``.rrd``; a file
that must read must give an ``.rrd`` that shows what the one of the original recording shows (the same
steps, vehicle boxes, images and events, read back with :class:`rerun.chunk.RrdReader`).
"""

from __future__ import annotations

import dataclasses
import struct
import subprocess
import sys
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import zstandard

from lcdata.mcap_write import (
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
)

_CHUNK_HEAD = struct.Struct("<QQQI")
MIB = 1 << 20


# -- MCAP records, written by hand (the crafted files are what no writer makes) -----------------------
def record(opcode: int, body: bytes) -> bytes:
    """One MCAP record: opcode, u64 length, body."""
    return struct.pack("<BQ", opcode, len(body)) + body


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def channel_record(channel_id: int, topic: str, schema_id: int = 0, encoding: str = "protobuf") -> bytes:
    """A Channel record without metadata."""
    return record(
        OP_CHANNEL,
        struct.pack("<HH", channel_id, schema_id) + _string(topic) + _string(encoding) + struct.pack("<I", 0),
    )


def message_header(channel_id: int, log_time: int, payload_size: int) -> bytes:
    """The record header and fixed fields of a Message record whose payload (``payload_size`` bytes) follows."""
    return struct.pack("<BQHIQQ", OP_MESSAGE, 22 + payload_size, channel_id, 0, log_time, log_time)


def chunk_record(compressed: bytes, size: int, compression: str = "zstd", crc: int = 0) -> bytes:
    """A Chunk record holding ``compressed`` (records of ``size`` bytes once decompressed)."""
    return record(
        OP_CHUNK,
        _CHUNK_HEAD.pack(0, 0, size, crc)
        + _string(compression)
        + struct.pack("<Q", len(compressed))
        + compressed,
    )


def zstd_chunk(records: bytes, compression: str = "zstd") -> bytes:
    """``records`` in a zstd chunk with their CRC-32 (``compression`` may name something else on purpose)."""
    return chunk_record(
        zstandard.ZstdCompressor().compress(records), len(records), compression, zlib.crc32(records)
    )


def zeros_frame(prefix: bytes, size: int) -> bytes:
    """A zstd frame (content size in its header) of ``prefix`` then zeros, ``size`` bytes in all, made without
    holding them in memory."""
    cobj = zstandard.ZstdCompressor().compressobj(size=size)
    out = [cobj.compress(prefix)]
    block = bytes(MIB)
    left = size - len(prefix)
    while left > 0:
        out.append(cobj.compress(block[: min(left, MIB)]))
        left -= MIB
    out.append(cobj.flush())
    return b"".join(out)


def top_records(data: bytes) -> list[tuple[int, bytes]]:
    """The records of a complete file's data section, up to and without the data end (message indexes left
    out: they point into chunks that the crafted files change)."""
    pos, out = len(MAGIC), []
    while True:
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if opcode == OP_DATA_END:
            return out
        if opcode != OP_MESSAGE_INDEX:
            out.append((opcode, data[pos + 9 : pos + 9 + length]))
        pos += 9 + length


def inner_records(body: bytes) -> list[bytes]:
    """The records of one zstd chunk (its body), each whole."""
    _start, _end, size, _crc = _CHUNK_HEAD.unpack_from(body, 0)
    (n,) = struct.unpack_from("<I", body, _CHUNK_HEAD.size)
    p = _CHUNK_HEAD.size + 4 + n + 8
    data = zstandard.ZstdDecompressor().decompress(body[p:], max_output_size=size)
    out, pos = [], 0
    while pos < len(data):
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        out.append(data[pos : pos + 9 + length])
        pos += 9 + length
    return out


def assemble(records: Iterable[bytes]) -> bytes:
    """A file of ``records``: magic, the records, data end, a footer without summary, magic."""
    return (
        MAGIC
        + b"".join(records)
        + record(OP_DATA_END, struct.pack("<I", 0))
        + record(OP_FOOTER, struct.pack("<QQI", 0, 0, 0))
        + MAGIC
    )


def split(base: bytes) -> tuple[list[bytes], list[bytes], list[bytes]]:
    """A file of our writer taken apart: the records before the first chunk (header, metadata), the schema and
    channel records of its chunks, and its message records, in file order."""
    head: list[bytes] = []
    defs: list[bytes] = []
    messages: list[bytes] = []
    for opcode, body in top_records(base):
        if opcode != OP_CHUNK:
            if not defs and not messages:
                head.append(record(opcode, body))
            continue
        for rec in inner_records(body):
            (defs if rec[0] in (OP_SCHEMA, OP_CHANNEL) else messages).append(rec)
    return head, defs, messages


# -- files of another writer: the ``mcap`` package -----------------------------------------------------
def foreign(
    src: Path,
    dst: Path,
    *,
    compression: str = "lz4",
    chunked: bool = True,
    order: Callable[[list[Any]], list[Any]] = lambda m: m,
    twice: str = "",
    two_channels: str = "",
) -> Path:
    """Write ``src`` again with ``mcap.writer.Writer`` (chunks of 4 KiB, ``compression`` "lz4", "zstd" or
    ""), messages in the order ``order`` gives; ``twice``: a topic whose messages are all written twice;
    ``two_channels``: a topic whose messages alternate between two channels."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    kind = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "": CompressionType.NONE}[compression]
    with src.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
        messages = list(reader.iter_messages(log_time_order=False))
    with dst.open("wb") as out:
        writer = Writer(out, chunk_size=4096, compression=kind, use_chunking=chunked)
        writer.start(profile="", library="another-writer")
        for name, data in metadata:
            writer.add_metadata(name, data)
        schema_ids = {
            s.id: writer.register_schema(s.name, s.encoding, s.data) for s in summary.schemas.values()
        }
        channel_ids = {
            c.id: [writer.register_channel(c.topic, c.message_encoding, schema_ids[c.schema_id])]
            for c in summary.channels.values()
        }
        for c in summary.channels.values():
            if c.topic == two_channels:
                channel_ids[c.id].append(
                    writer.register_channel(c.topic, c.message_encoding, schema_ids[c.schema_id])
                )
        for i, (_schema, channel, message) in enumerate(order(messages)):
            ids = channel_ids[channel.id]
            for _ in range(2 if channel.topic == twice else 1):
                writer.add_message(ids[i % len(ids)], message.log_time, message.data, message.publish_time)
        writer.finish()
    return dst


def _channel_fields(rec: bytes) -> tuple[int, int, str]:
    """(channel id, schema id, topic) of a whole Channel record."""
    channel_id, schema_id, n = struct.unpack_from("<HHI", rec, 9)
    return channel_id, schema_id, rec[17 : 17 + n].decode()


def rrd_content(path: Path) -> dict[str, int]:
    """What an ``.rrd`` of lc-view shows, counted: time points of the vehicle boxes, vehicle boxes in all,
    images, events."""
    from rerun.chunk import RrdReader

    out = {"steps": 0, "boxes": 0, "images": 0, "events": 0}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        entity, batch = chunk.entity_path.lstrip("/"), chunk.to_record_batch()
        if entity == "world/vehicles/boxes":
            out["steps"] += batch.num_rows
            out["boxes"] += sum(batch.column("LineStrips2D:strips").value_lengths().fill_null(0).to_pylist())
        elif entity in ("camera/bev", "log/events"):
            out["images" if entity == "camera/bev" else "events"] += batch.num_rows
    return out


def _base_episode(root: Path) -> Path:
    from lcdata.record import record_episode
    from lcsim.config import paper_scenario

    paper = paper_scenario()
    config = dataclasses.replace(
        paper, traffic=dataclasses.replace(paper.traffic, num_vehicles=8), time_limit_s=3.0
    )
    return record_episode(config, 0, "rule", root / "base" / "ep.mcap", writer="inline", overwrite=True).path


def _sparse_grid(path: Path, rows: int) -> Path:
    """A recording whose every step holds one vehicle of its own id: ``rows`` steps x ``rows`` ids."""
    import numpy as np

    from lcdata import EpisodeWriter

    one = np.ones(1)
    with EpisodeWriter(path, metadata={"driver": "crafted"}, start_time_ns=0, overwrite=True) as w:
        for k in range(rows):
            w.write_vehicles(k, k * 0.05, np.array([k]), one * k, one, one * 0, one, one * 0, np.array([1]),
                             np.array([1]), one * 4, one * 2)  # fmt: skip
    return path


def _road_file(path: Path, *, far_x: float = 10.0, road: dict[str, Any] | None = None) -> Path:
    """20 steps of two vehicles under the paper scenario's config, the second at ``far_x``, the road changed
    by ``road``."""
    import numpy as np

    from lcdata import EpisodeWriter
    from lcsim.config import paper_scenario

    config = paper_scenario().to_dict()
    config["road"] = {**config["road"], **(road or {})}
    two = np.ones(2)
    with EpisodeWriter(
        path, metadata={"driver": "crafted", "config": config}, start_time_ns=0, overwrite=True
    ) as w:
        for k in range(20):
            w.write_vehicles(k, k * 0.05, np.array([0, 1]), np.array([k, far_x]), two, two * 0, two, two * 0,
                             np.array([1, 1]), np.array([1, 1]), two * 4, two * 2)  # fmt: skip
    return path


def build(root: Path, Case: type) -> list:
    """Make the files under ``root`` and return the cases (``Case`` is :class:`tools.audit_inputs.Case`)."""
    base = _base_episode(root)
    head, defs, messages = split(base.read_bytes())
    files = root / "mcap"
    files.mkdir(exist_ok=True)

    def write(name: str, records: Iterable[bytes]) -> Path:
        path = files / name
        path.write_bytes(assemble(records))
        return path

    reference = root / "reference.rrd"
    view_main = "import sys; sys.argv[0] = 'lc-view'; from lccli.view import main; raise SystemExit(main())"
    subprocess.run([sys.executable, "-c", view_main, str(base), "--save", str(reference)], cwd=root, check=True,
                   capture_output=True)  # fmt: skip

    def view(path: Path, name: str) -> tuple[list[str], Path]:
        out = root / "rrd" / f"{name}.rrd"
        return ["lc-view", str(path), "--save", str(out), "--overwrite"], out

    def refused(path: Path, name: str, what: str) -> Any:
        argv, out = view(path, name)
        return Case(what, argv, check=lambda: f"{out.name} was written" if out.exists() else "")

    def reads(path: Path, name: str, what: str) -> Any:
        argv, out = view(path, name)

        def check() -> str:
            if not out.exists():
                return f"{out.name} was not written"
            got, want = rrd_content(out), rrd_content(reference)
            return "" if got == want else f"{out.name} holds {got}, the original recording's .rrd {want}"

        return Case(what, argv, expect="ok", check=check)

    channels = {_channel_fields(rec)[2]: _channel_fields(rec) for rec in defs if rec[0] == OP_CHANNEL}
    vehicles_id, vehicles_schema, _ = channels["/vehicles"]
    junk_id = max(c[0] for c in channels.values()) + 1
    junk_channel = channel_record(junk_id, "/junk")
    # 15 chunks of 200 MiB each: a message on /junk (defined once, before) whose payload keeps the chunk in
    # memory (~120 KB file)
    junk = zstd_chunk(junk_channel)
    payload = 200 * MIB
    big = chunk_record(zeros_frame(message_header(junk_id, 1, payload), 31 + payload), 31 + payload)
    # 40 chunks of 4 MiB: each under any chunk limit, together 160 MiB from a file of a few kilobytes
    mid = chunk_record(zeros_frame(message_header(junk_id, 1, 4 * MIB - 31), 4 * MIB), 4 * MIB)
    # zero bytes decompressed are empty records of opcode 0 (9 bytes each): 64 MiB = 7.5 million records
    empty_records = chunk_record(zeros_frame(b"", 64 * MIB), 64 * MIB)
    few_records = chunk_record(zeros_frame(b"", 3_900_000), 3_900_000)
    good = zstd_chunk(b"".join(defs + messages))
    half = len(messages) // 2
    redefined = channel_record(vehicles_id, "/other", vehicles_schema)
    small = zstandard.ZstdCompressor().compress(b"".join(defs))
    lies = chunk_record(small, 1 << 40)
    by_time = lambda ms: sorted(ms, key=lambda m: m[2].log_time, reverse=True)  # noqa: E731
    in_dir = root / "mcap_dir"
    in_dir.mkdir(exist_ok=True)
    (in_dir / "good.mcap").write_bytes(base.read_bytes())
    (in_dir / "zz_bomb.mcap").write_bytes(assemble([*head, good, junk, *[big] * 15]))
    quarters = [messages[i * len(messages) // 4 : (i + 1) * len(messages) // 4] for i in range(4)]
    ten_chunks = [zstd_chunk(b"".join(messages[i::10][::-1])) for i in range(10)]
    f = files
    return [
        # a valid file of another writer, each compression of the MCAP specification
        reads(
            foreign(base, f / "lz4.mcap", compression="lz4"), "lz4", "lc-view: mcap-package file, lz4 chunks"
        ),
        reads(
            foreign(base, f / "zstd.mcap", compression="zstd"),
            "zstd",
            "lc-view: mcap-package file, zstd chunks",
        ),
        reads(
            foreign(base, f / "none.mcap", compression=""),
            "none",
            "lc-view: mcap-package file, uncompressed chunks",
        ),
        reads(
            foreign(base, f / "flat.mcap", chunked=False), "flat", "lc-view: mcap-package file without chunks"
        ),
        reads(
            foreign(base, f / "reversed.mcap", compression="zstd", order=by_time),
            "reversed",
            "lc-view: mcap-package file, messages in reverse log-time order",
        ),
        reads(
            foreign(base, f / "two_channels.mcap", compression="zstd", two_channels="/vehicles"),
            "two_channels",
            "lc-view: /vehicles on two channels of one file",
        ),
        reads(
            write("repeated_defs.mcap", [*head, *(zstd_chunk(b"".join(defs + part)) for part in quarters)]),
            "repeated_defs",
            "lc-view: schema and channel records repeated in every chunk",
        ),
        reads(
            write("chunks_out_of_order.mcap", [*head, zstd_chunk(b"".join(defs)), *ten_chunks]),
            "chunks_out_of_order",
            "lc-view: messages out of log-time order across chunks",
        ),
        # compressions the specification does not define
        refused(
            write("bz2.mcap", [*head, zstd_chunk(b"".join(defs + messages), "bz2")]),
            "bz2",
            "lc-view: chunk compression 'bz2'",
        ),
        refused(
            write("upper.mcap", [*head, zstd_chunk(b"".join(defs + messages), "LZ4")]),
            "upper",
            "lc-view: chunk compression 'LZ4' (upper case)",
        ),
        # small files that decompress to far more than they could hold
        refused(
            write("bomb_memory.mcap", [*head, good, junk, *[big] * 15]),
            "bomb_memory",
            "lc-view: 15 chunks of 200 MiB kept alive by their payloads",
        ),
        refused(
            write("bomb_cpu.mcap", [*head, good, empty_records, empty_records]),
            "bomb_cpu",
            "lc-view: 2 chunks of 7.5 million empty records",
        ),
        refused(
            write("bomb_total.mcap", [*head, good, junk, *[mid] * 40]),
            "bomb_total",
            "lc-view: 40 chunks of 4 MiB (each allowed, 160 MiB in all)",
        ),
        refused(
            write("bomb_records.mcap", [*head, good, few_records]),
            "bomb_records",
            "lc-view: a 3.9 MB chunk of 433,000 empty records",
        ),
        refused(
            write("declared_huge.mcap", [*head, lies, zstd_chunk(b"".join(messages))]),
            "declared_huge",
            "lc-view: a chunk declaring 1 TiB uncompressed",
        ),
        refused(in_dir, "in_dir", "lc-view: a directory holding a good file and a 100 KB bomb"),
        # messages recorded twice, channels that change meaning
        refused(
            write("duplicate_chunk.mcap", [*head, good, zstd_chunk(b"".join(messages))]),
            "duplicate_chunk",
            "lc-view: every message recorded twice (the chunk repeated)",
        ),
        refused(
            foreign(base, f / "twice.mcap", compression="zstd", twice="/vehicles"),
            "twice",
            "lc-view: mcap-package file, every /vehicles message written twice",
        ),
        refused(
            write(
                "redefined.mcap",
                [
                    *head,
                    zstd_chunk(b"".join(defs + messages[:half])),
                    zstd_chunk(redefined + b"".join(messages[half:])),
                ],
            ),
            "redefined",
            "lc-view: a channel id redefined to another topic mid-file",
        ),
        refused(
            _road_file(f / "far.mcap", far_x=1e9),
            "far",
            "lc-view: a vehicle at x = 1e9 m (a road of 333 million dashes to draw)",
        ),
        refused(
            _road_file(f / "lanes.mcap", road={"num_lanes": 10**8}),
            "lanes",
            "lc-view: a config road of 100 million lanes",
        ),
        refused(
            _road_file(f / "no_dash.mcap", road={"dash_length_m": 0.0, "dash_gap_m": 0.0}),
            "no_dash",
            "lc-view: a config road with dashes and gaps of 0 m",
        ),
        refused(
            _sparse_grid(f / "sparse.mcap", 12_000),
            "sparse",
            "lc-view: 12,000 steps of one vehicle each, every one a new id",
        ),
    ]
