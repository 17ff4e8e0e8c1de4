"""lc-experiment end to end on the tiny preset: report contents, resumability, staleness, CLI errors."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from lccli.experiment import experiment_main
from lcmodels.experiment import (
    FIG5_NAME,
    FIG6_NAME,
    INVOCATIONS,
    ORACLE_KEY,
    PAPER_TABLE3,
    PAPER_TABLE4,
    PRESETS,
    REPORT_NAME,
    ROWS,
    RULE_KEY,
    Experiment,
    Preset,
    StageKey,
    outputs_digest,
    policy_dir,
)
from lcmodels.experiment.recipe import load_recipe
from lcmodels.policy.checkpoint import find_predictor, read_meta

SEEDS = 2
RECIPES = PRESETS["tiny"].recipes


@pytest.mark.slow
def test_tiny_preset_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One pipeline run of every packaged recipe (under pytest-xdist a shared fixture would run once per worker)."""
    run_dir = tmp_path / "tiny"
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(run_dir), "-q"]) == 0
    check_every_recipe_kind_ran(run_dir)
    check_report_holds_the_numbers_of_the_metrics_files(run_dir)
    check_parallel_policies_equal_sequential_ones(run_dir)
    check_a_safety_stage_waits_for_its_follower_and_runs_once_it_is_trained(run_dir)
    check_rerun_skips_everything_and_a_changed_recipe_is_stale(run_dir, capsys)
    check_publish_copies_the_report_and_every_metrics_file(run_dir, tmp_path / "published", capsys)
    check_a_folder_published_with_weights_resumes_as_the_run(run_dir, tmp_path, capsys)
    check_the_report_states_the_wall_time_of_every_invocation(run_dir)
    check_skip_train_reports_complete_policies_with_their_time_and_keeps_the_command(run_dir)


# ------------------------------------------------------------------------------------------------ helpers
def md_table(report: str, heading: str) -> list[dict[str, str]]:
    """Rows of the first markdown table after the line starting with ``heading``, as dicts by header."""
    lines = report.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    rows = []
    header: list[str] | None = None
    for line in lines[start + 1 :]:
        if not line.startswith("|"):
            if header is not None:
                break
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if header is None:
            header = cells
        elif not set(line) <= set("|-"):
            rows.append(dict(zip(header, cells, strict=True)))
    return rows


def parse_cell(cell: str) -> tuple[float, float | None]:
    m = re.fullmatch(r"(-?[0-9.]+)(?: ± ([0-9.]+))?", cell)
    assert m, f"not a number cell: {cell!r}"
    return float(m.group(1)), (float(m.group(2)) if m.group(2) else None)


def stage_metrics(out: Path, key: str, seed: int = 0, part: str = "eval") -> dict:
    path = out / key / "metrics.json" if key in (RULE_KEY, ORACLE_KEY) else policy_dir(out, key, seed) / part / "metrics.json"
    return json.loads(path.read_text())


def check_cell(cell: str, values: list[float]) -> None:
    mean, std = parse_cell(cell)
    a = np.asarray(values, dtype=float)
    assert mean == pytest.approx(a.mean(), abs=0.051), (cell, values)
    if len(a) > 1:
        assert std is not None and std == pytest.approx(a.std(ddof=1), abs=0.051), (cell, values)
    else:
        assert std is None


# ------------------------------------------------------------------------------------------------ checks
def check_every_recipe_kind_ran(run_dir: Path) -> None:
    """Clone, DAgger and train stages, paper / best / demo / ablation recipes, the safety layer and both references."""
    kinds, stages = set(), set()
    for name in RECIPES:
        r = load_recipe(name)
        kinds.add(r.kind)
        for s in range(SEEDS):
            for st in r.stages:
                stages.add(st)
                assert (policy_dir(run_dir, name, s) / st).is_dir(), (name, st)
            m = stage_metrics(run_dir, name, s)
            assert m["test"]["episodes"] == PRESETS["tiny"].test_episodes
            assert set(m["val"]) == {str(v) for v in PRESETS["tiny"].val_seeds}
    assert kinds == {"paper", "best", "demo", "ablation"} and stages == {"clone", "dagger", "train", "shielded"}
    assert (run_dir / "analytic-predictor" / "lane-aware" / "predictor.pt").is_file()  # the analytic base: a stage
    safety = stage_metrics(run_dir, "hybrid-ppo", 0, "safety")
    assert safety["test"]["planner_choices"] > 0 and safety["config"]["follow"]
    # the shielded stage trained behind the layer that follows pure-ppo of the same seed, from the train stage's
    # policy, and the evaluation and the safety layer took its policy
    for s in range(SEEDS):
        rec = {st: json.loads((run_dir / "stages" / f"hybrid-ppo__seed{s}__{st}.json").read_text())
               for st in ("train", "shielded", "eval", "safety")}  # fmt: skip
        follow = json.loads((run_dir / "stages" / f"pure-ppo__seed{s}__train.json").read_text())
        shielded = policy_dir(run_dir, "hybrid-ppo", s) / "shielded"
        assert rec["shielded"]["inputs"]["init_policy"] == outputs_digest(rec["train"]["outputs"])
        assert rec["shielded"]["inputs"]["follow"] == outputs_digest(follow["outputs"])
        assert rec["eval"]["inputs"]["policy"] == rec["safety"]["inputs"]["policy"] == outputs_digest(
            rec["shielded"]["outputs"])
        assert rec["shielded"]["config"]["shield"]["penalty"] == load_recipe("hybrid-ppo").table("shielded").penalty
        counts = json.loads((shielded / "shield.json").read_text())
        assert counts["choices"] > 0 and 0 <= counts["overrides"] <= counts["choices"]
        assert counts["to_step"] == PRESETS["tiny"].cap_dict["timesteps"]
    for ref in (RULE_KEY, ORACLE_KEY):
        assert stage_metrics(run_dir, ref)["test"]["episodes"] == PRESETS["tiny"].test_episodes


