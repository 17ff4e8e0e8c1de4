"""Structured fuzzing of MCAP chunk headers: declared sizes, compression names, CRCs, record lengths, the
compressed stream itself and the records inside, on a small valid file written here. The reader must read the
file or refuse it with a one-line ``ValueError``, quickly, within a memory limit.

The reading happens in a child process (``spawn``) whose address space is limited (``RLIMIT_AS``), so that a
blow-up fails the test instead of the machine; the pytest process itself (torch imported) is not limited.
"""

from __future__ import annotations

import functools
import multiprocessing
import multiprocessing.connection
import pathlib
import resource
import struct
import warnings
import zlib
from collections.abc import Iterator
from typing import Any

import lz4.frame
import pytest
import zstandard
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from lcdata.mcap_write import OP_CHUNK
from tests.test_mcap_reader import MIB, assemble, message, record, take_apart, zeros_frame
from tests.test_mcap_writer import write_episode

MEMORY_LIMIT = 1_500_000_000
"""Address space of the reading process: imports take about 0.6 GB of it, a file may cost the rest."""


def _read(path: str) -> tuple[str, str, list[str], int]:
    """(outcome, detail, warnings, peak RSS in kB) of reading ``path`` whole: ``ok`` (detail: the rows),
    ``refused`` (a ValueError: its message), ``memory`` or ``error`` (anything else)."""
    from lcdata.reader import read_episode

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            episode = read_episode(path)
            outcome = (
                "ok",
                f"{len(episode.tracks)} rows, {len(episode.steps)} steps, {len(episode.events)} events",
            )
        except ValueError as exc:
            outcome = ("refused", str(exc))
        except MemoryError:
            outcome = ("memory", "MemoryError")
        except Exception as exc:
            outcome = ("error", f"{type(exc).__name__}: {exc}")
    return (*outcome, [str(w.message) for w in caught], resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def _serve(conn: multiprocessing.connection.Connection, limit: int) -> None:
    """The child: limit the address space, then read each path sent until ``None``."""
    resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    while (path := conn.recv()) is not None:
        conn.send(_read(path))


class LimitedReader:
    """``read_episode`` in a long-lived child process under an address-space limit, restarted after a hang or
    a death."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._context = multiprocessing.get_context("spawn")
        self._start()

    def _start(self) -> None:
        self._conn, child = self._context.Pipe()
        self._proc = self._context.Process(target=_serve, args=(child, self.limit), daemon=True)
        self._proc.start()
        child.close()

    def read(self, path: pathlib.Path, timeout: float) -> tuple[str, str, list[str], int]:
        """Like :func:`_read`; outcome ``hang`` after ``timeout`` seconds, ``died`` when the child dies."""
        self._conn.send(str(path))
        try:
            if self._conn.poll(timeout):
                return self._conn.recv()
            outcome = ("hang", f"no answer after {timeout} s")
        except EOFError:
            outcome = ("died", "")
        self._proc.kill()
        self._proc.join()
        outcome = (outcome[0], outcome[1] or f"exit code {self._proc.exitcode}")
        self._start()
        return (*outcome, [], 0)

    def close(self) -> None:
        self._conn.send(None)
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()


@pytest.fixture(scope="module")
def reader() -> Iterator[LimitedReader]:
    limited = LimitedReader(MEMORY_LIMIT)
    yield limited
    limited.close()


class Parts:
    """The small valid file (about ten 4 KiB chunks): the records before its chunks, and its chunks."""

    def __init__(self, head: list[bytes], chunks: list[bytes]) -> None:
        self.head, self.chunks = head, chunks

    def __repr__(self) -> str:  # hypothesis prints it with a failing example
        return f"Parts({len(self.head)} records, {len(self.chunks)} chunks)"


@pytest.fixture(scope="module")
def parts(tmp_path_factory: pytest.TempPathFactory) -> Parts:
    path = tmp_path_factory.mktemp("fuzz_mcap") / "ep.mcap"
    write_episode(path, steps=30, chunk_size=4096)
    head, _, _ = take_apart(path)
    data, pos, chunks = path.read_bytes(), sum(map(len, head)) + 8, []
    while data[pos] == OP_CHUNK:
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        chunks.append(data[pos : pos + 9 + length])
        pos += 9 + length
        while data[pos] == 0x07:  # message indexes: left out
            pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    return Parts(head, chunks)


@functools.cache
def _frame(kind: str, size: int) -> bytes:
    """A zstd frame of ``size`` bytes: zeros (empty records, 9 bytes each), or one message on channel 1 whose
    payload is zeros (it keeps its chunk in memory)."""
    return zeros_frame(b"" if kind == "zeros" else message(1, 1, size - 31), size)


U64 = st.integers(0, 2**64 - 1)
SIZES = st.sampled_from([0, 1, 8, 4 * MIB, 4 * MIB + 1, 64 * MIB, 64 * MIB + 1, 1 << 30, 2**63, 2**64 - 1])


FIELDS: dict[str, st.SearchStrategy[Any]] = {
    # the declared uncompressed size: anything, a size at a limit, near the true one, what the stream holds
    "size": st.one_of(U64, SIZES, st.sampled_from(["near", "stream"])),
    "size_near": st.integers(-64, 64),
    "compression": st.sampled_from(["", "lz4", "zstd", "bz2", "ZSTD", "zstd\0", "lz4 "])
    | st.text(max_size=6),
    "crc": st.just(0) | st.integers(0, 2**32 - 1),
    # the compressed records: the same records in lz4 or none (the name follows), garbage, cut short, or a
    # zstd frame of zeros (empty records) or of one message with a payload of zeros
    "stream": st.sampled_from(["lz4", "none", "garbage", "truncated"])
    | st.tuples(st.sampled_from(["zeros", "message"]), st.sampled_from([MIB, 4 * MIB, 64 * MIB, 200 * MIB])),
    "records_size": st.one_of(U64, st.integers(-64, 64)),
    "record_length": st.one_of(U64, st.integers(-64, 64)),
    "inner": st.tuples(st.integers(0, 1000), U64 | st.integers(0, 64)),  # a record length inside the chunk
    # a consistent bomb: such a frame, declared at its true size, no CRC
    "bomb": st.tuples(st.sampled_from(["zeros", "message"]), st.sampled_from([4 * MIB, 64 * MIB, 200 * MIB])),
}


@st.composite
def chunk_damage(draw: st.DrawFn) -> dict[str, Any]:
    """Which chunk, how many times it is repeated, and one to three of :data:`FIELDS` changed (``None``: the
    true value)."""
    changed = draw(st.sets(st.sampled_from(sorted(FIELDS)), min_size=1, max_size=3))
    if "size" in changed:
        changed.add("size_near")
    damage: dict[str, Any] = {name: draw(FIELDS[name]) if name in changed else None for name in FIELDS}
    damage["which"] = draw(st.integers(0, 1000))
    damage["repeat"] = draw(st.sampled_from([1, 1, 2, 15, 40]))
    return damage


def damaged_file(
    head: list[bytes], chunks: list[bytes], damage: dict[str, Any], path: pathlib.Path
) -> pathlib.Path:
    """The file with one chunk changed as ``damage`` says (and repeated ``damage["repeat"]`` times)."""
    i = damage["which"] % len(chunks)
    body = chunks[i][9:]
    _start, _end, size, crc = struct.unpack_from("<QQQI", body, 0)
    (n,) = struct.unpack_from("<I", body, 28)
    compression = body[32 : 32 + n].decode()
    compressed = body[32 + n + 8 :]
    records = zstandard.ZstdDecompressor().decompress(compressed, max_output_size=size)
    if damage["inner"] is not None:  # a record length inside the chunk
        offsets, p = [], 0
        while p < len(records):
            offsets.append(p)
            p += 9 + struct.unpack_from("<Q", records, p + 1)[0]
        at, value = damage["inner"]
        mutable = bytearray(records)
        struct.pack_into("<Q", mutable, offsets[at % len(offsets)] + 1, value)
        records = bytes(mutable)
        compressed, size, crc = (
            zstandard.ZstdCompressor().compress(records),
            len(records),
            zlib.crc32(records),
        )
    stream = damage["stream"]
    if damage["bomb"] is not None:
        stream, damage = damage["bomb"], {**damage, "size": "stream", "crc": 0}
    if stream == "lz4":
        compressed, compression = lz4.frame.compress(records), "lz4"
    elif stream == "none":
        compressed, compression = records, ""
    elif stream == "garbage":
        compressed = bytes(range(256)) * 4
    elif stream == "truncated":
        compressed = compressed[: len(compressed) // 2]
    elif isinstance(stream, tuple):
        compressed = _frame(*stream)
    if damage["size"] == "stream":  # what the stream holds
        size = stream[1] if isinstance(stream, tuple) else len(records)
    elif damage["size"] == "near":
        size = max(0, size + damage["size_near"])
    elif damage["size"] is not None:
        size = damage["size"]
    if damage["compression"] is not None:
        compression = damage["compression"]
    crc = crc if damage["crc"] is None else damage["crc"]
    name = compression.encode()
    records_size = len(compressed)
    if damage["records_size"] is not None:
        value = damage["records_size"]
        records_size = value if value > 64 else max(0, records_size + value)
    new_body = (struct.pack("<QQQI", 0, 0, size, crc) + struct.pack("<I", len(name)) + name
                + struct.pack("<Q", records_size) + compressed)  # fmt: skip
    new = record(OP_CHUNK, new_body)
    if damage["record_length"] is not None:
        value = damage["record_length"]
        length = value if value > 64 else max(0, len(new_body) + value)
        new = struct.pack("<BQ", OP_CHUNK, length) + new_body
    return assemble(path, [*head, *chunks[:i], *[new] * damage["repeat"], *chunks[i + 1 :]])


def known(bomb: tuple[str, int], repeat: int, which: int = 5) -> dict[str, Any]:
    """A damage found by the audit: ``bomb`` in chunk ``which``, repeated."""
    return {**dict.fromkeys(FIELDS), "bomb": bomb, "which": which, "repeat": repeat}


@settings(max_examples=40, deadline=None, print_blob=True, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                                 HealthCheck.too_slow])  # fmt: skip
@given(damage=chunk_damage())
@example(damage=known(("message", 200 * MIB), 15))  # ~120 KB: 3 GB of payloads kept alive
@example(damage=known(("zeros", 64 * MIB), 3))  # ~6 KB more: 22 million empty records to walk
@example(damage=known(("message", 4 * MIB), 40))  # every chunk allowed, 160 MiB in all
def test_damaged_chunk_headers_read_or_are_refused_quickly_within_memory(
    reader: LimitedReader, parts: Parts, tmp_path_factory: pytest.TempPathFactory, damage: dict[str, Any]
) -> None:
    path = damaged_file(parts.head, parts.chunks, damage, tmp_path_factory.mktemp("case") / "ep.mcap")
    outcome, detail, warned, _peak = reader.read(path, timeout=60)  # (no answer in a minute: a hang)
    assert outcome in ("ok", "refused"), f"{outcome}: {detail[:300]}"
    if outcome == "refused":
        assert str(path) in detail and "\n" not in detail.strip(), detail
    assert not any("MemoryError" in w for w in warned), warned  # a blow-up the scan took for damage


def test_the_harness_reports_what_is_not_a_refusal_and_limits_memory(
    reader: LimitedReader, tmp_path: pathlib.Path
) -> None:
    """Anything but a ValueError comes back as such (a missing file: FileNotFoundError), and the limit holds:
    2 GB cannot be allocated under it."""
    outcome, detail, *_ = reader.read(tmp_path / "missing.mcap", timeout=60)
    assert outcome == "error" and detail.startswith("FileNotFoundError")
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    proc = ctx.Process(target=_allocate, args=(child, MEMORY_LIMIT), daemon=True)
    proc.start()
    assert conn.recv() == "MemoryError"
    proc.join(30)


def _allocate(conn: multiprocessing.connection.Connection, limit: int) -> None:
    resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    try:
        bytearray(2_000_000_000)
        conn.send("allocated")
    except MemoryError:
        conn.send("MemoryError")
