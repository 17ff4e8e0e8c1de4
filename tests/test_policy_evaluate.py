"""Evaluation and policies as drivers: reproducible held-out episodes, recorded predictions, lc-eval, lc-record with a policy, a policy behind the safety layer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lccli.evaluate import eval_main
from lccli.policy import train_policy_main
from lcmodels.policy import (
    load_policy,
    train_policy,
)
from lcmodels.policy.driverspec import safety_layer_of
from lcmodels.policy.evaluate import PolicyDriver, driver_for, evaluate, wilson_interval
from lcmodels.policy.obs import scenario_for_mode
from lcsim.config import tiny_scenario
from lcsim.planning import SafetyLayerConfig
from tests.conftest import CountingPool

from .conftest import EVAL_KEYS, tiny_policy


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

    train_policy(tiny_policy(obs="prediction", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "run",
                 predictor=predictor_path)
    drv = PolicyDriver(load_policy(tmp_path / "run" / "policy.safetensors"))
    evaluate(drv, drv.config, episodes=2, out_dir=tmp_path / "ev", batch=2)
    ep = read_episode(sorted((tmp_path / "ev").glob("*.mcap"))[0])
    assert len(ep.predictions) > 0 and len(ep.steps) > 0
    assert set(ep.predictions["k"]) == set(range(1, 11))


def test_cli_train_and_eval_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--timesteps", "128", "--set", "n_envs=2",
                              "--set", "n_steps=32", "--set", "eval_episodes=2", "--out", str(out), "-q"]) == 0
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


def test_lc_record_with_a_policy_driver_writes_its_predictions(tmp_path: Path, predictor_path: Path) -> None:
    from lccli.record import record_main
    from lcdata.reader import read_episode
    from lcdata.record import record_episode

    train_policy(tiny_policy(obs="prediction", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "run",
                 predictor=predictor_path)
    drv = PolicyDriver(load_policy(tmp_path / "run" / "policy.safetensors"))
    res = record_episode(drv.config, 4, drv, tmp_path / "ep.mcap")  # what lc-record --driver policy:CKPT runs
    ep = read_episode(res.path)
    assert sorted(set(ep.predictions["step"])) == sorted(ep.steps["step"])  # one prediction set per decision
    assert set(ep.predictions["k"]) == set(range(1, 11))
    assert record_main(["--driver", f"policy:{tmp_path / 'missing.safetensors'}", "--out", str(tmp_path / "o")]) == 2


@pytest.mark.slow
def test_the_safety_layer_follows_a_policy_without_image_and_refuses_one_with(tmp_path: Path) -> None:
    train_policy(tiny_policy(obs="pure", timesteps=64, n_steps=16, eval_episodes=0), tmp_path / "pure")
    driver, config = driver_for(f"lookahead:{tmp_path / 'pure' / 'policy.safetensors'}")
    assert driver.name == "lookahead-ppo-pure" and config.render_image is False
    summary, _ = evaluate(driver, config, episodes=2, batch=2)
    assert summary["episodes"] == 2
    train_policy(tiny_policy(obs="image", timesteps=32, n_steps=16, eval_episodes=0), tmp_path / "image")
    with pytest.raises(ValueError, match="reads the image"):
        driver_for(f"lookahead-blind:{tmp_path / 'image' / 'policy.safetensors'}")
    image, pure = tmp_path / "image" / "policy.safetensors", tmp_path / "pure" / "policy.safetensors"
    guarded, image_config = driver_for(f"lookahead-blind:{image}", safety=safety_layer_of(f"lookahead-blind:{image}",
                                                                                        follow=str(pure)))  # fmt: skip
    assert guarded.name == "ppo-image+lookahead-blind-ppo-pure" and image_config.render_image is True
    assert isinstance(guarded.proposer, PolicyDriver) and guarded.proposer.policy.obs_mode == "image"
    summary, _ = evaluate(guarded, image_config, episodes=2, batch=2)
    assert summary["episodes"] == 2
    with pytest.raises(ValueError, match=r"driver to follow: .* reads the image"):
        driver_for(f"safety-layer:{image}", safety=SafetyLayerConfig(follow=str(image)))
    with pytest.raises(ValueError, match="apply to a driver behind it"):
        driver_for(str(pure), safety=SafetyLayerConfig(follow="rule"))
    assert eval_main([f"lookahead:{image}", "--lookahead-follow", str(tmp_path / "missing.safetensors"), "--no-record"]) == 2
    assert eval_main([f"lookahead-blind:{image}", "--lookahead-follow", "rule", "--lookahead-horizon", "2",
                      "--episodes", "2", "--no-record", "--json-out", str(tmp_path / "guarded.json")]) == 0
    guarded_summary = json.loads((tmp_path / "guarded.json").read_text())
    assert guarded_summary["driver"] == "ppo-image+lookahead-blind-rule"
    assert 0 <= guarded_summary["planner_overrides"] <= guarded_summary["planner_choices"] <= guarded_summary["decisions"]
    assert eval_main([f"lookahead-blind:{tmp_path / 'missing.safetensors'}", "--no-record"]) == 2
    longer, _ = driver_for(f"safety-layer:{tmp_path / 'pure' / 'policy.safetensors'}",
                           safety=SafetyLayerConfig(horizon_decisions=3, samples=2))  # fmt: skip
    assert (longer.config.horizon_decisions, longer.config.samples, longer.config.blind) == (3, 2, True)
    with pytest.raises(ValueError, match="apply to a driver behind it"):
        driver_for("rule", safety=SafetyLayerConfig(samples=2))
    assert eval_main(["lookahead", "--lookahead-samples", "2", "--no-record"]) == 2  # samples need blindness
    assert eval_main(["lookahead", "--lookahead-perceived", "--no-record"]) == 2  # so does perception
    assert eval_main([f"lookahead-blind:{image}", "--lookahead-follow", "rule", "--lookahead-horizon", "2",
                      "--lookahead-perceived", "--episodes", "2", "--no-record", "--json-out",
                      str(tmp_path / "perceived.json")]) == 0  # fmt: skip
    perceived = json.loads((tmp_path / "perceived.json").read_text())
    assert perceived["driver"] == "ppo-image+lookahead-perceived-rule"
    # the file says how it was made: the safety layer's settings and the command
    assert perceived["safety_layer"]["perceived"] and perceived["safety_layer"]["horizon_decisions"] == 2
    assert perceived["safety_layer"]["follow"] == "rule" and perceived["command"].startswith("lc-eval lookahead-blind:")
    # the same layer in today's spelling: the same figures
    assert eval_main([f"safety-layer:{image}", "--follow", "rule", "--set", "safety.horizon_decisions=2", "--episodes",
                      "2", "--no-record", "--json-out", str(tmp_path / "today.json")]) == 0  # fmt: skip
    today = json.loads((tmp_path / "today.json").read_text())
    drop = ("command", "wall_s")
    assert {k: v for k, v in today.items() if k not in drop} == {k: v for k, v in perceived.items() if k not in drop}
    assert eval_main([str(image), "--set", "safety.samples=2", "--no-record"]) == 2  # behind no layer
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


def test_an_evaluation_cut_over_processes_gives_the_serial_figures_episode_for_episode() -> None:
    from lcmodels.policy.evaluate import evaluate_sharded, shard_pool
    from lcmodels.zoo import zoo_entry

    hybrid, pure = zoo_entry("hybrid-ppo"), zoo_entry("pure-ppo")
    spec = f"lookahead-blind:{hybrid.policy}"
    options = {"predictor": str(hybrid.predictor), "batch": 3,  # the zoo's layer, shorter
               "safety": SafetyLayerConfig(horizon_decisions=4, samples=2, follow=str(pure.policy))}
    serial, rows = evaluate_sharded(spec, None, episodes=6, seed=3, shards=1, **options)
    with CountingPool(shard_pool(2)) as pool:
        cut, cut_rows = evaluate_sharded(spec, None, episodes=6, seed=3, shards=2, pool=pool, **options)
    assert pool.submitted == 2  # both shards ran in the pool's processes
    assert cut_rows == rows and serial["planner_choices"] > 0
    drop = {"wall_s", "decisions_per_s"}
    assert {k: v for k, v in cut.items() if k not in drop} == {k: v for k, v in serial.items() if k not in drop}


def test_lc_eval_workers_give_the_same_figures_and_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], shard_pools: list[CountingPool]
) -> None:
    pools = shard_pools
    runs = {}
    for workers in ("1", "2"):
        js, out = tmp_path / f"w{workers}.json", tmp_path / f"w{workers}"
        assert eval_main(["rule", "--scenario", "tiny", "--episodes", "8", "--batch", "3", "--workers", workers,
                          "--out", str(out), "--json-out", str(js), "-q"]) == 0  # fmt: skip
        summary = json.loads(js.read_text())
        files = {p.name: p.read_bytes() for p in sorted(out.glob("*.mcap"))}
        runs[workers] = ({k: v for k, v in summary.items() if k not in ("wall_s", "command", "decisions_per_s")}, files)
    assert "2 processes" in capsys.readouterr().out
    assert runs["1"] == runs["2"] and len(runs["1"][1]) == 8
    assert [p.submitted for p in pools] == [2]  # --workers 1 made no pool; --workers 2 cut the episodes in two
    import multiprocessing as mp

    assert not mp.active_children()  # the pool's processes are gone
    for argv, message in ((["random", "--workers", "2"], "random driver"),
                          (["rule", "--workers", "2", "--executor", "ray"], "--workers is for this machine")):
        assert eval_main([*argv, "--scenario", "tiny", "--episodes", "8", "--batch", "3", "--no-record"]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
    assert eval_main(["rule", "--scenario", "tiny", "--episodes", "2", "--workers", "2", "--breakdown",
                      "--no-record"]) == 2  # fmt: skip
    assert "breakdown runs in this process only" in capsys.readouterr().err


def test_a_json_out_that_cannot_be_written_is_refused_before_the_evaluation(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--json-out is written after the whole evaluation: where it cannot go is refused first, in one line."""
    a_file = tmp_path / "a_file"
    a_file.write_text("not a directory")
    for target, why in ((tmp_path, "is a directory"), (a_file / "summary.json", "not a directory"),
                        (Path("/proc/lc-test-summary.json"), "cannot be written")):
        assert eval_main(["rule", "--scenario", "tiny", "--episodes", "1", "--no-record", "--overwrite",
                          "--json-out", str(target)]) == 2
        captured = capsys.readouterr()
        assert why in captured.err and captured.err.count("\n") == 1
        assert "held-out evaluation" not in captured.out  # refused before evaluating


def test_a_full_disk_under_lc_eval_is_one_line(tmp_path: Path) -> None:
    """Recording the episodes on a disk that fills up (a file-size limit) ends in one line, not a traceback."""
    import resource
    import subprocess
    import sys

    argv = ["rule", "--scenario", "tiny", "--episodes", "2", "--out", str(tmp_path / "eval"), "-q"]
    code = f"import sys; sys.argv[0] = 'lc-eval'; from lccli.evaluate import eval_main; sys.exit(eval_main({argv!r}))"

    def small_disk() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (16 << 10, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, preexec_fn=small_disk,
                          timeout=300)
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert len(err) == 1 and err[0].startswith("lc-eval: error:") and "File too large" in err[0], err
