"""Linear MCAP scan that survives truncated files.

``mcap.reader.make_reader`` needs the summary at the end of the file, which a killed writer never
wrote. This scanner walks the data section record by record from the start, decompresses each chunk
and stops at the first record that is incomplete or corrupt, so a ``.partial`` file yields every
message of every complete chunk. It is also the normal read path: an episode is read whole anyway.

Files come from elsewhere, so the scan is bounded by the file's own size (:class:`Limits`): a chunk's
declared size is checked against a maximum, against its compressed size and against what the file may
decompress to in all *before* it is decompressed, and decompression never writes more than the declared
size. Messages are returned in log-time order per topic (the MCAP specification does not order them);
a message recorded twice is refused. Whatever is refused (:class:`McapRefused`, a ``ValueError`` naming
the file, one line) is refused whole, unlike damage, after which the complete part before it is kept.
"""

from __future__ import annotations

import dataclasses
import operator
import pathlib
import struct
import zlib

import zstandard

from lcdata.mcap_write import (
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_METADATA,
    OP_SCHEMA,
)

_RECORD_HEADER = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQI")

COMPRESSIONS = ("", "lz4", "zstd")
"""The chunk compressions the MCAP specification defines; any other name is refused."""
MAX_CHUNK_BYTES = 64 << 20
"""The most uncompressed bytes one chunk may declare: 64 times the chunk size of this package's writer and of the
``mcap`` package's (1 MiB)."""
MAX_CHUNK_RATIO = 1000
"""The most uncompressed bytes per compressed byte a chunk over :data:`RATIO_FREE_BYTES` may declare. Recordings
compress a few to one; lz4 cannot pass about 255 to 1; zstd reaches 32000 to 1 only on runs of one byte."""
RATIO_FREE_BYTES = 4 << 20
"""Chunks up to this size are not held to :data:`MAX_CHUNK_RATIO` (a chunk of constant images may exceed it)."""


class McapRefused(ValueError):
    """A file refused whole: a :class:`Limits` exceeded, a compression the specification does not define, a
    message recorded twice, a channel redefined. The message names the file and is one line."""


