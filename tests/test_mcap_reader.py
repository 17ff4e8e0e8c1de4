"""read_episode: round trip into DataFrames, truncated-file recovery, clear errors, directory helpers; files of
another writer (every MCAP compression, messages out of order, channels defined again) and hostile ones (chunks
that decompress to far more than the file, messages recorded twice), each made here."""

from __future__ import annotations

import pathlib
import struct
import tracemalloc
import warnings
import zlib
from collections.abc import Callable

import numpy as np
import pandas as pd
import pytest
import zstandard
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from lcdata import TruncatedFileWarning, iter_episodes, list_episodes, read_episode
from lcdata.mcap_scan import MAX_CHUNK_BYTES, Limits, McapRefused, scan_mcap
from lcdata.mcap_write import MAGIC, OP_CHANNEL, OP_CHUNK, OP_DATA_END, OP_MESSAGE, OP_SCHEMA
from lcdata.reader import EGO_COLUMNS, STEP_COLUMNS, TRACK_COLUMNS, Episode
from lcdata.wire import decode_varints, varint
from tests.test_mcap_writer import METADATA, N_VEHICLES, write_episode


@pytest.fixture
def episode_file(tmp_path: pathlib.Path) -> tuple[pathlib.Path, dict[str, np.ndarray]]:
    path = tmp_path / "ep.mcap"
    return path, write_episode(path, steps=30, chunk_size=4096)


def test_tracks_round_trip(episode_file: tuple[pathlib.Path, dict[str, np.ndarray]]) -> None:
    path, s = episode_file
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        episode = read_episode(path)
    tracks = episode.tracks
    assert list(tracks.columns) == TRACK_COLUMNS and len(tracks) == 30 * N_VEHICLES
    assert episode.complete and (tracks["episode"] == "ep").all()
    np.testing.assert_array_equal(tracks["step"], np.repeat(np.arange(30), N_VEHICLES))
    np.testing.assert_array_equal(tracks["t"], np.repeat(np.arange(30) * 0.05, N_VEHICLES))
    np.testing.assert_array_equal(tracks["vehicle_id"], np.tile(s["ids"], 30))
    for name in ("x", "y", "yaw", "speed", "accel", "lane", "target_lane"):
        np.testing.assert_array_equal(tracks[name], s[name].ravel(), err_msg=name)
    np.testing.assert_array_equal(tracks["length"], np.tile(s["length"], 30))
    np.testing.assert_array_equal(tracks["is_ego"], tracks["vehicle_id"] == 0)
    assert (
        tracks["step"].dtype == np.int64
        and tracks["lane"].dtype == np.int64
        and tracks["x"].dtype == np.float64
    )


def test_other_tables_round_trip(episode_file: tuple[pathlib.Path, dict[str, np.ndarray]]) -> None:
    path, s = episode_file
    episode = read_episode(path)
    meta = episode.metadata
    assert meta["config"] == METADATA["config"] and meta["seed"] == 7 and meta["driver"] == "rule-based"
    assert meta["scenario"] == "test" and meta["episode_id"] == "ep" and meta["version"]

    ego = episode.ego
    assert list(ego.columns) == EGO_COLUMNS and len(ego) == 30
    np.testing.assert_array_equal(ego["speed"], s["speed"][:, 0])
    assert ego.loc[12, "collision_with"] == 2 and (ego.drop(index=12)["collision_with"] == -1).all()
    assert ego.loc[5, "lane_invasion"] == 1 and ego["off_road"].sum() == 1 and ego.loc[20, "off_road"]
    assert ego["steer"].eq(-0.1).all()

    steps = episode.steps
    assert list(steps.columns) == STEP_COLUMNS and steps["step"].tolist() == [0, 10, 20]
    assert steps["action"].tolist() == [0, 1, 2] and steps["mask_right"].tolist() == [False, True, True]
    assert steps["r_forward"].tolist() == [0.0, 5.0, 10.0] and steps["terminated"].tolist() == [
        False,
        False,
        True,
    ]
    assert steps["outcome"].tolist() == ["", "", "collision"]
    np.testing.assert_array_equal(episode.observations()[10], np.arange(81).reshape(9, 9))

    events = episode.events
    assert events[["step", "kind", "text", "level"]].values.tolist() == [
        [12, "collision", "ego hit vehicle 2", "warning"]
    ]
    assert events["t"].iloc[0] == pytest.approx(0.6)
    assert episode.collisions["other_id"].tolist() == [2]

    pred = episode.predictions
    assert len(pred) == 3 * 3 * 5 and set(pred["k"]) == {1, 2, 3, 4, 5}
    row = pred[(pred.step == 10) & (pred.slot == 1) & (pred.k == 2)].iloc[0]
    assert (row.vehicle_id, row.x, row.y) == (2, 12.0, 13.0)

    assert episode.image_steps.tolist() == [0, 10, 20]
    image = episode.image(10)
    assert image.shape == (3, 120, 120) and image.dtype == np.uint8 and (image == 10).all()
    assert [step for step, _ in episode.images()] == [0, 10, 20]
    with pytest.raises(KeyError, match="no image at step 5"):
        episode.image(5)


