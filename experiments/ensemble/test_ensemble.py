"""experiments/ensemble/ensemble.py: the ensemble decides by the members' mean probabilities and refuses mismatched members."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lcmodels.policy import PolicyConfig, load_policy, train_policy
from lcmodels.policy.evaluate import PolicyDriver
from lcsim.core import LaneChangeCore

from .ensemble import EnsembleDriver, load_ensemble, main


def _tiny(**kw) -> PolicyConfig:
    base = dict(scenario="tiny", timesteps=128, n_envs=2, n_steps=32, batch_size=64, n_epochs=2,
                eval_episodes=2, eval_batch=2, checkpoint_every=64, buffer_size=500, learning_starts=32)
    base.update(kw)
    return PolicyConfig(**base)


@pytest.fixture(scope="module")
def members(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("ens")
    paths = []
    for seed in (0, 1):
        train_policy(_tiny(obs="pure", eval_episodes=0, seed=seed, learning_rate=3e-2), root / f"s{seed}")
        paths.append(root / f"s{seed}" / "policy.safetensors")
    return paths


def _states(driver, n: int = 4, decisions: int = 6) -> list[dict[str, np.ndarray]]:
    core = LaneChangeCore(driver.config, n)
    core.reset(np.arange(n), [11 + k for k in range(n)])
    seen = []
    for _ in range(decisions):
        obs = core.observe()
        seen.append(obs)
        core.step(np.ones(n, dtype=np.int64))  # keep
    return seen


def test_one_member_decides_as_the_policy_and_two_by_their_mean(members: list[Path]) -> None:
    a, b = (load_policy(p) for p in members)
    alone, pair = EnsembleDriver([a]), EnsembleDriver([a, b])
    single = PolicyDriver(a)
    differ = 0
    for obs in _states(alone):
        mask = np.ones((len(obs["current"]), 3), dtype=bool)
        np.testing.assert_array_equal(alone(obs, mask, None), single(obs, mask, None))
        probs = []
        for m in (a, b):
            t, _ = m.model.policy.obs_to_tensor({"current": obs["current"]})
            with torch.no_grad():
                probs.append(m.model.policy.get_distribution(t).distribution.probs.numpy())
        np.testing.assert_allclose(pair.probabilities(obs), (probs[0] + probs[1]) / 2, rtol=1e-6)
        np.testing.assert_array_equal(pair(obs, mask, None), ((probs[0] + probs[1]) / 2).argmax(axis=1))
        differ += int((probs[0].argmax(axis=1) != probs[1].argmax(axis=1)).sum())
    assert differ > 0  # the two seeds disagree somewhere, so the mean is a real vote


def test_members_of_another_scenario_are_refused(members: list[Path], tmp_path: Path) -> None:
    train_policy(_tiny(obs="pure", eval_episodes=0, scenario="light", timesteps=64), tmp_path / "light")
    with pytest.raises(ValueError, match="scenario"):
        load_ensemble([members[0], tmp_path / "light" / "policy.safetensors"])


def test_cli_json_and_bad_input(members: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "e.json"
    assert main([str(p) for p in members] + ["--episodes", "2", "--batch", "2", "--json-out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text())
    assert printed["members"] == [str(p) for p in members] and printed["episodes"] == 2
    assert abs(sum(printed[f"{k}_rate"] for k in ("success", "collision", "off_road", "timeout")) - 1) < 1e-9
    bad = tmp_path / "bad.zip"
    bad.write_bytes(members[0].read_bytes()[:1000])
    for argv in ([str(bad)], [str(tmp_path / "missing.zip")], [str(members[0]), "--episodes", "0"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("eval_ensemble: error:") and "\n" not in err
