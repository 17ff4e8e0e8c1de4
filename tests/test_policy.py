"""The policy stack: extractor shapes, the prediction wrapper, short training runs, resume, warm start, eval."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.env_checker import check_env

from lccli.evaluate import eval_main
from lccli.policy import train_policy_main
from lcdata.record import episode_seed, record_episodes
from lcmodels.fileio import file_sha256
from lcmodels.policy import (
    VGG16,
    CompactVGG,
    HybridExtractor,
    PolicyConfig,
    bc_loss,
    load_demonstrations,
    load_policy,
    policy_vec_env,
    pretrain,
    read_meta,
    train_policy,
)
from lcmodels.policy.evaluate import PolicyDriver, driver_for, evaluate, wilson_interval
from lcmodels.policy.obs import OBS_MODES, episode_stats, policy_observation_space, scenario_for_mode
from lcmodels.policy.train import build_model, default_learning_rate
from lcmodels.policy.warmstart import Demonstrations
from lcmodels.predictor import Predictor, PredictorConfig, TrajectoryTransformer
from lcsim.config import tiny_scenario
from lcsim.core import KEEP, RUNNING, LaneChangeCore
from lcsim.sb3 import LaneChangeSB3VecEnv

EVAL_KEYS = {"success_rate", "collision_rate", "off_road_rate", "timeout_rate", "mean_safe_forward_m",
             "mean_return", "success_rate_ci95", "collision_rate_ci95", "off_road_rate_ci95",
             "timeout_rate_ci95", "mean_safe_forward_m_ci95", "mean_return_ci95", "episodes"}  # fmt: skip


@pytest.fixture(scope="module")
def predictor_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small predictor (untrained: exactly the constant-velocity baseline, which is what it starts as)."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("pred") / "predictor.pt"
    Predictor(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1))).save(path)
    return path


def _tiny(**kw) -> PolicyConfig:
    base = dict(scenario="tiny", timesteps=128, n_envs=2, n_steps=32, batch_size=64, n_epochs=2,
                eval_episodes=2, eval_batch=2, checkpoint_every=64, buffer_size=500, learning_starts=32)
    base.update(kw)
    return PolicyConfig(**base)


@pytest.mark.parametrize("mode", OBS_MODES)
def test_extractor_output_size_per_mode(mode: str) -> None:
    space = policy_observation_space(tiny_scenario(), mode)
    ext = HybridExtractor(space)
    batch = {k: torch.as_tensor(np.stack([s.sample() for _ in range(3)])).float() for k, s in space.spaces.items()}
    out = ext(batch)
    widths = {"current": 64, "image": 10, "prediction": 64}
    assert out.shape == (3, sum(widths[k] for k in space.spaces)) == (3, ext.features_dim)
    assert set(ext.keys) == set(space.spaces)


def test_contact_features_against_hand_values() -> None:
    from lcmodels.policy.extractor import CONTACT_BODY_M, ContactFeatures
    from lcsim.core import CURRENT_FEATURES

    col = {name: i for i, name in enumerate(CURRENT_FEATURES)}
    cur = torch.zeros(1, 5, len(CURRENT_FEATURES))
    cur[0, 0, col["vx_mps"]] = 8.0  # the ego's own row is not a slot
    # A leader 20 m ahead, 2 m/s slower; a follower 10 m behind, 1 m/s faster; a leader pulling away; an empty slot.
    for row, (x, vx) in enumerate([(20.0, -2.0), (-10.0, 1.0), (30.0, 3.0)], start=1):
        cur[0, row, col["x_m"]], cur[0, row, col["vx_mps"]], cur[0, row, col["present"]] = x, vx, 1.0
    ttc, gap, prox = ContactFeatures(4)(cur).reshape(3, 4)
    expected_ttc = [(20.0 - CONTACT_BODY_M) / 2.0 / 10.0, (10.0 - CONTACT_BODY_M) / 1.0 / 10.0, 1.0, 1.0]
    torch.testing.assert_close(ttc, torch.tensor(expected_ttc))
    torch.testing.assert_close(gap, torch.tensor([(20 - CONTACT_BODY_M) / 50, (10 - CONTACT_BODY_M) / 50,
                                                  (30 - CONTACT_BODY_M) / 50, 1.0]))
    torch.testing.assert_close(prox, torch.tensor([5 / 20, 5 / 10, 5 / 30, 0.0]))


def test_window_features_against_hand_values() -> None:
    """Leader 30 m ahead closing at 2 m/s; right: a vehicle alongside that the ego passes; left: a faster
    follower 20 m back. Worked by hand on the 0.5 s grid, with the module's margins."""
    from lcmodels.policy.extractor import (
        CONTACT_BODY_M,
        WINDOW_CHANGE_S,
        WINDOW_HEADWAY_S,
        WINDOW_HORIZON_S,
        WINDOW_MARGIN_M,
        WindowFeatures,
    )
    from lcsim.core import CURRENT_FEATURES

    col = {name: i for i, name in enumerate(CURRENT_FEATURES)}
    cur = torch.zeros(1, 9, len(CURRENT_FEATURES))
    # slot 0 the leader, slot 2 the leader right, slot 5 the follower left (lcsim.config.LANE_SLOTS)
    for slot, (x, vx) in {0: (30.0, -2.0), 2: (3.0, -1.0), 5: (-20.0, 1.0)}.items():
        cur[0, 1 + slot, col["x_m"]], cur[0, 1 + slot, col["vx_mps"]], cur[0, 1 + slot, col["present"]] = x, vx, 1.0
    h, body, margin = WINDOW_HORIZON_S, CONTACT_BODY_M, WINDOW_MARGIN_M
    trap = (30.0 - body - margin) / 2.0  # 11.6 s
    grid = [0.5 * i for i in range(33)]
    before = [t for t in grid if t <= trap]
    # right: clear once it is body + margin behind (it closes on nobody): 3 - t <= -6.8 from t = 9.8, so 10.0 on
    right_open = [t for t in grid if 3.0 - t <= -(body + margin)]
    right_can = [t for t in right_open if t in before]
    # left: the follower closes at 1 m/s, so it is clear while -20 + t <= -(body + margin + headway * 1), to t = 12.2;
    # a change started at t needs [t, t + 2.5] clear
    limit = 20.0 - body - margin - WINDOW_HEADWAY_S * 1.0
    left_open_until = min(t for t in grid if t > limit)  # 12.5, the first grid time not clear
    left_can = [t for t in before if t + WINDOW_CHANGE_S <= limit]
    expected = [trap / h,
                0.0, min(right_open) / h, 0.0, 1.0, len(right_can) / len(before),
                1.0, 0.0, left_open_until / h, 1.0, len(left_can) / len(before)]
    torch.testing.assert_close(WindowFeatures(8)(cur)[0], torch.tensor(expected))
    # nobody shown: no trap, both lanes open throughout
    torch.testing.assert_close(WindowFeatures(8)(torch.zeros(1, 9, 9))[0],
                               torch.tensor([1.0, 1.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 1.0, 1.0]))


