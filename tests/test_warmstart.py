"""Warm start: demonstrations observed the policy's way, behaviour cloning, sample weights, the collision weight in the returns."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest

from lcdata.record import record_episodes
from lcmodels.policy import (
    bc_loss,
    load_demonstrations,
    load_policy,
    policy_vec_env,
    pretrain,
    train_policy,
)
from lcmodels.policy.obs import policy_observation_space, scenario_for_mode
from lcmodels.policy.train import build_model
from lcmodels.policy.warmstart import Demonstrations, RowChunks
from lcsim.config import tiny_scenario
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import tiny_policy


def test_demonstration_returns_carry_the_collision_weight(tmp_path: Path) -> None:
    config = scenario_for_mode(tiny_scenario(), "pure")
    done = record_episodes(config, [8, 9], "rule", tmp_path / "demos", scenario="tiny", images=False)
    assert [r.outcome for r in done] == ["success", "collision"]  # one of each
    one, four = (load_demonstrations(tmp_path / "demos", "pure", None, gamma=0.9, collision_weight=w)
                 for w in (1.0, 4.0))
    np.testing.assert_array_equal(one.actions, four.actions)
    first = done[0].decisions
    np.testing.assert_array_equal(four.returns[:first], one.returns[:first])  # no crash: the same returns
    assert (four.returns[first:] < one.returns[first:]).all()  # every decision before a crash: dearer
    assert four.returns[-1] - one.returns[-1] == pytest.approx(3.0 * -500.0)  # the last: three more crashes


def test_warm_start_lowers_the_behaviour_cloning_loss(tmp_path: Path) -> None:
    config = tiny_scenario()
    record_episodes(config, [1, 2, 3], "rule", tmp_path / "demos", scenario="tiny")
    demos = load_demonstrations(tmp_path / "demos", "image", None, scenario=config)
    assert len(demos) > 20 and demos.obs["image"].shape[1:] == (3, 120, 120)
    env = policy_vec_env(LaneChangeSB3VecEnv(2, config), "image")
    model = build_model(tiny_policy(obs="image"), env)
    before = bc_loss(model, demos)
    losses = pretrain(model, demos, epochs=4, batch_size=32)
    after = bc_loss(model, demos)
    assert after < before * 0.8, (before, after, losses)


def test_cloning_from_row_chunks_is_cloning_from_their_concatenation(tmp_path: Path) -> None:
    """DAgger's training set stays in its rounds' arrays (RowChunks): the same batches, the same policy."""
    import torch

    config = tiny_scenario()
    record_episodes(config, [1, 2], "rule", tmp_path / "demos", scenario="tiny")
    demos = load_demonstrations(tmp_path / "demos", "image", None, scenario=config)
    cuts = [0, 7, 8, len(demos) // 2, len(demos)]  # chunks of 7 rows, 1 row and the rest
    chunked = Demonstrations({k: RowChunks([v[a:b] for a, b in itertools.pairwise(cuts)]) for k, v in demos.obs.items()},
                             demos.actions, demos.returns, demos.episodes)  # fmt: skip
    rows = np.array([len(demos) - 1, 0, 7, 3, 8, 7])
    for k, v in demos.obs.items():
        assert chunked.obs[k].shape == v.shape and np.array_equal(chunked.obs[k][rows], v[rows])
    with pytest.raises(IndexError):
        chunked.obs["image"][np.array([len(demos)])]
    env = policy_vec_env(LaneChangeSB3VecEnv(2, config), "image")
    models = [build_model(tiny_policy(obs="image"), env) for _ in range(2)]
    losses = [pretrain(m, d, epochs=2, batch_size=16, seed=3) for m, d in zip(models, (demos, chunked), strict=True)]
    assert losses[0] == losses[1]
    for a, b in zip(models[0].policy.parameters(), models[1].policy.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("heavier", [0, 2])
def test_sample_weights_decide_between_conflicting_labels(heavier: int) -> None:
    """The same states labelled both right and left: cloning follows the labels that weigh more."""
    space = policy_observation_space(tiny_scenario(), "pure")
    states = np.stack([space["current"].sample() for _ in range(8)] * 2)
    labels = np.array([0] * 8 + [2] * 8)
    weights = np.where(labels == heavier, 9.0, 1.0)
    env = policy_vec_env(LaneChangeSB3VecEnv(2, scenario_for_mode(tiny_scenario(), "pure")), "pure")
    model = build_model(tiny_policy(obs="pure"), env)
    pretrain(model, Demonstrations({"current": states}, labels, np.zeros(16, np.float32), 0, weights),
             epochs=60, batch_size=16, value_coef=0.0)  # fmt: skip
    chosen, _ = model.predict({"current": states[:8]}, deterministic=True)
    assert (chosen == heavier).all(), chosen


@pytest.mark.parametrize("balance", [True, False])
def test_the_action_balance_makes_rare_labels_count_more_and_can_be_turned_off(balance: bool) -> None:
    """Each state labelled right four times and left once at weight 3: balanced (left counts 1/sqrt of its share,
    twice right's) left weighs more; without the balance right does."""
    space = policy_observation_space(tiny_scenario(), "pure")
    distinct = np.stack([space["current"].sample() for _ in range(4)])
    states = np.concatenate([distinct] * 5)
    labels = np.array([0] * 16 + [2] * 4)
    weights = np.where(labels == 2, 3.0, 1.0)
    env = policy_vec_env(LaneChangeSB3VecEnv(2, scenario_for_mode(tiny_scenario(), "pure")), "pure")
    model = build_model(tiny_policy(obs="pure"), env)
    pretrain(model, Demonstrations({"current": states}, labels, np.zeros(20, np.float32), 0, weights),
             epochs=300, batch_size=20, value_coef=0.0, balance_actions=balance)  # fmt: skip
    chosen, _ = model.predict({"current": distinct}, deterministic=True)
    assert (chosen == (2 if balance else 0)).all(), chosen


def test_zero_timesteps_with_a_warm_start_gives_the_behaviour_cloned_policy(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    cfg = tiny_policy(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=3, eval_episodes=0)
    with caplog.at_level("INFO", logger="lcmodels.policy.train"):
        res = train_policy(cfg, tmp_path / "run")
    said = [r.getMessage() for r in caplog.records]
    assert "warm start: read 1/2 episodes" in said and "warm start: read 2/2 episodes" in said  # progress
    assert [m.split(",")[0] for m in said if m.startswith("warm start: epoch")] == [
        "warm start: epoch 1/3", "warm start: epoch 2/3", "warm start: epoch 3/3"]
    warm = res.metrics["train"]["warm_start"]
    assert res.timesteps == 0 and warm["nll_after"] < warm["nll_before"]
    demos = load_demonstrations(tmp_path / "demos", "pure", None, scenario=config)
    loaded = load_policy(tmp_path / "run" / "policy.safetensors")
    assert bc_loss(loaded.model, demos) == pytest.approx(warm["nll_after"], rel=1e-5)  # no online update
    with pytest.raises(ValueError, match="timesteps"):
        tiny_policy(timesteps=0)  # nothing to train without a warm start


def test_demonstrations_are_observed_the_policys_way(tmp_path: Path) -> None:
    """Episodes recorded with the nearest-vehicle observation serve a policy that observes lane slots."""

    from lcdata.offline import rebuild_observations
    from lcdata.reader import list_episodes, read_episode

    lanes = scenario_for_mode(tiny_scenario(), "pure")
    nearest = dataclasses.replace(lanes, neighbour_selection="nearest")
    record_episodes(nearest, [1, 2], "rule", tmp_path / "demos", scenario="tiny", images=False)
    demos = load_demonstrations(tmp_path / "demos", "pure", None, scenario=lanes)
    episodes = [read_episode(p) for p in list_episodes(tmp_path / "demos")]
    as_lanes = np.concatenate([np.stack([o["current"] for _, o in rebuild_observations(e, lanes)]) for e in episodes])
    as_recorded = np.concatenate([np.stack([o["current"] for _, o in rebuild_observations(e)]) for e in episodes])
    assert np.array_equal(demos.obs["current"], as_lanes)
    assert not np.array_equal(as_lanes, as_recorded)  # the two selections do show other vehicles here
    wide = load_demonstrations(tmp_path / "demos", "pure", None, scenario=dataclasses.replace(lanes, num_neighbours=16))
    assert wide.obs["current"].shape[1:] == (17, 9)  # recorded with 8 slots, observed with 16
    assert np.array_equal(wide.obs["current"][:, :9], as_lanes)
    with pytest.raises(ValueError, match="another scenario"):  # a change to the episode itself is refused
        load_demonstrations(tmp_path / "demos", "pure", None, scenario=dataclasses.replace(lanes, time_limit_s=30.0))


def test_a_checkpoint_from_before_lane_slots_is_seen_as_nearest() -> None:
    from lcmodels.policy.checkpoint import scenario_differences

    stored = tiny_scenario().to_dict()
    del stored["neighbour_selection"]  # as written before the field existed
    assert scenario_differences(stored, tiny_scenario()) == [
        "neighbour_selection: checkpoint 'nearest', requested 'lanes'"]
