"""Corpus windows: frames, no episode mixing, no future leakage, split by episode, statistics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lcdata.corpus import (
    Corpus,
    WindowOptions,
    from_frame,
    heading_from_positions,
    split_episodes,
    to_frame,
)
from lcmodels.predictor.synthetic import synthetic_tracks


@pytest.fixture(scope="module")
def two_episodes() -> list[pd.DataFrame]:
    a = synthetic_tracks(episode="a", seed=1, num_vehicles=6, num_steps=120)
    b = synthetic_tracks(episode="b", seed=2, num_vehicles=6, num_steps=120)
    b["x"] += 10_000.0  # far away: a window mixing both episodes would show huge coordinates
    return [a, b]


def test_frame_round_trip_and_heading() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5, 7, 2))
    origin = rng.normal(size=(5, 2))
    heading = rng.uniform(-np.pi, np.pi, 5)
    np.testing.assert_allclose(from_frame(to_frame(pts, origin, heading), origin, heading), pts, atol=1e-12)
    # Heading by backward difference, skipping a standing tail and masked points.
    hist = np.array([[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [2.0, 2.0]]])
    assert heading_from_positions(hist)[0] == pytest.approx(np.pi / 4)
    assert heading_from_positions(hist, np.array([[True, False, False, True]]))[0] == pytest.approx(np.pi / 4)
    assert heading_from_positions(np.zeros((1, 4, 2)))[0] == 0.0


def test_window_options_validation() -> None:
    with pytest.raises(ValueError, match="history_steps"):
        WindowOptions(history_steps=1)
    with pytest.raises(ValueError, match="stride"):
        WindowOptions(stride=0)
    with pytest.raises(ValueError, match="future_steps"):
        WindowOptions(future_steps=2.5)  # type: ignore[arg-type]


def test_windows_are_agent_centric_and_never_mix_episodes(two_episodes: list[pd.DataFrame]) -> None:
    corpus = Corpus.from_tracks(two_episodes, WindowOptions(history_steps=5, future_steps=4, stride=3))
    batch = corpus.gather()
    assert batch.size == len(corpus) > 0
    np.testing.assert_allclose(batch.history[:, -1], 0.0, atol=1e-6)
    np.testing.assert_allclose(batch.history[:, -2, 1], 0.0, atol=1e-5)  # heading from the last difference
    assert batch.history[:, -2, 0].max() < 0  # moving forward
    tracks = pd.concat(two_episodes).set_index(["episode", "step", "vehicle_id"]).sort_index()
    for i in np.random.default_rng(0).choice(batch.size, 40, replace=False):
        ep = corpus.episodes[batch.episode_index[i]].episode
        vid, t0 = int(batch.vehicle_id[i]), int(batch.step[i])
        world_h = from_frame(batch.history[i].astype(np.float64), batch.origin[i], batch.heading[i])
        world_f = from_frame(batch.future[i].astype(np.float64), batch.origin[i], batch.heading[i])
        rows = tracks.loc[(ep, slice(t0 - 4, t0 + 4), vid), ["x", "y"]].to_numpy()
        np.testing.assert_allclose(np.concatenate((world_h, world_f)), rows, atol=1e-3)
        # Neighbours come from the same episode: they are within the road's reach, not 10 km away.
        nb = batch.neighbours[i][batch.neighbour_mask[i]]
        assert np.all(np.abs(nb) < 1_000.0)


def test_history_never_contains_future_data() -> None:
    tracks = synthetic_tracks(episode="e", seed=3, num_vehicles=8, num_steps=80)
    opts = WindowOptions(history_steps=6, future_steps=5)
    t0 = 40
    before = Corpus.from_tracks(tracks, opts)
    changed = tracks.copy()
    later = changed["step"] > t0
    rng = np.random.default_rng(0)
    changed.loc[later, "x"] += rng.normal(0, 5, later.sum())
    changed.loc[later, "y"] += rng.normal(0, 5, later.sum())
    after = Corpus.from_tracks(changed, opts)
    rows_b = np.flatnonzero(before.index[:, 2] == t0)
    rows_a = np.flatnonzero(after.index[:, 2] == t0)
    b, a = before.gather(rows_b), after.gather(rows_a)
    np.testing.assert_array_equal(b.history, a.history)
    np.testing.assert_array_equal(b.neighbours, a.neighbours)
    np.testing.assert_array_equal(b.neighbour_mask, a.neighbour_mask)
    np.testing.assert_array_equal(b.heading, a.heading)
    assert not np.array_equal(b.future, a.future)


def test_gaps_missing_neighbours_and_order() -> None:
    tracks = synthetic_tracks(episode="g", seed=4, num_vehicles=4, num_steps=60)
    # Vehicle 2 disappears for steps 20..24: no window of it may span the gap.
    tracks = tracks[~((tracks.vehicle_id == 2) & tracks.step.between(20, 24))]
    corpus = Corpus.from_tracks(tracks, WindowOptions(history_steps=5, future_steps=5, num_neighbours=8))
    idx = corpus.index
    v2 = idx[corpus.episodes[0].vehicle_ids[idx[:, 1]] == 2]
    assert np.all((v2[:, 2] + 5 < 20) | (v2[:, 2] - 4 > 24))
    batch = corpus.gather()
    assert batch.neighbours.shape[1:] == (8, 5, 2)
    assert not batch.neighbour_mask[:, 3:].any()  # only 3 other vehicles exist
    assert np.all(batch.neighbours[~batch.neighbour_mask] == 0.0)
    d = np.linalg.norm(batch.neighbours[:, :3, -1], axis=-1)
    present = batch.neighbour_mask[:, :3, -1]
    ok = present[:, 0] & present[:, 1] & present[:, 2]
    assert np.all(np.diff(d[ok], axis=1) >= -1e-4)  # nearest first


def test_gather_subset_keeps_requested_order(two_episodes: list[pd.DataFrame]) -> None:
    corpus = Corpus.from_tracks(two_episodes, WindowOptions(history_steps=4, future_steps=3, stride=5))
    rows = np.random.default_rng(1).permutation(len(corpus))[:30]
    full, sub = corpus.gather(), corpus.gather(rows)
    np.testing.assert_array_equal(sub.future, full.future[rows])
    np.testing.assert_array_equal(sub.vehicle_id, full.vehicle_id[rows])


def test_stride_and_duplicate_episode_ids(two_episodes: list[pd.DataFrame]) -> None:
    c1 = Corpus.from_tracks(two_episodes, WindowOptions(history_steps=4, future_steps=3, stride=1))
    c4 = Corpus.from_tracks(two_episodes, WindowOptions(history_steps=4, future_steps=3, stride=4))
    assert len(c4) < len(c1) / 3
    with pytest.raises(ValueError, match="unique"):
        Corpus.from_tracks([two_episodes[0], two_episodes[0]])


@pytest.mark.parametrize("n", [1, 2, 3, 7, 20])
def test_split_by_episode(n: int) -> None:
    ids = [f"run-{i:03d}" for i in range(n)]
    split = split_episodes(ids, seed=5)
    parts = [set(split.train), set(split.val), set(split.test)]
    assert sorted(i for p in parts for i in p) == list(range(n))  # each episode exactly once
    assert not (parts[0] & parts[1]) and not (parts[0] & parts[2]) and not (parts[1] & parts[2])
    if n >= 3:
        assert all(parts)
    assert split_episodes(ids, seed=5) == split  # deterministic
    shuffled = ids[::-1]
    s2 = split_episodes(shuffled, seed=5)  # independent of load order
    assert {shuffled[i] for i in s2.test} == {ids[i] for i in split.test}


def test_statistics(two_episodes: list[pd.DataFrame]) -> None:
    tracks = synthetic_tracks(episode="s", seed=0, num_vehicles=12, num_steps=600)
    corpus = Corpus.from_tracks(tracks, WindowOptions(future_steps=40))
    stats = corpus.statistics()
    assert stats["windows"] == len(corpus)
    assert 0.0 < stats["lane_change_fraction"] < 0.5
    assert stats["accel_p1_mps2"] <= stats["accel_p50_mps2"] <= stats["accel_p99_mps2"]
    assert stats["accel_std_mps2"] > 0


def test_load_tracks_from_recorded_mcap(tmp_path: Path) -> None:
    from lcdata import EpisodeWriter
    from lcdata.corpus import load_tracks

    for i in range(2):
        tracks = synthetic_tracks(episode=f"rec{i}", seed=i, num_vehicles=4, num_steps=30)
        with EpisodeWriter(tmp_path / f"rec{i}.mcap", metadata={"seed": i}, background=False) as w:
            for step, g in tracks.groupby("step"):
                cols = {
                    c: g[c].to_numpy() for c in ("x", "y", "yaw", "speed", "accel", "lane", "target_lane")
                }
                w.write_vehicles(
                    int(step), float(g["t"].iloc[0]), g["vehicle_id"].to_numpy(), length=g["length"].to_numpy(),
                    width=g["width"].to_numpy(), **cols,
                )  # fmt: skip
    frames = load_tracks(tmp_path)
    assert len(frames) == 2
    corpus = Corpus.from_tracks(frames, WindowOptions(history_steps=5, future_steps=5))
    assert corpus.episode_ids == ["rec0", "rec1"]
    direct = Corpus.from_tracks(
        [synthetic_tracks(episode=f"rec{i}", seed=i, num_vehicles=4, num_steps=30) for i in range(2)],
        WindowOptions(history_steps=5, future_steps=5),
    )
    np.testing.assert_allclose(corpus.gather().future, direct.gather().future, atol=1e-5)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"no \.mcap"):
        load_tracks(tmp_path / "empty")
