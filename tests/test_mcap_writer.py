"""EpisodeWriter: wire encoders, MCAP validity (official reader, Rerun), file life cycle, crash safety."""

from __future__ import annotations

import json
import pathlib
import shutil
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lcdata import EpisodeWriter, TruncatedFileWarning, partial_path, read_episode
from lcdata.encode import encode_cubes, encode_ego, encode_image, encode_transform, encode_vehicles
from lcdata.proto import lc_pb2

ROOT = pathlib.Path(__file__).resolve().parents[1]
N_VEHICLES = 4
METADATA = {"config": {"dt_s": 0.05, "num_lanes": 4}, "seed": 7, "driver": "rule-based", "scenario": "test"}


def make_state(steps: int, n: int = N_VEHICLES, seed: int = 0) -> dict[str, np.ndarray]:
    """Small deterministic (steps, n) simulator-like arrays."""
    rng = np.random.default_rng(seed)
    return {
        "ids": np.arange(n, dtype=np.int64),
        "x": rng.uniform(0, 100, (steps, n)), "y": rng.uniform(0, 14, (steps, n)),
        "yaw": rng.normal(0, 0.1, (steps, n)), "speed": rng.uniform(5, 9, (steps, n)),
        "accel": rng.normal(0, 1, (steps, n)), "lane": rng.integers(0, 4, (steps, n)),
        "target_lane": rng.integers(-1, 4, (steps, n)),
        "length": np.full(n, 4.18), "width": np.full(n, 1.99),
    }  # fmt: skip


def write_episode(path: pathlib.Path, steps: int = 30, **kwargs) -> dict[str, np.ndarray]:
    """Write a small episode with every topic; return the arrays written."""
    s = make_state(steps)
    with EpisodeWriter(path, metadata=METADATA, start_time_ns=1_700_000_000_000_000_000, **kwargs) as w:
        w.write_lane_markings(0.0, [np.array([[0.0, k * 3.5], [200.0, k * 3.5]]) for k in range(5)],
                              [True, False, False, False, True])  # fmt: skip
        for k in range(steps):
            t = k * 0.05
            w.write_vehicles(k, t, s["ids"], s["x"][k], s["y"][k], s["yaw"][k], s["speed"][k], s["accel"][k],
                             s["lane"][k], s["target_lane"][k], s["length"], s["width"])  # fmt: skip
            w.write_ego(k, t, speed=s["speed"][k, 0], lane=s["lane"][k, 0], collision_with=2 if k == 12 else -1,
                        lane_invasion=1 if k == 5 else -1, off_road=k == 20, steer=-0.1, throttle=0.5, brake=0.0)  # fmt: skip
            w.write_transform(k, t, s["x"][k, 0], s["y"][k, 0], s["yaw"][k, 0])
            if k == 12:
                w.write_collision(k, t, other_id=2, ego_x=s["x"][k, 0], ego_y=s["y"][k, 0], ego_speed=7.0,
                                  other_speed=6.0)  # fmt: skip
                w.write_event(k, t, "collision", "ego hit vehicle 2", "warning")
            if k % 10 == 0:
                w.write_image(k, t, np.full((3, 120, 120), k, dtype=np.uint8))
                w.write_scene(k, t, s["ids"], s["x"][k], s["y"][k], s["yaw"][k], s["length"], s["width"])
                w.write_rl_step(k, t, action=k // 10 % 3, action_mask=[k > 0, True, False], reward=0.5 * k,
                                reward_components={"forward": 0.5 * k}, decision=k // 10,
                                terminated=k == 20, outcome="collision" if k == 20 else "",
                                obs_current=np.arange(81).reshape(9, 9))  # fmt: skip
                w.write_prediction(
                    k, t, np.array([1, 2, -1]), np.arange(3 * 5 * 2, dtype=float).reshape(3, 5, 2)
                )
    return s