def test_window_features_widen_the_sensor_branch_and_need_lane_slots(tmp_path: Path) -> None:
    space = policy_observation_space(tiny_scenario(), "pure")
    both = HybridExtractor(space, contact_features=True, window_features=True)
    contact = HybridExtractor(space, contact_features=True)
    assert both.branches["current"].net[1].in_features == contact.branches["current"].net[1].in_features + 11
    batch = {k: torch.as_tensor(np.stack([s.sample() for _ in range(2)])).float() for k, s in space.spaces.items()}
    assert torch.isfinite(both(batch)).all()
    res = train_policy(_tiny(obs="pure", window_features=True, timesteps=64, n_steps=16, batch_size=32,
                             eval_episodes=0), tmp_path)
    assert res.timesteps == 64
    loaded = load_policy(tmp_path / "policy.safetensors")  # the extractor comes back with the features
    assert loaded.model.policy.features_extractor.branches["current"].net[1].in_features == (
        both.branches["current"].net[1].in_features)
    with pytest.raises(ValueError, match="window_features"):
        _tiny(obs="pure", window_features=True, neighbours="nearest")


def test_window_features_with_accelerations_see_a_follower_speeding_up() -> None:
    """A follower in the left lane 25 m back at the ego's speed: at constant speeds the lane stays open, but
    accelerating at 2 m/s^2 relative to the ego (after 2.5 s: 6.25 m nearer, closing at 5 m/s) it closes in a
    few seconds. The first 11 outputs are those without the acceleration column."""
    from lcmodels.policy.extractor import WINDOW_HORIZON_S, WindowFeatures
    from lcsim.core import CURRENT_FEATURES

    col = {name: i for i, name in enumerate(CURRENT_FEATURES)}
    cur = torch.zeros(1, 9, len(CURRENT_FEATURES) + 1)
    cur[0, 1 + 5, col["x_m"]], cur[0, 1 + 5, col["present"]] = -25.0, 1.0  # slot 5: the follower left
    cur[0, 0, -1], cur[0, 1 + 5, -1] = 0.5, 2.5  # the ego accelerates at 0.5, the follower at 2.5
    out = WindowFeatures(8, accel=True)(cur)[0]
    assert out.shape == (22,)
    torch.testing.assert_close(out[:11], WindowFeatures(8)(cur[..., :-1])[0])
    left_const, left_accel = out[6:11], out[17:22]
    assert left_const[0] == 1.0 and left_const[2] == 1.0  # changeable now, open throughout
    assert left_accel[0] == 1.0  # still changeable now ...
    assert 0.0 < left_accel[2] * WINDOW_HORIZON_S < 8.0  # ... but it closes within 8 s
    assert left_accel[4] < left_const[4]
    # a relative acceleration of zero reads as the constant-speed look (the trap aside: it is on the grid)
    cur[0, 1 + 5, -1] = 0.5
    same = WindowFeatures(8, accel=True)(cur)[0]
    torch.testing.assert_close(same[12:], same[1:11])


def test_accel_features_observe_accelerations_clone_from_plain_demos_and_train(tmp_path: Path) -> None:
    """``accel_features`` widens ``current`` to 10 columns and the window look to 22; demonstrations recorded
    without the column are replayed with it; the run trains, saves and loads with its scenario."""
    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    cfg = _tiny(obs="pure", window_features=True, accel_features=True, timesteps=64, n_steps=16, batch_size=32,
                warm_start=str(tmp_path / "demos"), warm_start_epochs=1, eval_episodes=2)
    assert cfg.scenario_config().observe_acceleration
    demos = load_demonstrations(tmp_path / "demos", "pure", None, scenario=cfg.scenario_config())
    assert demos.obs["current"].shape[1:] == (9, 10) and np.abs(demos.obs["current"][..., 9]).max() > 0.0
    res = train_policy(cfg, tmp_path / "run")
    assert res.timesteps == 64
    loaded = load_policy(tmp_path / "run" / "policy.safetensors")
    assert loaded.scenario.observe_acceleration
    assert loaded.model.observation_space["current"].shape == (9, 10)
    window = loaded.model.policy.features_extractor.branches["current"].extra.parts[-1]
    assert window.out_features == 22
    without = dataclasses.replace(loaded.scenario, observe_acceleration=False)
    with pytest.raises(ValueError, match="observe_acceleration"):  # loading for another observation says why
        load_policy(tmp_path / "run" / "policy.safetensors", scenario=without)


