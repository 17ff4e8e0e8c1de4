"""DAgger: rounds labelled by the oracle or a driver, resumed rounds equal uninterrupted ones."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lcdata.record import episode_seed, record_episodes
from lcmodels.policy import (
    load_demonstrations,
    load_policy,
    train_policy,
)
from lcmodels.policy.evaluate import PolicyDriver
from lcmodels.policy.obs import scenario_for_mode
from lcsim.config import tiny_scenario
from lcsim.core import KEEP, RUNNING, LaneChangeCore
from lcsim.planning import SafetyLayerConfig

from .conftest import tiny_policy


@pytest.mark.slow
def test_dagger_round_labels_the_policys_states_with_the_oracle_and_saves_a_loadable_policy(tmp_path: Path) -> None:
    from lcmodels.policy.dagger import collect, dagger

    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    cfg = tiny_policy(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=2, eval_episodes=0)
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
    cut = dagger(tmp_path / "bc", tmp_path / "dg-workers", rounds=1, episodes=2, epochs=1, seed=7, workers=2,
                 eval_episodes=0)  # the episodes collected in two processes: the same states, in the same order
    assert cut[0]["states_labelled"] == records[0]["states_labelled"]
    with np.load(tmp_path / "dg" / "round1" / "states.npz") as a, np.load(tmp_path / "dg-workers" / "round1" / "states.npz") as b:
        assert np.array_equal(a["labels"], b["labels"]) and np.array_equal(a["current"], b["current"])
    with pytest.raises(FileExistsError):
        dagger(tmp_path / "bc", tmp_path / "dg", rounds=1, episodes=1, epochs=1)
    # the demonstrations moved (a published experiment resumed elsewhere): named, they are found; else one line
    (tmp_path / "demos").rename(tmp_path / "moved")
    with pytest.raises(FileNotFoundError, match=r"not at .*demos any more; name where they are now"):
        dagger(tmp_path / "bc", tmp_path / "dg2", rounds=1, episodes=2, epochs=1, seed=7, workers=1, eval_episodes=0)
    moved = dagger(tmp_path / "bc", tmp_path / "dg2", rounds=1, episodes=2, epochs=1, seed=7, workers=1,
                   eval_episodes=0, demonstrations=tmp_path / "moved")  # fmt: skip
    assert moved[0]["training_states"] == records[0]["training_states"]


@pytest.mark.slow
def test_dagger_resumed_gives_the_rounds_of_an_uninterrupted_run(tmp_path: Path) -> None:
    from lcmodels.policy.dagger import dagger

    config = scenario_for_mode(tiny_scenario(), "pure")
    record_episodes(config, [1, 2], "oracle", tmp_path / "demos", scenario="tiny", images=False)
    train_policy(tiny_policy(obs="pure", timesteps=0, warm_start=str(tmp_path / "demos"), warm_start_epochs=2,
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
    # the run and its rounds moved together (a published experiment resumed elsewhere): found by the policy's hash
    dagger(tmp_path / "bc", tmp_path / "half", rounds=1, **args)
    (tmp_path / "elsewhere").mkdir()
    for name in ("bc", "half"):
        (tmp_path / name).rename(tmp_path / "elsewhere" / name)
    moved = dagger(tmp_path / "elsewhere" / "bc", tmp_path / "elsewhere" / "half", rounds=2, resume=True, **args)
    assert moved[1]["training_states"] == straight[1]["training_states"]
    c = load_policy(tmp_path / "elsewhere" / "half" / "round2" / "policy.safetensors").model.policy.state_dict()
    assert all(torch.equal(a[k], c[k]) for k in a)


@pytest.mark.slow
def test_dagger_with_a_driver_as_the_expert_labels_every_state_with_its_decision(tmp_path: Path) -> None:
    from lcmodels.policy.dagger import collect_from_driver, dagger

    train_policy(tiny_policy(obs="pure", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "run")
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
    assert records[0]["balance_actions"] is True
    with pytest.raises(ValueError, match="action balance: True there, False asked"):
        dagger(tmp_path / "run", tmp_path / "dg", rounds=2, episodes=3, epochs=1, seed=7, workers=1,
               eval_episodes=0, expert=expert, balance_actions=False, resume=True)  # fmt: skip
    with pytest.raises(ValueError, match="there, oracle asked"):
        dagger(tmp_path / "run", tmp_path / "dg", rounds=2, episodes=3, epochs=1, seed=7, workers=1,
               eval_episodes=0, resume=True)  # fmt: skip
    short_layer = SafetyLayerConfig(horizon_decisions=2, perceived=False)  # what lookahead-blind: means, 1 s
    with pytest.raises(ValueError, match=r"expert's safety layer: .*horizon_decisions': 16.* there"):
        dagger(tmp_path / "run", tmp_path / "dg", rounds=2, episodes=3, epochs=1, seed=7, workers=1,
               eval_episodes=0, expert=expert, expert_safety=short_layer, resume=True)  # fmt: skip
    with pytest.raises(ValueError, match="apply to an expert behind it"):
        dagger(tmp_path / "run", tmp_path / "bad", rounds=1, episodes=3, epochs=1, seed=7, workers=1,
               eval_episodes=0, expert="oracle", expert_safety=short_layer)  # fmt: skip
    short = collect_from_driver(policy, [7, 8, 9], expert, batch=3, safety=short_layer)
    records = dagger(tmp_path / "run", tmp_path / "dg-short", rounds=1, episodes=3, epochs=1, seed=7, workers=1,
                     eval_episodes=0, expert=expert, expert_safety=short_layer)  # fmt: skip
    assert records[0]["expert_safety_layer"] == short_layer.to_dict()
    # rounds recorded before the one config (the expert's settings as given then) resume with the same layer
    book = json.loads((tmp_path / "dg-short" / "dagger.json").read_text())
    del book["rounds"][0]["expert_safety_layer"]
    book["rounds"][0]["expert_lookahead"] = {"horizon_decisions": 2}
    (tmp_path / "dg-short" / "dagger.json").write_text(json.dumps(book))
    assert len(dagger(tmp_path / "run", tmp_path / "dg-short", rounds=1, episodes=3, epochs=1, seed=7, workers=1,
                      eval_episodes=0, expert=expert, expert_safety=short_layer, resume=True)) == 1  # fmt: skip
    with np.load(tmp_path / "dg-short" / "round1" / "states.npz") as kept:
        assert np.array_equal(kept["labels"], short.labels)


def test_dagger_refuses_rounds_whose_seeds_reach_the_validation_episodes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The rounds drive user seeds ``seed .. seed + rounds * episodes - 1``: the last must stay below the first
    validation seed, or the policy would be trained on the episodes it is chosen on."""
    from lccli.dagger import main
    from lcmodels.policy.dagger import dagger
    from lcsim.suite import VALIDATION_SEED_BASE

    with pytest.raises(ValueError, match="validation episodes' seeds"):
        dagger(tmp_path / "run", tmp_path / "out", rounds=2, episodes=10, seed=VALIDATION_SEED_BASE - 19)
    assert not (tmp_path / "out").exists()
    code = main([str(tmp_path / "run"), "--out", str(tmp_path / "out"), "--rounds", "3", "--episodes", "5",
                 "--seed", str(VALIDATION_SEED_BASE - 14)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "evaluation's seeds start there" in err and "Traceback" not in err
