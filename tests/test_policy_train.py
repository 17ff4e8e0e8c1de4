"""Training runs: short runs of every algorithm and mode, seeds, resume, initial policies, the frozen image branch, what a checkpoint refuses."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from lccli.policy import train_policy_main
from lcdata.record import record_episodes
from lcmodels.fileio import file_sha256
from lcmodels.policy import (
    load_policy,
    policy_vec_env,
    read_meta,
    train_policy,
)
from lcmodels.policy.obs import scenario_for_mode
from lcmodels.policy.plan import policy_scenario
from lcmodels.policy.train import default_learning_rate
from lcmodels.predictor import Predictor, PredictorConfig, TrajectoryTransformer
from lcsim.config import tiny_scenario
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import EVAL_KEYS, tiny_policy


@pytest.mark.parametrize(("algo", "mode"), [("ppo", "pure"), ("ppo", "image"), ("ppo", "prediction"),
                                            ("ppo", "hybrid"), ("a2c", "hybrid"),
                                            pytest.param("dqn", "hybrid", marks=pytest.mark.slow)])
def test_short_training_saves_loads_and_evaluates(tmp_path: Path, predictor_path: Path, algo: str, mode: str) -> None:
    cfg = tiny_policy(algo=algo, obs=mode, n_steps=8 if algo == "a2c" else 32)
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
    res = train_policy(tiny_policy(obs="hybrid", slots=16, timesteps=64, n_steps=16, batch_size=32, eval_episodes=2),
                       tmp_path, predictor=predictor_path)
    assert res.metrics["eval"]["episodes"] == 2
    loaded = load_policy(tmp_path / "policy.safetensors")
    assert loaded.scenario.num_neighbours == 16
    space = loaded.model.observation_space
    assert space["current"].shape == (17, 9) and space["prediction"].shape[0] == 16
    with pytest.raises(ValueError, match="num_neighbours"):
        load_policy(tmp_path / "policy.safetensors", scenario=policy_scenario(tiny_policy(obs="hybrid")))
    with pytest.raises(ValueError, match="slots"):
        tiny_policy(obs="pure", slots=17)


def test_same_seed_same_policy(tmp_path: Path) -> None:
    a = train_policy(tiny_policy(obs="pure", eval_episodes=0), tmp_path / "a")
    b = train_policy(tiny_policy(obs="pure", eval_episodes=0), tmp_path / "b")
    assert a.timesteps == b.timesteps
    pa, pb = load_policy(tmp_path / "a" / "policy.safetensors"), load_policy(tmp_path / "b" / "policy.safetensors")
    for (ka, va), (kb, vb) in zip(pa.model.policy.state_dict().items(), pb.model.policy.state_dict().items(),
                                  strict=True):
        assert ka == kb and torch.equal(va, vb), ka


def test_resume_continues_the_step_count(tmp_path: Path) -> None:
    first = train_policy(tiny_policy(obs="pure", timesteps=64, eval_episodes=0), tmp_path)
    assert first.timesteps == 64
    second = train_policy(tiny_policy(obs="pure", timesteps=192, eval_episodes=0), tmp_path)
    assert second.timesteps == 192
    assert second.metrics["train"]["resumed_from"] == 64
    steps = [int(r.split(",")[0]) for r in (tmp_path / "progress.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and steps[-1] == 192
    # the evaluation follows the policy: continuing a finished run evaluates the new policy
    third = train_policy(tiny_policy(obs="pure", timesteps=192, eval_episodes=2), tmp_path)
    assert third.metrics["eval"]["policy_sha256"] == file_sha256(tmp_path / "policy.safetensors")
    fourth = train_policy(tiny_policy(obs="pure", timesteps=256, eval_episodes=2), tmp_path)
    assert fourth.timesteps == 256
    assert fourth.metrics["eval"]["policy_sha256"] == file_sha256(tmp_path / "policy.safetensors")
    assert fourth.metrics["eval"]["policy_sha256"] != third.metrics["eval"]["policy_sha256"]
    # a run with another config in the same directory is refused, saying what differs
    with pytest.raises(ValueError, match="algo"):
        train_policy(tiny_policy(obs="pure", algo="a2c"), tmp_path)


def test_checkpoint_refuses_another_predictor(tmp_path: Path, predictor_path: Path) -> None:
    train_policy(tiny_policy(obs="prediction", timesteps=64, eval_episodes=0, n_steps=16), tmp_path / "run",
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


def test_init_policy_starts_online_training_from_its_weights(tmp_path: Path) -> None:
    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    train_policy(tiny_policy(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=2,
                       eval_episodes=0), tmp_path / "bc")  # fmt: skip
    start = tmp_path / "bc" / "policy.safetensors"
    fresh = train_policy(tiny_policy(obs="pure", learning_rate=1e-12, eval_episodes=0), tmp_path / "fresh")
    res = train_policy(tiny_policy(obs="pure", learning_rate=1e-12, eval_episodes=0, init_policy=str(start)),
                       tmp_path / "init")  # fmt: skip
    assert res.metrics["train"]["warm_start"]["sha256"] == file_sha256(start)
    want = load_policy(start).model.policy.state_dict()
    for run, same in ((tmp_path / "init", True), (tmp_path / "fresh", False)):  # a learning rate of ~0 keeps them
        got = load_policy(run / "policy.safetensors").model.policy.state_dict()
        close = all(torch.allclose(got[k], want[k], atol=1e-6) for k in want)
        assert close == same, run
    assert fresh.timesteps == res.timesteps
    with pytest.raises(ValueError, match="observation mode"):
        train_policy(tiny_policy(obs="image", eval_episodes=0, init_policy=str(start)), tmp_path / "other")
    # From the command line, PPO continuing from a policy defaults to a tenth of the usual learning rate
    assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--timesteps", "64", "--set", "n_envs=2",
                              "--set", "n_steps=32", "--set", "eval_episodes=0", "--init-policy", str(start),
                              "--out", str(tmp_path / "cli"), "-q"]) == 0  # fmt: skip
    stored = json.loads((tmp_path / "cli" / "run.json").read_text())["config"]
    assert stored["learning_rate"] == 3e-5 == default_learning_rate("ppo", fine_tune=True)
    assert default_learning_rate("ppo") == 3e-4 and default_learning_rate("dqn", fine_tune=True) == 1e-4
    with pytest.raises(ValueError, match="init_policy"):
        tiny_policy(obs="pure", warm_start=str(tmp_path / "demos"), init_policy=str(start))


@pytest.mark.slow
def test_frozen_image_branch_trains_faster_form_and_saves_a_plain_policy(tmp_path: Path, predictor_path: Path) -> None:
    """``freeze_image``: the image branch of the initial policy runs in the observation wrapper; the run's
    policy.safetensors is a plain hybrid policy with that branch unchanged, acting as the training form did; the
    training checkpoint is refused as a policy; a resume needs only the run directory."""
    from lcmodels.policy.checkpoint import load_weights, policy_model
    from lcmodels.policy.extractor import IMAGE_FEATURES, ImageEncoder, make_image_net

    train_policy(tiny_policy(obs="hybrid", timesteps=64, eval_episodes=0), tmp_path / "start", predictor=predictor_path)
    start = tmp_path / "init.safetensors"
    (tmp_path / "start" / "policy.safetensors").rename(start)
    out = tmp_path / "frozen"
    cfg = tiny_policy(obs="hybrid", timesteps=128, init_policy=str(start), freeze_image=True)
    res = train_policy(cfg, out, predictor=predictor_path)
    assert EVAL_KEYS <= set(res.metrics["eval"]) and res.timesteps == 128
    before = load_policy(start, predictor=predictor_path).model.policy.state_dict()  # moved away from its predictor
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
            tiny_policy(**bad)