def check_report_holds_the_numbers_of_the_metrics_files(run_dir: Path) -> None:
    report = (run_dir / REPORT_NAME).read_text()
    for name in (FIG5_NAME, FIG6_NAME):
        png = run_dir / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
        assert f"]({name})" in report
    assert "lc-experiment --preset tiny --seeds 2" in report and '"corpus_episodes": 3' in report

    pred = json.loads((run_dir / "predictor" / "metrics.json").read_text())
    t2 = {r["Predictor"]: r for r in md_table(report, "## Table II")}
    for label, key in (("Transformer (ours), m", "model"), ("Constant velocity, m", "constant_velocity"),
                       ("Constant acceleration, m", "constant_acceleration")):  # fmt: skip
        assert float(t2[label]["ADE / MAD"]) == pytest.approx(pred[key]["ade"], abs=5e-5)
        assert float(t2[label]["FDE / FAD"]) == pytest.approx(pred[key]["fde"], abs=5e-5)
    assert t2["Paper (Hybrid-PPO), units as reported"]["ADE / MAD"] == "0.382"

    labels = {v: k for k, v in ROWS.items()}
    recipes = [load_recipe(n) for n in RECIPES]
    for heading, paper, n_rows in (("## Table III", PAPER_TABLE3, 4), ("## Table IV", PAPER_TABLE4, 4)):
        rows = md_table(report, heading)
        assert len(rows) == n_rows
        for row in rows:
            key = labels[row["Method"]]
            want = f"{paper[key][0]:.1f} / {paper[key][1]:.1f}" if key in paper else "—"
            assert row["paper: success / collision %"] == want
            for kind, col in (("paper", "paper-faithful recipe: success %"), ("best", "best recipe: success %")):
                cands = [r.name for r in recipes if r.row == key and r.kind == kind]
                if not cands:
                    assert row[col] == "—"
                    continue
                chosen = re.search(r"\(`([a-z0-9-]+)`\)", row[col]).group(1)
                assert chosen in cands

                def val(name: str) -> float:
                    return float(np.mean([v["success_rate"] for s in range(SEEDS)
                                          for v in stage_metrics(run_dir, name, s)["val"].values()]))

                assert val(chosen) == max(val(c) for c in cands)  # chosen on validation, never on test
                check_cell(row[col].split(" (`")[0], [100 * stage_metrics(run_dir, chosen, s)["test"]["success_rate"]
                                                      for s in range(SEEDS)])  # fmt: skip
    every = {re.search(r"\(`([^`]+)`\)$", r["row"]).group(1): r for r in md_table(report, "## Every row")}
    behind = {f"{n}+safety" for n in RECIPES if load_recipe(n).safety is not None}  # also behind their layer
    assert behind == {"hybrid-ppo+safety", "distil-safety-ppo+safety"}
    assert set(every) == {RULE_KEY, ORACLE_KEY, *RECIPES, *behind}
    refs = {re.search(r"\(`([^`]+)`\)$", r["driver"]).group(1): r for r in md_table(report, "## References")}
    assert set(refs) == {RULE_KEY, ORACLE_KEY, *behind}
    rule = stage_metrics(run_dir, RULE_KEY)["test"]
    assert refs[RULE_KEY]["success %"] == every[RULE_KEY]["held-out success %"]
    assert every[RULE_KEY]["held-out success %"].startswith(f"{100 * rule['success_rate']:.1f} [")
    warm = md_table(report, "## Warm start")
    assert [int(r["seed"]) for r in warm] == list(range(SEEDS))
    # A training stage records the compute behind its outputs: training summed over every resumed part.
    for name in RECIPES:
        r = load_recipe(name)
        for s in range(SEEDS):
            for st in (x for x in r.stages if x != "dagger"):
                record = json.loads((run_dir / "stages" / f"{name}__seed{s}__{st}.json").read_text())
                metrics = stage_metrics(run_dir, name, s, st)
                assert record["wall_s"] == pytest.approx(metrics["train"]["wall_s"])


def without_wall_times(metrics: dict) -> dict:
    """The results of an evaluation, without what differs between two runs of it: wall times."""
    return {part: ({k: v for k, v in metrics[part].items() if k != "wall_s"} if part == "test" else
                   {s: {k: v for k, v in e.items() if k != "wall_s"} for s, e in metrics[part].items()})
            for part in ("test", "val")}  # fmt: skip


