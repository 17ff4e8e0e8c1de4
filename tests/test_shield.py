"""Training behind the safety layer: it executes the policy's proposals and each override costs the penalty."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lcmodels.policy.shield import Shield, ShieldedSB3VecEnv, shield_for
from lcsim.planning import PRIVILEGED, LookaheadDriver, SafetyLayerConfig
from lcsim.registry import make_driver, scenario
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import tiny_policy

LEFT = 2


def test_the_shielded_env_steps_what_the_layer_executes_and_takes_the_penalty_per_override() -> None:
    """A proposer that always asks for the left lane: the shielded env drives what the layer lets through, the
    same road as an unshielded env given those decisions, with the penalty taken exactly where it overrode."""
    config = scenario("tiny")
    penalty = 7.5
    look = SafetyLayerConfig(horizon_decisions=4, samples=2)
    shield = Shield(LookaheadDriver(look, rule=make_driver("rule")), penalty)
    twin = Shield(LookaheadDriver(look, rule=make_driver("rule")), penalty)  # what the layer will execute
    shielded, plain = ShieldedSB3VecEnv(4, config, shield), LaneChangeSB3VecEnv(4, config)
    shielded.seed(11)
    plain.seed(11)
    obs_s, obs_p = shielded.reset(), plain.reset()
    overridden_total = 0
    for _ in range(40):
        proposed = np.full(4, LEFT)
        executed, _ = twin.execute(proposed, shielded.venv.core)
        obs_s, r_s, d_s, _ = shielded.step(proposed)
        obs_p, r_p, d_p, _ = plain.step(executed)
        overridden = executed != proposed
        overridden_total += int(overridden.sum())
        np.testing.assert_allclose(r_s, r_p - penalty * overridden, rtol=0, atol=1e-4)
        np.testing.assert_array_equal(d_s, d_p)
        for k in obs_p:
            np.testing.assert_array_equal(obs_s[k], obs_p[k])
    assert shield.replaced == overridden_total and 0 < shield.overrides < overridden_total  # and refused changes
    assert shield.counts() == twin.counts() and shield.overrides < shield.choices


def test_a_shield_must_be_blind_and_its_penalty_a_number_at_least_zero() -> None:
    with pytest.raises(ValueError, match="needs a blind layer"):
        Shield(LookaheadDriver(PRIVILEGED), 1.0)
    with pytest.raises(ValueError, match=r"penalty .* must be a number >= 0"):
        Shield(LookaheadDriver(SafetyLayerConfig()), -1.0)
    with pytest.raises(ValueError, match=r"safety\.follow"):
        shield_for(SafetyLayerConfig(), 1.0, scenario("tiny"))


def test_shielded_training_is_reproducible_feels_the_penalty_and_resumes_its_step_count(tmp_path: Path) -> None:
    """train_policy with a shield that follows a pure policy: the same seed gives the same weights, another penalty
    other weights, and a run stopped at its first checkpoint resumes from there and says so in shield.json."""
    from lcmodels.policy.plan import resolve
    from lcmodels.policy.train import train_policy, train_run

    follow = tmp_path / "follow"
    train_policy(tiny_policy(obs="pure", timesteps=64, n_steps=32, eval_episodes=0), follow)
    look = SafetyLayerConfig(horizon_decisions=3, samples=2, follow=str(follow / "policy.safetensors"))

    def run(out: Path, timesteps: int, penalty: float = 50.0) -> bytes:
        cfg = tiny_policy(obs="pure", timesteps=timesteps, n_steps=32, eval_episodes=0, checkpoint_every=64,
                          init_policy=str(follow / "policy.safetensors"))  # fmt: skip
        train_run(resolve(cfg, layer=look, penalty=penalty), out)
        return (out / "policy.safetensors").read_bytes()

    whole = run(tmp_path / "whole", 128)
    assert run(tmp_path / "again", 128) == whole
    assert run(tmp_path / "free", 128, penalty=0.0) != whole
    counts = json.loads((tmp_path / "whole" / "shield.json").read_text())
    assert counts["penalty"] == 50.0 and counts["choices"] > 0 and counts["to_step"] == 128
    assert counts["overrides"] <= counts["replaced"] and counts["replaced"] > 0
    run(tmp_path / "parts", 64)
    run(tmp_path / "parts", 128)
    resumed = json.loads((tmp_path / "parts" / "shield.json").read_text())
    assert resumed["from_step"] == 64 and resumed["to_step"] == 128