@dataclasses.dataclass(frozen=True, slots=True)
class Limits:
    """What reading one file may cost, from its size: chunk bytes decompressed in all, records parsed in all.

    Recordings of this package decompress to a few times their size, with records of about a kilobyte; the
    limits leave ample room above that, a floor for small files and a ceiling for all.
    """

    decompressed_bytes: int
    records: int

    BYTES_PER_FILE_BYTE = 64
    MIN_BYTES = 64 << 20
    MAX_BYTES = 2 << 30
    FILE_BYTES_PER_RECORD = 4
    MIN_RECORDS = 100_000
    MAX_RECORDS = 5_000_000

    @classmethod
    def for_file(cls, size: int) -> Limits:
        """The limits of a file of ``size`` bytes."""
        return cls(
            decompressed_bytes=min(cls.MAX_BYTES, max(cls.MIN_BYTES, cls.BYTES_PER_FILE_BYTE * size)),
            records=min(cls.MAX_RECORDS, max(cls.MIN_RECORDS, size // cls.FILE_BYTES_PER_RECORD)),
        )


@dataclasses.dataclass(slots=True)
class ChannelData:
    """Everything recorded on one channel: topic, schema and message payloads in file order."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    log_times: list[int] = dataclasses.field(default_factory=list)
    payloads: list[memoryview] = dataclasses.field(default_factory=list)


@dataclasses.dataclass(slots=True)
class ScanResult:
    """Content of an MCAP file, keyed by topic."""

    channels: dict[str, ChannelData]
    metadata: dict[str, dict[str, str]]
    complete: bool  # the data-end record was reached
    chunks: int  # complete chunks read
    messages: int
    stop_reason: str  # why the scan stopped early ("" when complete)


def _string(buf: memoryview, pos: int) -> tuple[str, int]:
    (size,) = _U32.unpack_from(buf, pos)
    pos += 4
    return str(buf[pos : pos + size], "utf-8"), pos + size


def _string_map(buf: memoryview, pos: int) -> tuple[dict[str, str], int]:
    (size,) = _U32.unpack_from(buf, pos)
    pos += 4
    end = pos + size
    out: dict[str, str] = {}
    while pos < end:
        key, pos = _string(buf, pos)
        out[key], pos = _string(buf, pos)
    return out, end


class _Scanner:
    def __init__(self, path: pathlib.Path, file_size: int) -> None:
        self.path = path
        self.file_size = file_size
        self.limits = Limits.for_file(file_size)
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.by_id: dict[int, ChannelData] = {}
        self.channels: dict[str, ChannelData] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.messages = 0
        self.records_read = 0
        self.decompressed = 0

    def records(self, buf: memoryview, pos: int, end: int, *, in_chunk: bool) -> tuple[int, str]:
        """Handle records in ``buf[pos:end]``; return where it stopped and why ("" = clean).

        Raises:
            McapRefused: a limit exceeded, or content the reader refuses whole.
        """
        header = _RECORD_HEADER.size
        limit = self.limits.records
        while pos < end:
            if pos + header > end:
                return pos, "incomplete record header"
            self.records_read += 1
            if self.records_read > limit:
                raise McapRefused(
                    f"{self.path}: more than {limit:,} MCAP records, the most read from a file of "
                    f"{self.file_size:,} bytes (one per {Limits.FILE_BYTES_PER_RECORD} bytes of file, "
                    f"at least {Limits.MIN_RECORDS:,}, at most {Limits.MAX_RECORDS:,})"
                )
            opcode, length = _RECORD_HEADER.unpack_from(buf, pos)
            body = pos + header
            if body + length > end:
                return pos, f"incomplete record (opcode 0x{opcode:02x}, {length} bytes)"
            try:
                reason = self._record(buf, opcode, body, length, in_chunk)
            except McapRefused:
                raise
            except (struct.error, UnicodeDecodeError, ValueError, IndexError, MemoryError) as exc:
                return pos, f"corrupt record (opcode 0x{opcode:02x} at byte {pos}: {type(exc).__name__})"
            if reason == "end":
                return body + length, "end"
            if reason:
                return pos, reason
            pos = body + length
        return pos, ""

    def _record(self, buf: memoryview, opcode: int, body: int, length: int, in_chunk: bool) -> str:
        """Handle one record; return why to stop ("" = go on, "end" = the data end)."""
        if opcode == OP_MESSAGE:
            channel_id, _seq, log_time, _pub = _MESSAGE.unpack_from(buf, body)
            channel = self.by_id.get(channel_id)
            if channel is None:
                return f"message on unknown channel {channel_id}"
            channel.log_times.append(log_time)
            channel.payloads.append(buf[body + 22 : body + length])
            self.messages += 1
        elif opcode == OP_CHUNK and not in_chunk:
            return self.chunk(buf, body, body + length)
        elif opcode == OP_SCHEMA:
            (schema_id,) = _U16.unpack_from(buf, body)
            name, p = _string(buf, body + 2)
            encoding, p = _string(buf, p)
            (size,) = _U32.unpack_from(buf, p)
            self.schemas[schema_id] = (name, encoding, bytes(buf[p + 4 : p + 4 + size]))
        elif opcode == OP_CHANNEL:
            channel_id, schema_id = struct.unpack_from("<HH", buf, body)
            topic, p = _string(buf, body + 4)
            message_encoding, _ = _string(buf, p)
            self._channel(channel_id, topic, message_encoding, *self.schemas.get(schema_id, ("", "", b"")))
        elif opcode == OP_METADATA and not in_chunk:
            name, p = _string(buf, body)
            self.metadata[name], _ = _string_map(buf, p)
        elif opcode in (OP_DATA_END, OP_FOOTER) and not in_chunk:
            return "end"
        return ""

    def _channel(
        self,
        channel_id: int,
        topic: str,
        message_encoding: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
    ) -> None:
        """Register a channel. A channel may be defined again (in every chunk, say) but not differently; several
        channels of one topic share its messages, and must share its schema."""
        known = self.by_id.get(channel_id)
        if known is not None:
            if (known.topic, known.schema_name) != (topic, schema_name):
                raise McapRefused(
                    f"{self.path}: MCAP channel {channel_id} is defined twice, as {known.topic} "
                    f"({known.schema_name or 'no schema'}) then as {topic} ({schema_name or 'no schema'})"
                )
            return
        channel = self.channels.get(topic)
        if channel is None:
            channel = self.channels[topic] = ChannelData(
                topic, schema_name, schema_encoding, schema_data, message_encoding
            )
        elif channel.schema_name != schema_name:
            raise McapRefused(
                f"{self.path}: topic {topic} is recorded with two schemas, "
                f"{channel.schema_name or 'none'} and {schema_name or 'none'}"
            )
        self.by_id[channel_id] = channel

    def chunk(self, buf: memoryview, pos: int, end: int) -> str:
        """Check a chunk's declared sizes against the limits, then decompress it (never past its declared size)
        and handle its records."""
        at = pos - _RECORD_HEADER.size
        _start, _end, size, crc = _CHUNK_HEAD.unpack_from(buf, pos)
        compression, p = _string(buf, pos + _CHUNK_HEAD.size)
        (records_size,) = _U64.unpack_from(buf, p)
        if p + 8 + records_size > end:
            return f"corrupt chunk (its {records_size} bytes of records overrun the record)"
        data = buf[p + 8 : p + 8 + records_size]
        where = f"{self.path}: the MCAP chunk at byte {at}"
        if compression not in COMPRESSIONS:
            raise McapRefused(
                f"{where} is compressed with {compression[:40]!r}, which the MCAP specification does not "
                f"define (it defines 'zstd', 'lz4' and '' for none)"
            )
        if size > MAX_CHUNK_BYTES:
            raise McapRefused(
                f"{where} declares {size:,} bytes uncompressed, more than the {MAX_CHUNK_BYTES:,} a chunk "
                "may hold"
            )
        if size > RATIO_FREE_BYTES and size > MAX_CHUNK_RATIO * records_size:
            raise McapRefused(
                f"{where} declares {size:,} bytes uncompressed from {records_size:,} compressed, more "
                f"than {MAX_CHUNK_RATIO} to 1"
            )
        self.decompressed += size
        budget = self.limits.decompressed_bytes
        if self.decompressed > budget:
            raise McapRefused(
                f"{self.path}: its chunks decompress to more than {budget:,} bytes, the most read from a file of "
                f"{self.file_size:,} bytes ({Limits.BYTES_PER_FILE_BYTE} times its size, at least "
                f"{Limits.MIN_BYTES >> 20} MiB, at most {Limits.MAX_BYTES >> 30} GiB)"
            )
        try:
            records = _decompress(compression, data, size)
        except ImportError:
            raise McapRefused(
                f"{where} is compressed with lz4, which needs the lz4 package (pip install lz4)"
            ) from None
        except (zstandard.ZstdError, RuntimeError) as exc:  # lz4 raises RuntimeError
            return f"corrupt chunk ({' '.join(str(exc).split())[:120]})"
        if len(records) != size or (crc and zlib.crc32(records) != crc):
            return "corrupt chunk (size or CRC mismatch)"
        _, reason = self.records(memoryview(records), 0, size, in_chunk=True)
        return reason


def _decompress(compression: str, data: memoryview, size: int) -> bytes | memoryview:
    """The records of a chunk: at most ``size + 1`` bytes are ever produced, whatever the compressed stream
    claims (a zstd frame's declared content size would otherwise be allocated as it stands)."""
    if compression == "":
        return data
    limit = size + 1
    parts: list[bytes] = []
    if compression == "zstd":
        reader = zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True)
        while limit > 0 and (part := reader.read(limit)):
            parts.append(part)
            limit -= len(part)
    else:
        import lz4.frame  # a dependency of mcap; imported here so that a missing package refuses lz4 by name

        rest: bytes | memoryview = data
        while limit > 0 and len(rest):
            decompressor = lz4.frame.LZ4FrameDecompressor()
            part = decompressor.decompress(rest, max_length=limit)
            parts.append(part)
            limit -= len(part)
            if not decompressor.eof:
                break
            rest = decompressor.unused_data or b""
    return parts[0] if len(parts) == 1 else b"".join(parts)


def _in_log_time_order(channel: ChannelData, path: pathlib.Path) -> None:
    """Sort a channel's messages by log time (stable), and refuse one recorded twice (same time, same bytes)."""
    times = channel.log_times
    if all(map(operator.lt, times, times[1:])):  # the usual case: strictly increasing
        return
    if not all(map(operator.le, times, times[1:])):
        order = sorted(range(len(times)), key=times.__getitem__)
        channel.log_times = times = [times[i] for i in order]
        channel.payloads = [channel.payloads[i] for i in order]
    i, n = 0, len(times)
    while i < n:
        j = i + 1
        while j < n and times[j] == times[i]:
            j += 1
        if j - i > 1:
            seen: set[bytes] = set()
            for payload in channel.payloads[i:j]:
                key = bytes(payload)
                if key in seen:
                    raise McapRefused(
                        f"{path}: {channel.topic} holds the same message twice at log time {times[i]} ns "
                        "(a repeated chunk, or a writer that wrote it twice); it would be read twice"
                    )
                seen.add(key)
        i = j


def scan_mcap(path: str | pathlib.Path) -> ScanResult:
    """Read every complete record of an MCAP file, each topic's messages in log-time order.

    Raises:
        ValueError: the file does not start with the MCAP magic.
        McapRefused: a :class:`Limits` exceeded, a chunk compression the MCAP specification does not define,
            a message recorded twice, a channel redefined (a ``ValueError`` too).
    """
    path = pathlib.Path(path)
    data = path.read_bytes()
    if len(data) < len(MAGIC) and MAGIC.startswith(data):
        raise ValueError(f"{path}: truncated MCAP file ({len(data)} bytes, shorter than the MCAP magic)")
    if not data.startswith(MAGIC):
        raise ValueError(f"{path}: not an MCAP file (missing MCAP magic bytes)")
    buf = memoryview(data)
    scanner = _Scanner(path, len(data))
    chunks_before = 0
    pos, reason = len(MAGIC), ""
    # Count chunks as we go: walk top-level records one by one so a bad chunk stops the scan.
    while pos < len(buf):
        stop, reason = scanner.records(buf, pos, min(len(buf), _next_record_end(buf, pos)), in_chunk=False)
        if reason:
            break
        if buf[pos] == OP_CHUNK:
            chunks_before += 1
        pos = stop
    else:
        reason = "file ends before the data-end record"
    complete = reason == "end"
    for channel in scanner.channels.values():
        _in_log_time_order(channel, path)
    return ScanResult(
        channels=scanner.channels,
        metadata=scanner.metadata,
        complete=complete,
        chunks=chunks_before,
        messages=scanner.messages,
        stop_reason="" if complete else reason,
    )


def _next_record_end(buf: memoryview, pos: int) -> int:
    """End offset of the record starting at ``pos`` (may lie past the buffer if truncated)."""
    if pos + _RECORD_HEADER.size > len(buf):
        return len(buf)
    _opcode, length = _RECORD_HEADER.unpack_from(buf, pos)
    return pos + _RECORD_HEADER.size + length