def test_truncated_file_recovers_complete_chunks(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path
) -> None:
    path, s = episode_file
    data = path.read_bytes()
    (summary_start,) = struct.unpack_from("<Q", data, len(data) - 8 - 20)  # from the footer
    recovered = []
    for fraction in (0.3, 0.6, 0.9):
        cut = tmp_path / f"cut{fraction}.mcap.partial"
        cut.write_bytes(data[: int(summary_start * fraction)])
        with pytest.warns(TruncatedFileWarning, match=r"recovered (\d+) messages from (\d+) complete chunks"):
            episode = read_episode(cut)
        assert not episode.complete and episode.message_count > 0
        tracks = episode.tracks
        n_steps = tracks["step"].nunique()
        np.testing.assert_array_equal(tracks["x"], s["x"][:n_steps].ravel())
        recovered.append(episode.message_count)
    assert recovered == sorted(recovered) and recovered[0] < recovered[-1]

    # Losing only the summary (index) section loses no data: no warning, every message read.
    cut = tmp_path / "no_summary.mcap"
    cut.write_bytes(data[:summary_start])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        episode = read_episode(cut)
    assert episode.complete and len(episode.tracks) == len(s["x"].ravel())


def test_a_record_that_cannot_be_decoded_reads_as_a_damaged_file_not_a_truncated_one(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path
) -> None:
    """A file whose bytes are all there but hold a record that does not decode is damaged: the warning says so,
    with the record's place, and the chunks before it are recovered as from a truncated file."""
    path, _ = episode_file
    data = path.read_bytes()
    pos = len(MAGIC)
    while data[pos] != OP_CHUNK:  # to the end of the first chunk
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    topic = b"\xff\xfe"  # not UTF-8
    body = struct.pack("<HHI", 99, 0, len(topic)) + topic + struct.pack("<I", 0) + struct.pack("<I", 0)
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(data[:pos] + struct.pack("<BQ", OP_CHANNEL, len(body)) + body + data[pos:])
    with pytest.warns(TruncatedFileWarning, match=r"damaged MCAP file \(corrupt record \(opcode 0x04 at byte"):
        episode = read_episode(bad)
    assert not episode.complete and episode.message_count > 0


def test_non_mcap_file_raises(tmp_path: pathlib.Path) -> None:
    bad = tmp_path / "notes.mcap"
    bad.write_text("hello, not an mcap\n")
    with pytest.raises(ValueError, match=r"notes\.mcap: not an MCAP file"):
        read_episode(bad)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.mcap"):
        read_episode(empty)