def check_parallel_policies_equal_sequential_ones(run_dir: Path) -> None:
    """Three recipes redone by ``--jobs 2`` worker processes give the same policies and figures as the first run
    (DAgger's rounds too, whose collection then runs inside the worker: a pool's worker cannot start another)."""
    redo = [("paper-ppo-pure", 0), ("a2c-hybrid", 1), ("pure-ppo-dagger", 0)]
    before = {}
    for key, seed in redo:
        d = policy_dir(run_dir, key, seed)
        before[key] = (without_wall_times(stage_metrics(run_dir, key, seed)), (d / "train" / "policy.safetensors").read_bytes())
        (d / "train" / "policy.safetensors").unlink()  # outputs changed: the stage is redone from scratch
        if (d / "dagger").is_dir():
            (d / "dagger" / "dagger.json").unlink()  # and the DAgger rounds before it
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(run_dir), "--jobs", "2", "-q"]) == 0
    for key, seed in redo:
        d = policy_dir(run_dir, key, seed)
        after = (without_wall_times(stage_metrics(run_dir, key, seed)), (d / "train" / "policy.safetensors").read_bytes())
        assert after == before[key]


def check_a_safety_stage_waits_for_its_follower_and_runs_once_it_is_trained(run_dir: Path) -> None:
    """hybrid-ppo's shielded and safety stages read the final policy of pure-ppo (its layer's follower, same seed):
    they are ready once that is complete, not before; the safety stage run alone gives the run's own figures, and
    is refused while the policy it follows is not trained."""
    exp = Experiment(PRESETS["tiny"], run_dir, seeds=SEEDS)
    graph = exp.graph()
    follower, train = StageKey("pure-ppo", 1, "train"), StageKey("hybrid-ppo", 1, "train")
    shielded, safety = StageKey("hybrid-ppo", 1, "shielded"), StageKey("hybrid-ppo", 1, "safety")
    assert graph.needed(shielded) == [StageKey.of("predictor"), train, follower]
    assert set(graph.needed(safety)) == {StageKey.of("predictor"), shielded, follower}
    assert [k.stage for k in graph.needed(train) if k.recipe == "hybrid-ppo"] == ["clone"]
    done = graph.upstream(shielded) - {follower}
    assert follower in graph.ready(done) and shielded not in graph.ready(done)
    assert shielded in graph.ready(done | {follower})
    assert {s.status for s in exp.plan()} == {"skipped"}  # every stage of the run, the safety stages too
    metrics = safety.path(run_dir) / "metrics.json"
    before = without_wall_times(json.loads(metrics.read_text()))
    metrics.unlink()
    policy = follower.path(run_dir) / "policy.safetensors"
    kept = policy.read_bytes()
    policy.unlink()
    plan = {s.name: s.status for s in exp.plan()}
    assert plan[follower.name] == "would run (outputs missing or changed)"
    assert plan[shielded.name] == f"would run (after {follower.name})"
    assert plan[safety.name] == f"would run (after {shielded.name})"  # not trained: the safety stage waits
    with pytest.raises(ValueError, match=f"stage {safety} needs .* not complete .*after {follower}"):
        exp.run_stage(safety)
    assert not metrics.exists()
    policy.write_bytes(kept)
    plan = {s.name: s.status for s in exp.plan()}
    assert plan[safety.name] == "would run (outputs missing or changed)"
    assert {st for n, st in plan.items() if n != safety.name} == {"skipped"}
    res = exp.run_stage(safety)
    assert res.status == "done" and res.name == "hybrid-ppo/seed1/safety"
    assert without_wall_times(json.loads(metrics.read_text())) == before


def test_a_preset_trains_some_recipes_with_more_seeds_and_their_followers_with_them(tmp_path: Path) -> None:
    paper = PRESETS["paper"]
    assert dict(paper.recipe_seeds) == {"hybrid-ppo": 2}
    exp = Experiment(paper, tmp_path / "p")
    seeds = {r.name: exp.seeds_of(r.name) for r in exp.recipes()}
    assert seeds.pop("hybrid-ppo") == 2 and seeds.pop("pure-ppo") == 2  # pure-ppo: its safety layer's follower
    assert set(seeds.values()) == {1} and exp.max_seeds == 2
    exp3 = Experiment(paper, tmp_path / "p", seeds=3)
    assert {exp3.seeds_of(r.name) for r in exp3.recipes()} == {3}
    only = dataclasses.replace(paper, recipes=("hybrid-ppo",))
    assert [(r.name, Experiment(only, tmp_path / "p").seeds_of(r.name)) for r in Experiment(only, tmp_path).recipes()] \
        == [("hybrid-ppo", 2), ("pure-ppo", 2)]
    with pytest.raises(ValueError, match="recipe_seeds: 'hybrid-ppo' needs an integer >= 1, got 0"):
        Preset(name="x", recipe_seeds=(("hybrid-ppo", 0),))


