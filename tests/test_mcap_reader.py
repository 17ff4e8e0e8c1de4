"""read_episode: round trip into DataFrames, truncated-file recovery, clear errors, directory helpers."""

from __future__ import annotations

import pathlib
import struct
import warnings

import numpy as np
import pytest
from mcap.writer import Writer as McapWriter

from lcdata import TruncatedFileWarning, iter_episodes, list_episodes, read_episode
from lcdata.reader import EGO_COLUMNS, STEP_COLUMNS, TRACK_COLUMNS
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