def test_foreign_mcap_raises(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "foreign.mcap"
    with path.open("wb") as f:
        writer = McapWriter(f)
        writer.start()
        schema = writer.register_schema("Point", "jsonschema", b"{}")
        channel = writer.register_channel("/points", "json", schema)
        writer.add_message(channel, 1, b'{"x": 1}', 1)
        writer.finish()
    with pytest.raises(ValueError, match=r"foreign\.mcap: MCAP file holds no lc-toolkit data"):
        read_episode(path)


def test_list_and_iter_episodes(tmp_path: pathlib.Path) -> None:
    for name in ("b.mcap", "a.mcap", "nested/c.mcap"):
        write_episode(tmp_path / name, steps=2)
    (tmp_path / "d.mcap.partial").write_bytes((tmp_path / "a.mcap").read_bytes()[:200])
    assert [p.relative_to(tmp_path).as_posix() for p in list_episodes(tmp_path)] == [
        "a.mcap",
        "b.mcap",
        "nested/c.mcap",
    ]
    assert len(list_episodes(tmp_path, include_partial=True)) == 4
    assert [e.episode_id for e in iter_episodes(tmp_path)] == ["a", "b", "c"]


def test_decode_varints_matches_encoder() -> None:
    values = [0, 1, 127, 128, 300, 2**31, 2**63 - 1]
    data = np.frombuffer(b"".join(varint(v) for v in values), dtype=np.uint8)
    assert decode_varints(data).tolist() == values
    assert decode_varints(np.array([5, 6], np.uint8)).tolist() == [5, 6]


# -- files from elsewhere: another writer, every compression; hostile chunk headers --------------------------
MIB = 1 << 20


def record(opcode: int, body: bytes) -> bytes:
    """One MCAP record: opcode, u64 length, body."""
    return struct.pack("<BQ", opcode, len(body)) + body


def chunk(
    records: bytes,
    *,
    compression: str = "zstd",
    size: int | None = None,
    compressed: bytes | None = None,
    crc: int | None = None,
) -> bytes:
    """A Chunk record of ``records`` (zstd unless ``compressed`` is given); ``size`` and ``crc`` default to the
    true ones."""
    data = zstandard.ZstdCompressor().compress(records) if compressed is None else compressed
    size = len(records) if size is None else size
    crc = zlib.crc32(records) if crc is None else crc
    name = compression.encode()
    return record(OP_CHUNK, struct.pack("<QQQI", 0, 0, size, crc) + struct.pack("<I", len(name)) + name
                  + struct.pack("<Q", len(data)) + data)  # fmt: skip


def zeros_frame(prefix: bytes, size: int) -> bytes:
    """A zstd frame, its content size in its header, of ``prefix`` then zeros (``size`` bytes), made piecewise."""
    cobj = zstandard.ZstdCompressor().compressobj(size=size)
    parts, left = [cobj.compress(prefix)], size - len(prefix)
    while left > 0:
        parts.append(cobj.compress(bytes(min(left, MIB))))
        left -= MIB
    return b"".join([*parts, cobj.flush()])


def message(channel_id: int, log_time: int, payload_size: int) -> bytes:
    """A Message record's header and fixed fields; ``payload_size`` bytes of payload belong after it."""
    return struct.pack("<BQHIQQ", OP_MESSAGE, 22 + payload_size, channel_id, 0, log_time, log_time)


def take_apart(path: pathlib.Path) -> tuple[list[bytes], list[bytes], list[bytes]]:
    """A file of our writer as records: those before the first chunk (header, metadata), the schema and channel
    records of its chunks, its message records; each whole, in file order."""
    data, pos = path.read_bytes(), len(MAGIC)
    head: list[bytes] = []
    defs: list[bytes] = []
    messages: list[bytes] = []
    while (opcode := data[pos]) != OP_DATA_END:
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        body = data[pos + 9 : pos + 9 + length]
        if opcode == OP_CHUNK:
            (n,) = struct.unpack_from("<I", body, 28)
            inner = zstandard.ZstdDecompressor().decompress(body[28 + 4 + n + 8 :])
            p = 0
            while p < len(inner):
                (size,) = struct.unpack_from("<Q", inner, p + 1)
                (defs if inner[p] in (OP_SCHEMA, OP_CHANNEL) else messages).append(inner[p : p + 9 + size])
                p += 9 + size
        elif not defs:
            head.append(data[pos : pos + 9 + length])
        pos += 9 + length
    return head, defs, messages


def assemble(path: pathlib.Path, records: list[bytes]) -> pathlib.Path:
    """Write a file of ``records``: magic, the records, data end, a footer without summary, magic."""
    path.write_bytes(
        MAGIC + b"".join(records) + record(OP_DATA_END, bytes(4)) + record(0x02, bytes(20)) + MAGIC
    )
    return path


def rewrite_with_mcap_package(src: pathlib.Path, dst: pathlib.Path, compression: str = "lz4", *,
                              chunked: bool = True, reverse: bool = False, twice: str = "",
                              two_channels: str = "") -> pathlib.Path:  # fmt: skip
    """``src`` written again by ``mcap.writer.Writer`` (another writer): chunks of 4 KiB compressed with
    ``compression`` ("lz4", "zstd", "" for none) or no chunks; messages in reverse log-time order; every
    message of topic ``twice`` written twice; the messages of topic ``two_channels`` alternating between two
    channels of that topic."""
    kinds = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "": CompressionType.NONE}
    with src.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
        messages = list(reader.iter_messages(log_time_order=False))
    if reverse:
        messages.sort(key=lambda m: m[2].log_time, reverse=True)
    with dst.open("wb") as out:
        writer = McapWriter(out, chunk_size=4096, compression=kinds[compression], use_chunking=chunked)
        writer.start(profile="", library="another-writer")
        for name, data in metadata:
            writer.add_metadata(name, data)
        schemas = {s.id: writer.register_schema(s.name, s.encoding, s.data) for s in summary.schemas.values()}
        channels = {}
        for c in summary.channels.values():
            copies = 2 if c.topic == two_channels else 1
            channels[c.id] = [writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
                              for _ in range(copies)]  # fmt: skip
        for i, (_schema, channel, m) in enumerate(messages):
            ids = channels[channel.id]
            for _ in range(2 if channel.topic == twice else 1):
                writer.add_message(ids[i % len(ids)], m.log_time, m.data, m.publish_time)
        writer.finish()
    return dst