def test_a_worker_that_dies_ends_the_run_in_one_line_and_a_rerun_resumes(tmp_path: Path) -> None:
    """A ``--jobs`` worker killed (as the kernel's out-of-memory killer does) stops the run with an error naming
    what is left, instead of a wait for a result that never comes; the same run then completes."""
    import multiprocessing
    import os
    import signal

    killed: list[int] = []

    def kill_the_workers(msg: str) -> None:
        if not killed and "/train] running" in msg:
            for child in multiprocessing.active_children():
                os.kill(child.pid, signal.SIGKILL)
                killed.append(child.pid)

    preset = dataclasses.replace(PRESETS["tiny"], recipes=("paper-ppo-pure", "paper-a2c"), oracle=False)
    with pytest.raises(ChildProcessError) as exc:
        Experiment(preset, tmp_path / "run", progress=kill_the_workers).run(jobs=2)
    assert killed and "a worker process died" in str(exc.value) and "\n" not in str(exc.value)
    assert "paper-ppo-pure/seed0" in str(exc.value) or "paper-a2c/seed0" in str(exc.value)
    assert not multiprocessing.active_children()  # no worker left behind
    Experiment(preset, tmp_path / "run").run(jobs=2)
    for name in preset.recipes:
        assert stage_metrics(tmp_path / "run", name)["test"]["episodes"] == preset.test_episodes


def test_a_progress_callback_that_fails_on_a_workers_line_stops_the_run_and_a_rerun_resumes(tmp_path: Path) -> None:
    """A training step's line comes from a ``--jobs`` worker process; the callback's exception on it ends the run
    (no worker left behind, none blocked on its progress lines), and the same run then completes."""
    import multiprocessing

    class Stop(Exception):
        pass

    def stop_at_a_training_step(msg: str) -> None:
        if "/train] step " in msg:
            raise Stop

    preset = dataclasses.replace(PRESETS["tiny"], recipes=("paper-ppo-pure", "paper-a2c"), oracle=False)
    with pytest.raises(Stop):
        Experiment(preset, tmp_path / "run", progress=stop_at_a_training_step).run(jobs=2)
    assert not multiprocessing.active_children()
    Experiment(preset, tmp_path / "run").run(jobs=2)
    for name in preset.recipes:
        assert stage_metrics(tmp_path / "run", name)["test"]["episodes"] == preset.test_episodes


def test_a_second_run_in_a_directory_in_use_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import fcntl

    run_dir = tmp_path / "busy"
    run_dir.mkdir()
    with open(run_dir / ".lock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        fh.write("4242")
        fh.flush()
        capsys.readouterr()
        assert experiment_main(["--preset", "tiny", "--out", str(run_dir), "-q"]) == 2
        err = capsys.readouterr().err
        assert "another lc-experiment (pid 4242) is running" in err and len(err.strip().splitlines()) == 1
    assert not (run_dir / "corpus").exists()


def check_rerun_skips_everything_and_a_changed_recipe_is_stale(run_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    policies = sorted(run_dir.glob("policies/*/seed*/*/policy.safetensors"))
    before = {p: p.stat().st_mtime_ns for p in policies}
    capsys.readouterr()
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(run_dir)]) == 0
    out = capsys.readouterr().out
    n_stages = len(list((run_dir / "stages").glob("*.json")))
    assert f"0 stages computed, {n_stages} complete and skipped" in out
    assert out.count("complete, skipped") == n_stages
    assert {p: p.stat().st_mtime_ns for p in policies} == before

    # A recipe file with other demonstration episodes: its demos, clone, train and evaluation are stale, and so
    # are the shielded stage of hybrid-ppo, whose safety layer follows it, and distil-safety-ppo, whose DAgger
    # starts from it; the packaged recipe sharing the old demonstrations and every other recipe stay complete.
    changed = load_recipe("pure-ppo").with_settings(["demos.seed=6000"])
    path = run_dir.parent / "pure-ppo.toml"
    path.write_text(changed.to_toml())
    recipes = tuple(str(path) if n == "pure-ppo" else n for n in RECIPES)
    exp = Experiment(dataclasses.replace(PRESETS["tiny"], recipes=recipes), run_dir, seeds=SEEDS)
    plan = {s.name: s.status for s in exp.plan()}
    stale = {n for n, st in plan.items() if st != "skipped"}
    # the plan lists every stage of the graph: the evaluations and safety stages after a stale policy wait for it
    assert stale == {"demos/oracle-s6000-n2"} | {f"pure-ppo/seed{s}/{st}" for s in range(SEEDS) for st in ("clone", "train")} \
        | {f"hybrid-ppo/seed{s}/shielded" for s in range(SEEDS)} \
        | {f"pure-ppo/seed{s}/eval" for s in range(SEEDS)} | {f"hybrid-ppo/seed{s}/{st}" for s in range(SEEDS) for st in ("eval", "safety")} \
        | {f"distil-safety-ppo/seed{s}/{st}" for s in range(SEEDS) for st in ("dagger", "eval", "safety")}
    assert plan["demos/oracle-s6000-n2"] == "would run (new)"
    assert all(plan[n].startswith("would run (after ") for n in stale - {"demos/oracle-s6000-n2"})
    assert len(plan) == n_stages + 1  # the new demonstrations besides the old ones, which other recipes read
    assert {p: p.stat().st_mtime_ns for p in policies} == before


