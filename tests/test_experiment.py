"""lc-experiment end to end on the tiny preset: report contents, resumability, staleness, CLI errors."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from lccli.experiment import experiment_main
from lcmodels.experiment import (
    FIG5_NAME,
    FIG6_NAME,
    INVOCATIONS,
    METHOD_BY_KEY,
    METHODS,
    PAPER_TABLE3,
    PAPER_TABLE4,
    PRESETS,
    REPORT_NAME,
    RULE_KEY,
    RULE_LABEL,
    Experiment,
    Preset,
    policy_config,
    policy_dir,
)
from lcmodels.policy.train import check_run_dir

SEEDS = 2


@pytest.mark.slow
def test_tiny_preset_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One pipeline run (under pytest-xdist a shared fixture would run once per worker)."""
    run_dir = tmp_path / "tiny"
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(run_dir), "-q"]) == 0
    check_report_holds_the_numbers_of_the_metrics_files(run_dir)
    check_parallel_policies_equal_sequential_ones(run_dir)
    check_rerun_skips_everything_and_a_changed_preset_value_is_stale(run_dir, capsys)
    check_publish_copies_the_report_and_every_metrics_file_it_names(run_dir, tmp_path / "published", capsys)
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


def evals(out: Path, key: str) -> list[dict]:
    if key == RULE_KEY:
        return [json.loads((out / RULE_KEY / "metrics.json").read_text())["eval"]]
    return [json.loads((policy_dir(out, key, s) / "metrics.json").read_text())["eval"] for s in range(SEEDS)]


def check_cell(cell: str, values: list[float]) -> None:
    mean, std = parse_cell(cell)
    a = np.asarray(values, dtype=float)
    assert mean == pytest.approx(a.mean(), abs=0.051), (cell, values)
    if len(a) > 1:
        assert std is not None and std == pytest.approx(a.std(ddof=1), abs=0.051), (cell, values)
    else:
        assert std is None


# ------------------------------------------------------------------------------------------------ checks
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

    labels = {m.label: m.key for m in METHODS} | {RULE_LABEL: RULE_KEY}
    for heading, paper, n_rows in (("## Table III", PAPER_TABLE3, 5), ("## Table IV", PAPER_TABLE4, 4)):
        rows = md_table(report, heading)
        assert len(rows) == n_rows
        for row in rows:
            key = labels[row["Method"]]
            ev = evals(run_dir, key)
            assert int(row["seeds"]) == len(ev)
            for rate in ("success", "collision", "timeout"):
                check_cell(row[f"{rate.capitalize()} % (ours)"], [100 * e[f"{rate}_rate"] for e in ev])
                want = f"{paper[key][('success', 'collision', 'timeout').index(rate)]:.1f}" if key in paper else "—"
                assert row[f"{rate.capitalize()} % (paper)"] == want
            check_cell(row["Off-road % (ours)"], [100 * e["off_road_rate"] for e in ev])
            check_cell(row["Safe forward m (ours)"], [e["mean_safe_forward_m"] for e in ev])
            check_cell(row["Return (ours)"], [e["mean_return"] for e in ev])
    warm = md_table(report, "## Warm start")
    assert [int(r["seed"]) for r in warm] == list(range(SEEDS))
    # A policy stage records the compute behind its outputs: training summed over every resumed part
    # (what its metrics.json says) plus the evaluation, not only the last invocation.
    for m in METHODS:
        for s in range(SEEDS):
            name = f"{m.key}__seed{s}.json"
            record = json.loads((run_dir / "stages" / name).read_text())
            metrics = json.loads((policy_dir(run_dir, m.key, s) / "metrics.json").read_text())
            assert record["wall_s"] == pytest.approx(metrics["train"]["wall_s"] + metrics["eval"]["wall_s"])


def without_wall_times(metrics: dict) -> dict:
    """The results of a run, without what differs between two runs of it: wall times (the policy file that
    was evaluated is the same bytes, so its hash stays in)."""
    return {part: {k: v for k, v in metrics[part].items() if k != "wall_s"}
            for part in ("config", "eval", "train")}


def check_parallel_policies_equal_sequential_ones(run_dir: Path) -> None:
    """Two policy stages redone by ``--jobs 2`` worker processes give the same metrics as the first run."""
    redo = [("ppo-pure", 0), ("a2c-hybrid", 1)]
    before = {}
    for key, seed in redo:
        path = policy_dir(run_dir, key, seed)
        before[key] = without_wall_times(json.loads((path / "metrics.json").read_text()))
        (path / "policy.safetensors").unlink()  # outputs changed: the stage is redone from scratch
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(run_dir), "--jobs", "2", "-q"]) == 0
    for key, seed in redo:
        after = json.loads((policy_dir(run_dir, key, seed) / "metrics.json").read_text())
        assert after["eval"]["episodes"] == PRESETS["tiny"].eval_episodes
        assert without_wall_times(after) == before[key]


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


