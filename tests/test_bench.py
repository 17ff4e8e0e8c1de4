"""The benchmark: the suite and its seeds, the sealed path through the ledger, lc-bench's table, and a trained
policy on another road."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lccli.bench import main as bench_main
from lccli.evaluate import eval_main
from lccli.record import record_main
from lcmodels.bench.ledger import read_ledger
from lcmodels.policy.driverspec import safety_layer_of
from lcmodels.policy.evaluate import eval_user_seeds
from lcsim.envs import observation_space
from lcsim.planning import SafetyLayerConfig
from lcsim.registry import scenario
from lcsim.suite import (
    MAX_VALIDATION_SEED,
    SEALED_SEED_BASE,
    SUITE_SCENARIOS,
    SUITES,
    is_sealed,
)

ROOT = Path(__file__).resolve().parent.parent


def test_the_suite_spans_the_dimensions_and_keeps_the_observation():
    assert len(SUITES["highway"]) >= 6 and SUITES["highway"][0] == "paper"
    paper = scenario("paper")
    space = observation_space(paper)
    changed = set()
    for name in SUITES["highway"]:
        cfg = scenario(name)  # every suite scenario is a registered name
        assert observation_space(cfg) == space, name  # a policy of the paper's road drives on all of them
        if cfg.road.num_lanes != paper.road.num_lanes:
            changed.add("lanes")
        if cfg.traffic.num_vehicles / cfg.road.num_lanes != paper.traffic.num_vehicles / paper.road.num_lanes:
            changed.add("density")
        if cfg.traffic.speed_kmh != paper.traffic.speed_kmh and cfg.ego.target_speed_kmh != paper.ego.target_speed_kmh:
            changed.add("speeds")
        if cfg.traffic.speed_spread_kmh != paper.traffic.speed_spread_kmh:
            changed.add("spread")
        if cfg.traffic.human_like != paper.traffic.human_like:
            changed.add("style")
    assert changed == {"lanes", "density", "speeds", "spread", "style"}
    assert SUITE_SCENARIOS["paper"].test_episodes >= 2000


def test_sealed_seeds_are_used_by_nothing_else():
    last_validation = eval_user_seeds(100_000, MAX_VALIDATION_SEED - 1)[-1]
    assert last_validation < SEALED_SEED_BASE
    blocks = [s.sealed_seeds() for s in SUITE_SCENARIOS.values()]
    flat = [u for b in blocks for u in b]
    assert len(set(flat)) == len(flat) and all(is_sealed(u) for u in flat) and max(flat) < 2**32
    assert not is_sealed(SEALED_SEED_BASE - 1)
    with pytest.raises(ValueError, match="sealed"):
        eval_user_seeds(10, MAX_VALIDATION_SEED)


def test_commands_other_than_the_final_path_refuse_the_sealed_episodes(tmp_path: Path, capsys):
    assert eval_main(["rule", "--seed", str(MAX_VALIDATION_SEED), "--episodes", "2", "--no-record"]) == 2
    err = capsys.readouterr().err.strip()
    assert "sealed" in err and len(err.splitlines()) == 1
    assert record_main(["--scenario", "tiny", "--driver", "rule", "--seed", str(SEALED_SEED_BASE + 5),
                        "--out", str(tmp_path / "rec")]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert "sealed" in err and len(err.splitlines()) == 1 and not (tmp_path / "rec").exists()
    assert record_main(["--scenario", "tiny", "--driver", "rule", "--seed", str(SEALED_SEED_BASE - 1),
                        "--episodes", "2", "--out", str(tmp_path / "rec")]) == 2  # fmt: skip
    assert "sealed" in capsys.readouterr().err


def test_a_trained_policy_drives_on_another_road_when_its_observation_fits(tmp_path: Path, capsys):
    js = tmp_path / "dense.json"
    assert eval_main(["zoo:pure-ppo", "--scenario", "five-lane", "--episodes", "3", "--no-record", "-q",
                      "--json-out", str(js)]) == 0  # fmt: skip
    assert json.loads(js.read_text())["episodes"] == 3
    odd = tmp_path / "six.toml"
    odd.write_text("num_neighbours = 6\n")
    assert eval_main(["zoo:pure-ppo", "--scenario", str(odd), "--episodes", "2", "--no-record", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "cannot drive in that scenario" in err and len(err.splitlines()) == 1


def test_lc_bench_validation_table_and_resume(tiny_suite: Path, tmp_path: Path, capsys):
    out = tmp_path / "bench"
    argv = ["keep", "rule", "--suite", "tiny", "--episodes", "5", "--out", str(out), "-q"]
    assert bench_main(argv) == 0
    first = capsys.readouterr().out
    summary = json.loads((out / "bench.json").read_text())
    assert summary["split"] == "validation seed 0" and [r["scenario"] for r in summary["scenarios"]] == ["tiny-a",
                                                                                                       "tiny-b"]
    for row in summary["scenarios"]:
        assert set(row["drivers"]) == {"oracle", "rule", "keep"}  # the ceiling and floor come with every table
        oracle = row["drivers"]["oracle"]
        if oracle["success_rate"] > 0:
            assert oracle["normalised"] == 1.0
            keep = row["drivers"]["keep"]
            assert keep["normalised"] == pytest.approx(keep["success_rate"] / oracle["success_rate"])
    keep_row = next(d for d in summary["drivers"] if d["driver"] == "rule")
    assert keep_row["mcnemar_vs_first"]["first"] == "keep" and 0 <= keep_row["mcnemar_vs_first"]["p_value"] <= 1
    md = (out / "BENCH.md").read_text()
    assert "ceiling: oracle" in md and "Wilson 95%" in md and "McNemar p" in md
    for stem in ("bench_normalised", "bench_intervals"):  # the figures beside the table, embedded in it
        assert (out / f"{stem}.png").stat().st_size > 0 and (out / f"{stem}.svg").stat().st_size > 0
        assert f"({stem}.svg)" in md
    assert not tiny_suite.exists()  # validation never writes the ledger
    assert bench_main(argv) == 0  # a rerun resumes: every cell from the cache, the same table
    assert json.loads((out / "bench.json").read_text()) == summary
    again = capsys.readouterr().out
    assert "6 cells: 6 cached" in again and "6 cells: 6 run" in first


def test_lc_bench_final_goes_through_the_ledger_once(tiny_suite: Path, tmp_path: Path, capsys):
    argv = ["keep", "--suite", "tiny", "--final", "--out", str(tmp_path / "final"), "-q"]
    assert bench_main(argv) == 0
    entries = read_ledger(tiny_suite)
    assert len(entries) == 6  # oracle, rule, keep on two roads
    for e in entries:
        assert e["episodes"] == 6 and len(e["outcomes"]) == 6 and is_sealed(e["user_seeds"][0])
        assert e["split"] == "test" and e["identity"]["kind"] == "driver" and "date" in e and "commit" in e
        assert e["success"] == e["outcomes"].count("s")
    assert bench_main(argv) == 0  # measured once: a rerun reads the ledger and appends nothing
    assert len(read_ledger(tiny_suite)) == 6
    assert "from the ledger" in capsys.readouterr().out
    for bad in (["keep", "--final", "--episodes", "3"], ["keep", "--final", "--seed", "1"]):
        assert bench_main([*bad, "--suite", "tiny", "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert "sealed" in err and len(err.splitlines()) == 1
    with tiny_suite.open("a") as f:
        f.write('{"v": 1, "key": "x"}\n')
    assert bench_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "line 7" in err and len(err.splitlines()) == 1


def test_lc_bench_takes_a_users_own_policy(tiny_suite: Path, tmp_path: Path, monkeypatch, capsys):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "my_lane_policy.py").write_text(
        "import numpy as np\n\n"
        "def keep(obs):\n    return np.ones(len(obs['current']), dtype=np.int64)\n\n"
        "def left_when_allowed(obs, action_mask):\n"
        "    return np.where(action_mask[:, 2], 2, 1)\n\n"
        "def broken(obs):\n    return np.zeros((2, 2))\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mine"))
    out = tmp_path / "bench"
    assert bench_main(["my_lane_policy:keep", "keep", "my_lane_policy:left_when_allowed", "--suite", "tiny",
                       "--episodes", "4", "--out", str(out), "-q"]) == 0  # fmt: skip
    summary = json.loads((out / "bench.json").read_text())
    for row in summary["scenarios"]:  # the callable that keeps its lane drives as the built-in keep driver
        assert row["drivers"]["my_lane_policy:keep"]["success_rate"] == row["drivers"]["keep"]["success_rate"]
    capsys.readouterr()
    for bad, message in (("my_lane_policy:broken", "expected (4,) integers"), ("my_lane_policy:nope", "no callable"),
                         ("no_such_module_here:act", "cannot import"), ("runs/none.safetensors", "does not exist")):
        assert bench_main([bad, "--suite", "tiny", "--episodes", "4", "--out", str(tmp_path / "b2"), "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err


def test_the_same_seed_gives_the_same_cells(tiny_suite: Path, tmp_path: Path):
    for d in ("a", "b"):
        assert bench_main(["rule", "--suite", "tiny", "--episodes", "4", "--seed", "3", "--out", str(tmp_path / d),
                           "-q"]) == 0  # fmt: skip
    a, b = (json.loads((tmp_path / d / "bench.json").read_text()) for d in ("a", "b"))
    assert a["scenarios"] == b["scenarios"]
    assert np.isfinite([r["drivers"]["rule"]["success_rate"] for r in a["scenarios"]]).all()


def test_lc_bench_list_and_errors(capsys):
    assert bench_main(["--list"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in SUITES["highway"]) and "sealed test episodes" in out
    for argv, message in ((["rule", "--suite", "nope"], "unknown suite"), ([], "at least one POLICY"),
                          (["rule", "--scenario", "nope"], "unknown suite scenario"),
                          (["rule", "--lookahead-horizon", "4"], "safety layer"),
                          (["zoo:pure-ppo", "--follow", "rule"], "safety layer")):
        assert bench_main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err


def test_keys_capture_what_changes_the_driving_and_nothing_else():
    from lcmodels.bench.run import resolve_driver

    def key(spec, **kw):
        return resolve_driver(spec, **kw).identity

    def layer(spec, table=None, follow=None):
        return key(spec, safety=safety_layer_of(spec, table, follow))

    base = key("lookahead-blind:zoo:pure-ppo")
    assert layer("lookahead-blind:zoo:pure-ppo", {"horizon_decisions": 16}) == base  # the default, spelt out
    assert layer("lookahead-blind:zoo:pure-ppo", {"horizon_decisions": 32}) != base
    assert layer("lookahead-blind:zoo:pure-ppo", follow="rule") != base
    assert key("lookahead:zoo:pure-ppo") != base  # not blind
    # today's spelling: the same layer, the same key
    assert key("safety-layer:zoo:pure-ppo", safety=SafetyLayerConfig(perceived=False)) == base
    assert layer("safety-layer:zoo:pure-ppo", {"perceived": False, "samples": 1}) == base
    assert key("safety-layer:zoo:pure-ppo") == layer("lookahead-blind:zoo:pure-ppo", {"perceived": True})
    assert key("safety-layer:rule", safety=SafetyLayerConfig(perceived=False)) == key("lookahead-blind")
    with pytest.raises(ValueError, match="apply to a driver behind it"):
        key("zoo:pure-ppo", safety=SafetyLayerConfig())
    # the same weights wherever the file lies: the zoo's copy is the experiment's policy
    assert key("zoo:pure-ppo") == key(str(ROOT / "docs/results/paper-best/policies/pure-ppo/seed1/train/policy.safetensors"))
    assert key("zoo:pure-ppo") != key("zoo:pure-ppo-dagger")


def test_workers_give_the_cells_of_one_process(tiny_suite: Path, tmp_path: Path):
    runs = {}
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}"
        assert bench_main(["rule", "keep", "--suite", "tiny", "--episodes", "6", "--batch", "3", "--workers", workers,
                           "--out", str(out), "-q"]) == 0  # fmt: skip
        cells = [json.loads(p.read_text()) for p in (out / "cells").glob("*.json")]
        runs[workers] = sorted((c["label"], c["scenario"], c["outcomes"]) for c in cells)  # every episode's outcome
    assert len(runs["1"]) == 6 and runs["1"] == runs["2"]