def test_an_interrupted_recording_stage_keeps_the_time_of_its_first_part(tmp_path: Path) -> None:
    """A recording stage stopped after 2 of its 3 episodes and resumed records the time of both parts."""

    class Stop(Exception):
        pass

    def stop_after_two(msg: str) -> None:
        if "2/3 episodes" in msg:
            raise Stop

    run_dir = tmp_path / "run"
    with pytest.raises(Stop):
        Experiment(PRESETS["tiny"], run_dir, progress=stop_after_two).run_stage(StageKey.of("corpus"))
    pending = json.loads((run_dir / "stages" / "corpus.pending.json").read_text())
    first = pending["wall_s_parts"]
    assert first > 0 and len(list((run_dir / "corpus").glob("*.mcap"))) == 2
    res = Experiment(PRESETS["tiny"], run_dir).run_stage(StageKey.of("corpus"))
    assert res.status == "done" and len(list((run_dir / "corpus").glob("*.mcap"))) == 3
    record = json.loads((run_dir / "stages" / "corpus.json").read_text())
    # the one episode left took less than the two of the first part; the record holds both parts
    assert first < record["wall_s"] <= first + res.run_s
    assert res.wall_s == record["wall_s"]


def test_an_interrupted_invocation_keeps_its_wall_time_until_its_last_progress_line(tmp_path: Path) -> None:
    class Stop(Exception):
        pass

    lines: list[str] = []

    def stop_at_the_third_episode(msg: str) -> None:
        lines.append(msg)
        if "3/3 episodes" in msg:
            raise Stop

    with pytest.raises(Stop):
        Experiment(PRESETS["tiny"], tmp_path / "run", progress=stop_at_the_third_episode).run()
    (inv,) = json.loads((tmp_path / "run" / INVOCATIONS).read_text())
    assert not inv["finished"] and inv["wall_s"] > 0 and len(lines) >= 4


def test_policy_stage_config_follows_the_recipe_and_the_preset() -> None:
    tiny = PRESETS["tiny"]
    a2c = load_recipe("paper-a2c").policy_config("train", scenario="tiny", seed=1, caps=tiny.cap_dict)
    assert (a2c.algo, a2c.obs, a2c.seed, a2c.learning_rate, a2c.n_steps, a2c.timesteps) == ("a2c", "hybrid", 1, 7e-4, 8, 128)
    assert load_recipe("paper-dqn").policy_config("train", scenario="paper", seed=0).learning_rate == 1e-4
    best = load_recipe("hybrid-ppo")
    clone = best.policy_config("clone", scenario="paper", seed=0, warm_start="/d")
    train = best.policy_config("train", scenario="paper", seed=0, init_policy="/p.safetensors")
    assert (clone.timesteps, clone.warm_start, clone.warm_start_epochs, clone.window_features) == (0, "/d", 20, True)
    assert (train.timesteps, train.learning_rate, train.freeze_image, train.init_policy) == (1_200_000, 3e-5, True,
                                                                                           "/p.safetensors")
    with pytest.raises(ValueError, match="corpus_episodes"):
        Preset(name="x", corpus_episodes=2)