def check_rerun_skips_everything_and_a_changed_preset_value_is_stale(
    run_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    zips = sorted(run_dir.glob("policies/*/seed*/policy.safetensors"))
    assert len(zips) == len(METHODS) * SEEDS
    before = {p: p.stat().st_mtime_ns for p in zips}
    capsys.readouterr()
    assert experiment_main(["--preset", "tiny", "--seeds", str(SEEDS), "--out", str(run_dir)]) == 0
    out = capsys.readouterr().out
    n_stages = 4 + len(METHODS) * SEEDS
    assert f"0 stages computed, {n_stages} complete and skipped" in out
    assert out.count("complete, skipped") == n_stages
    assert {p: p.stat().st_mtime_ns for p in zips} == before

    # Records and runs written before PolicyConfig had `slots` stand for 8 slots: still complete, resumable.
    for path in (run_dir / "stages").glob("*seed*.json"):
        record = json.loads(path.read_text())
        del record["config"]["slots"]
        path.write_text(json.dumps(record))
    run_json = policy_dir(run_dir, "ppo-pure", 0) / "run.json"
    stored = json.loads(run_json.read_text())
    del stored["config"]["slots"]
    run_json.write_text(json.dumps(stored))
    assert {s.status for s in Experiment(PRESETS["tiny"], run_dir, seeds=SEEDS).plan()} == {"skipped"}
    check_run_dir(policy_config(PRESETS["tiny"], METHOD_BY_KEY["ppo-pure"], 0, None), run_json.parent, None)

    # One more demo episode: the demos and the warm-started runs are stale, nothing else.
    changed = Experiment(dataclasses.replace(PRESETS["tiny"], demo_episodes=3), run_dir, seeds=SEEDS)
    plan = {s.name: s.status for s in changed.plan()}
    warm = {f"ppo-hybrid-warm/seed{s}" for s in range(SEEDS)}
    assert {n for n, st in plan.items() if st != "skipped"} == {"demos"} | warm
    assert plan["demos"].startswith("would run (stale: config changed")
    # Redo the demos for real: the warm-started runs now see other inputs; the rest stays complete.
    assert changed.demos().status == "done"
    assert len(list((run_dir / "demos").glob("*.mcap"))) == 3
    plan = {s.name: s.status for s in changed.plan()}
    assert plan["demos"] == "skipped"
    assert {n for n, st in plan.items() if st != "skipped"} == warm
    assert all("inputs changed" in plan[n] for n in warm)
    assert {p: p.stat().st_mtime_ns for p in zips} == before


def test_an_interrupted_recording_stage_keeps_the_time_of_its_first_part(tmp_path: Path) -> None:
    """A recording stage stopped after 2 of its 3 episodes and resumed records the time of both parts."""

    class Stop(Exception):
        pass

    def stop_after_two(msg: str) -> None:
        if "2/3 episodes" in msg:
            raise Stop

    run_dir = tmp_path / "run"
    with pytest.raises(Stop):
        Experiment(PRESETS["tiny"], run_dir, progress=stop_after_two).corpus()
    pending = json.loads((run_dir / "stages" / "corpus.pending.json").read_text())
    first = pending["wall_s_parts"]
    assert first > 0 and len(list((run_dir / "corpus").glob("*.mcap"))) == 2
    res = Experiment(PRESETS["tiny"], run_dir).corpus()
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


def test_policy_stage_config_follows_the_preset() -> None:
    tiny = PRESETS["tiny"]
    from lcmodels.experiment import policy_config

    a2c = policy_config(tiny, METHOD_BY_KEY["a2c-hybrid"], 1, None)
    assert (a2c.algo, a2c.obs, a2c.seed, a2c.learning_rate, a2c.n_steps) == ("a2c", "hybrid", 1, 7e-4, 8)
    assert policy_config(tiny, METHOD_BY_KEY["dqn-hybrid"], 0, None).learning_rate == 1e-4
    warm = policy_config(tiny, METHOD_BY_KEY["ppo-hybrid-warm"], 0, Path("demos"))
    assert warm.warm_start == str(Path("demos").resolve())
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



def check_publish_copies_the_report_and_every_metrics_file_it_names(
    run_dir: Path, dest: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lcmodels.publish import publish

    publish(run_dir, dest)
    report = (dest / REPORT_NAME).read_text()
    assert report == (run_dir / REPORT_NAME).read_text()
    named = re.findall(r"`([^`]+/metrics\.json)`", report)
    assert len(named) == 2 + len(METHODS) * SEEDS
    for rel in named:
        assert (dest / rel).read_bytes() == (run_dir / rel).read_bytes()
    assert (dest / FIG5_NAME).is_file() and (dest / FIG6_NAME).is_file()
    big = [p for p in dest.rglob("*") if p.suffix in (".zip", ".safetensors", ".pt", ".mcap", ".npy")]
    assert not big and sum(p.stat().st_size for p in dest.rglob("*") if p.is_file()) < 2_000_000
    with pytest.raises(ValueError, match="exists"):
        publish(run_dir, dest)  # nothing is overwritten silently
    (dest / "NOTE.md").write_text("written by hand")
    (dest / "stages" / "gone__seed9.json").write_text("{}")  # a stage the run no longer has
    publish(run_dir, dest, overwrite=True)
    assert (dest / "NOTE.md").read_text() == "written by hand" and not (dest / "stages" / "gone__seed9.json").exists()
    assert (dest / REPORT_NAME).read_text() == report


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
    for m in METHODS:
        for s in range(SEEDS):
            row = stages[f"{m.key}/seed{s}"]
            # The demos, redone with the first episode count again, are the same bytes as at first (start times
            # derive from the seeds), so the warm-started runs are complete again too.
            record = json.loads((run_dir / "stages" / f"{m.key}__seed{s}.json").read_text())
            assert row["this run"] == "skipped" and float(row["recorded wall s"]) == pytest.approx(record["wall_s"], abs=0.051)
    for heading in ("## Reproduce", "## Table III", "## Table IV"):
        assert report.split(heading)[1].split("##")[0] == before.split(heading)[1].split("##")[0]
