"""The vectorised /vehicles decoder agrees with the field-by-field one, and falls back when it must."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from lcdata import EpisodeWriter, read_episode
from lcdata import reader as reader_module
from lcdata.fast_tracks import decode_tracks_fast
from lcdata.proto import lc_pb2


def slow(payloads: list, path: pathlib.Path) -> dict[str, np.ndarray]:
    saved = reader_module.decode_tracks_fast
    reader_module.decode_tracks_fast = lambda p: None
    try:
        return reader_module._decode_tracks(payloads, path)
    finally:
        reader_module.decode_tracks_fast = saved


@pytest.mark.parametrize("sizes", [[5] * 40, [3, 7, 7, 0, 1, 3, 200] * 3])
def test_fast_equals_slow(tmp_path: pathlib.Path, sizes: list[int]) -> None:
    rng = np.random.default_rng(0)
    with EpisodeWriter(tmp_path / "e.mcap", metadata={}) as w:
        for k, n in enumerate(sizes):
            f = lambda n=n: rng.normal(size=n)  # noqa: E731
            w.write_vehicles(k * 70, k * 3.5, np.arange(n), f(), f(), f(), f(), f(), rng.integers(-1, 5, n),
                             rng.integers(-1, 5, n), f(), f())  # fmt: skip
    ep = read_episode(tmp_path / "e.mcap")
    payloads = ep._scan.channels["/vehicles"].payloads
    fast = decode_tracks_fast(payloads)
    expected = slow(payloads, ep.path)
    assert fast is not None and fast.keys() == expected.keys()
    for name in fast:
        assert fast[name].dtype == expected[name].dtype and fast[name].tobytes() == expected[name].tobytes(), name
    assert len(ep.tracks) == sum(sizes)


def test_other_field_order_falls_back() -> None:
    msg = lc_pb2.VehicleTracks(step=3, t=0.15, x=[1.0, 2.0], ids=[0, 1], y=[0.0, 1.0], yaw=[0, 0], speed=[1, 1],
                               accel=[0, 0], lane=[0, 1], target_lane=[0, 1], length=[4, 4], width=[2, 2])  # fmt: skip
    payload = memoryview(msg.SerializeToString())
    assert decode_tracks_fast([payload]) is None or decode_tracks_fast([payload])["x"].tolist() == [1.0, 2.0]
    cols = reader_module._decode_tracks([payload], pathlib.Path("x"))
    assert cols["x"].tolist() == [1.0, 2.0] and cols["step"].tolist() == [3, 3]