def test_cli_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        experiment_main(["--preset", "tiny", "--seeds", "0", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    f = tmp_path / "file"
    f.write_text("x")
    capsys.readouterr()
    assert experiment_main(["--preset", "tiny", "--out", str(f)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is not a directory" in err
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("not an experiment")
    assert experiment_main(["--preset", "tiny", "--out", str(other)]) == 2
    assert "experiment.json" in capsys.readouterr().err
    assert (other / "keep.txt").exists()
    with pytest.raises(SystemExit) as exc:
        experiment_main(["--help"])
    assert exc.value.code == 0
    assert "REPORT.md" in capsys.readouterr().out
    assert experiment_main(["--preset", "tiny", "--recipe", "no-such-recipe", "--out", str(tmp_path / "y")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown recipe 'no-such-recipe'" in err and not (tmp_path / "y").exists()


def check_publish_copies_the_report_and_every_metrics_file(run_dir: Path, dest: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    from lcmodels.publish import publish

    publish(run_dir, dest)
    report = (dest / REPORT_NAME).read_text()
    assert report == (run_dir / REPORT_NAME).read_text()
    metrics = sorted(p.relative_to(run_dir) for p in run_dir.rglob("metrics.json"))
    own_folder = json.dumps(str(run_dir.resolve()) + "/")[1:-1].encode()
    assert len(metrics) > 3 * len(RECIPES)
    for rel in metrics:
        # the run's bytes, with the run's own folder (as JSON spells it) relative to it: no machine folder published
        assert (dest / rel).read_bytes() == (run_dir / rel).read_bytes().replace(own_folder, b"")
    assert (dest / FIG5_NAME).is_file() and (dest / FIG6_NAME).is_file()
    big = [p for p in dest.rglob("*") if p.suffix in (".zip", ".safetensors", ".pt", ".mcap", ".npy", ".npz")]
    assert not big and sum(p.stat().st_size for p in dest.rglob("*") if p.is_file()) < 4_000_000
    with pytest.raises(ValueError, match="exists"):
        publish(run_dir, dest)  # nothing is overwritten silently
    (dest / "NOTE.md").write_text("written by hand")
    (dest / "stages" / "gone__seed9.json").write_text("{}")  # a stage the run no longer has
    publish(run_dir, dest, overwrite=True)
    assert (dest / "NOTE.md").read_text() == "written by hand" and not (dest / "stages" / "gone__seed9.json").exists()
    assert (dest / REPORT_NAME).read_text() == report
    # A run stopped on purpose: refused, unless asked; then what its stages finished is copied, splits included.
    pending = run_dir / "stages" / "stopped.pending.json"
    pending.write_text("{}")
    try:
        with pytest.raises(ValueError, match="unfinished stage"):
            publish(run_dir, dest.with_name("partial"))
        publish(run_dir, dest.with_name("partial"), allow_pending=True)
    finally:
        pending.unlink()
    split = Path("policies") / "pure-ppo" / "seed0" / "eval" / "val-seed0.json"
    assert (dest.with_name("partial") / split).read_bytes() == (run_dir / split).read_bytes()
    assert not (dest.with_name("partial") / "stages" / "stopped.pending.json").exists()


def check_a_folder_published_with_weights_resumes_as_the_run(run_dir: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    """A run published with its weights, copied elsewhere and run again: the recordings are re-made to the same
    bytes, every other stage is complete, and the report's tables are the run's."""
    from lcmodels.publish import publish

    dest = tmp_path / "published-weights"
    files = publish(run_dir, dest, weights=True)
    assert not [f for f in files if f.suffix == ".mcap" or "checkpoints" in f.parts]
    assert {f.name for f in files} >= {"policy.safetensors", "predictor.pt"}
    resumed = tmp_path / "resumed"
    shutil.copytree(dest, resumed)
    capsys.readouterr()
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(resumed)]) == 0
    out = capsys.readouterr().out
    ran = sorted(re.findall(r"\[([^\]]+)\] running", out))
    assert ran and all(name == "corpus" or name.startswith("demos/") for name in ran), ran
    for rec in (run_dir / "corpus").glob("*.mcap"):
        assert (resumed / "corpus" / rec.name).read_bytes() == rec.read_bytes()
    before, after = (run_dir / REPORT_NAME).read_text(), (resumed / REPORT_NAME).read_text()
    for heading in ("## Table III", "## Table IV", "## References", "## Every row"):
        assert md_table(after, heading) == md_table(before, heading)
    # a policy of the copy whose card names a predictor no longer there reads the copy's own, found by SHA-256
    policy = resumed / "policies" / "hybrid-ppo" / "seed0" / "train" / "policy.safetensors"
    meta = read_meta(policy)
    assert not Path(meta["predictor"]["path"]).is_absolute()  # no path of the machine it was trained on
    gone = meta | {"predictor": meta["predictor"] | {"path": str(tmp_path / "gone" / "predictor.pt")}}
    assert find_predictor(gone, policy) == (resumed / "predictor" / "predictor.pt").resolve()
    other = gone | {"predictor": gone["predictor"] | {"sha256": "0" * 64}}
    assert find_predictor(other, policy) is None  # a predictor with other weights is not taken for it
    (tmp_path / "retrained.pt").write_bytes(b"other weights")
    replaced = meta | {"predictor": meta["predictor"] | {"path": str(tmp_path / "retrained.pt")}}
    assert find_predictor(replaced, policy) == (resumed / "predictor" / "predictor.pt").resolve()  # by hash
    unhashed = {"predictor": {"path": str(tmp_path / "gone" / "predictor.pt")}}
    assert find_predictor(unhashed, policy) is None  # without a hash, no search for "some" predictor


def check_the_report_states_the_wall_time_of_every_invocation(run_dir: Path) -> None:
    """Three runs of the directory (the first, the --jobs 2 redo, the rerun): the report sums all three."""
    invocations = json.loads((run_dir / INVOCATIONS).read_text())
    assert len(invocations) == 3 and all(inv["finished"] for inv in invocations)
    assert invocations[0]["wall_s"] > invocations[2]["wall_s"] > 0  # the rerun only skips and reports
    m = re.search(r"wall time: \*\*([0-9.]+) min\*\* over 3 invocation\(s\)", (run_dir / REPORT_NAME).read_text())
    assert m and float(m.group(1)) == pytest.approx(sum(inv["wall_s"] for inv in invocations) / 60, abs=0.051)


def check_skip_train_reports_complete_policies_with_their_time_and_keeps_the_command(run_dir: Path) -> None:
    before = (run_dir / REPORT_NAME).read_text()
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(run_dir), "--skip-train", "-q"]) == 0
    report = (run_dir / REPORT_NAME).read_text()
    stages = {r["stage"]: r for r in md_table(report, "## Stages")}
    for name in RECIPES:
        for s in range(SEEDS):
            for st in (*load_recipe(name).stages, "eval"):
                row = stages[f"{name}/seed{s}/{st}"]
                record = json.loads((run_dir / "stages" / f"{name}__seed{s}__{st}.json").read_text())
                assert row["this run"] == "skipped"
                assert float(row["recorded wall s"]) == pytest.approx(record["wall_s"], abs=0.051)
    for heading in ("## Reproduce", "## Table III", "## Table IV"):
        assert report.split(heading)[1].split("##")[0] == before.split(heading)[1].split("##")[0]


def test_an_interrupted_evaluation_keeps_the_splits_it_finished(tmp_path: Path) -> None:
    """The rule-based driver's evaluation stopped after its validation split: the rerun evaluates only the test split."""

    class Stop(Exception):
        pass

    def stop_after_validation(msg: str) -> None:
        if "] val (seed" in msg:
            raise Stop

    preset = dataclasses.replace(PRESETS["tiny"], recipes=())
    with pytest.raises(Stop):
        Experiment(preset, tmp_path / "run", progress=stop_after_validation).run_stage(StageKey.of(RULE_KEY))
    first = tmp_path / "run" / RULE_KEY / "val-seed0.json"
    stamp = first.stat().st_mtime_ns
    assert not (tmp_path / "run" / RULE_KEY / "metrics.json").exists()
    lines: list[str] = []
    res = Experiment(preset, tmp_path / "run", progress=lines.append).run_stage(StageKey.of(RULE_KEY))
    assert res.status == "done" and first.stat().st_mtime_ns == stamp
    assert not any("] val (seed" in line for line in lines) and any("] test (seed" in line for line in lines)
    m = json.loads((tmp_path / "run" / RULE_KEY / "metrics.json").read_text())
    assert m["val"]["0"] == json.loads(first.read_text()) and m["test"]["episodes"] == preset.test_episodes


def test_a_followed_policy_is_trained_before_the_recipes_whose_layer_follows_it() -> None:
    from lcmodels.experiment import recipe_ranks
    from lcmodels.experiment.recipe import load_recipe

    recipes = [load_recipe(n) for n in ("a2c-hybrid", "hybrid-ppo", "pure-ppo")]
    rank = recipe_ranks(recipes)
    assert rank["pure-ppo"] < rank["hybrid-ppo"] < rank["a2c-hybrid"]
    # a chain: a follows b, which follows pure-ppo: pure-ppo, then b, then a
    hybrid = recipes[1]
    b = dataclasses.replace(hybrid, name="b")
    a = dataclasses.replace(hybrid, name="a", safety=dataclasses.replace(hybrid.safety, follow="b"))
    rank = recipe_ranks([a, b, *recipes])
    assert rank["pure-ppo"] < rank["b"] < rank["a"] < rank["a2c-hybrid"]
    # the paper preset's graph, in the order one process runs it: both pure-ppo seeds before either hybrid-ppo seed
    exp = Experiment(PRESETS["paper"], Path("unused"))
    order = [k for k in exp.graph().keys() if k.recipe is not None]
    first = {}
    for i, k in enumerate(order):
        first.setdefault(k.recipe, i)
    assert first["pure-ppo"] < first["hybrid-ppo"] < first["a2c-hybrid"]
    assert max(i for i, k in enumerate(order) if k.recipe == "pure-ppo") < first["hybrid-ppo"]


def test_jobs_cut_the_runs_own_evaluations_over_processes_with_the_same_figures(
    tmp_path: Path, shard_pools: list
) -> None:
    import multiprocessing as mp

    pools = shard_pools
    # three batches of test episodes: two shards
    preset = dataclasses.replace(PRESETS["tiny"], recipes=("paper-ppo-pure",), oracle=False, test_episodes=40)
    for jobs in (1, 2):
        Experiment(preset, tmp_path / f"j{jobs}").run(jobs=jobs)
    assert len(pools) == 1 and pools[0].shards >= 4  # --jobs 2: the rule's and the policy's test episodes
    assert not mp.active_children()  # closed with the run
    for key in (RULE_KEY, "paper-ppo-pure"):
        a, b = stage_metrics(tmp_path / "j1", key), stage_metrics(tmp_path / "j2", key)
        assert without_wall_times(a) == without_wall_times(b) and a["test"]["episodes"] == 40, key


def test_skip_train_lists_the_stages_waiting_for_a_follower_as_not_run(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert experiment_main(["--preset", "tiny", "--recipe", "hybrid-ppo", "--out", str(out), "--skip-train", "-q"]) == 0
    stages = {r["stage"]: r["this run"] for r in md_table((out / REPORT_NAME).read_text(), "## Stages")}
    for st in (*load_recipe("hybrid-ppo").stages, "eval"):  # the shielded stage and what follows it too
        assert stages[f"hybrid-ppo/seed0/{st}"] == "not run", st
    assert stages["pure-ppo/seed0/eval"] == "not run"


def test_a_dagger_stage_taught_by_the_safety_layer_starts_from_the_policy_it_follows(tmp_path: Path) -> None:
    """``distil-safety-ppo``: its DAgger stage comes first, starts from pure-ppo's policy of the same seed, and has
    that policy behind the recipe's safety layer label the states, corrections weighted as the recipe says."""
    preset = dataclasses.replace(PRESETS["tiny"], recipes=("distil-safety-ppo",), oracle=False)
    run_dir = tmp_path / "run"
    exp = Experiment(preset, run_dir)
    recipe = next(r for r in exp.recipes() if r.name == "distil-safety-ppo")
    for key in ("demos/oracle-s5000-n2", "pure-ppo/seed0/clone", "pure-ppo/seed0/train", "distil-safety-ppo/seed0/dagger"):
        assert exp.run_stage(StageKey.parse(key)).status == "done", key
    follow = json.loads((run_dir / "stages" / "pure-ppo__seed0__train.json").read_text())
    rec = json.loads((run_dir / "stages" / "distil-safety-ppo__seed0__dagger.json").read_text())
    assert rec["inputs"] == {"clone": outputs_digest(follow["outputs"]), "expert": outputs_digest(follow["outputs"])}
    assert rec["config"]["correction_weight"] == 4.0 and rec["config"]["safety"]["samples"] == recipe.safety.samples
    start = policy_dir(run_dir, "pure-ppo", 0) / "train"
    book = json.loads((policy_dir(run_dir, "distil-safety-ppo", 0) / "dagger" / "dagger.json").read_text())
    assert Path(book["run_dir"]) == start and book["demonstrations"] == ""
    (r1,) = book["rounds"]
    assert r1["expert"] == f"safety-layer:{(start / 'policy.safetensors').resolve()}"
    assert r1["expert_safety_layer"] == {"blind": True, "follow": "", "perceived": True,
                                         "horizon_decisions": recipe.safety.horizon_decisions,
                                         "samples": recipe.safety.samples}  # fmt: skip
    assert r1["correction_weight"] == 4.0 and r1["training_states"] == r1["states_labelled"] > 0
    with np.load(policy_dir(run_dir, "distil-safety-ppo", 0) / "dagger" / "round1" / "states.npz") as states:
        assert r1["agreement"] == pytest.approx(float((states["labels"] == states["actions"]).mean()))
    # a stage recorded before the weight was a setting trained at weight 1: complete for a recipe asking 1, stale here
    path = run_dir / "stages" / "distil-safety-ppo__seed0__dagger.json"
    rec["config"].pop("correction_weight")
    path.write_text(json.dumps(rec))
    unweighted = tmp_path / "distil-safety-ppo.toml"
    unweighted.write_text(load_recipe("distil-safety-ppo").with_settings(["dagger.correction_weight=1.0"]).to_toml())
    again = Experiment(dataclasses.replace(preset, recipes=(str(unweighted),)), run_dir)
    assert again.run_stage(StageKey.parse("distil-safety-ppo/seed0/dagger")).status == "skipped"
    assert exp.run_stage(StageKey.parse("distil-safety-ppo/seed0/dagger")).status == "done"


def test_a_preset_with_a_suite_measures_every_run_on_its_roads_and_tables_them_with_figures(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The ablation's shape, small: two recipes with two seeds each, every final policy on every road of a suite
    next to the ceiling and floor, one table with the methods' paired tests and the figures; a rerun is complete."""
    import json

    from lcsim import suite as suite_mod
    from lcsim.config import tiny_scenario
    from lcsim.suite import SuiteScenario

    for name, block in (("tiny-a", 900), ("tiny-b", 901)):
        monkeypatch.setitem(suite_mod.SUITE_SCENARIOS, name, SuiteScenario(name=name, block=block, test_episodes=6,
                                                                            what="tiny", make=tiny_scenario))  # fmt: skip
    monkeypatch.setitem(suite_mod.SUITES, "tiny", ("tiny-a", "tiny-b"))
    preset = dataclasses.replace(PRESETS["tiny"], recipes=("paper-ppo-pure", "ablation-lane-aware"), oracle=False,
                                 recipe_seeds=(("paper-ppo-pure", 2), ("ablation-lane-aware", 2)), suite="tiny",
                                 suite_episodes=3)  # fmt: skip
    out = tmp_path / "run"
    Experiment(preset, out).run()
    summary = json.loads((out / "bench" / "bench.json").read_text())
    assert [g["group"] for g in summary["groups"]] == ["paper-ppo-pure", "ablation-lane-aware"]
    assert summary["groups"][0]["runs"] == ["paper-ppo-pure/seed0", "paper-ppo-pure/seed1"]
    test = summary["groups"][1]["mcnemar_vs_first_group"]
    assert test["paired_by"] == "key" and test["pairs"] == [["paper-ppo-pure/seed0", "ablation-lane-aware/seed0"],
                             ["paper-ppo-pure/seed1", "ablation-lane-aware/seed1"]] and test["n"] == 2 * 2 * 3
    for row in summary["scenarios"]:
        assert {"oracle", "rule", "ablation-lane-aware/seed1"} <= set(row["drivers"]) and row["episodes"] == 3
    md = (out / "bench" / "BENCH.md").read_text()
    assert "(bench_normalised.svg)" in md and (out / "bench" / "bench_intervals.png").stat().st_size > 0
    cells = json.loads((out / "policies" / "ablation-lane-aware" / "seed0" / "suite" / "suite.json").read_text())
    assert set(cells["cells"]) == {"tiny-a", "tiny-b"} and len(cells["cells"]["tiny-a"]["outcomes"]) == 3
    again = Experiment(preset, out).plan()
    assert {s.status for s in again} == {"skipped"}
