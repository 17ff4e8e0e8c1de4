"""The sensor branch that reads the vehicles as a set (``sensor_encoder="attention"``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lcmodels.policy import load_policy, train_policy
from lcmodels.policy.extractor import CURRENT_SCALE, EgoAttention, HybridExtractor, WindowFeatures
from lcmodels.policy.obs import policy_observation_space
from lcsim.config import tiny_scenario
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import tiny_policy

_PRESENT = 8


def _rows(batch: int, slots: int, shown: int, seed: int = 0) -> torch.Tensor:
    """Sensor rows: the ego (all zeros but present), ``shown`` vehicles at random, the other slots empty."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.randn(batch, 1 + slots, len(CURRENT_SCALE), generator=g) * torch.tensor(CURRENT_SCALE)
    rows[:, 0] = 0.0
    rows[..., _PRESENT] = 0.0
    rows[:, : 1 + shown, _PRESENT] = 1.0
    rows[:, 1 + shown :, :_PRESENT] = 0.0
    return rows


@pytest.mark.parametrize("contact", [False, True])
def test_the_order_of_the_slots_changes_nothing(contact: bool) -> None:
    torch.manual_seed(0)
    net = EgoAttention(len(CURRENT_SCALE), CURRENT_SCALE, 32, 16, contact=contact).eval()
    rows = _rows(4, 8, shown=6)
    order = torch.tensor([0, 5, 3, 8, 1, 7, 2, 6, 4])
    out = net(rows)
    torch.testing.assert_close(net(rows[:, order]), out)
    # a vehicle moved changes the output: the check above can fail
    moved = rows.clone()
    moved[:, 2, 0] += 30.0
    assert not torch.allclose(net(moved), out)


def test_empty_slots_are_not_read_and_any_number_of_slots_fits_the_same_weights() -> None:
    torch.manual_seed(1)
    net = EgoAttention(len(CURRENT_SCALE), CURRENT_SCALE, 32, 16, contact=True).eval()
    rows = _rows(3, 8, shown=4)
    out = net(rows)
    noisy = rows.clone()
    noisy[:, 6:, :_PRESENT] = 99.0  # garbage in slots marked empty
    torch.testing.assert_close(net(noisy), out)
    wider = torch.cat([rows, torch.zeros(3, 8, len(CURRENT_SCALE))], dim=1)  # 16 slots, the new ones empty
    torch.testing.assert_close(net(wider), out)
    fewer = rows[:, :5]  # only the shown vehicles
    torch.testing.assert_close(net(fewer), out)


def test_nobody_shown_reads_the_ego_alone() -> None:
    net = EgoAttention(len(CURRENT_SCALE), CURRENT_SCALE, 32, 16).eval()
    rows = _rows(2, 8, shown=0)
    assert torch.isfinite(net(rows)).all()


def test_window_features_join_the_attention_output() -> None:
    net = EgoAttention(len(CURRENT_SCALE), CURRENT_SCALE, 32, 16, window=WindowFeatures(8))
    assert net.net[0].in_features == 2 * 64 + 11
    assert net(_rows(2, 8, shown=3)).shape == (2, 16)


@pytest.mark.parametrize("mode", ["pure", "prediction", "hybrid"])
def test_the_extractor_uses_it_in_every_mode(mode: str) -> None:
    space = policy_observation_space(tiny_scenario(), mode)
    ext = HybridExtractor(space, sensor_encoder="attention", contact_features=True, window_features=True)
    assert isinstance(ext.branches["current"], EgoAttention)
    assert ext.features_dim == HybridExtractor(space).features_dim
    batch = {k: torch.as_tensor(np.stack([s.sample() for _ in range(2)])).float() for k, s in space.spaces.items()}
    assert ext(batch).shape == (2, ext.features_dim)
    with pytest.raises(ValueError, match="sensor encoder"):
        HybridExtractor(space, sensor_encoder="transformer")


def test_a_policy_with_it_trains_saves_and_loads_to_the_same_actions(tmp_path: Path) -> None:
    cfg = tiny_policy(obs="pure", sensor_encoder="attention", window_features=True, timesteps=64, n_steps=16,
                      batch_size=32, eval_episodes=0)
    train_policy(cfg, tmp_path)
    loaded = load_policy(tmp_path / "policy.safetensors")
    assert isinstance(loaded.model.policy.features_extractor.branches["current"], EgoAttention)
    env = LaneChangeSB3VecEnv(4, loaded.scenario)
    env.seed(3)
    obs = {"current": env.reset()["current"]}
    a, _ = loaded.model.predict(obs, deterministic=True)
    b, _ = load_policy(tmp_path / "policy.safetensors").model.predict(obs, deterministic=True)
    assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="sensor_encoder"):
        tiny_policy(sensor_encoder="set")
