"""Training on several roads at once (``PolicyConfig.train_roads``, :class:`lcsim.sb3.MixedRoadsSB3VecEnv`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lcmodels.policy import PolicyConfig, load_policy, train_policy
from lcmodels.policy.plan import policy_scenario
from lcsim.registry import scenario
from lcsim.sb3 import LaneChangeSB3VecEnv, MixedRoadsSB3VecEnv

from .conftest import tiny_policy


def test_each_block_is_the_road_it_names_seeded_as_the_whole_batch() -> None:
    roads = [scenario("tiny"), scenario("light"), scenario("three-lane")]
    mix = MixedRoadsSB3VecEnv(5, roads)  # blocks of 2, 2, 1
    alone = [LaneChangeSB3VecEnv(2, roads[0]), LaneChangeSB3VecEnv(2, roads[1]), LaneChangeSB3VecEnv(1, roads[2])]
    mix.seed(11)
    for env, first in zip(alone, (0, 2, 4), strict=True):
        env.seed(11 + first)
    obs = mix.reset()
    want = [env.reset() for env in alone]
    rng = np.random.default_rng(0)
    for _ in range(60):
        for k in obs:
            np.testing.assert_array_equal(obs[k], np.concatenate([w[k] for w in want]))
        np.testing.assert_array_equal(mix.action_masks(), np.concatenate([e.action_masks() for e in alone]))
        actions = rng.integers(0, 3, size=5)
        obs, reward, dones, infos = mix.step(actions)
        got = [env.step(actions[s]) for env, s in zip(alone, (slice(0, 2), slice(2, 4), slice(4, 5)), strict=True)]
        want = [g[0] for g in got]
        np.testing.assert_array_equal(reward, np.concatenate([g[1] for g in got]))
        np.testing.assert_array_equal(dones, np.concatenate([g[2] for g in got]))
        assert [i["outcome"] for i in infos] == [i["outcome"] for g in got for i in g[3]]
    assert mix.core.seeds.tolist() == [s for e in alone for s in e.venv.core.seeds.tolist()]
    assert mix.configs == tuple(roads) and mix.config is roads[0]
    mix.close()


def test_roads_with_other_observations_or_too_few_environments_are_refused() -> None:
    with pytest.raises(ValueError, match="one environment a road"):
        MixedRoadsSB3VecEnv(1, [scenario("tiny"), scenario("light")])
    small = policy_scenario(PolicyConfig(scenario="tiny", obs="pure", slots=6))
    with pytest.raises(ValueError, match="same observations"):
        MixedRoadsSB3VecEnv(2, [scenario("tiny"), small])


@pytest.mark.parametrize(
    ("roads", "n_envs", "match"),
    [("nowhere", 2, "must be a suite"), ("tiny,,nowhere", 2, "must be a suite"), ("highway", 4, "more than n_envs")],
)
def test_the_config_names_known_roads_and_enough_environments(roads: str, n_envs: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PolicyConfig(scenario="tiny", obs="pure", train_roads=roads, n_envs=n_envs)


def test_a_suite_names_its_roads() -> None:
    cfg = PolicyConfig(obs="pure", train_roads="highway", n_envs=16)
    assert cfg.road_names() == ("paper", "three-lane", "five-lane", "dense", "fast", "spread", "exact-idm")
    lanes = [c.road.num_lanes for c in cfg.road_configs()]
    assert lanes == [4, 3, 5, 4, 4, 4, 4]
    assert all(c.num_neighbours == cfg.slots for c in cfg.road_configs())


def test_a_policy_trains_on_two_roads_and_keeps_its_scenario(tmp_path) -> None:
    cfg = tiny_policy(obs="pure", train_roads="tiny,light", timesteps=64, n_steps=16, eval_episodes=0)
    res = train_policy(cfg, tmp_path / "run")
    assert res.timesteps == 64
    seeds = np.load(tmp_path / "run" / "train_episode_seeds.npy")
    assert len(set(seeds.tolist())) == len(seeds) >= 2
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["config"]["train_roads"] == "tiny,light" and run["scenario"]["traffic"]["num_vehicles"] == 8
    policy = load_policy(tmp_path / "run" / "policy.safetensors")
    assert policy.meta["train_config"]["train_roads"] == "tiny,light"
    again = train_policy(cfg, tmp_path / "run")  # complete: nothing to redo
    assert again.timesteps == 64
    with pytest.raises(ValueError, match="another configuration"):
        train_policy(tiny_policy(obs="pure", train_roads="tiny", timesteps=64, n_steps=16, eval_episodes=0),
                     tmp_path / "run")  # fmt: skip


def test_drawn_roads_span_the_suite_without_being_its_roads() -> None:
    from lcsim.suite import SUITE_SCENARIOS, drawn_roads

    roads = drawn_roads(64, seed=3)
    assert roads == drawn_roads(64, seed=3) and roads != drawn_roads(64, seed=4)
    assert roads[:5] == drawn_roads(5, seed=3)
    suite_roads = [s.make() for s in SUITE_SCENARIOS.values()]
    assert not any(r == s for r in roads for s in suite_roads)
    assert {r.road.num_lanes for r in roads} == {3, 4, 5}
    assert {r.traffic.human_like for r in roads} == {True, False}
    for r in roads:
        assert 22.0 <= r.traffic.speed_kmh <= 52.0 and 1.17 < r.ego.target_speed_kmh / r.traffic.speed_kmh < 1.28
        assert 22 * 3 <= r.traffic.num_vehicles <= 36 * 5
        assert abs(r.route_length_m - 0.96 * r.ego.target_speed_kmh / 3.6 * r.time_limit_s) < 0.1
    with pytest.raises(ValueError, match="count"):
        drawn_roads(0, seed=0)


def test_drawn_roads_follow_the_training_seed() -> None:
    a = PolicyConfig(obs="pure", train_roads="drawn:4", n_envs=4, seed=1)
    assert a.road_names() == ("drawn-0", "drawn-1", "drawn-2", "drawn-3")
    assert a.road_configs() == PolicyConfig(obs="pure", train_roads="drawn:4", n_envs=4, seed=1).road_configs()
    assert a.road_configs() != PolicyConfig(obs="pure", train_roads="drawn:4", n_envs=4, seed=2).road_configs()
    for bad in ("drawn:0", "drawn:x", "drawn:-1"):
        with pytest.raises(ValueError, match="drawn:N"):
            PolicyConfig(obs="pure", train_roads=bad, n_envs=4)