def assert_same_episode(got: Episode, want: Episode) -> None:
    """Every table and image of two readings of one episode are equal."""
    pd.testing.assert_frame_equal(got.tracks, want.tracks)
    for table in ("ego", "steps", "events", "collisions", "predictions"):
        pd.testing.assert_frame_equal(getattr(got, table), getattr(want, table), obj=table)
    assert got.image_steps.tolist() == want.image_steps.tolist()
    for (_, a), (_, b) in zip(got.images(), want.images(), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    ("compression", "chunked"), [("lz4", True), ("zstd", True), ("", True), ("lz4", False)]
)
def test_another_writers_file_reads_with_every_compression(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path, compression: str,
    chunked: bool,
) -> None:  # fmt: skip
    """The compressions the MCAP specification defines ("", "lz4", "zstd"), chunked or not, read in full:
    an lz4 file read as an empty, "truncated" episode."""
    path, _ = episode_file
    other = rewrite_with_mcap_package(path, tmp_path / "other.mcap", compression, chunked=chunked)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        episode = read_episode(other)
    assert episode.complete and episode.message_count == read_episode(path).message_count
    assert_same_episode(episode, read_episode(path))


def test_messages_out_of_log_time_order_are_put_in_order(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path
) -> None:
    """The specification does not order messages: another writer's in reverse order, or our chunks in
    reverse order, read as the original."""
    path, _ = episode_file
    want = read_episode(path)
    reverse = read_episode(rewrite_with_mcap_package(path, tmp_path / "reverse.mcap", "zstd", reverse=True))
    head, defs, messages = take_apart(path)
    chunks = [chunk(b"".join(messages[i : i + 40])) for i in range(0, len(messages), 40)]
    shuffled = read_episode(assemble(tmp_path / "chunks.mcap", [*head, chunk(b"".join(defs)), *chunks[::-1]]))
    for episode in (reverse, shuffled):
        assert_same_episode(episode, want)


