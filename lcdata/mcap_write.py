"""A lean, streaming MCAP writer (chunked, zstd) tuned for many small messages.

Why not ``mcap.writer.Writer``: its ``add_message`` does much per message (a record dataclass, a
``BytesIO`` with seeks, statistics bookkeeping) and it compresses each chunk on the caller's thread.
At a simulator rate of thousands of steps per second that alone would use most of the recording budget.
This writer lays the records of the chunk in progress out in one buffer (a record header packed in place,
the message index as three integer arrays), and compiled encoders write whole batches of records into the
same buffer (:meth:`McapStreamWriter.records_target`); finished chunks are compressed (zstandard releases
the GIL, so optionally on a background thread), written and flushed, so every complete chunk is on disk
even if the process is killed later.

The file layout follows the MCAP specification (https://mcap.dev/spec): magic, header, metadata,
chunks (schema and channel records live in the chunk where they were registered, followed by
message indexes), data end, a summary (schemas, channels, statistics, chunk and metadata indexes,
summary offsets), footer, magic. The official ``mcap`` reader and Rerun's MCAP loader read it.
Memory stays flat: only the chunk in progress and one chunk index per written chunk are kept.
"""

from __future__ import annotations

import logging
import queue
import struct
import threading
import zlib
from collections.abc import Callable, Sequence
from typing import BinaryIO

import numpy as np
import zstandard
from numba import njit

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

_MESSAGE_HEADER = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log, publish
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<BQQQQII4sQ")  # a chunk record up to its compressed records (compression "zstd")


def _string(text: str) -> bytes:
    data = text.encode()
    return _U32.pack(len(data)) + data


