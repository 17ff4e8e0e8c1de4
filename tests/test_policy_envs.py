"""The training environment's wrappers: the observation mode and its prediction, reward shaping, episode statistics, SB3's checker."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

from lcmodels.policy import (
    policy_vec_env,
)
from lcmodels.policy.obs import episode_stats, policy_observation_space, scenario_for_mode
from lcmodels.predictor import Predictor
from lcsim.config import tiny_scenario
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import tiny_policy


def test_prediction_wrapper_equals_the_predictor(predictor_path: Path) -> None:
    config = tiny_scenario()
    pred = Predictor.load(predictor_path)
    base = LaneChangeSB3VecEnv(3, scenario_for_mode(config, "hybrid"))
    env = policy_vec_env(base, "hybrid", pred)
    env.seed(5)
    obs = env.reset()
    assert set(obs) == {"current", "image", "prediction"} and obs["prediction"].shape == (3, 8, 10, 2)
    for _ in range(6):
        obs, _r, _d, _i = env.step(np.ones(3, dtype=np.int64))
    raw = base.venv.core.observe()
    h = raw["history"]
    direct = pred.predict_neighbours(h[..., :2], h[..., 2] > 0.5)
    np.testing.assert_array_equal(obs["prediction"], direct)
    np.testing.assert_array_equal(obs["current"], raw["current"])
    assert np.abs(direct).sum() > 0  # neighbours are there and predicted


def test_collision_weight_scales_only_the_learners_collision_reward() -> None:
    """Two wrappers on the same seeds and actions: the learner's rewards differ by (w - 1) times the
    collision component, the logged returns not at all."""
    config = scenario_for_mode(tiny_scenario(), "pure")
    envs = [policy_vec_env(LaneChangeSB3VecEnv(4, config), "pure", reward_scale=0.01, collision_weight=w)
            for w in (1.0, 4.0)]
    raw = LaneChangeSB3VecEnv(4, config)  # what the environment itself pays
    for env in (*envs, raw):
        env.seed(3)
        env.reset()
    rng = np.random.default_rng(0)
    crashes = 0
    finished: list[list] = [[], []]
    for _ in range(120):
        actions = rng.choice([0, 2], 4)  # changing lanes all the time: collisions come soon
        (_, r1, d1, i1), (_, r4, d4, i4) = (env.step(actions) for env in envs)
        for got, infos in zip(finished, (i1, i4), strict=True):
            got += [e for e in map(episode_stats, infos) if e is not None]
        assert np.array_equal(d1, d4)
        assert np.array_equal(r1, raw.step(actions)[1] * np.float32(0.01))  # weight 1: exactly the scaled reward
        col = np.array([info["reward_components"]["collision"] for info in i1])
        crashes += int((col < 0).sum())
        np.testing.assert_allclose(r4, r1 + 0.01 * 3.0 * col, rtol=1e-5, atol=1e-5)
    assert crashes > 0
    assert finished[0] and [e.ret for e in finished[0]] == [e.ret for e in finished[1]]
    with pytest.raises(ValueError, match="collision_weight"):
        tiny_policy(collision_weight=0.0)


def test_pure_mode_drops_the_image_and_skips_rendering() -> None:
    env = policy_vec_env(LaneChangeSB3VecEnv(2, scenario_for_mode(tiny_scenario(), "pure")), "pure")
    assert set(env.reset()) == {"current"}
    with pytest.raises(ValueError, match="predictor"):
        policy_vec_env(LaneChangeSB3VecEnv(2, tiny_scenario()), "prediction")


def test_policy_obs_env_passes_sb3_check_on_single_view(predictor_path: Path) -> None:
    """The wrapped observation space matches what the wrapper returns (a batch of one env)."""
    from lcsim.envs import LaneChangeEnv

    env = LaneChangeEnv(tiny_scenario())
    check_env(env, warn=False)
    space = policy_observation_space(tiny_scenario(), "hybrid")
    penv = policy_vec_env(LaneChangeSB3VecEnv(1, tiny_scenario()), "hybrid", Predictor.load(predictor_path))
    obs = penv.reset()
    for k, s in space.spaces.items():
        assert s.contains(obs[k][0]), k
