"""experiments/multi_rollout: the safety layer scoring decisions by the best of several base policies, each judged
across all the imagined futures, on small real episodes."""

import json

import numpy as np

from lcsim.config import ScenarioConfig, TrafficConfig
from lcsim.core import RUNNING, LaneChangeCore
from lcsim.drivers import KeepLaneDriver, RuleBasedDriver
from lcsim.planning import LookaheadDriver, SafetyLayerConfig

from .cost import main as cost_main
from .multi_rollout import FORCED, MultiRolloutLayer, TimedLayer, main

LAYER = SafetyLayerConfig(horizon_decisions=4, samples=2)


def _human_core(envs: int, seeds: list[int]) -> LaneChangeCore:
    cfg = ScenarioConfig(route_length_m=150.0, time_limit_s=25.0, render_image=False,
                         traffic=TrafficConfig(num_vehicles=24, spawn_behind_m=40.0, spawn_ahead_m=140.0,
                                               human_like=True))
    core = LaneChangeCore(cfg, envs)
    core.reset(range(envs), seeds)
    return core


def _drive(make, decisions: int = 12, seeds=(31, 32, 33)):
    """The decisions and the per-candidate scores of a fresh layer ``make()`` on the same small episodes."""
    core, driver = _human_core(len(seeds), list(seeds)), make()
    seen, alive = [], []
    for _ in range(decisions):
        if (core.outcome != RUNNING).any():
            break
        seen.append(driver({}, core.action_mask(), core))
        alive.append(driver.last_alive)
        core.step(seen[-1])
    return np.stack(seen), np.stack(alive), driver


def test_with_its_follower_alone_it_decides_as_the_product_safety_layer():
    plain = _drive(lambda: LookaheadDriver(LAYER))
    for bases in ([None], [None, None]):
        multi = _drive(lambda b=bases: MultiRolloutLayer(LAYER, bases=b))
        assert np.array_equal(plain[0], multi[0]) and np.array_equal(plain[1], multi[1], equal_nan=True)
        assert plain[2].overrides == multi[2].overrides
    timed = _drive(lambda: TimedLayer(LAYER))
    assert np.array_equal(plain[0], timed[0]) and timed[2].decisions > 0 and timed[2].cost()["cpu_s"] >= 0


def test_a_decision_scores_the_best_base_policys_share_of_all_futures_not_the_best_per_future():
    """Along the same states, each candidate's score is the larger of the two single-base layers' scores (the
    same imagined futures), never the share of futures some base survives (which re-optimises per future)."""
    def states():
        core = _human_core(4, [41, 42, 43, 44])
        rule = RuleBasedDriver()
        out = []
        for _ in range(10):
            if (core.outcome != RUNNING).any():
                break
            out.append(core.replicate(np.arange(core.num_envs)))
            core.step(rule({}, core.action_mask(), core))
        return out

    layers = [LookaheadDriver(LAYER, rule=RuleBasedDriver(FORCED)), LookaheadDriver(LAYER, rule=KeepLaneDriver()),
              MultiRolloutLayer(LAYER, bases=[RuleBasedDriver(FORCED), KeepLaneDriver()])]
    scored = 0
    for state in states():
        mask = state.action_mask()
        planned = np.ones(state.num_envs, dtype=np.int64)
        for layer in layers:
            layer.check(planned, mask, state.replicate(np.arange(state.num_envs)))
        a, b, both = (layer.last_alive for layer in layers)
        assert np.array_equal(both, np.fmax(a, b), equal_nan=True)
        scored += int(np.isfinite(both).sum())
    assert scored > 0 and layers[2].best_base.sum() > 0


def test_the_progress_tie_break_moves_only_among_the_decisions_of_the_best_score():
    bases = [None, RuleBasedDriver(FORCED)]
    plain = _drive(lambda: MultiRolloutLayer(LAYER, bases=bases))
    never = _drive(lambda: MultiRolloutLayer(LAYER, bases=bases, progress_gain_m=1_000.0))
    assert np.array_equal(plain[0], never[0]) and plain[2].overrides == never[2].overrides
    eager = _drive(lambda: MultiRolloutLayer(LAYER, bases=bases, progress_gain_m=0.0))
    taken = np.take_along_axis(eager[1], eager[0][..., None], axis=2)[..., 0]  # the score of what it did
    best = np.nanmax(np.where(np.isfinite(eager[1]), eager[1], -1.0), axis=2)
    chose = np.isfinite(eager[1]).sum(axis=2) > 1
    assert chose.any() and np.array_equal(taken[chose], best[chose])
    assert eager[2].overrides >= plain[2].overrides


def test_the_script_runs_the_layer_and_the_variant_and_pairs_them(tmp_path, capsys):
    common = ["safety-layer:rule", "--scenario", "three-lane", "--set", "safety.horizon_decisions=2",
              "--episodes", "2", "--batch", "2", "-q"]
    base, multi = tmp_path / "base.json", tmp_path / "multi.json"
    assert main([*common, "--baseline", "--json-out", str(base)]) == 0
    assert main([*common, "--bases", "follow,forced", "--against", str(base), "--json-out", str(multi)]) == 0
    record = json.loads(multi.read_text())
    assert len(record["outcomes"]) == 2 and record["mcnemar_vs"]["n"] == 2 and record["ms_per_decision"] > 0
    assert record["bases"] == ["follow", "forced"] and "ms per decision" not in capsys.readouterr().err
    assert main([*common, "--json-out", str(multi)]) == 2  # never over a file
    assert main(["rule", "--episodes", "2"]) == 2  # behind no safety layer
    assert main([*common, "--bases", "nosuchpolicy.safetensors"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("multi_rollout: error: ") for line in err)


def test_the_cost_script_times_both_on_the_same_states(tmp_path, capsys):
    out = tmp_path / "cost.json"
    assert cost_main(["safety-layer:rule", "--scenario", "three-lane", "--set", "safety.horizon_decisions=2",
                      "--envs", "2", "--decisions", "2", "--json-out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["layer"]["decisions"] == record["multi-rollout"]["decisions"] > 0
    assert cost_main(["safety-layer:rule", "--envs", "0"]) == 2
    assert capsys.readouterr().err.startswith("multi_rollout.cost: error: ")
