"""Linear MCAP scan that survives truncated files.

``mcap.reader.make_reader`` needs the summary at the end of the file, which a killed writer never
wrote. This scanner walks the data section record by record from the start, decompresses each chunk
and stops at the first record that is incomplete or corrupt, so a ``.partial`` file yields every
message of every complete chunk. It is also the normal read path: an episode is read whole anyway.
"""

from __future__ import annotations

import dataclasses
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
_CHUNK_HEAD = struct.Struct("<QQQI")


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


MAX_CHUNK_BYTES = 1 << 30
"""A chunk claiming more uncompressed bytes than this is taken as corrupt (the writer makes ~1 MiB chunks)."""


class _Scanner:
    def __init__(self) -> None:
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.by_id: dict[int, ChannelData] = {}
        self.channels: dict[str, ChannelData] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.messages = 0

    def records(self, buf: memoryview, pos: int, end: int, *, in_chunk: bool) -> tuple[int, str]:
        """Handle records in ``buf[pos:end]``; return where it stopped and why ("" = clean)."""
        header = _RECORD_HEADER.size
        while pos < end:
            if pos + header > end:
                return pos, "incomplete record header"
            opcode, length = _RECORD_HEADER.unpack_from(buf, pos)
            body = pos + header
            if body + length > end:
                return pos, f"incomplete record (opcode 0x{opcode:02x}, {length} bytes)"
            try:
                reason = self._record(buf, opcode, body, length, in_chunk)
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
            message_encoding, p = _string(buf, p)
            name, encoding, data = self.schemas.get(schema_id, ("", "", b""))
            channel = ChannelData(topic, name, encoding, data, message_encoding)
            self.by_id[channel_id] = channel
            self.channels.setdefault(topic, channel)
        elif opcode == OP_METADATA and not in_chunk:
            name, p = _string(buf, body)
            self.metadata[name], _ = _string_map(buf, p)
        elif opcode in (OP_DATA_END, OP_FOOTER) and not in_chunk:
            return "end"
        return ""

    def chunk(self, buf: memoryview, pos: int, end: int) -> str:
        _start, _end, size, crc = _CHUNK_HEAD.unpack_from(buf, pos)
        compression, p = _string(buf, pos + _CHUNK_HEAD.size)
        (records_size,) = struct.unpack_from("<Q", buf, p)
        data = buf[p + 8 : p + 8 + records_size]
        if size > MAX_CHUNK_BYTES:
            return f"corrupt chunk (claims {size} bytes uncompressed)"
        try:
            if compression == "zstd":
                records = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
            elif compression == "":
                records = bytes(data)
            else:
                return f"unsupported chunk compression {compression!r}"
        except zstandard.ZstdError as exc:
            return f"corrupt chunk ({exc})"
        if len(records) != size or (crc and zlib.crc32(records) != crc):
            return "corrupt chunk (size or CRC mismatch)"
        _, reason = self.records(memoryview(records), 0, size, in_chunk=True)
        return reason


def scan_mcap(path: str | pathlib.Path) -> ScanResult:
    """Read every complete record of an MCAP file.

    Raises:
        ValueError: the file does not start with the MCAP magic.
    """
    path = pathlib.Path(path)
    data = path.read_bytes()
    if len(data) < len(MAGIC) and MAGIC.startswith(data):
        raise ValueError(f"{path}: truncated MCAP file ({len(data)} bytes, shorter than the MCAP magic)")
    if not data.startswith(MAGIC):
        raise ValueError(f"{path}: not an MCAP file (missing MCAP magic bytes)")
    scanner = _Scanner()
    chunks_before = 0
    buf = memoryview(data)
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
