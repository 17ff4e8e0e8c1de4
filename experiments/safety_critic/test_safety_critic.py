"""The planner's survival labels (LookaheadDriver.last_alive) and experiments/safety_critic/safety_critic.py, on small real episodes."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from lcmodels.policy.train import PolicyConfig, train_policy
from lcsim.config import ScenarioConfig, TrafficConfig
from lcsim.core import KEEP, LEFT, RUNNING, LaneChangeCore
from lcsim.planning import LookaheadDriver, SafetyLayerConfig

from .safety_critic import CriticEnsemble, CriticGuard, SafetyCritic, critic_loss, main, train_critics


def small_config(**overrides) -> ScenarioConfig:
    """6 traffic vehicles on a 150 m route: fast, but with traffic around the ego."""
    kwargs = dict(traffic=TrafficConfig(num_vehicles=6, spawn_behind_m=40.0, spawn_ahead_m=80.0),
                  route_length_m=150.0, time_limit_s=25.0)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)


def _labelled(decisions: int = 40, envs: int = 4) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """(current, alive, masks) of the states with a choice the blind lookahead (following the rule) drove through."""
    planner = LookaheadDriver(SafetyLayerConfig(horizon_decisions=3, perceived=False))
    core = LaneChangeCore(small_config(render_image=False), envs)
    core.reset(np.arange(envs), [11 + k for k in range(envs)])
    current, alive, masks = [], [], []
    for _ in range(decisions):
        if not (core.outcome == RUNNING).any():
            break
        obs, mask = core.observe(), core.action_mask()
        actions = planner(obs, mask, core)
        choice = (mask.sum(axis=1) > 1) & (core.outcome == RUNNING)
        a = planner.last_alive
        assert a.shape == (envs, 3)
        assert np.array_equal(~np.isnan(a), mask & choice[:, None])  # imagined: allowed, and a choice to make
        seen = a[~np.isnan(a)]
        assert ((seen == 0) | (seen == 1)).all()  # one imagined future per decision
        rows = np.flatnonzero(choice)  # the planner's decision survives as many futures as the best one
        assert np.array_equal(a[rows, actions[rows]], np.nanmax(a[rows], axis=1))
        current.append(obs["current"][choice])
        alive.append(a[choice])
        masks.append(mask[choice])
        core.step(actions)
    return np.concatenate(current), np.concatenate(alive), masks


def test_the_lookahead_reports_the_survival_of_each_allowed_decision() -> None:
    current, alive, _ = _labelled()
    assert len(current) > 20 and not np.isnan(alive[:, KEEP]).any()
    assert np.nanmin(alive) == 0.0 < np.nanmax(alive)  # some imagined futures crash, some do not


def test_critics_fit_the_labels_deterministically() -> None:
    current, alive, _ = _labelled()
    crash = 1.0 - alive
    rate = np.clip(np.nanmean(crash, axis=0), 1e-6, 1 - 1e-6)  # the best constant: each decision's crash rate
    constant = -np.nanmean(crash * np.log(rate) + (1 - crash) * np.log(1 - rate))
    a = train_critics(current, alive, members=2, epochs=150, seed=3, hidden=32)
    b = train_critics(current, alive, members=2, epochs=150, seed=3, hidden=32)
    assert critic_loss(a, current, alive) < 0.7 * constant  # it reads the state, not only the base rate
    for ma, mb in zip(a.members, b.members, strict=True):
        assert all(
            torch.equal(x, y) for x, y in zip(ma.state_dict().values(), mb.state_dict().values(), strict=True)
        )
    p = a.crash_probability(current)
    assert p.shape == (len(current), 3) and ((p >= 0) & (p <= 1)).all()


def _fixed_critic(bias: tuple[float, float, float]) -> CriticEnsemble:
    """A critic that gives every state the same crash probabilities sigmoid(bias)."""
    net = SafetyCritic(8, hidden=8)
    with torch.no_grad():
        net.head[-1].weight.zero_()
        net.head[-1].bias.copy_(torch.tensor(bias))
    return CriticEnsemble([net])


def test_the_guard_overrides_only_decisions_it_expects_to_crash() -> None:
    def left(obs, mask, core):
        return np.where(np.asarray(mask)[:, LEFT], LEFT, KEEP)

    left.name = "left"

    core = LaneChangeCore(small_config(render_image=False), 4)
    core.reset(np.arange(4), [11, 12, 13, 14])
    sure = CriticGuard(
        left, _fixed_critic((5.0, -5.0, 5.0)), threshold=0.5, margin=0.2
    )  # changes crash, keep not
    lax = CriticGuard(left, _fixed_critic((5.0, -5.0, 5.0)), threshold=0.999, margin=0.2)
    wanted = 0
    for _ in range(20):
        obs, mask = core.observe(), core.action_mask()
        choice = (mask.sum(axis=1) > 1) & mask[:, LEFT]
        wanted += int(choice.sum())
        guarded = sure(obs, mask, core)
        assert (guarded[choice] == KEEP).all() and np.array_equal(
            guarded[~choice], left(obs, mask, core)[~choice]
        )
        assert np.array_equal(lax(obs, mask, core), left(obs, mask, core))
        core.step(left(obs, mask, core))
    assert wanted > 0 and sure.overrides == wanted and lax.overrides == 0 and sure.name == "left+critic"


def test_a_critic_saves_loads_and_refuses_bad_files(tmp_path: Path) -> None:
    critic = _fixed_critic((1.0, -1.0, 0.5))
    critic.meta = {"policy": "x"}
    critic.save(tmp_path / "critic.pt")
    back = CriticEnsemble.load(tmp_path / "critic.pt")
    x = np.random.default_rng(0).normal(size=(5, 9, 9)).astype(np.float32)
    assert np.allclose(back.crash_probability(x), critic.crash_probability(x)) and back.meta == {
        "policy": "x"
    }
    windowed = CriticEnsemble([SafetyCritic(8, hidden=8, window=True)])
    windowed.save(tmp_path / "window.pt")
    again = CriticEnsemble.load(tmp_path / "window.pt")
    assert again.members[0].window and np.allclose(again.crash_probability(x), windowed.crash_probability(x))
    blob = torch.load(tmp_path / "critic.pt", weights_only=True)
    del blob["window"]  # a critic saved before the option existed reads as contact features only
    torch.save(blob, tmp_path / "old.pt")
    assert not CriticEnsemble.load(tmp_path / "old.pt").members[0].window
    data = (tmp_path / "critic.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    torch.save({"format": "something else"}, tmp_path / "foreign.pt")
    for bad, what in (
        ("cut.pt", "corrupt or truncated"),
        ("foreign.pt", "not a safety critic"),
        ("missing.pt", "does not exist"),
    ):
        with pytest.raises(ValueError, match=what):
            CriticEnsemble.load(tmp_path / bad)


def test_cli_trains_and_evaluates_and_refuses_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    import json

    cfg = PolicyConfig(obs="pure", scenario="tiny", timesteps=64, n_envs=2, n_steps=16, batch_size=32, n_epochs=1,
                       eval_episodes=0, checkpoint_every=64)  # fmt: skip
    train_policy(cfg, tmp_path / "run")
    policy = str(tmp_path / "run" / "policy.safetensors")
    out = tmp_path / "critic"
    assert (
        main(
            [
                "train",
                policy,
                "--expert",
                f"lookahead-blind:{policy}",
                "--lookahead-horizon",
                "2",
                "--episodes",
                "2",
                "--workers",
                "1",
                "--epochs",
                "2",
                "--members",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    meta = json.loads((out / "critic.json").read_text())
    with np.load(out / "states.npz") as kept:
        assert (
            meta["labels"]["states"] == len(kept["actions"]) == len(kept["current"]) == len(kept["alive"]) > 0
        )
    assert (
        meta["lookahead"] == {"horizon_decisions": 2}
        and len(CriticEnsemble.load(out / "critic.pt").members) == 2
    )
    refit = tmp_path / "refit"
    assert (
        main(
            ["train", policy, "--from-states", str(out / "states.npz"), "--epochs", "1", "--out", str(refit)]
        )
        == 0
    )
    assert json.loads((refit / "critic.json").read_text())["labels"] == meta["labels"]
    window = tmp_path / "window"  # the same states, the critic reading the window features too
    assert main(["train", policy, "--from-states", str(out / "states.npz"), "--window-features", "--epochs", "1",
                 "--out", str(window)]) == 0  # fmt: skip
    assert json.loads((window / "critic.json").read_text())["window_features"] is True
    assert CriticEnsemble.load(window / "critic.pt").members[0].window
    assert not CriticEnsemble.load(refit / "critic.pt").members[0].window
    both = tmp_path / "both"  # two state files together: twice the states
    assert main(["train", policy, "--from-states", str(out / "states.npz"), str(out / "states.npz"),
                 "--epochs", "1", "--out", str(both)]) == 0  # fmt: skip
    assert json.loads((both / "critic.json").read_text())["labels"]["states"] == 2 * meta["labels"]["states"]
    capsys.readouterr()
    assert main(["score", "--critic", str(out / "critic.pt"), "--states", str(out / "states.npz")]) == 0
    scored = json.loads(capsys.readouterr().out)
    assert scored["states"] == meta["labels"]["states"] and len(scored["auc_per_decision"]) == 3
    assert [s["threshold"] for s in scored["screen"]] == sorted(s["threshold"] for s in scored["screen"])
    assert main(["eval", policy, "--critic", str(out / "critic.pt"), "--episodes", "2", "--batch", "2"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["driver"] == "ppo-pure+critic" and got["overrides"] <= got["choices"] <= got["decisions"]
    assert (
        abs(sum(got[k] for k in ("success_rate", "collision_rate", "off_road_rate", "timeout_rate")) - 1)
        < 1e-9
    )
    CriticEnsemble([SafetyCritic(4, hidden=8)]).save(tmp_path / "slots4.pt")
    train_policy(dataclasses.replace(cfg, neighbours="nearest"), tmp_path / "nearest")  # no lane slots
    nearest = str(tmp_path / "nearest" / "policy.safetensors")
    for bad in (
        ["train", policy, "--expert", "rule", "--out", str(tmp_path / "a")],  # not a lookahead
        ["train", str(tmp_path / "missing.zip"), "--out", str(tmp_path / "b")],
        ["train", policy, "--expert", f"lookahead:{policy}", "--out", str(out)],  # not empty: never overwritten
        ["train", policy, "--from-states", str(out / "critic.json"), "--out", str(tmp_path / "c")],
        ["eval", policy, "--critic", str(tmp_path / "missing.pt")],
        ["eval", policy, "--critic", str(tmp_path / "slots4.pt")],  # made for another number of neighbours
        ["eval", policy, "--critic", str(out / "critic.pt"), "--threshold", "1.5"],
        ["train", nearest, "--from-states", str(out / "states.npz"), "--window-features", "--out", str(tmp_path / "d")],
        ["eval", nearest, "--critic", str(window / "critic.pt"), "--episodes", "2"],  # window features, no lanes
    ):
        assert main(bad) == 2, bad
        err = capsys.readouterr().err.strip()
        assert err.startswith("safety_critic") and "\n" not in err, err
    assert not (tmp_path / "a").exists() and not (tmp_path / "c").exists() and not (tmp_path / "d").exists()


def test_auc_counts_ties_half() -> None:
    from .safety_critic import _auc

    y = np.array([False, False, True, True])
    assert _auc(np.array([0.1, 0.2, 0.3, 0.4]), y) == 1.0 and _auc(np.array([0.4, 0.3, 0.2, 0.1]), y) == 0.0
    assert _auc(np.zeros(4), y) == 0.5 and _auc(np.zeros(4), np.zeros(4, dtype=bool)) is None