def test_channels_defined_again_or_shared_by_a_topic_keep_every_message(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path
) -> None:
    """A channel defined again in every chunk (the specification allows identical repeats) and a topic on two
    channels lost messages silently: the repeat and the second channel started a list nobody read."""
    path, _ = episode_file
    want = read_episode(path)
    head, defs, messages = take_apart(path)
    repeated = [chunk(b"".join(defs + messages[i : i + 40])) for i in range(0, len(messages), 40)]
    assert_same_episode(read_episode(assemble(tmp_path / "repeated.mcap", [*head, *repeated])), want)
    shared = rewrite_with_mcap_package(path, tmp_path / "shared.mcap", "zstd", two_channels="/vehicles")
    assert_same_episode(read_episode(shared), want)


def test_duplicated_messages_and_redefined_channels_are_refused(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path
) -> None:
    path, _ = episode_file
    head, defs, messages = take_apart(path)
    twice = assemble(
        tmp_path / "twice.mcap", [*head, chunk(b"".join(defs + messages)), chunk(b"".join(messages))]
    )
    with pytest.raises(
        ValueError, match=r"twice\.mcap: /\S+ holds the same message twice at log time \d+ ns"
    ):
        read_episode(twice)
    doubled = rewrite_with_mcap_package(path, tmp_path / "doubled.mcap", "lz4", twice="/vehicles")
    with pytest.raises(ValueError, match=r"doubled\.mcap: /vehicles holds the same message twice"):
        read_episode(doubled)
    vehicles = next(d for d in defs if d[0] == OP_CHANNEL and b"/vehicles" in d)
    channel_id, schema_id = struct.unpack_from("<HH", vehicles, 9)
    other = record(OP_CHANNEL, struct.pack("<HHI", channel_id, schema_id, 6) + b"/other" + vehicles[17 + 9 :])
    redefined = assemble(tmp_path / "redefined.mcap", [*head, chunk(b"".join(defs + messages[:50])),
                                                       chunk(other + b"".join(messages[50:]))])  # fmt: skip
    with pytest.raises(ValueError, match=rf"redefined\.mcap: MCAP channel {channel_id} is defined twice, as "
                                         r"/vehicles \(lc\.VehicleTracks\) then as /other"):  # fmt: skip
        read_episode(redefined)


@pytest.mark.parametrize("name", ["bz2", "LZ4", "gzip"])
def test_a_compression_the_specification_does_not_define_is_refused_by_name(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path, name: str
) -> None:
    """It read as a truncated file: a warning, and nothing from its first chunk on."""
    path, _ = episode_file
    head, defs, messages = take_apart(path)
    bad = assemble(tmp_path / "bad.mcap", [*head, chunk(b"".join(defs + messages), compression=name)])
    with pytest.raises(ValueError, match=rf"bad\.mcap: the MCAP chunk at byte \d+ is compressed with '{name}', "
                                         "which the MCAP specification does not define"):  # fmt: skip
        read_episode(bad)


JUNK = 60000  # a channel id our writer does not use


def zeros_chunk(prefix: bytes, size: int) -> bytes:
    """A chunk (no CRC) of ``prefix`` then zeros, ``size`` bytes uncompressed: a few bytes per MiB compressed."""
    return chunk(b"", size=size, crc=0, compressed=zeros_frame(prefix, size))


def _junk_channel() -> bytes:
    return chunk(record(OP_CHANNEL, struct.pack("<HHI", JUNK, 0, 5) + b"/junk" + struct.pack("<I", 0) * 2))