@pytest.mark.parametrize("mode", ["pure", "hybrid"])
def test_contact_features_keep_the_sensor_branch_width(mode: str) -> None:
    space = policy_observation_space(tiny_scenario(), mode)
    plain, contact = HybridExtractor(space), HybridExtractor(space, contact_features=True)
    assert contact.features_dim == plain.features_dim
    first = contact.branches["current"].net[1]
    assert first.in_features == plain.branches["current"].net[1].in_features + 3 * 8
    batch = {k: torch.as_tensor(np.stack([s.sample() for _ in range(2)])).float() for k, s in space.spaces.items()}
    assert contact(batch).shape == (2, contact.features_dim)


def test_runs_stored_before_contact_features_read_as_without_them() -> None:
    stored = PolicyConfig().to_dict()
    assert stored["contact_features"] is True
    del stored["contact_features"]
    assert PolicyConfig.from_dict(stored).contact_features is False
    env = policy_vec_env(LaneChangeSB3VecEnv(2, scenario_for_mode(tiny_scenario(), "pure")), "pure")
    inputs = {flag: build_model(_tiny(obs="pure", contact_features=flag), env).policy.features_extractor
              .branches["current"].net[-4].in_features for flag in (False, True)}  # fmt: skip
    assert inputs == {False: 9 * 9, True: 9 * 9 + 3 * 8}


def test_vgg16_and_compact_on_a_120px_batch() -> None:
    x = torch.rand(2, 3, 120, 120)
    vgg = VGG16()
    assert vgg(x).shape == (2, 10)
    assert sum(isinstance(m, torch.nn.Conv2d) for m in vgg.modules()) == 13
    assert CompactVGG()(x).shape == (2, 10)
    space = spaces.Dict({"current": spaces.Box(-1, 1, (9, 9)), "image": spaces.Box(0, 255, (3, 120, 120), np.uint8)})
    assert HybridExtractor(space, image_net="vgg16").features_dim == 74


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
        _tiny(collision_weight=0.0)


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


def test_pure_mode_drops_the_image_and_skips_rendering() -> None:
    env = policy_vec_env(LaneChangeSB3VecEnv(2, scenario_for_mode(tiny_scenario(), "pure")), "pure")
    assert set(env.reset()) == {"current"}
    with pytest.raises(ValueError, match="predictor"):
        policy_vec_env(LaneChangeSB3VecEnv(2, tiny_scenario()), "prediction")


@pytest.mark.parametrize(("algo", "mode"), [("ppo", "pure"), ("ppo", "image"), ("ppo", "prediction"),
                                            ("ppo", "hybrid"), ("a2c", "hybrid"), ("dqn", "hybrid")])
def test_short_training_saves_loads_and_evaluates(tmp_path: Path, predictor_path: Path, algo: str, mode: str) -> None:
    cfg = _tiny(algo=algo, obs=mode, n_steps=8 if algo == "a2c" else 32)
    res = train_policy(cfg, tmp_path, predictor=predictor_path)
    assert res.timesteps >= 128
    meta = read_meta(tmp_path / "policy.safetensors")
    assert (meta["algo"], meta["obs_mode"]) == (algo, mode)
    loaded = load_policy(tmp_path / "policy.safetensors")
    assert loaded.model.num_timesteps == res.timesteps
    ev = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert EVAL_KEYS <= set(ev) and ev["episodes"] == 2
    assert abs(sum(ev[f"{o}_rate"] for o in ("success", "collision", "off_road", "timeout")) - 1.0) < 1e-9
    assert len(list((tmp_path / "eval" / "episodes").glob("*.mcap"))) == 2
    rows = (tmp_path / "progress.csv").read_text().splitlines()
    assert rows[0].startswith("timesteps,wall_s") and len(rows) >= 2


def test_wider_slots_train_load_and_refuse_the_paper_count(tmp_path: Path, predictor_path: Path) -> None:
    """16 lane slots (--slots 16): the observation, the prediction of each slot and the checkpoint follow."""
    res = train_policy(_tiny(obs="hybrid", slots=16, timesteps=64, n_steps=16, batch_size=32, eval_episodes=2),
                       tmp_path, predictor=predictor_path)
    assert res.metrics["eval"]["episodes"] == 2
    loaded = load_policy(tmp_path / "policy.safetensors")
    assert loaded.scenario.num_neighbours == 16
    space = loaded.model.observation_space
    assert space["current"].shape == (17, 9) and space["prediction"].shape[0] == 16
    with pytest.raises(ValueError, match="num_neighbours"):
        load_policy(tmp_path / "policy.safetensors", scenario=_tiny(obs="hybrid").scenario_config())
    with pytest.raises(ValueError, match="slots"):
        _tiny(obs="pure", slots=17)


def test_same_seed_same_policy(tmp_path: Path) -> None:
    a = train_policy(_tiny(obs="pure", eval_episodes=0), tmp_path / "a")
    b = train_policy(_tiny(obs="pure", eval_episodes=0), tmp_path / "b")
    assert a.timesteps == b.timesteps
    pa, pb = load_policy(tmp_path / "a" / "policy.safetensors"), load_policy(tmp_path / "b" / "policy.safetensors")
    for (ka, va), (kb, vb) in zip(pa.model.policy.state_dict().items(), pb.model.policy.state_dict().items(),
                                  strict=True):
        assert ka == kb and torch.equal(va, vb), ka