def _string_map(mapping: dict[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in mapping.items())
    return _U32.pack(len(body)) + body




COMPRESSION_LEVEL = -3
"""Default zstd level of the chunks: on recorded episodes, -3 compresses a little less than level 1 in about
half its time (lz4 less than both, at the speed of -3); the time saved is worth more than the few per cent of
file size."""

MESSAGE_HEADER_BYTES = _MESSAGE_HEADER.size
"""Bytes of a message record before its data (:func:`message_header`)."""


def message_header(channel_id: int, log_time: int, data_size: int) -> bytes:
    """A message record header (sequence 0, publish time = log time) for ``data_size`` bytes of message
    data, for :meth:`McapStreamWriter.add_message_records`."""
    return _MESSAGE_HEADER.pack(OP_MESSAGE, 22 + data_size, channel_id, 0, log_time, log_time)


CHUNK_SLACK = 1 << 18
"""Bytes the chunk buffer holds beyond the chunk size (a batch that crosses the chunk size is cut after)."""
_SPARE_BUFFERS: list[bytearray] = []  # chunk buffers of finished writers, for the next ones (no fresh pages to fault)
_SPARE_LOCK = threading.Lock()
_MAX_SPARE_BUFFERS = 4


def _take_buffer(size: int) -> bytearray:
    with _SPARE_LOCK:
        for i, buf in enumerate(_SPARE_BUFFERS):
            if len(buf) >= size:
                return _SPARE_BUFFERS.pop(i)
    return bytearray(size)


def _give_back_buffer(buf: bytearray) -> None:
    with _SPARE_LOCK:
        if len(_SPARE_BUFFERS) < _MAX_SPARE_BUFFERS:
            _SPARE_BUFFERS.append(buf)


def _channel_counts(channels: np.ndarray) -> dict[int, int]:
    """Messages per channel id (channel ids are small: registered one after the other)."""
    counts = np.bincount(channels)
    return {int(c): int(counts[c]) for c in np.flatnonzero(counts)}


@njit(cache=True)
def _group_by_channel(channels: np.ndarray, times: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                             np.ndarray]:  # fmt: skip
    """The channels in the order of their first message, their message counts, and the (M, 2) (log time, offset)
    entries grouped by channel in that order (in offset order within a channel)."""
    first = np.full(channels.max() + 1 if channels.size else 0, -1, dtype=np.int64)
    counts = np.zeros(first.size, dtype=np.int64)
    order = np.empty(first.size, dtype=np.int64)
    seen = 0
    for i in range(channels.size):
        c = channels[i]
        if first[c] < 0:
            first[c] = i
            order[seen] = c
            seen += 1
        counts[c] += 1
    order = order[:seen]
    start = np.zeros(first.size, dtype=np.int64)
    at = 0
    for c in order:
        start[c] = at
        at += counts[c]
    entries = np.empty((channels.size, 2), dtype=np.int64)
    for i in range(channels.size):
        c = channels[i]
        entries[start[c], 0], entries[start[c], 1] = times[i], offsets[i]
        start[c] += 1
    return order, counts[order], entries


def _chunk_index(channels: np.ndarray, times: np.ndarray, offsets: np.ndarray) -> dict[int, np.ndarray]:
    """The message index of a chunk: (M, 2) (log time, offset) entries per channel id, in offset order, the
    channels in the order of their first message (the messages are given in offset order)."""
    order, counts, entries = _group_by_channel(channels, times, offsets)
    ends = np.cumsum(counts).tolist()
    return {c: entries[end - n : end] for c, n, end in zip(order.tolist(), counts.tolist(), ends, strict=True)}


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body



def _failure(what: str, error: BaseException) -> Exception:
    """The writer thread's failure as the caller gets it: an ``OSError`` (a full disk) stays one, with its
    ``errno`` (a command reports it as a write error, in one line), anything else a ``RuntimeError``."""
    if isinstance(error, OSError):
        return OSError(error.errno, f"{what}: {error.strerror or error}", error.filename)
    return RuntimeError(what)

class McapStreamWriter:
    """Write an MCAP file record by record.

    Args:
        stream: a binary file opened for writing (the writer closes it in :meth:`finish`).
        chunk_size: uncompressed bytes after which a chunk is closed.
        compression_level: zstd level (:data:`COMPRESSION_LEVEL` by default).
        chunk_crc: store the CRC-32 of each chunk's records. Without it (the default) the chunk CRC is 0
            ("not computed", as the MCAP specification allows) and each chunk's zstd frame carries its
            own content checksum (XXH64), which decompression checks: the same protection against a
            damaged chunk for a twentieth of the CPU time.
        background: compress and write chunks on a worker thread.
        profile, library: header fields.
    """

    def __init__(
        self,
        stream: BinaryIO,
        *,
        chunk_size: int = 1 << 20,
        compression_level: int = COMPRESSION_LEVEL,
        chunk_crc: bool = False,
        background: bool = True,
        profile: str = "",
        library: str = "lc-toolkit",
    ) -> None:
        self._stream = stream
        self._chunk_size = chunk_size
        self._compressor = zstandard.ZstdCompressor(level=compression_level, write_checksum=not chunk_crc)
        self._chunk_crc = chunk_crc
        self._pos = 0  # file offset; touched only by the I/O side
        # The chunk in progress: its records in _buf[:_len], its messages' channel ids, log times and offsets in
        # _index[:, :_messages] (offset order). A chunk without messages keeps the time range of the one before.
        self._buf = _take_buffer(chunk_size + CHUNK_SLACK)
        self._u8 = np.frombuffer(self._buf, dtype=np.uint8)
        self._len = 0
        self._index = np.zeros((3, 4096), dtype=np.int64)
        self._messages = 0
        self._chunk_start = 0
        self._chunk_end = 0
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self._counts: dict[int, int] = {}
        self._message_count = 0
        self._start_time = 0
        self._end_time = 0
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self._error: BaseException | None = None
        self._finished = False
        self._queue: queue.Queue[Callable[[], None] | None] | None = None
        self._thread: threading.Thread | None = None
        if background:
            self._queue = queue.Queue(maxsize=2)
            self._thread = threading.Thread(target=self._worker, name="mcap-writer", daemon=True)
            self._thread.start()
        self._submit(lambda: self._write(MAGIC + _record(OP_HEADER, _string(profile) + _string(library))))

    # -- public API -------------------------------------------------------------------------------
    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Add a schema record to the current chunk; return its id (1, 2, ...)."""
        schema_id = len(self._schemas) + 1
        record = _record(
            OP_SCHEMA, _U16.pack(schema_id) + _string(name) + _string(encoding) + _U32.pack(len(data)) + data
        )
        self._schemas.append(record)
        self._append(record)
        return schema_id

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str] | None = None
    ) -> int:
        """Add a channel record to the current chunk; return its id (1, 2, ...)."""
        channel_id = len(self._channels) + 1
        body = _U16.pack(channel_id) + _U16.pack(schema_id) + _string(topic) + _string(message_encoding)
        record = _record(OP_CHANNEL, body + _string_map(metadata or {}))
        self._channels.append(record)
        self._counts[channel_id] = 0
        self._append(record)
        return channel_id

    def add_message(
        self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0
    ) -> None:
        """Append one message record (times in ns) to the current chunk."""
        offset = self._len
        end = offset + MESSAGE_HEADER_BYTES + len(data)
        if end > len(self._buf) or self._messages == self._index.shape[1]:
            self._grow(end, self._messages + 1)
        _MESSAGE_HEADER.pack_into(self._buf, offset, OP_MESSAGE, 22 + len(data), channel_id, sequence, log_time,
                                  publish_time)  # fmt: skip
        self._buf[offset + MESSAGE_HEADER_BYTES : end] = data
        index, m = self._index, self._messages
        index[0, m], index[1, m], index[2, m] = channel_id, log_time, offset
        self._messages, self._len = m + 1, end
        if end >= self._chunk_size:
            self.flush_chunk()

    def add_message_records(self, records: bytes, channel_ids: Sequence[int] | np.ndarray,
                            log_times: Sequence[int] | np.ndarray, sizes: Sequence[int] | np.ndarray) -> None:  # fmt: skip
        """Append consecutive complete message records (each :func:`message_header` + data) given as one
        bytes object: the file is the one :meth:`add_message` would make for each record in turn.

        ``channel_ids``, ``log_times`` and ``sizes`` (record bytes, header included) describe the
        records in order and must match their headers. For callers that encode many messages at once:
        a few array operations per call, not per record.
        """
        channel_ids = np.asarray(channel_ids, dtype=np.int64)
        log_times = np.asarray(log_times, dtype=np.int64)
        sizes = np.asarray(sizes, dtype=np.int64)
        if not len(channel_ids) == len(log_times) == len(sizes):
            raise ValueError("channel_ids, log_times and sizes must have one entry per record")
        m = len(sizes)
        out, pos, index, first = self.records_target(len(records), m)
        out[pos : pos + len(records)] = np.frombuffer(records, dtype=np.uint8)
        index[0, first : first + m], index[1, first : first + m] = channel_ids, log_times
        if m:
            index[2, first] = pos
            np.cumsum(sizes[:-1], out=index[2, first + 1 : first + m])
            index[2, first + 1 : first + m] += pos
        self.records_written(pos + len(records), first + m)

    def records_target(self, nbytes: int, messages: int) -> tuple[np.ndarray, int, np.ndarray, int]:
        """Room for ``messages`` message records of at most ``nbytes`` bytes in all, written by the caller (e.g. a
        compiled encoder) straight into the chunk buffer: returns ``(buffer, position, index, messages so far)``,
        the uint8 buffer to write from ``position`` on and the (3, capacity) int64 message index (channel id,
        log time, offset in the chunk) to fill from column ``messages so far`` on. Then call
        :meth:`records_written`; nothing else may touch the writer in between."""
        if self._len + nbytes > len(self._buf) or self._messages + messages > self._index.shape[1]:
            self._grow(self._len + nbytes, self._messages + messages)
        return self._u8, self._len, self._index, self._messages

    def records_written(self, end: int, messages: int) -> None:
        """The records written after :meth:`records_target` end at ``end`` and the index has ``messages``
        entries. The chunk is cut after the record that reaches the chunk size, as :meth:`add_message` would."""
        first = self._messages
        self._len, self._messages = end, messages
        while self._len >= self._chunk_size and first < self._messages:
            index = self._index
            ends = np.append(index[2, first + 1 : self._messages], self._len)
            m = first + int(np.argmax(ends >= self._chunk_size))  # the record that fills the chunk
            cut = int(ends[m - first])
            rest, later = self._len - cut, self._messages - m - 1
            self._len, self._messages = cut, m + 1
            self.flush_chunk()
            if rest:
                self._u8[:rest] = self._u8[cut : cut + rest]
                index[:, :later] = index[:, m + 1 : m + 1 + later]
                index[2, :later] -= cut
            self._len, self._messages, first = rest, later, 0

    def _grow(self, nbytes: int, messages: int) -> None:
        if nbytes > len(self._buf):
            buf = bytearray(max(nbytes, 2 * len(self._buf)))
            buf[: self._len] = memoryview(self._buf)[: self._len]
            self._buf, self._u8 = buf, np.frombuffer(buf, dtype=np.uint8)
        if messages > self._index.shape[1]:
            index = np.zeros((3, max(messages, 2 * self._index.shape[1])), dtype=np.int64)
            index[:, : self._messages] = self._index[:, : self._messages]
            self._index = index

    @property
    def chunk_size(self) -> int:
        """Uncompressed bytes after which a chunk is closed."""
        return self._chunk_size

    @property
    def message_counts(self) -> dict[int, int]:
        """Messages written so far per channel id."""
        counts = dict(self._counts)
        for channel_id, n in _channel_counts(self._index[0, : self._messages]).items():
            counts[channel_id] += n
        return counts

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a metadata record (outside chunks) after the chunks written so far."""
        record = _record(OP_METADATA, _string(name) + _string_map(data))

        def job() -> None:
            start = self._write(record)
            body = _U64.pack(start) + _U64.pack(len(record)) + _string(name)
            self._metadata_indexes.append(_record(OP_METADATA_INDEX, body))

        self.flush_chunk()
        self._submit(job)

    def flush_chunk(self) -> None:
        """Close the chunk in progress (if it holds anything) and queue it for writing."""
        if not self._len:
            return
        m = self._messages
        channels, times, offsets = (row[:m] for row in self._index)
        indexes = _chunk_index(channels, times, offsets)
        for channel_id, n in _channel_counts(channels).items():
            self._counts[channel_id] += n
        if m:
            self._chunk_start, self._chunk_end = int(times.min()), int(times.max())
            first = self._message_count == 0
            self._start_time = self._chunk_start if first else min(self._start_time, self._chunk_start)
            self._end_time = self._chunk_end if first else max(self._end_time, self._chunk_end)
        start, end = self._chunk_start, self._chunk_end
        self._message_count += m
        records: bytes | memoryview = memoryview(self._buf)[: self._len]
        if self._queue is not None:  # written later, on the worker thread: the buffer is reused before that
            records = bytes(records)
        self._len, self._messages = 0, 0
        self._submit(lambda: self._write_chunk(records, indexes, start, end))

    def finish(self) -> None:
        """Write the summary and footer, stop the worker and close the stream."""
        if self._finished:
            return
        self._finished = True
        self.flush_chunk()
        self._submit(self._write_summary)
        self._stop_worker()
        self._stream.close()
        self._release_buffer()
        if self._error is not None:
            raise _failure("MCAP writing failed", self._error) from self._error

    def abort(self) -> None:
        """Stop without writing the summary (the file stays a recoverable partial file)."""
        if self._finished:
            return
        self._finished = True
        self._stop_worker()
        self._stream.close()
        self._release_buffer()

    def _release_buffer(self) -> None:
        """Hand the chunk buffer to the next writer of this process (nothing refers to it any more)."""
        buf, self._buf = self._buf, bytearray()
        self._u8, self._len, self._messages = np.frombuffer(self._buf, dtype=np.uint8), 0, 0
        _give_back_buffer(buf)

    def _append(self, record: bytes) -> None:
        end = self._len + len(record)
        if end > len(self._buf):
            self._grow(end, self._messages)
        self._buf[self._len : end] = record
        self._len = end

    # -- I/O side ---------------------------------------------------------------------------------
    def _submit(self, job: Callable[[], None]) -> None:
        if self._error is not None:
            raise _failure("MCAP writer thread failed", self._error) from self._error
        if self._queue is None:
            job()
        else:
            self._queue.put(job)

    def _worker(self) -> None:
        assert self._queue is not None
        while (job := self._queue.get()) is not None:
            if self._error is None:
                try:
                    job()
                except BaseException as exc:  # reported on the caller's next call
                    if not isinstance(exc, OSError):  # a full disk is the caller's to report, in its words
                        log.exception("MCAP writer thread failed")
                    self._error = exc

    def _stop_worker(self) -> None:
        if self._queue is not None and self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._queue = None

    def _write(self, data: bytes) -> int:
        start = self._pos
        self._stream.write(data)
        self._pos += len(data)
        return start

    def _write_chunk(self, records: bytes | memoryview, indexes: dict[int, np.ndarray], start: int, end: int) -> None:
        compressed = self._compressor.compress(records)
        crc = zlib.crc32(records) if self._chunk_crc else 0
        head = _CHUNK_HEAD.pack(OP_CHUNK, _CHUNK_HEAD.size - 9 + len(compressed), start, end, len(records), crc, 4,
                                b"zstd", len(compressed))  # fmt: skip
        chunk_start = self._write(head)  # (the compressed records follow without being copied into one record)
        self._write(compressed)
        chunk_length = self._pos - chunk_start
        index_start = self._pos
        offsets = []
        parts = []
        for channel_id, pairs in indexes.items():
            offsets.append(_U16.pack(channel_id) + _U64.pack(index_start + sum(map(len, parts))))
            entries = pairs.astype("<u8").tobytes()
            parts.append(_record(OP_MESSAGE_INDEX, _U16.pack(channel_id) + _U32.pack(len(entries)) + entries))
        self._write(b"".join(parts))
        offset_map = b"".join(offsets)
        self._chunk_indexes.append(
            _record(
                OP_CHUNK_INDEX,
                _U64.pack(start)
                + _U64.pack(end)
                + _U64.pack(chunk_start)
                + _U64.pack(chunk_length)
                + _U32.pack(len(offset_map))
                + offset_map
                + _U64.pack(self._pos - index_start)
                + _string("zstd")
                + _U64.pack(len(compressed))
                + _U64.pack(len(records)),
            )
        )
        self._stream.flush()

    def _write_summary(self) -> None:
        self._write(_record(OP_DATA_END, _U32.pack(0)))
        summary_start = self._pos
        counts = b"".join(_U16.pack(c) + _U64.pack(n) for c, n in self._counts.items())
        statistics = _record(
            OP_STATISTICS,
            struct.pack(
                "<QHIIIIQQ",
                self._message_count,
                len(self._schemas),
                len(self._channels),
                0,
                len(self._metadata_indexes),
                len(self._chunk_indexes),
                self._start_time,
                self._end_time,
            )
            + _U32.pack(len(counts))
            + counts,
        )
        groups = [
            (OP_SCHEMA, b"".join(self._schemas)),
            (OP_CHANNEL, b"".join(self._channels)),
            (OP_STATISTICS, statistics),
            (OP_CHUNK_INDEX, b"".join(self._chunk_indexes)),
            (OP_METADATA_INDEX, b"".join(self._metadata_indexes)),
        ]
        summary = bytearray()
        offsets = bytearray()
        for opcode, data in groups:
            if data:
                offsets += _record(
                    OP_SUMMARY_OFFSET, struct.pack("<BQQ", opcode, summary_start + len(summary), len(data))
                )
                summary += data
        summary_offset_start = summary_start + len(summary)
        summary += offsets
        footer_head = struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start)
        crc = zlib.crc32(footer_head, zlib.crc32(summary))
        self._write(bytes(summary) + footer_head + _U32.pack(crc) + MAGIC)
        self._stream.flush()