BOMBS: dict[str, tuple[Callable[[], list[bytes]], str]] = {
    # the audit's file: 15 chunks of 200 MiB, each a message whose payload kept its chunk alive (3.4 GB)
    "declared too large": (
        lambda: [_junk_channel(), *[zeros_chunk(message(JUNK, 1, 200 * MIB), 31 + 200 * MIB)] * 15],
        r"declares 209,715,231 bytes uncompressed, more than the 67,108,864 a chunk may hold",
    ),
    "ratio": (
        lambda: [zeros_chunk(b"", 32 * MIB)],
        r"declares 33,554,432 bytes uncompressed from [\d,]+ compressed, more than 1000 to 1",
    ),
    # 4 MiB chunks, each allowed, 20 of them more than a small file may decompress to
    "total": (
        lambda: [_junk_channel(), *[zeros_chunk(message(JUNK, 1, 4 * MIB - 31), 4 * MIB)] * 20],
        r"its chunks decompress to more than 67,108,864 bytes, the most read from a file of [\d,]+ bytes",
    ),
    # zero bytes are empty records (opcode 0, 9 bytes): 3.9 MB of them are 433,333 records to walk
    "records": (
        lambda: [zeros_chunk(b"", 3_900_000)],
        r"more than 100,000 MCAP records, the most read from a file of [\d,]+ bytes",
    ),
    "declared 1 TiB": (
        lambda: [chunk(b"\0" * 90, size=1 << 40)],
        r"declares 1,099,511,627,776 bytes uncompressed",
    ),
}
"""Chunks a small file may hold (made on demand), and the refusal each must end in."""


@pytest.mark.parametrize("bomb", list(BOMBS))
def test_small_files_that_decompress_to_too_much_are_refused_before_the_work(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path, bomb: str
) -> None:
    """Refused in one line with little memory: declared sizes are checked before decompressing."""
    path, _ = episode_file
    head, defs, messages = take_apart(path)
    make, refusal = BOMBS[bomb]
    chunks = make()
    bad = assemble(tmp_path / "bomb.mcap", [*head, chunk(b"".join(defs + messages)), *chunks])
    assert bad.stat().st_size < 200_000
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=rf"bomb\.mcap: .*{refusal}") as caught:
            read_episode(bad)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "\n" not in str(caught.value) and isinstance(caught.value, McapRefused)
    assert peak < 100 * MIB, peak  # refused before the work: little memory (tools/audit_inputs.py times it)


def test_a_frame_larger_than_its_chunk_declares_is_never_decompressed_whole(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]], tmp_path: pathlib.Path
) -> None:
    """A zstd frame whose header claims 256 MiB was allocated whole, whatever the chunk declared; now no more
    than the chunk's declared size is produced, and the chunk is damage: the complete part before it reads."""
    path, _ = episode_file
    head, defs, messages = take_apart(path)
    lying = chunk(b"", size=1000, crc=0, compressed=zeros_frame(b"", 256 * MIB))  # the frame claims 256 MiB
    bad = assemble(tmp_path / "lying.mcap", [*head, chunk(b"".join(defs + messages)), lying])
    tracemalloc.start()
    try:
        with pytest.warns(TruncatedFileWarning, match=r"corrupt chunk \(size or CRC mismatch\)"):
            episode = read_episode(bad)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50 * MIB and len(episode.tracks) == len(read_episode(path).tracks)


def test_limits_scale_with_the_file_and_leave_room_for_recordings(
    episode_file: tuple[pathlib.Path, dict[str, np.ndarray]],
) -> None:
    small, mid, huge = Limits.for_file(10_000), Limits.for_file(10 * MIB), Limits.for_file(1 << 40)
    assert (small.decompressed_bytes, small.records) == (64 * MIB, 100_000)
    assert (mid.decompressed_bytes, mid.records) == (640 * MIB, 10 * MIB // 4)
    assert (huge.decompressed_bytes, huge.records) == (2 << 30, 5_000_000)
    path, _ = episode_file  # constant images: one of the most compressible recordings there is
    scan = scan_mcap(path)
    assert scan.complete and scan.messages < Limits.for_file(path.stat().st_size).records
    assert MAX_CHUNK_BYTES == 64 * MIB