def test_resume_continues_the_step_count(tmp_path: Path) -> None:
    first = train_policy(_tiny(obs="pure", timesteps=64, eval_episodes=0), tmp_path)
    assert first.timesteps == 64
    second = train_policy(_tiny(obs="pure", timesteps=192, eval_episodes=0), tmp_path)
    assert second.timesteps == 192
    assert second.metrics["train"]["resumed_from"] == 64
    steps = [int(r.split(",")[0]) for r in (tmp_path / "progress.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and steps[-1] == 192
    # the evaluation follows the policy: continuing a finished run evaluates the new policy
    third = train_policy(_tiny(obs="pure", timesteps=192, eval_episodes=2), tmp_path)
    assert third.metrics["eval"]["policy_sha256"] == file_sha256(tmp_path / "policy.safetensors")
    fourth = train_policy(_tiny(obs="pure", timesteps=256, eval_episodes=2), tmp_path)
    assert fourth.timesteps == 256
    assert fourth.metrics["eval"]["policy_sha256"] == file_sha256(tmp_path / "policy.safetensors")
    assert fourth.metrics["eval"]["policy_sha256"] != third.metrics["eval"]["policy_sha256"]
    # a run with another config in the same directory is refused, saying what differs
    with pytest.raises(ValueError, match="algo"):
        train_policy(_tiny(obs="pure", algo="a2c"), tmp_path)


def test_checkpoint_refuses_another_predictor(tmp_path: Path, predictor_path: Path) -> None:
    train_policy(_tiny(obs="prediction", timesteps=64, eval_episodes=0, n_steps=16), tmp_path / "run",
                 predictor=predictor_path)
    torch.manual_seed(1)
    other = tmp_path / "other.pt"
    Predictor(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1))).save(other)
    with pytest.raises(ValueError, match="predictor"):
        load_policy(tmp_path / "run" / "policy.safetensors", predictor=other)
    with pytest.raises(ValueError, match="observation mode"):
        load_policy(tmp_path / "run" / "policy.safetensors", obs_mode="pure")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes((tmp_path / "run" / "policy.safetensors").read_bytes()[:500])
    with pytest.raises(ValueError, match="truncated"):
        read_meta(bad)


def test_warm_start_lowers_the_behaviour_cloning_loss(tmp_path: Path) -> None:
    config = tiny_scenario()
    record_episodes(config, [1, 2, 3], "rule", tmp_path / "demos", scenario="tiny")
    demos = load_demonstrations(tmp_path / "demos", "image", None, scenario=config)
    assert len(demos) > 20 and demos.obs["image"].shape[1:] == (3, 120, 120)
    env = policy_vec_env(LaneChangeSB3VecEnv(2, config), "image")
    model = build_model(_tiny(obs="image"), env)
    before = bc_loss(model, demos)
    losses = pretrain(model, demos, epochs=4, batch_size=32)
    after = bc_loss(model, demos)
    assert after < before * 0.8, (before, after, losses)


@pytest.mark.parametrize("heavier", [0, 2])
def test_sample_weights_decide_between_conflicting_labels(heavier: int) -> None:
    """The same states labelled both right and left: cloning follows the labels that weigh more."""
    space = policy_observation_space(tiny_scenario(), "pure")
    states = np.stack([space["current"].sample() for _ in range(8)] * 2)
    labels = np.array([0] * 8 + [2] * 8)
    weights = np.where(labels == heavier, 9.0, 1.0)
    env = policy_vec_env(LaneChangeSB3VecEnv(2, scenario_for_mode(tiny_scenario(), "pure")), "pure")
    model = build_model(_tiny(obs="pure"), env)
    pretrain(model, Demonstrations({"current": states}, labels, np.zeros(16, np.float32), 0, weights),
             epochs=60, batch_size=16, value_coef=0.0)  # fmt: skip
    chosen, _ = model.predict({"current": states[:8]}, deterministic=True)
    assert (chosen == heavier).all(), chosen


def test_zero_timesteps_with_a_warm_start_gives_the_behaviour_cloned_policy(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    cfg = _tiny(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=3, eval_episodes=0)
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
        _tiny(timesteps=0)  # nothing to train without a warm start


def test_init_policy_starts_online_training_from_its_weights(tmp_path: Path) -> None:
    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    train_policy(_tiny(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=2,
                       eval_episodes=0), tmp_path / "bc")  # fmt: skip
    start = tmp_path / "bc" / "policy.safetensors"
    fresh = train_policy(_tiny(obs="pure", learning_rate=1e-12, eval_episodes=0), tmp_path / "fresh")
    res = train_policy(_tiny(obs="pure", learning_rate=1e-12, eval_episodes=0, init_policy=str(start)),
                       tmp_path / "init")  # fmt: skip
    assert res.metrics["train"]["warm_start"]["sha256"] == file_sha256(start)
    want = load_policy(start).model.policy.state_dict()
    for run, same in ((tmp_path / "init", True), (tmp_path / "fresh", False)):  # a learning rate of ~0 keeps them
        got = load_policy(run / "policy.safetensors").model.policy.state_dict()
        close = all(torch.allclose(got[k], want[k], atol=1e-6) for k in want)
        assert close == same, run
    assert fresh.timesteps == res.timesteps
    with pytest.raises(ValueError, match="observation mode"):
        train_policy(_tiny(obs="image", eval_episodes=0, init_policy=str(start)), tmp_path / "other")
    # From the command line, PPO continuing from a policy defaults to a tenth of the usual learning rate
    assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--timesteps", "64", "--n-envs", "2",
                              "--n-steps", "32", "--eval-episodes", "0", "--init-policy", str(start),
                              "--out", str(tmp_path / "cli"), "-q"]) == 0  # fmt: skip
    stored = json.loads((tmp_path / "cli" / "run.json").read_text())["config"]
    assert stored["learning_rate"] == 3e-5 == default_learning_rate("ppo", fine_tune=True)
    assert default_learning_rate("ppo") == 3e-4 and default_learning_rate("dqn", fine_tune=True) == 1e-4
    with pytest.raises(ValueError, match="init_policy"):
        _tiny(obs="pure", warm_start=str(tmp_path / "demos"), init_policy=str(start))