# -- encoders against the protobuf runtime -----------------------------------------------------------
def test_vehicle_tracks_encoding_is_valid_protobuf() -> None:
    s = make_state(1, n=7)
    cols = [s[k] if s[k].ndim == 1 else s[k][0] for k in
            ("ids", "x", "y", "yaw", "speed", "accel", "lane", "target_lane", "length", "width")]  # fmt: skip
    msg = lc_pb2.VehicleTracks.FromString(encode_vehicles(123456789, 2.5, *cols))
    assert msg.step == 123456789 and msg.t == 2.5
    for name, col in zip(("ids", "x", "y", "yaw", "speed", "accel", "lane", "target_lane", "length", "width"),
                         cols, strict=True):  # fmt: skip
        np.testing.assert_array_equal(np.asarray(getattr(msg, name)), col, err_msg=name)
    empty = lc_pb2.VehicleTracks.FromString(encode_vehicles(3, 0.1, *[c[:0] for c in cols]))
    assert empty.step == 3 and len(empty.x) == 0


def test_ego_state_encoding_is_valid_protobuf() -> None:
    msg = lc_pb2.EgoState.FromString(encode_ego(2**40, 1.25, 8.3, 3, -1, 4, True, -0.2, 0.7, 0.1))
    assert (msg.step, msg.t, msg.speed, msg.lane, msg.collision_with) == (2**40, 1.25, 8.3, 3, -1)
    assert (msg.lane_invasion, msg.off_road, msg.steer, msg.throttle, msg.brake) == (4, True, -0.2, 0.7, 0.1)
    zero = lc_pb2.EgoState.FromString(encode_ego(0, 0.0, 0.0, 0, 0, 0, False, 0.0, 0.0, 0.0))
    assert zero.collision_with == 0 and not zero.off_road


def test_foxglove_encodings_are_valid_protobuf() -> None:
    chw = np.random.default_rng(0).integers(0, 255, (3, 6, 5), dtype=np.uint8)
    image = RawImage.FromString(encode_image(3_000_000_001, chw))
    assert (image.width, image.height, image.step, image.encoding) == (5, 6, 15, "rgb8")
    assert image.timestamp.seconds == 3 and image.timestamp.nanos == 1
    np.testing.assert_array_equal(
        np.frombuffer(image.data, np.uint8).reshape(6, 5, 3).transpose(2, 0, 1), chw
    )
    with pytest.raises(ValueError, match="3, H, W"):
        encode_image(0, chw[0])

    tf = FrameTransform.FromString(encode_transform(5, 10.0, -2.0, np.pi / 2))
    assert (tf.parent_frame_id, tf.child_frame_id, tf.translation.x, tf.translation.y) == (
        "world",
        "ego",
        10.0,
        -2.0,
    )
    assert tf.rotation.z == pytest.approx(np.sqrt(0.5)) and tf.rotation.w == pytest.approx(np.sqrt(0.5))

    entity = SceneUpdate.FromString(b"\x12" + bytes([0]))  # empty entity parses
    assert len(entity.entities) == 1
    x, y, yaw = np.array([1.0, 2.0]), np.array([3.0, 4.0]), np.array([0.0, np.pi])
    raw = encode_cubes(
        x, y, yaw, np.array([4.0, 5.0]), np.array([2.0, 1.8]), 1.5, np.array([[1, 0, 0, 1], [0, 0, 1, 1]])
    )
    from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity

    cubes = SceneEntity.FromString(raw).cubes
    assert [c.pose.position.x for c in cubes] == [1.0, 2.0] and [c.size.x for c in cubes] == [4.0, 5.0]
    assert cubes[1].pose.orientation.w == pytest.approx(0.0, abs=1e-12) and cubes[1].color.b == 1.0
    assert cubes[0].pose.position.z == 0.75 and cubes[0].size.z == 1.5


