"""A lean, streaming MCAP writer (chunked, zstd) tuned for many small messages.

Why not ``mcap.writer.Writer``: its ``add_message`` does much per message (a record dataclass, a
``BytesIO`` with seeks, statistics bookkeeping) and it compresses each chunk on the caller's thread.
At the simulator's rate that alone would use most of the recording budget (``tools/bench_mcap.py`` measures
the overhead of recording). This writer appends each message record to a ``bytearray`` with one
``struct.pack`` and hands finished chunks to a background thread that compresses them (zstandard releases the GIL), writes them and
flushes the file, so every complete chunk is on disk even if the process is killed later.

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


def _batch_counts(batches: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> dict[int, int]:
    """Messages per channel id in :meth:`McapStreamWriter.add_message_records`' batches."""
    if not batches:
        return {}
    ids, counts = np.unique(np.concatenate([b[0] for b in batches]), return_counts=True)
    return dict(zip(ids.tolist(), counts.tolist(), strict=True))


def _merge_index(singles: dict[int, list[int]], batches: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
                 ) -> dict[int, np.ndarray]:  # fmt: skip
    """The message index of a chunk: (M, 2) (log time, offset) entries per channel id, in offset order, the
    channels in the order of their first message (what adding the messages one at a time gives)."""
    if not batches:
        return {c: np.array(flat, dtype=np.int64).reshape(-1, 2) for c, flat in singles.items()}
    ids = [np.concatenate([b[0] for b in batches])]
    times = [np.concatenate([b[1] for b in batches])]
    offsets = [np.concatenate([b[2] for b in batches])]
    for channel_id, flat in singles.items():
        pairs = np.array(flat, dtype=np.int64).reshape(-1, 2)
        ids.append(np.full(len(pairs), channel_id))
        times.append(pairs[:, 0])
        offsets.append(pairs[:, 1])
    channel, time, offset = (np.concatenate(parts) for parts in (ids, times, offsets))
    order = np.argsort(offset, kind="stable")
    channel, time, offset = channel[order], time[order], offset[order]
    firsts = np.unique(channel, return_index=True)[1]
    return {int(c): np.stack((time[channel == c], offset[channel == c]), axis=1) for c in channel[np.sort(firsts)]}


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
        self._chunk: list[bytes | memoryview] = []  # records of the chunk in progress
        self._chunk_bytes = 0
        self._chunk_start = 0
        self._chunk_end = 0
        self._chunk_messages = 0
        self._message_index: dict[int, list[int]] = {}  # (log time, offset) pairs per channel, add_message's
        self._batches: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # add_message_records' (channels, times, offsets)
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
        header = _MESSAGE_HEADER.pack(OP_MESSAGE, 22 + len(data), channel_id, sequence, log_time, publish_time)
        offset = self._chunk_bytes
        index = self._message_index.get(channel_id)
        if index is None:
            index = self._message_index[channel_id] = []
        index += (log_time, offset)
        self._counts[channel_id] += 1
        if self._chunk_messages == 0:
            self._chunk_start = self._chunk_end = log_time
        elif log_time < self._chunk_start:
            self._chunk_start = log_time
        elif log_time > self._chunk_end:
            self._chunk_end = log_time
        self._chunk_messages += 1
        self._chunk += (header, data)
        self._chunk_bytes = offset + len(header) + len(data)
        if self._chunk_bytes >= self._chunk_size:
            self.flush_chunk()

    def add_message_records(self, records: bytes, channel_ids: Sequence[int] | np.ndarray,
                            log_times: Sequence[int] | np.ndarray, sizes: Sequence[int] | np.ndarray) -> None:  # fmt: skip
        """Append consecutive complete message records (each :func:`message_header` + data) given as one
        bytes object: the file is the one :meth:`add_message` would make for each record in turn.

        ``channel_ids``, ``log_times`` and ``sizes`` (record bytes, header included) describe the
        records in order and must match their headers. For callers that encode many messages at once:
        a few array operations per call, not per record (their message index entries are sorted out
        when the chunk is written).
        """
        channel_ids = np.asarray(channel_ids, dtype=np.int64)
        log_times = np.asarray(log_times, dtype=np.int64)
        sizes = np.asarray(sizes, dtype=np.int64)
        if not len(channel_ids) == len(log_times) == len(sizes):
            raise ValueError("channel_ids, log_times and sizes must have one entry per record")
        view = memoryview(records)
        pos = 0  # of the first record not yet in a chunk
        while len(sizes):
            ends = np.cumsum(sizes)
            ends += self._chunk_bytes
            m = len(sizes)
            if ends[-1] >= self._chunk_size:  # the records up to the one that fills the chunk
                m = int(np.argmax(ends >= self._chunk_size)) + 1
            times = log_times[:m]
            first, last = int(times.min()), int(times.max())
            if self._chunk_messages == 0:
                self._chunk_start, self._chunk_end = first, last
            else:
                self._chunk_start, self._chunk_end = min(self._chunk_start, first), max(self._chunk_end, last)
            self._chunk_messages += m
            self._batches.append((channel_ids[:m], times, ends[:m] - sizes[:m]))
            end = pos + int(ends[m - 1]) - self._chunk_bytes
            self._chunk.append(view[pos:end])
            self._chunk_bytes, pos = int(ends[m - 1]), end
            channel_ids, log_times, sizes = channel_ids[m:], log_times[m:], sizes[m:]
            if self._chunk_bytes >= self._chunk_size:
                self.flush_chunk()

    @property
    def message_counts(self) -> dict[int, int]:
        """Messages written so far per channel id."""
        counts = dict(self._counts)
        for channel_id, n in _batch_counts(self._batches).items():
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
        if not self._chunk:
            return
        records = b"".join(self._chunk)
        indexes = _merge_index(self._message_index, self._batches)
        for channel_id, n in _batch_counts(self._batches).items():
            self._counts[channel_id] += n
        start, end = self._chunk_start, self._chunk_end
        if self._chunk_messages:
            first = self._message_count == 0
            self._start_time = start if first else min(self._start_time, start)
            self._end_time = end if first else max(self._end_time, end)
        self._message_count += self._chunk_messages
        self._chunk = []
        self._chunk_bytes = 0
        self._message_index, self._batches = {}, []
        self._chunk_messages = 0
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
        if self._error is not None:
            raise _failure("MCAP writing failed", self._error) from self._error

    def abort(self) -> None:
        """Stop without writing the summary (the file stays a recoverable partial file)."""
        if self._finished:
            return
        self._finished = True
        self._stop_worker()
        self._stream.close()

    def _append(self, record: bytes) -> None:
        self._chunk.append(record)
        self._chunk_bytes += len(record)

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

    def _write_chunk(self, records: bytes, indexes: dict[int, np.ndarray], start: int, end: int) -> None:
        compressed = self._compressor.compress(records)
        body = b"".join(
            (
                _U64.pack(start),
                _U64.pack(end),
                _U64.pack(len(records)),
                _U32.pack(zlib.crc32(records) if self._chunk_crc else 0),
                _string("zstd"),
                _U64.pack(len(compressed)),
                compressed,
            )
        )
        chunk_start = self._write(_record(OP_CHUNK, body))
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