def test_demonstrations_are_observed_the_policys_way(tmp_path: Path) -> None:
    """Episodes recorded with the nearest-vehicle observation serve a policy that observes lane slots."""
    import dataclasses

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


def test_rule_driver_evaluation_is_reproducible_and_recorded(tmp_path: Path) -> None:
    from lcsim.drivers import RuleBasedDriver

    config = scenario_for_mode(tiny_scenario(), "pure")
    s1, eps1 = evaluate(RuleBasedDriver(), config, episodes=6, seed=2, out_dir=tmp_path / "a", batch=4)
    s2, eps2 = evaluate(RuleBasedDriver(), config, episodes=6, seed=2, batch=6)
    assert [e.outcome for e in eps1] == [e.outcome for e in eps2]
    assert [e.ret for e in eps1] == [e.ret for e in eps2]  # batching does not change episodes
    assert s1["success_rate"] == s2["success_rate"]
    assert len(list((tmp_path / "a").glob("*.mcap"))) == 6
    lo, hi = wilson_interval(3, 6)
    assert 0 < lo < 0.5 < hi < 1


def test_policy_driver_records_predictions(tmp_path: Path, predictor_path: Path) -> None:
    from lcdata.reader import read_episode

    train_policy(_tiny(obs="prediction", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "run",
                 predictor=predictor_path)
    drv = PolicyDriver(load_policy(tmp_path / "run" / "policy.safetensors"))
    evaluate(drv, drv.config, episodes=2, out_dir=tmp_path / "ev", batch=2)
    ep = read_episode(sorted((tmp_path / "ev").glob("*.mcap"))[0])
    assert len(ep.predictions) > 0 and len(ep.steps) > 0
    assert set(ep.predictions["k"]) == set(range(1, 11))


def test_cli_train_and_eval_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--timesteps", "128", "--n-envs", "2",
                              "--n-steps", "32", "--eval-episodes", "2", "--out", str(out), "-q"]) == 0
    js = tmp_path / "eval.json"
    assert eval_main([str(out / "policy.safetensors"), "--episodes", "3", "--seed", "1", "--json-out", str(js),
                      "--no-record", "-q"]) == 0
    data = json.loads(js.read_text())
    assert EVAL_KEYS <= set(data) and data["episodes"] == 3 and data["overlap_with_training"] == 0
    assert data["wall_s"] > 0 and data["decisions"] > data["episodes"]  # what the evaluation cost
    assert "success" in capsys.readouterr().out
    # bad input: one line, exit 2
    assert eval_main([str(tmp_path / "missing.safetensors")]) == 2
    assert train_policy_main(["--obs", "hybrid", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith(("lc-eval: error", "lc-train-policy: error")) for line in err)


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


def test_lc_record_with_a_policy_driver_writes_its_predictions(tmp_path: Path, predictor_path: Path) -> None:
    from lccli.record import record_main
    from lcdata.reader import read_episode
    from lcdata.record import record_episode

    train_policy(_tiny(obs="prediction", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "run",
                 predictor=predictor_path)
    drv = PolicyDriver(load_policy(tmp_path / "run" / "policy.safetensors"))
    res = record_episode(drv.config, 4, drv, tmp_path / "ep.mcap")  # what lc-record --driver policy:CKPT runs
    ep = read_episode(res.path)
    assert sorted(set(ep.predictions["step"])) == sorted(ep.steps["step"])  # one prediction set per decision
    assert set(ep.predictions["k"]) == set(range(1, 11))
    assert record_main(["--driver", f"policy:{tmp_path / 'missing.safetensors'}", "--out", str(tmp_path / "o")]) == 2


def test_dagger_round_labels_the_policys_states_with_the_oracle_and_saves_a_loadable_policy(tmp_path: Path) -> None:
    from lcmodels.policy.dagger import collect, dagger

    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    cfg = _tiny(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=2, eval_episodes=0)
    train_policy(cfg, tmp_path / "bc")
    demos = load_demonstrations(tmp_path / "demos", "pure", None, scenario=config)
    got = collect(tmp_path / "bc" / "policy.safetensors", [7, 8])
    assert len(got.labels) == len(got.obs["current"]) > 0 and got.searches >= 1 and len(got.outcomes) == 2
    assert set(got.labels.tolist()) <= {0, 1, 2} and got.agreed <= len(got.labels)
    again = collect(tmp_path / "bc" / "policy.safetensors", [7, 8])
    assert np.array_equal(again.labels, got.labels) and np.array_equal(again.obs["current"], got.obs["current"])
    winning = collect(tmp_path / "bc" / "policy.safetensors", [7, 8], labels="winning")  # the same states, other labels
    assert np.array_equal(winning.obs["current"], got.obs["current"]) and winning.harmless == got.harmless
    assert (winning.labels != got.labels).sum() == got.harmless  # exactly the harmless deviations keep their own
    with pytest.raises(ValueError, match="labels"):
        collect(tmp_path / "bc" / "policy.safetensors", [7], labels="best")
    records = dagger(tmp_path / "bc", tmp_path / "dg", rounds=1, episodes=2, epochs=1, seed=7, workers=1,
                     eval_episodes=2)  # fmt: skip
    assert records[0]["states_labelled"] == len(got.labels)  # the same seeds, the same policy: the same states
    assert records[0]["training_states"] == len(demos) + len(got.labels)
    assert set(records[0]["eval"]) >= {"success_rate", "collision_rate"}
    loaded = load_policy(tmp_path / "dg" / "round1" / "policy.safetensors")
    assert loaded.meta["dagger"]["round"] == 1
    with pytest.raises(FileExistsError):
        dagger(tmp_path / "bc", tmp_path / "dg", rounds=1, episodes=1, epochs=1)


def test_dagger_resumed_gives_the_rounds_of_an_uninterrupted_run(tmp_path: Path) -> None:
    from lcmodels.policy.dagger import dagger

    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    train_policy(_tiny(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=2,
                       eval_episodes=0), tmp_path / "bc")  # fmt: skip
    args = dict(episodes=2, epochs=1, seed=7, workers=1, eval_episodes=0)
    straight = dagger(tmp_path / "bc", tmp_path / "straight", rounds=2, **args)
    dagger(tmp_path / "bc", tmp_path / "parts", rounds=1, **args)
    resumed = dagger(tmp_path / "bc", tmp_path / "parts", rounds=2, resume=True, **args)
    assert [r["round"] for r in resumed] == [1, 2]
    for key in ("states_labelled", "training_states", "epoch_losses"):
        assert resumed[1][key] == straight[1][key], key
    a = load_policy(tmp_path / "straight" / "round2" / "policy.safetensors").model.policy.state_dict()
    b = load_policy(tmp_path / "parts" / "round2" / "policy.safetensors").model.policy.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="labels: plan there, winning asked"):
        dagger(tmp_path / "bc", tmp_path / "parts", rounds=3, resume=True, **{**args, "labels": "winning"})
    with pytest.raises(FileNotFoundError, match="no DAgger rounds"):
        dagger(tmp_path / "bc", tmp_path / "empty", rounds=1, resume=True, **args)


def test_dagger_with_a_driver_as_the_expert_labels_every_state_with_its_decision(tmp_path: Path) -> None:
    from lcmodels.policy.dagger import collect_from_driver, dagger

    train_policy(_tiny(obs="pure", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "run")
    policy = tmp_path / "run" / "policy.safetensors"
    keep = collect_from_driver(policy, [7, 8, 9], "keep", batch=2)
    assert len(keep.labels) == len(keep.obs["current"]) > 0 and len(keep.outcomes) == 3
    drv, decisions, with_choice = PolicyDriver(load_policy(policy)), 0, 0  # the same episodes, counted
    core = LaneChangeCore(drv.config, 3)
    core.reset(range(3), [episode_seed(u) for u in (7, 8, 9)])
    while (core.outcome == RUNNING).any():
        mask = core.action_mask()
        decisions += int((core.outcome == RUNNING).sum())
        with_choice += int(((core.outcome == RUNNING) & (mask.sum(axis=1) > 1)).sum())
        core.step(drv(core.observe(), mask, core))
    assert len(keep.labels) == with_choice < decisions  # mid-change states (no choice) are not kept
    assert (keep.labels == KEEP).all() and keep.agreed <= len(keep.labels) and keep.alive is None
    expert = f"lookahead-blind:{policy}"
    got = collect_from_driver(policy, [7, 8, 9], expert, batch=2)
    assert got.alive.shape == (len(got.labels), 3) and not np.isnan(got.alive[:, KEEP]).any()
    rows = np.arange(len(got.labels))  # the planner's decision survives as many imagined futures as the best one
    # (a decision the simulator does not allow, as an untrained policy proposes, stands only when nothing survives)
    assert np.array_equal(np.nan_to_num(got.alive)[rows, got.labels], np.nanmax(got.alive, axis=1))
    assert np.array_equal(got.obs["current"], keep.obs["current"])  # the policy drives: the same states
    again = collect_from_driver(policy, [7, 8, 9], expert, batch=3)  # batching does not change a label
    assert np.array_equal(np.sort(again.labels), np.sort(got.labels)) and again.agreed == got.agreed
    records = dagger(tmp_path / "run", tmp_path / "dg", rounds=1, episodes=3, epochs=1, seed=7, workers=1,
                     eval_episodes=0, expert=expert)  # fmt: skip
    assert records[0]["expert"] == expert and records[0]["states_labelled"] == len(got.labels)
    assert records[0]["training_states"] == len(got.labels)  # a run without demonstrations: its states only
    with np.load(tmp_path / "dg" / "round1" / "states.npz") as kept:  # the policy's own decisions are kept
        assert np.array_equal(kept["actions"], again.actions) and np.array_equal(kept["labels"], again.labels)
    assert got.agreed == int((got.actions == got.labels).sum())
    with pytest.raises(ValueError, match=r"correction weight: 1\.0 there, 5\.0 asked"):
        dagger(tmp_path / "run", tmp_path / "dg", rounds=2, episodes=3, epochs=1, seed=7, workers=1,
               eval_episodes=0, expert=expert, correction_weight=5.0, resume=True)  # fmt: skip
    with pytest.raises(ValueError, match="there, oracle asked"):
        dagger(tmp_path / "run", tmp_path / "dg", rounds=2, episodes=3, epochs=1, seed=7, workers=1,
               eval_episodes=0, resume=True)  # fmt: skip
    with pytest.raises(ValueError, match=r"expert's lookahead: \{\} there"):
        dagger(tmp_path / "run", tmp_path / "dg", rounds=2, episodes=3, epochs=1, seed=7, workers=1,
               eval_episodes=0, expert=expert, expert_lookahead={"horizon_decisions": 2}, resume=True)  # fmt: skip
    for bad, what in (({"expert": "oracle", "expert_lookahead": {"horizon_decisions": 2}}, "lookahead expert only"),
                      ({"expert": f"lookahead:{policy}", "expert_lookahead": {"samples": 2}}, "samples")):
        with pytest.raises(ValueError, match=what):
            dagger(tmp_path / "run", tmp_path / "bad", rounds=1, episodes=3, epochs=1, seed=7, workers=1,
                   eval_episodes=0, **bad)  # fmt: skip
    short = collect_from_driver(policy, [7, 8, 9], expert, batch=3, lookahead={"horizon_decisions": 2})
    records = dagger(tmp_path / "run", tmp_path / "dg-short", rounds=1, episodes=3, epochs=1, seed=7, workers=1,
                     eval_episodes=0, expert=expert, expert_lookahead={"horizon_decisions": 2})  # fmt: skip
    assert records[0]["expert_lookahead"] == {"horizon_decisions": 2}
    with np.load(tmp_path / "dg-short" / "round1" / "states.npz") as kept:
        assert np.array_equal(kept["labels"], short.labels)


def test_a_lookahead_follows_a_policy_without_image_and_refuses_one_with(tmp_path: Path) -> None:
    train_policy(_tiny(obs="pure", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "pure")
    driver, config = driver_for(f"lookahead:{tmp_path / 'pure' / 'policy.safetensors'}")
    assert driver.name == "lookahead-ppo-pure" and config.render_image is False
    summary, _ = evaluate(driver, config, episodes=2, batch=2)
    assert summary["episodes"] == 2
    train_policy(_tiny(obs="image", timesteps=32, n_steps=16, eval_episodes=0), tmp_path / "image")
    with pytest.raises(ValueError, match="reads the image"):
        driver_for(f"lookahead-blind:{tmp_path / 'image' / 'policy.safetensors'}")
    image, pure = tmp_path / "image" / "policy.safetensors", tmp_path / "pure" / "policy.safetensors"
    guarded, image_config = driver_for(f"lookahead-blind:{image}", follow=str(pure))  # it proposes, pure follows
    assert guarded.name == "ppo-image+lookahead-blind-ppo-pure" and image_config.render_image is True
    assert isinstance(guarded.proposer, PolicyDriver) and guarded.proposer.policy.obs_mode == "image"
    summary, _ = evaluate(guarded, image_config, episodes=2, batch=2)
    assert summary["episodes"] == 2
    with pytest.raises(ValueError, match=r"driver to follow: .* reads the image"):
        driver_for(f"lookahead-blind:{image}", follow=str(image))
    with pytest.raises(ValueError, match="applies to lookahead:POLICY"):
        driver_for(str(pure), follow="rule")
    assert eval_main([f"lookahead:{image}", "--lookahead-follow", str(tmp_path / "missing.safetensors"), "--no-record"]) == 2
    assert eval_main([f"lookahead-blind:{image}", "--lookahead-follow", "rule", "--lookahead-horizon", "2",
                      "--episodes", "2", "--no-record", "--json-out", str(tmp_path / "guarded.json")]) == 0
    guarded_summary = json.loads((tmp_path / "guarded.json").read_text())
    assert guarded_summary["driver"] == "ppo-image+lookahead-blind-rule"
    assert 0 <= guarded_summary["planner_overrides"] <= guarded_summary["planner_choices"] <= guarded_summary["decisions"]
    assert eval_main([f"lookahead-blind:{tmp_path / 'missing.safetensors'}", "--no-record"]) == 2
    longer, _ = driver_for(f"lookahead-blind:{tmp_path / 'pure' / 'policy.safetensors'}",
                           lookahead={"horizon_decisions": 3, "samples": 2})  # fmt: skip
    assert (longer.config.horizon_decisions, longer.config.samples, longer.config.blind) == (3, 2, True)
    with pytest.raises(ValueError, match="lookahead drivers only"):
        driver_for("rule", lookahead={"samples": 2})
    assert eval_main(["lookahead", "--lookahead-samples", "2", "--no-record"]) == 2  # samples need blindness
    assert eval_main(["lookahead", "--lookahead-perceived", "--no-record"]) == 2  # so does perception
    assert eval_main([f"lookahead-blind:{image}", "--lookahead-follow", "rule", "--lookahead-horizon", "2",
                      "--lookahead-perceived", "--episodes", "2", "--no-record", "--json-out",
                      str(tmp_path / "perceived.json")]) == 0  # fmt: skip
    assert json.loads((tmp_path / "perceived.json").read_text())["driver"] == "ppo-image+lookahead-perceived-rule"
    assert eval_main(["lookahead-blind", "--lookahead-horizon", "2", "--lookahead-samples", "2", "--episodes", "2",
                      "--scenario", "tiny", "--no-record", "--json-out", str(tmp_path / "la.json")]) == 0
    assert json.loads((tmp_path / "la.json").read_text())["episodes"] == 2
    from lccli.record import record_main
    from lcdata.reader import read_episode

    out = tmp_path / "rec"
    assert record_main(["--driver", f"lookahead-blind:{tmp_path / 'pure' / 'policy.safetensors'}", "--seed", "3",
                        "--no-images", "--out", str(out)]) == 0  # fmt: skip
    (path,) = out.glob("*.mcap")
    assert "lookahead-blind-ppo-pure" in path.name and len(read_episode(path).steps) > 0
    assert record_main(["--driver", f"lookahead:{tmp_path / 'image' / 'policy.safetensors'}", "--out", str(out)]) == 2
    assert record_main(["--driver", f"lookahead-blind:{tmp_path / 'image' / 'policy.safetensors'}", "--lookahead-follow",
                        "rule", "--seed", "4", "--out", str(out)]) == 0  # fmt: skip
    (guarded_path,) = out.glob("*ppo-image+lookahead-blind-rule*.mcap")
    assert len(read_episode(guarded_path).steps) > 0
    assert record_main(["--driver", "rule", "--lookahead-follow", "rule", "--out", str(out)]) == 2
    assert record_main(["--driver", f"lookahead-blind:{tmp_path / 'image' / 'policy.safetensors'}", "--lookahead-follow",
                        "rule", "--lookahead-horizon", "2", "--lookahead-perceived", "--seed", "5",
                        "--out", str(out)]) == 0  # fmt: skip
    (perceived_path,) = out.glob("*ppo-image+lookahead-perceived-rule*.mcap")
    assert len(read_episode(perceived_path).steps) > 0
    assert record_main(["--driver", "rule", "--lookahead-perceived", "--out", str(out)]) == 2
    assert record_main(["--driver", f"lookahead:{tmp_path / 'pure' / 'policy.safetensors'}", "--lookahead-perceived",
                        "--out", str(out)]) == 2  # perception needs a blind planner


def test_frozen_image_branch_trains_faster_form_and_saves_a_plain_policy(tmp_path: Path, predictor_path: Path) -> None:
    """``freeze_image``: the image branch of the initial policy runs in the observation wrapper; the run's
    policy.safetensors is a plain hybrid policy with that branch unchanged, acting as the training form did; the
    training checkpoint is refused as a policy; a resume needs only the run directory."""
    from lcmodels.policy.checkpoint import load_weights, policy_model
    from lcmodels.policy.extractor import IMAGE_FEATURES, ImageEncoder, make_image_net

    train_policy(_tiny(obs="hybrid", timesteps=64, eval_episodes=0), tmp_path / "start", predictor=predictor_path)
    start = tmp_path / "init.safetensors"
    (tmp_path / "start" / "policy.safetensors").rename(start)
    out = tmp_path / "frozen"
    cfg = _tiny(obs="hybrid", timesteps=128, init_policy=str(start), freeze_image=True)
    res = train_policy(cfg, out, predictor=predictor_path)
    assert EVAL_KEYS <= set(res.metrics["eval"]) and res.timesteps == 128
    before = load_policy(start).model.policy.state_dict()
    plain = load_policy(out / "policy.safetensors")
    after = plain.model.policy.state_dict()
    image_keys = [k for k in before if ".branches.image." in k]
    assert image_keys and all(torch.equal(before[k], after[k]) for k in image_keys)  # frozen
    assert not all(torch.equal(before[k], after[k]) for k in before)  # the rest trained
    # The plain policy acts as the training form does on the same observations, each as its wrapper builds them.
    state = json.loads((out / "checkpoints" / "latest.json").read_text())
    ckpt = out / "checkpoints" / state["weights"]
    training_form = policy_model(read_meta(ckpt), future_steps=plain.predictor.future_steps)
    load_weights(training_form, ckpt)
    net = make_image_net("compact", 3, plain.scenario.render.image_size_px, 10)
    net.load_state_dict(torch.load(out / "image_encoder.pt", weights_only=True))
    base = LaneChangeSB3VecEnv(3, plain.scenario)
    base.seed(5)
    raw = base.reset()
    obs = policy_vec_env(base, "hybrid", plain.predictor).convert(raw)
    wrapper = policy_vec_env(base, "hybrid", plain.predictor, image_encoder=ImageEncoder(net, 10))
    feats = wrapper.convert(raw)
    assert set(feats) == set(wrapper.observation_space.spaces) == {"current", IMAGE_FEATURES, "prediction"}
    assert feats[IMAGE_FEATURES].shape == (3, 10) and feats[IMAGE_FEATURES].any()

    def probs(model, o):
        t, _ = model.policy.obs_to_tensor(o)
        with torch.no_grad():
            return model.policy.get_distribution(t).distribution.probs

    torch.testing.assert_close(probs(plain.model, obs), probs(training_form, feats), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="training checkpoint"):
        load_policy(ckpt)
    start.unlink()  # resuming reads the branch kept in the run directory
    res = train_policy(dataclasses.replace(cfg, timesteps=192), out, predictor=predictor_path)
    assert res.metrics["train"]["resumed_from"] == 128 and res.timesteps == 192
    for bad in (dict(obs="hybrid", freeze_image=True), dict(obs="pure", init_policy=str(start), freeze_image=True)):
        with pytest.raises(ValueError, match="freeze_image"):
            _tiny(**bad)
