"""Hand-written encoders must produce exactly the protobuf runtime's bytes (and stay right when reused)."""

from __future__ import annotations

import numpy as np
import pytest
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.timestamp_pb2 import Timestamp

from lcdata.encode import (
    ImageEncoder,
    VehicleEncoder,
    encode_ego,
    encode_entity,
    encode_image,
    encode_rl_step,
    encode_scene_entity_update,
    encode_scene_update,
    encode_timestamp,
    vehicle_head,
)
from lcdata.mcap_write import message_header
from lcdata.proto import lc_pb2
from lcdata.sim_records import SimStepEncoder
from lcdata.wire import f_bytes


def test_rl_step_bytes_equal_the_protobuf_runtime() -> None:
    rng = np.random.default_rng(0)
    doubles = [0.0, -0.0, 1.5, -3.25, float("nan"), float("inf"), 1e-300]
    ints = [0, 1, 127, 128, 300, 2**31 - 1, -1, -300, 2**40]
    shapes = [None, (9, 9), (0, 9), (3,), ()]
    for _ in range(500):
        step, decision = int(rng.choice(ints)), int(rng.choice(ints))
        action = int(rng.choice([0, 1, 2, -1, 200, 2**31 - 1, -(2**31)]))
        mask = (rng.random(int(rng.choice([3, 3, 0, 2, 5]))) < 0.5).tolist()
        d = [float(rng.choice(doubles)) if rng.random() < 0.7 else float(rng.normal()) for _ in range(6)]
        terminated, truncated = bool(rng.random() < 0.3), bool(rng.random() < 0.3)
        outcome = str(rng.choice(["", "success", "collision", "timeout", "off_road"]))
        shape = shapes[rng.integers(len(shapes))]
        obs = None if shape is None else rng.normal(size=shape).astype(np.float32)
        msg = lc_pb2.RLStep(step=step, t=d[0], decision=decision, action=action, action_mask=mask, reward=d[1],
                            r_collision=d[2], r_off_road=d[3], r_forward=d[4], r_success=d[5],
                            terminated=terminated, truncated=truncated, outcome=outcome)  # fmt: skip
        if obs is not None:
            msg.obs_current.extend(obs.ravel().tolist())
            msg.obs_current_shape.extend(obs.shape)
        ours = encode_rl_step(step, d[0], decision, action, mask, *d[1:], terminated, truncated, outcome, obs)
        assert ours == msg.SerializeToString()


@pytest.mark.parametrize("time_ns", [0, 5, 999_999_999, 10**9, 1_700_000_000_123_456_789, -(10**9) - 1])
def test_timestamp_bytes_equal_the_protobuf_runtime(time_ns: int) -> None:
    stamp = Timestamp()
    stamp.FromNanoseconds(time_ns)
    assert encode_timestamp(1, time_ns) == f_bytes(1, stamp.SerializeToString())
    assert encode_timestamp(1, time_ns) == f_bytes(1, stamp.SerializeToString())  # cached
    assert encode_timestamp(3, time_ns) == f_bytes(3, stamp.SerializeToString())


def test_image_encoder_reused_across_sizes_and_times() -> None:
    rng = np.random.default_rng(1)
    encoder = ImageEncoder()
    for h, w, t in ((6, 5, 1), (6, 5, 2_000_000_123), (4, 7, 3), (6, 5, 10**18)):
        chw = rng.integers(0, 255, (3, h, w), dtype=np.uint8)
        data = encoder.encode(t, chw)
        assert data == encode_image(t, chw)
        image = RawImage.FromString(data)
        assert (image.width, image.height, image.step, image.frame_id) == (w, h, 3 * w, "ego")
        assert image.timestamp.ToNanoseconds() == t
        np.testing.assert_array_equal(np.frombuffer(image.data, np.uint8).reshape(h, w, 3).transpose(2, 0, 1), chw)


def test_scene_entity_update_is_the_composition() -> None:
    cubes = bytes(range(200))
    assert encode_scene_entity_update(7, "vehicles", cubes) == encode_scene_update([encode_entity(7, "vehicles", cubes)])


