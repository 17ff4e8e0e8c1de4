"""Every registered env passes gymnasium's and stable-baselines3's checkers; vector envs work."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import lcsim
from lcsim.envs import LaneChangeVectorEnv
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import small_config


@pytest.mark.parametrize("env_id", lcsim.ENV_IDS)
def test_registered_envs_pass_checkers(env_id):
    env = gym.make(env_id)
    gym_check_env(env.unwrapped, skip_render_check=False)
    sb3_check_env(gym.make(env_id).unwrapped, warn=True)


def test_step_info_and_spaces():
    env = gym.make("lcsim/LaneChangeLight-v0")
    obs, info = env.reset(seed=1)
    assert set(obs) == {"current", "history", "image"}
    assert obs["current"].shape == (9, 9) and obs["history"].shape == (8, 10, 3)
    assert info["action_mask"].dtype == bool and info["action_mask"][1]
    obs, reward, _terminated, _truncated, info = env.step(1)
    assert set(info["reward_components"]) == {"collision", "off_road", "forward", "success"}
    assert reward == pytest.approx(sum(info["reward_components"].values()))
    assert info["reward_components"]["forward"] > 0
    assert env.unwrapped.render() is None  # no render mode asked: nothing drawn
    viewer = gym.make("lcsim/LaneChangeLight-v0", render_mode="rgb_array")
    viewer.reset(seed=1)
    frame = viewer.render()
    assert frame.shape == (480, 480, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) >= 4  # road, markings, vehicles, ego: not blank
    with pytest.raises(ValueError, match="action"):
        env.step(3)
    with pytest.raises(ValueError, match="action"):  # not truncated to 1
        env.step(1.5)


def test_make_vec_uses_native_batched_env():
    venv = gym.make_vec("lcsim/LaneChangeLight-v0", num_envs=3, vectorization_mode="vector_entry_point")
    assert isinstance(venv.unwrapped, LaneChangeVectorEnv)
    obs, info = venv.reset(seed=0)
    assert obs["image"].shape == (3, 3, 120, 120)
    for _ in range(3):
        obs, reward, _term, _trunc, info = venv.step(np.array([1, 2, 0]))
    assert reward.shape == (3,) and info["action_mask"].shape == (3, 3)


def test_registered_ids_work_in_subprocess_vector_envs():
    venv = gym.vector.AsyncVectorEnv([lambda: gym.make("lcsim/LaneChangeLight-v0")] * 2)
    try:
        obs, _ = venv.reset(seed=3)
        obs, reward, *_ = venv.step(np.array([1, 1]))
        assert obs["current"].shape == (2, 9, 9) and np.all(reward > 0)
    finally:
        venv.close()


def test_registered_ids_work_in_fresh_interpreters():
    """SB3 starts subprocesses with forkserver/spawn: ``"lcsim:<id>"`` imports lcsim there first."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = make_vec_env("lcsim:lcsim/LaneChangeLight-v0", n_envs=2, seed=5, vec_env_cls=SubprocVecEnv,
                        vec_env_kwargs={"start_method": "spawn"})
    try:
        obs = venv.reset()
        obs, reward, _done, _infos = venv.step(np.array([1, 1]))
        assert obs["image"].shape == (2, 3, 120, 120) and reward.shape == (2,)
    finally:
        venv.close()


def test_sb3_adapter_autoreset_and_masks():
    cfg = small_config(time_limit_s=3.0)
    venv = LaneChangeSB3VecEnv(4, cfg)
    venv.seed(11)
    obs = venv.reset()
    assert obs["current"].shape == (4, 9, 9)
    masks = np.stack(venv.env_method("action_masks"))
    assert masks.shape == (4, 3) and masks[:, 1].all()
    done_seen = False
    for _ in range(8):
        obs, _reward, dones, infos = venv.step_async(np.ones(4, dtype=int)) or venv.step_wait()
        for d, info in zip(dones, infos, strict=True):
            if d:
                done_seen = True
                assert "terminal_observation" in info and "is_success" in info
                assert info["TimeLimit.truncated"] == (info["outcome"] == "timeout")
    assert done_seen


def test_success_milestones_are_paid_once_each_in_order_as_the_ego_passes_them():
    """Each decision pays the rewards of the milestones the ego passed during it, once each, in order;
    two close milestones are passed in one decision."""
    from lcsim.config import EgoConfig, RewardConfig
    from lcsim.core import KEEP, LaneChangeCore

    cfg = small_config(ego=EgoConfig(adaptive_cruise=True), render_image=False, time_limit_s=60.0,
                       reward=RewardConfig(milestones=(0.2, 0.2001, 0.6, 1.0), milestone_rewards=(1.0, 2.0, 4.0, 8.0)))
    core = LaneChangeCore(cfg, 2)
    core.reset([0, 1], [3, 4])
    marks = np.array(cfg.reward.milestones) * cfg.route_length_m
    paid, both_at_once = np.zeros(2), False
    while (core.outcome == "").any():
        before = core.sim.x[:, 0].copy()
        running = core.outcome == ""
        res = core.step(np.full(2, KEEP))
        after = core.sim.x[:, 0]
        for e in np.flatnonzero(running):
            passed = (before[e] < marks) & (marks <= after[e])
            want = float(np.sum(np.array(cfg.reward.milestone_rewards)[passed]))
            assert res.components["success"][e] == want, (e, before[e], after[e])
            both_at_once |= bool(passed[0] and passed[1])
        paid += res.components["success"]
    assert list(core.outcome) == ["success", "success"] and list(paid) == [15.0, 15.0]
    assert both_at_once


def test_observed_acceleration_is_a_tenth_column_and_changes_nothing_else():
    """``observe_acceleration`` appends each shown vehicle's (and the ego's) last-step acceleration; the other
    nine columns, the history and the episode are as without it; the env still passes both checkers."""
    from lcsim.core import ACCEL_FEATURE, LaneChangeCore, current_features
    from lcsim.envs import LaneChangeEnv

    plain, accel = small_config(render_image=False), small_config(render_image=False, observe_acceleration=True)
    assert current_features(accel)[-1] == ACCEL_FEATURE and len(current_features(accel)) == 10
    cores = [LaneChangeCore(c, 3) for c in (plain, accel)]
    rng = np.random.default_rng(0)
    for core in cores:
        core.reset(np.arange(3), [11, 12, 13])
    moved = 0.0
    for _ in range(12):
        actions = rng.integers(0, 3, 3)
        a, b = (core.observe() for core in cores)
        assert b["current"].shape == (3, 9, 10)
        np.testing.assert_array_equal(a["current"], b["current"][..., :9])
        np.testing.assert_array_equal(a["history"], b["history"])
        sim, nb = cores[1].sim, cores[1].neighbours(np.arange(3))
        rows = np.concatenate([np.zeros((3, 1), dtype=np.int64), nb], axis=1)
        want = np.where(rows >= 0, np.take_along_axis(sim.accel, np.maximum(rows, 0), axis=1), 0.0)
        np.testing.assert_array_equal(b["current"][..., 9], want.astype(np.float32))
        moved = max(moved, float(np.abs(want).max()))
        for core in cores:
            core.step(actions)
    assert moved > 0.05  # the column does carry accelerations, not zeros
    env = LaneChangeEnv(accel)
    gym_check_env(env, skip_render_check=True)
    sb3_check_env(LaneChangeEnv(accel), warn=True)