# -- the file ------------------------------------------------------------------------------------------
def test_official_mcap_reader_decodes_every_message(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "ep.mcap"
    write_episode(path, chunk_size=2048)
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.chunk_count > 3
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert (
            topics["/vehicles"] == "lc.VehicleTracks"
            and topics["/camera/bev_semantic"] == "foxglove.RawImage"
        )
        assert topics["/scene"] == "foxglove.SceneUpdate" and topics["/log"] == "foxglove.Log"
        assert all(c.message_encoding == "protobuf" for c in summary.channels.values())
        decoded = list(reader.iter_decoded_messages())
        assert len(decoded) == summary.statistics.message_count
        for _schema, _channel, message, proto in decoded:
            assert message.log_time == message.publish_time
            assert proto.ListFields() or proto.ByteSize() == 0
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert json.loads(meta["lc"]["config"]) == METADATA["config"]
    assert meta["lc"]["seed"] == "7" and meta["lc"]["episode_id"] == "ep"


@pytest.mark.parametrize("background", [False, True])
def test_batched_steps_equal_the_steps_one_by_one(tmp_path: pathlib.Path, background: bool) -> None:
    """``write_sim_steps`` (static and per-step columns, batches across step 127/128 and across chunk
    boundaries) writes the file that ``write_vehicles`` + ``write_ego`` step by step write (after a first
    step that registers both channels, as a batch does before its first message)."""
    k = 300
    s = make_state(k, n=6, seed=3)
    names = ("ids", "x", "y", "yaw", "speed", "accel", "lane", "target_lane", "length", "width")
    ego = [(float(s["speed"][i, 0]), int(s["lane"][i, 0]), i % 7 - 1, i % 5 - 1, i % 11 == 0, 0.1 * i, 0.5, 0.0)
           for i in range(k)]  # fmt: skip
    options = {"metadata": METADATA, "start_time_ns": 10**15, "chunk_size": 8000, "background": background}
    with EpisodeWriter(tmp_path / "one" / "ep.mcap", **options) as w:
        w.write_sim_step(0, 0.0, [s[name][0] if s[name].ndim == 2 else s[name] for name in names], *ego[0])
        for i in range(1, k):
            w.write_vehicles(i, 0.05 * i, *(s[name][i] if s[name].ndim == 2 else s[name] for name in names))
            speed, lane, collision, invasion, off_road, steer, throttle, brake = ego[i]
            w.write_ego(i, 0.05 * i, speed=speed, lane=lane, collision_with=collision, lane_invasion=invasion,
                        off_road=off_road, steer=steer, throttle=throttle, brake=brake)  # fmt: skip
    one = w.path.read_bytes()
    with EpisodeWriter(tmp_path / "batched" / "ep.mcap", **options) as w:
        for a, b in ((0, 1), (1, 120), (120, 133), (133, 133), (133, 300)):  # an empty batch too
            columns = [s[name] if s[name].ndim == 1 else s[name][a:b] for name in names]
            columns[1] = list(s["x"][a:b, None, :])  # a list of (1, N) rows, as the recorder gives them
            w.write_sim_steps(range(a, b), [0.05 * i for i in range(a, b)], columns, ego[a:b])
    assert w.path.read_bytes() == one
    assert read_episode(w.path).tracks.shape[0] == 6 * k
    with pytest.raises(ValueError, match="one entry per step"), EpisodeWriter(tmp_path / "bad.mcap", **options) as w:
        w.write_sim_steps([0, 1], [0.0], [s[name] for name in names], ego[:2])


def test_time_is_start_plus_sim_time(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "ep.mcap"
    write_episode(path, steps=3)
    with path.open("rb") as f:
        times = [m.log_time for _s, c, m in make_reader(f).iter_messages(topics=["/vehicles"])]
    assert times == [1_700_000_000_000_000_000 + k * 50_000_000 for k in range(3)]


def test_refuses_to_overwrite(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "ep.mcap"
    path.write_bytes(b"keep me")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        EpisodeWriter(path, metadata=METADATA)
    assert path.read_bytes() == b"keep me" and not partial_path(path).exists()
    write_episode(path, steps=2, overwrite=True)
    assert read_episode(path).tracks["step"].max() == 1


def test_partial_then_rename(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "sub" / "ep.mcap"
    with EpisodeWriter(path, metadata=METADATA) as w:
        w.write_ego(0, 0.0, speed=1.0, lane=0)
        assert partial_path(path).exists() and not path.exists()
    assert path.exists() and not partial_path(path).exists()


def test_exception_leaves_partial_only(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "ep.mcap"
    with pytest.raises(RuntimeError, match="boom"), EpisodeWriter(path, metadata=METADATA) as w:
        w.write_ego(0, 0.0, speed=1.0, lane=0)
        raise RuntimeError("boom")
    assert not path.exists() and partial_path(path).exists()


_CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    sys.path.insert(0, {root!r})
    from lcdata import EpisodeWriter
    n = 4
    w = EpisodeWriter({path!r}, metadata={{"seed": 1}}, chunk_size=2048, background={background})
    for k in range(300):
        z = np.zeros(n)
        w.write_vehicles(k, k * 0.05, np.arange(n), z + k, z, z, z, z, z, z, z + 4, z + 2)
        w.write_ego(k, k * 0.05, speed=float(k), lane=0)
    print("ready", flush=True)
    time.sleep(60)
    """
)


@pytest.mark.parametrize("background", [False, True])
def test_sigkill_leaves_recoverable_partial(tmp_path: pathlib.Path, background: bool) -> None:
    path = tmp_path / "killed.mcap"
    code = _CHILD.format(root=str(ROOT), path=str(path), background=background)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert not path.exists() and partial_path(path).exists()
    with pytest.warns(TruncatedFileWarning, match=r"recovered \d+ messages from \d+ complete chunks"):
        episode = read_episode(partial_path(path))
    steps = episode.ego["step"].to_numpy()
    assert len(steps) > 100  # several complete chunks of ~20 steps each
    np.testing.assert_array_equal(steps, np.arange(len(steps)))  # a clean prefix
    assert episode.tracks["step"].max() <= steps.max() + 1
    assert episode.metadata["seed"] == 1 and not episode.complete


def _rerun() -> str | None:
    exe = pathlib.Path(sys.executable).with_name("rerun")
    return str(exe) if exe.exists() else shutil.which("rerun")


@pytest.mark.skipif(_rerun() is None, reason="rerun CLI not installed")
def test_rerun_decodes_every_channel(tmp_path: pathlib.Path) -> None:
    path, rrd = tmp_path / "ep.mcap", tmp_path / "ep.rrd"
    s = write_episode(path, steps=21)
    subprocess.run([_rerun(), "mcap", "convert", "--disable-raw-fallback", str(path), "-o", str(rrd)],
                   check=True, capture_output=True, timeout=120)  # fmt: skip
    import rerun.chunk

    decoded: dict[str, set[str]] = {}
    vehicles_x = []
    for chunk in rerun.chunk.RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        names = {f.name for f in batch.schema if "message_log_time" in batch.schema.names}
        decoded.setdefault(chunk.entity_path, set()).update(names)
        if chunk.entity_path == "/vehicles" and "lc.VehicleTracks:message" in batch.schema.names:
            for row in batch.column("lc.VehicleTracks:message").to_pylist():
                vehicles_x.append(row[0]["x"])
    expected = {"/vehicles": "lc.VehicleTracks:message", "/ego/state": "lc.EgoState:message",
                "/ego/collision": "lc.EgoCollision:message", "/rl/step": "lc.RLStep:message",
                "/prediction": "lc.Prediction:message", "/scene": "foxglove.SceneUpdate:message",
                "/camera/bev_semantic": "Image:buffer", "/tf": "Transform3D:parent_frame", "/log": "TextLog:text"}  # fmt: skip
    for topic, column in expected.items():
        assert column in decoded.get(topic, set()), f"{topic} not decoded by Rerun: {decoded.get(topic)}"
        assert not any("raw" in name.lower() for name in decoded[topic]), decoded[topic]
    np.testing.assert_array_equal(np.array(vehicles_x), s["x"])


@pytest.mark.parametrize("background", [True, False])
def test_chunk_buffers_are_recycled_and_outsized_records_get_their_own(
    tmp_path: pathlib.Path, background: bool
) -> None:
    """Many chunks (buffers reused) and images larger than a chunk buffer (1 KiB chunks + 64 KiB slack)."""
    path = tmp_path / "big.mcap"
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 255, (3, 160, 160), dtype=np.uint8) for _ in range(5)]  # 75 KiB each
    s = make_state(60)
    with EpisodeWriter(path, metadata=METADATA, chunk_size=1024, background=background) as w:
        for k in range(60):
            w.write_vehicles(k, k * 0.05, s["ids"], s["x"][k], s["y"][k], s["yaw"][k], s["speed"][k], s["accel"][k],
                             s["lane"][k], s["target_lane"][k], s["length"], s["width"])  # fmt: skip
            if k % 12 == 0:
                w.write_image(k, k * 0.05, images[k // 12])
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.chunk_count > 10
        got_images, xs = [], []
        for _, channel, _, msg in reader.iter_decoded_messages():
            if channel.topic == "/camera/bev_semantic":
                got_images.append(np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.width, 3))
            else:
                xs.append(np.asarray(msg.x))
    assert len(got_images) == 5 and len(xs) == 60
    for want, got in zip(images, got_images, strict=True):
        np.testing.assert_array_equal(got, want.transpose(1, 2, 0))
    np.testing.assert_array_equal(np.stack(xs), s["x"])


@pytest.mark.parametrize("chunk_crc", [False, True])
def test_chunk_checksums_are_checked_by_every_reader(tmp_path: pathlib.Path, chunk_crc: bool) -> None:
    """Chunks carry a CRC-32 (``chunk_crc``, files of earlier versions) or a zstd frame checksum (the default):
    both files read everywhere, and a flipped byte in a chunk is caught either way."""
    from lcdata.mcap_scan import scan_mcap

    path = tmp_path / "ep.mcap"
    s = make_state(40)
    with EpisodeWriter(path, metadata=METADATA, chunk_crc=chunk_crc, compression_level=1, chunk_size=4096,
                       background=False) as w:  # fmt: skip
        for k in range(40):
            w.write_vehicles(k, k * 0.05, *(s[name][k] if s[name].ndim == 2 else s[name] for name in s))
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert sum(1 for _ in reader.iter_messages()) == 40
    assert read_episode(path).tracks.shape[0] == 40 * N_VEHICLES
    data = bytearray(path.read_bytes())
    chunk = data.index(b"zstd") + 4 + 8 + 40  # inside the first chunk's compressed records
    data[chunk] ^= 0xFF
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    assert scan_mcap(damaged).messages < 40


def test_an_overwritten_file_is_replaced_whole_and_its_blocks_freed_later(tmp_path: pathlib.Path) -> None:
    """``replace_file`` renames over the old file as ``os.replace`` does (never a moment without a complete file)
    and closes the descriptor it held on the old one afterwards, on the release thread: none is left open."""
    import os
    import time

    from lcdata.writer import replace_file

    target = tmp_path / "ep.mcap"
    target.write_bytes(b"old" * 1000)
    before = len(os.listdir("/proc/self/fd"))
    for k in range(5):
        source = tmp_path / "ep.mcap.partial"
        source.write_bytes(bytes([k]) * 2000)
        replace_file(source, target)
        assert target.read_bytes() == bytes([k]) * 2000 and not source.exists()
    fresh = tmp_path / "new.mcap"
    (tmp_path / "new.mcap.partial").write_bytes(b"x")
    replace_file(tmp_path / "new.mcap.partial", fresh)  # no old file: a plain rename
    assert fresh.read_bytes() == b"x"
    deadline = time.monotonic() + 10
    while len(os.listdir("/proc/self/fd")) > before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(os.listdir("/proc/self/fd")) <= before