@pytest.mark.parametrize("n", [0, 1, 7])
def test_vehicle_encoder_batches_equal_the_protobuf_runtime(n: int) -> None:
    """A batch of K messages (columns per step and the same at every step) = K messages of the runtime."""
    rng = np.random.default_rng(n)
    steps = [0, 1, 127, 128, 20000, 2**40]
    k = len(steps)
    names = ("ids", "x", "y", "yaw", "speed", "accel", "lane", "target_lane", "length", "width")
    per_step = {"x", "y", "yaw", "speed", "accel", "lane", "target_lane"}
    cols = [rng.normal(size=(k, n)) * 50 if name in per_step else np.arange(n) + 0.25 for name in names]
    cols[0] = np.arange(n) + 3  # ids
    cols[6] = cols[7] = rng.integers(-1, 5, size=(k, n))  # lanes: int64 in, int32 on the wire
    encoder = VehicleEncoder()
    for repeat in range(2):  # the template is reused
        bodies = encoder.bodies(k, *cols)
        for i, step in enumerate(steps):
            t = 0.05 * step + repeat + 0.5  # t = 0 is written explicitly (the runtime omits it): valid, not equal
            msg = lc_pb2.VehicleTracks(step=step, t=t)
            for name, col in zip(names, cols, strict=True):
                getattr(msg, name).extend((col[i] if col.ndim == 2 else col).tolist())
            ours = vehicle_head(step, t) + bodies[i].tobytes()
            assert ours == msg.SerializeToString()
            assert encoder.encode(step, t, *(c[i] if c.ndim == 2 else c for c in cols)) == ours
    with pytest.raises(ValueError, match="expected 10 columns"):
        encoder.bodies(k, *cols[:9])


def test_sim_step_records_equal_the_encoders_one_message_at_a_time() -> None:
    """The compiled batch = message_header + vehicle_head + VehicleEncoder bodies, then the header and
    encode_ego, for each step (steps across varint sizes, negative and zero fields), N changing between calls."""
    rng = np.random.default_rng(5)
    encoder, vehicles = SimStepEncoder(), VehicleEncoder()
    steps = np.array([0, 1, 127, 128, 16383, 16384, 2**40, -3])
    k = len(steps)
    ts = np.linspace(0.0, 99.987, k)  # t = 0 too
    ego = np.column_stack((rng.normal(size=k) * 9, [0, 1, -1, 3, 1000, 2000, -5, 2], [-1, 0, 4, -1, 99, 2**33, 0, 1],
                           [-1, -1, 0, 2, 3, 4, 5, 6], [0, 1, 0, 0, 2, 0, 1, 0], rng.normal(size=(k, 3))))  # fmt: skip
    origin = 1_704_067_200_000_000_000
    for n in (5, 0, 3, 3):
        cols = [np.arange(n) + 3] + [rng.normal(size=(k, n)) for _ in range(5)]
        cols += [rng.integers(-1, 5, size=(k, n)), rng.integers(-1, 5, size=(k, n)), np.full(n, 4.2), np.full(n, 1.9)]
        records, times, sizes = encoder.encode(steps, ts, ego, cols, origin, 3, 4)
        bodies = vehicles.bodies(k, *cols)
        want = []
        for i, step in enumerate(steps.tolist()):
            time_ns = origin + round(float(ts[i]) * 1e9)
            head = vehicle_head(step, float(ts[i])) + bodies[i].tobytes()
            speed, lane, collision, invasion, off_road, steer, throttle, brake = ego[i].tolist()
            state = encode_ego(step, float(ts[i]), speed, int(lane), int(collision), int(invasion), bool(off_road),
                               steer, throttle, brake)  # fmt: skip
            want += [message_header(3, time_ns, len(head)) + head, message_header(4, time_ns, len(state)) + state]
            assert times[2 * i] == times[2 * i + 1] == time_ns
        assert records == b"".join(want)
        assert sizes.tolist() == [len(r) for r in want]
