"""The hybrid features extractor: output sizes per mode, the contact and window features against hand values, the image networks."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.utils import obs_as_tensor

from lcdata.record import record_episodes
from lcmodels.policy import (
    VGG16,
    CompactVGG,
    HybridExtractor,
    PolicyConfig,
    StridedCompact,
    bc_loss,
    load_demonstrations,
    load_policy,
    policy_vec_env,
    pretrain,
    train_policy,
)
from lcmodels.policy.extractor import pooled_images, prepools
from lcmodels.policy.obs import OBS_MODES, policy_observation_space, scenario_for_mode
from lcmodels.policy.plan import policy_scenario
from lcmodels.policy.train import build_model
from lcsim.config import tiny_scenario
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import tiny_policy


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
    res = train_policy(tiny_policy(obs="pure", window_features=True, timesteps=64, n_steps=16, batch_size=32,
                             eval_episodes=0), tmp_path)
    assert res.timesteps == 64
    loaded = load_policy(tmp_path / "policy.safetensors")  # the extractor comes back with the features
    assert loaded.model.policy.features_extractor.branches["current"].net[1].in_features == (
        both.branches["current"].net[1].in_features)
    with pytest.raises(ValueError, match="window_features"):
        tiny_policy(obs="pure", window_features=True, neighbours="nearest")


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
    cfg = tiny_policy(obs="pure", window_features=True, accel_features=True, timesteps=64, n_steps=16, batch_size=32,
                warm_start=str(tmp_path / "demos"), warm_start_epochs=1, eval_episodes=2)
    assert policy_scenario(cfg).observe_acceleration
    demos = load_demonstrations(tmp_path / "demos", "pure", None, scenario=policy_scenario(cfg))
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
    inputs = {flag: build_model(tiny_policy(obs="pure", contact_features=flag), env).policy.features_extractor
              .branches["current"].net[-4].in_features for flag in (False, True)}  # fmt: skip
    assert inputs == {False: 9 * 9, True: 9 * 9 + 3 * 8}


def test_vgg16_and_compact_on_a_120px_batch() -> None:
    x = torch.rand(2, 3, 120, 120)
    vgg = VGG16()
    assert vgg(x).shape == (2, 10)
    assert sum(isinstance(m, torch.nn.Conv2d) for m in vgg.modules()) == 13
    assert CompactVGG()(x).shape == (2, 10)
    strided = StridedCompact()
    assert strided(x).shape == (2, 10)
    # the same channels and reduction as the compact network: a 32x5x5 map from 120 px (and from 64 px, 3x3)
    assert strided.head[1].in_features == 32 * 5 * 5 and StridedCompact(size=64).head[1].in_features == 32 * 3 * 3
    space = spaces.Dict({"current": spaces.Box(-1, 1, (9, 9)), "image": spaces.Box(0, 255, (3, 120, 120), np.uint8)})
    assert HybridExtractor(space, image_net="vgg16").features_dim == 74
    assert HybridExtractor(space, image_net="strided").features_dim == 74


def test_pooled_images_are_the_networks_first_layer() -> None:
    """The pooling computed ahead of the compact networks is their AvgPool2d (remainder dropped), and a
    network fed it gives what it gives the full image."""
    x = np.random.default_rng(3).integers(0, 256, (4, 3, 121, 121), dtype=np.uint8)
    pooled = pooled_images(x, np.array([2, 0]))
    ref = torch.nn.functional.avg_pool2d(torch.as_tensor(x[[2, 0]]).float(), 3)
    assert pooled.shape == (2, 3, 40, 40)
    torch.testing.assert_close(torch.from_numpy(pooled), ref)
    for net in (CompactVGG(size=121), StridedCompact(size=121)):
        assert prepools(net)
        full = net(torch.as_tensor(x).float() / 255.0)
        torch.testing.assert_close(net(torch.from_numpy(pooled_images(x)) / 255.0), full)
    assert not prepools(VGG16())
    with pytest.raises(ValueError, match="uint8"):
        pooled_images(x.astype(np.float32))


@pytest.mark.parametrize("net", ["compact", "strided"])
def test_cloning_feeds_pooled_images_with_the_full_images_loss(tmp_path: Path, net: str) -> None:
    """bc_loss (pooled images) equals the policy's own loss on the full images; pretrain learns with them."""
    config = scenario_for_mode(tiny_scenario(), "image")
    record_episodes(config, [1], "oracle", tmp_path / "demos", scenario="tiny")
    demos = load_demonstrations(tmp_path / "demos", "image", None, scenario=config)
    env = policy_vec_env(LaneChangeSB3VecEnv(1, config), "image")
    model = build_model(tiny_policy(obs="image", image_net=net), env)
    with torch.no_grad():
        obs = obs_as_tensor(demos.obs, model.policy.device)
        _v, log_prob, _e = model.policy.evaluate_actions(obs, torch.as_tensor(demos.actions))
    assert bc_loss(model, demos) == pytest.approx(float(-log_prob.mean()), rel=1e-5)
    losses = pretrain(model, demos, epochs=3, learning_rate=3e-3)
    assert losses[-1] < losses[0]
