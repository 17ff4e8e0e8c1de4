"""Each command against a symbolic link planted in its output folder, a path read back from one of its files
that leads elsewhere, a record edited by hand, a name made of a user's values, a user's callable that fails,
and Ctrl-C: the link's target is never written or deleted, and the command refuses in one line (or writes
safely)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lccli.bench import main as bench_main
from lccli.calibrate import main as calibrate_main
from lccli.dagger import main as dagger_main
from lccli.evaluate import eval_main
from lccli.experiment import experiment_main
from lccli.policy import train_policy_main
from lccli.record import record_main
from lccli.tune import main as tune_main
from lcdata.record import episode_filename
from lckit.fileio import UnsafePathError
from lcmodels.experiment import PRESETS, Experiment, StageKey
from lcmodels.experiment.store import StageStore, Verdict
from lcmodels.fileio import file_sha256
from lcmodels.sweep import MAX_TRIALS, Sweep, trial_name

TINY_TRAIN = ["--obs", "pure", "--scenario", "tiny", "--timesteps", "64", "--set", "n_envs=2", "--set", "n_steps=32",
              "--set", "batch_size=64", "--set", "eval_episodes=0", "-q"]  # fmt: skip


@pytest.fixture
def victim(tmp_path: Path) -> Path:
    """A folder elsewhere with a file that must stay as it is."""
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    (folder / "thesis.tex").write_text("years of work")
    return folder / "thesis.tex"


def untouched(victim: Path) -> bool:
    return victim.read_text() == "years of work" and sorted(p.name for p in victim.parent.iterdir()) == ["thesis.tex"]


def one_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert all(w in err for w in words), err
    return err


# ------------------------------------------------------------------------------------------- lc-calibrate
def test_lc_calibrate_refuses_a_partial_that_is_a_link(tmp_path: Path, victim: Path, capsys) -> None:
    out = tmp_path / "road.toml"
    (tmp_path / "road.toml.partial").symlink_to(victim)
    assert calibrate_main([str(tmp_path / "data"), "--out", str(out), "-q"]) == 2
    one_line(capsys, "lc-calibrate: error:", "symbolic link")
    (tmp_path / "road.toml.partial").unlink()
    out.symlink_to(victim)  # nor the scenario file itself, --overwrite or not
    assert calibrate_main([str(tmp_path / "data"), "--out", str(out), "--overwrite", "-q"]) == 2
    one_line(capsys, "symbolic link")
    assert untouched(victim)


# ---------------------------------------------------------------------------------------------- lc-record
def test_lc_record_refuses_a_partial_or_a_lock_that_is_a_link(tmp_path: Path, victim: Path, capsys) -> None:
    out = tmp_path / "rec"
    out.mkdir()
    rec = ["--vehicles", "8", "--steps", "40", "--no-images", "--out", str(out)]
    partial = out / (episode_filename("paper", "rule", 0) + ".partial")
    for link in (partial, out / ".lc-record.lock", out / "record.json"):
        link.symlink_to(victim)
        assert record_main(rec) == 2
        one_line(capsys, "lc-record: error:", "symbolic link")
        link.unlink()
    assert untouched(victim) and sorted(p.name for p in out.iterdir()) == []


def test_an_episode_writer_never_writes_through_a_link(tmp_path: Path, victim: Path) -> None:
    from lcdata.record import record_episode
    from lcsim.config import tiny_scenario

    (tmp_path / "ep.mcap.partial").symlink_to(victim)
    with pytest.raises(UnsafePathError):
        record_episode(tiny_scenario(), 0, "rule", tmp_path / "ep.mcap", writer="inline")
    assert untouched(victim)


# ------------------------------------------------------------------------------------------ lc-experiment
def test_lc_experiment_refuses_a_stage_folder_or_a_record_that_leads_elsewhere(tmp_path: Path, victim: Path,
                                                                               capsys) -> None:  # fmt: skip
    run = tmp_path / "run"
    run.mkdir()
    (run / "experiment.json").write_text("{}")
    (run / "corpus").symlink_to(victim.parent)  # a stale stage's folder: its rmtree would empty the target
    assert experiment_main(["--preset", "tiny", "--out", str(run), "-q"]) == 2
    one_line(capsys, "lc-experiment: error:", "corpus", "leads out of")
    (run / "corpus").unlink()
    (run / "stages").mkdir()
    (run / "stages" / "corpus.pending.json.partial").symlink_to(victim)
    assert experiment_main(["--preset", "tiny", "--out", str(run), "-q"]) == 2
    one_line(capsys, "symbolic link")
    assert untouched(victim)


def test_a_stage_record_with_outputs_null_is_stale_and_one_outside_the_stage_is_refused(
        tmp_path: Path, victim: Path, capsys) -> None:  # fmt: skip
    run = tmp_path / "run"
    exp = Experiment(PRESETS["tiny"], run)
    key = StageKey.of("corpus")
    job = exp.graph()[key].job(exp.context(), {})
    (run / "stages").mkdir(parents=True)
    (run / "experiment.json").write_text("{}")
    record = {"stage": "corpus", "config": job.config, "inputs": job.inputs, "wall_s": 1.0}
    for outputs in (None, [], {"a.mcap": 7}, "x"):
        (run / "stages" / "corpus.json").write_text(json.dumps(record | {"outputs": outputs}))
        plan = {s.name: s.status for s in exp.plan()}
        assert plan["corpus"] == "would run (stale: corpus.json does not read as a stage record)"
    (run / "stages" / "corpus.json").write_text(json.dumps(record | {"wall_s": "soon", "outputs": {}}))
    assert {s.name: s.status for s in exp.plan()}["corpus"].startswith("would run (stale")
    # a policy elsewhere named by its absolute path, with its true hash: never read as the stage's output
    (run / "stages" / "corpus.json").write_text(json.dumps(record | {"outputs": {str(victim): file_sha256(victim)}}))
    with pytest.raises(UnsafePathError, match="leads out of"):
        exp.plan()
    assert experiment_main(["--preset", "tiny", "--out", str(run), "--dry-run"]) == 2
    one_line(capsys, "corpus.json", "leads out of", "remove the record")
    (run / "corpus").mkdir()
    (run / "corpus" / "a.mcap").symlink_to(victim)  # in the folder, but a link to elsewhere
    (run / "stages" / "corpus.json").write_text(json.dumps(record | {"outputs": {"a.mcap": file_sha256(victim)}}))
    with pytest.raises(UnsafePathError, match="leads out of"):
        exp.plan()
    assert untouched(victim)


def test_a_stale_stage_removes_a_link_in_the_run_as_a_link(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "kept").mkdir(parents=True)
    (run / "kept" / "file").write_text("mine")
    (run / "corpus").symlink_to(run / "kept")  # inside the run: no escape, but not the stage's own folder
    store = StageStore(run)
    attempt = store.begin(StageKey.of("corpus"), Verdict(False, "new"), {}, {})
    assert attempt.path.is_dir() and not attempt.path.is_symlink()
    assert (run / "kept" / "file").read_text() == "mine"
    (run / "corpus" / "inner").symlink_to(run / "kept")
    store.begin(StageKey.of("corpus"), Verdict(False, "stale"), {}, {})  # rmtree: the link inside goes as a link
    assert (run / "kept" / "file").read_text() == "mine" and not (run / "corpus" / "inner").exists()


def interrupt(command: str, argv: list[str], once: Path, cwd: Path) -> tuple[int, str]:
    """Run ``command``'s entry point (``module:function``) with ``argv`` as a user would, press Ctrl-C (SIGINT) once
    ``once`` exists, and return its exit status and stderr."""
    module, main = command.split(":")
    code = f"import sys; from {module} import {main}; raise SystemExit({main}(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", code, *argv], cwd=cwd, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 600
        while not once.exists():
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, f"{once} never appeared"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        return proc.wait(timeout=600), proc.communicate()[1]
    finally:
        if proc.poll() is None:
            proc.kill()


def test_ctrl_c_in_lc_experiment_is_one_line_and_exit_130(tmp_path: Path) -> None:
    run = tmp_path / "run"
    rc, err = interrupt("lccli.experiment:experiment_main", ["--preset", "tiny", "--out", str(run), "-q"],
                        run / "stages" / "corpus.pending.json", tmp_path)  # fmt: skip
    lines = err.strip().splitlines()
    assert rc == 130 and len(lines) == 1 and "lc-experiment: interrupted" in lines[0], err
    assert "rerun the same command" in lines[0]


# ------------------------------------------------------------------------------------------------ lc-bench
def test_lc_bench_never_writes_its_table_through_a_link_nor_over_a_users_file(tiny_suite: Path, tmp_path: Path,
                                                                              victim: Path, capsys) -> None:  # fmt: skip
    out = tmp_path / "bench"
    out.mkdir()
    argv = ["rule", "--suite", "tiny", "--scenario", "tiny-a", "--episodes", "2", "--out", str(out), "-q"]
    for name in ("BENCH.md", "bench.json", "BENCH.md.partial"):
        (out / name).symlink_to(victim)
        assert bench_main(argv) == 2
        one_line(capsys, "lc-bench: error:", "symbolic link")
        (out / name).unlink()
    (out / "cells").symlink_to(victim.parent)
    assert bench_main(argv) == 2
    one_line(capsys, "cells", "leads out of")
    (out / "cells").unlink()
    assert untouched(victim)
    (out / "BENCH.md").write_text("# my notes on the benchmark\n")
    assert bench_main(argv) == 2
    one_line(capsys, "lc-bench did not write it", "--overwrite")
    assert (out / "BENCH.md").read_text() == "# my notes on the benchmark\n"
    assert bench_main([*argv, "--overwrite"]) == 0
    assert (out / "BENCH.md").read_text().rstrip().splitlines()[-1].startswith("`lc-bench ")
    assert bench_main(argv) == 0  # its own table it replaces


def test_lc_bench_names_a_callable_that_fails_and_what_it_returned(tiny_suite: Path, tmp_path: Path,
                                                                   monkeypatch, capsys) -> None:  # fmt: skip
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "odd_policies.py").write_text(
        "import numpy as np\n\n"
        "def three(obs, mask, extra):\n    return np.ones(len(mask), dtype=np.int64)\n\n"
        "def none():\n    return 1\n\n"
        "def boom(obs):\n    raise RuntimeError('the network is on holiday')\n\n"
        "def words(obs):\n    return ['left'] * len(obs['current'])\n\n"
        "def nothing(obs):\n    return None\n\n"
        "def ragged(obs):\n    return [[1], [1, 2]]\n\n"
        "def far(obs):\n    return np.full(len(obs['current']), 7)\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mine"))
    for name, words in (("three", ["takes (obs, mask, extra)", "fn(obs)"]), ("none", ["takes ()"]),
                        ("boom", ["raised RuntimeError: the network is on holiday"]),
                        ("words", ["returned a list of", "str"]), ("nothing", ["returned NoneType None"]),
                        ("ragged", ["returned a list of 2 item(s)"]), ("far", ["from 7 to 7", "0..2"])):
        argv = [f"odd_policies:{name}", "--suite", "tiny", "--scenario", "tiny-a", "--episodes", "2", "--out",
                str(tmp_path / "b"), "-q"]  # fmt: skip
        assert bench_main(argv) == 2, name
        one_line(capsys, "lc-bench: error:", f"odd_policies:{name}", *words)


# ----------------------------------------------------------------------------------------- lc-train-policy
def test_lc_train_policy_overwrite_never_deletes_through_a_linked_folder(tmp_path: Path, victim: Path,
                                                                         capsys) -> None:  # fmt: skip
    out = tmp_path / "run"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"config": {"obs": "image"}}))
    (victim.parent / "step-64.safetensors").write_text("someone's weights")
    (out / "checkpoints").symlink_to(victim.parent)
    assert train_policy_main([*TINY_TRAIN, "--out", str(out), "--overwrite"]) == 2
    one_line(capsys, "lc-train-policy: error:", "checkpoints", "leads out of")
    assert (victim.parent / "step-64.safetensors").read_text() == "someone's weights"
    assert victim.read_text() == "years of work"
    from lcmodels.policy.train import remove_run_outputs

    (out / "checkpoints").unlink()
    (out / "tb").mkdir()
    (out / "tb" / "PPO_1").symlink_to(victim.parent)  # deeper: tb/*/events... would reach through it
    (victim.parent / "events.out.tfevents.1").write_text("someone's log")
    with pytest.raises(UnsafePathError):
        remove_run_outputs(out)
    assert (victim.parent / "events.out.tfevents.1").exists() and (out / "run.json").exists()  # nothing went


def test_ctrl_c_in_lc_train_policy_is_one_line_and_exit_130(tmp_path: Path) -> None:
    run = tmp_path / "run"
    argv = [*TINY_TRAIN, "--timesteps", "1000000", "--out", str(run)]
    rc, err = interrupt("lccli.policy:train_policy_main", argv, run / "run.json", tmp_path)
    lines = err.strip().splitlines()
    assert rc == 130 and len(lines) == 1 and "lc-train-policy: interrupted" in lines[0], err
    assert "rerun the same command" in lines[0]


# ------------------------------------------------------------------------------------------------ lc-tune
BASE = '[base]\nobs = "pure"\nscenario = "tiny"\ntimesteps = 64\nn_envs = 2\nn_steps = 32\nbatch_size = 64\n' \
       'n_epochs = 1\neval_episodes = 0\n'


def test_lc_tune_names_its_trials_safely_and_caps_their_number(tmp_path: Path, capsys) -> None:
    road = tmp_path / "roads" / "sub" / ".." / "my road.toml"
    (tmp_path / "roads" / "sub").mkdir(parents=True)
    (tmp_path / "roads" / "my road.toml").write_text('[traffic]\nnum_vehicles = 8\n')
    (tmp_path / "s.toml").write_text(f"seeds = [0]\n{BASE}[grid]\nscenario = [{json.dumps(str(road))}]\n")
    ((name, _),) = Sweep.from_file(tmp_path / "s.toml").trials()
    assert "/" not in name and ".." not in name and name.endswith("_seed0") and len(name) <= 110
    assert name == trial_name({"scenario": str(road)}) + "_seed0"
    assert trial_name({"gamma": 0.9, "window_features": False}) == "gamma=0.9_window_features=false"  # as before
    assert trial_name({"gamma": "x" * 500}) != trial_name({"gamma": "x" * 501})  # cut, and still apart
    assert tune_main([str(tmp_path / "s.toml"), "--out", str(tmp_path / "out"), "-q"]) == 0
    assert [p.name for p in (tmp_path / "out" / "trials").iterdir()] == [name]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "roads", "s.toml"]
    # 10^9 trials: refused at once, from the axes' lengths, before one is made
    axes = {k: [0.5 + i / 100 for i in range(10)] for k in ("learning_rate", "gamma", "ent_coef", "reward_scale",
                                                            "collision_weight", "exploration_fraction")}
    axes |= {"n_epochs": list(range(1, 11)), "warm_start_epochs": list(range(1, 11)), "eval_seed": list(range(10))}
    (tmp_path / "big.toml").write_text(BASE + "[grid]\n" + "".join(f"{k} = {v}\n" for k, v in axes.items()))
    assert tune_main([str(tmp_path / "big.toml"), "--out", str(tmp_path / "big"), "-q"]) == 2
    one_line(capsys, "1000000000 trials", f"at most {MAX_TRIALS}")
    (tmp_path / "twice.toml").write_text(BASE + "[grid]\ngamma = [0.9, 0.90]\n")
    assert tune_main([str(tmp_path / "twice.toml"), "--out", str(tmp_path / "twice"), "-q"]) == 2
    one_line(capsys, "share the folder")
    assert not (tmp_path / "big").exists() and not (tmp_path / "twice").exists()


# ----------------------------------------------------------------------------------------------- lc-dagger
@pytest.mark.parametrize(("book", "words"), [
    ({"run_dir": "x", "rounds": [{"round": "1/../../x", "states_labelled": 0, "episodes": 1, "user_seeds": [0, 0]}]},
     ["round 1 is not a record"]),
    ({"run_dir": "x", "rounds": "abc"}, ["rounds is not a list"]),
    ({"run_dir": "x", "rounds": [{"round": 1, "states_labelled": 3, "episodes": 1}]}, ["round 1 is not a record"]),
    ({"run_dir": "x", "rounds": [None]}, ["round 1 is not a record"]),
    ({"run_dir": 7, "rounds": []}, ["not a record of DAgger rounds"]),
    ([1, 2], ["not a record of DAgger rounds"]),
    ({"run_dir": "x", "rounds": None}, ["lists no finished round"]),
])
def test_lc_dagger_resume_refuses_malformed_rounds_in_one_line(tmp_path: Path, capsys, book, words) -> None:
    out = tmp_path / "dg"
    out.mkdir()
    (out / "dagger.json").write_text(json.dumps(book))
    assert dagger_main([str(tmp_path / "run"), "--out", str(out), "--resume"]) == 2
    one_line(capsys, "lc-dagger: error:", *words)


def test_lc_dagger_resume_refuses_a_round_folder_that_leads_elsewhere(tmp_path: Path, victim: Path, capsys) -> None:
    out = tmp_path / "dg"
    out.mkdir()
    round1 = {"round": 1, "states_labelled": 0, "episodes": 1, "user_seeds": [0, 0]}
    (out / "dagger.json").write_text(json.dumps({"run_dir": "x", "rounds": [round1]}))
    (out / "round1").symlink_to(victim.parent)
    assert dagger_main([str(tmp_path / "run"), "--out", str(out), "--resume"]) == 2
    one_line(capsys, "round1", "leads out of")
    assert untouched(victim)


# --------------------------------------------------------------------------------------------------- zoo:
def test_a_zoo_name_is_an_entry_of_the_zoo_and_nothing_above_it(tmp_path: Path, monkeypatch, capsys) -> None:
    from lcmodels.policy.driverspec import resolve_policy_spec
    from lcmodels.zoo import CHECKOUT_ZOO

    zoo = tmp_path / "zoo"
    (zoo / "inner").mkdir(parents=True)
    policy = CHECKOUT_ZOO / "pure-ppo" / "policy.safetensors"
    (zoo / "policy.safetensors").write_bytes(policy.read_bytes())  # the zoo folder's parent holds a policy
    (tmp_path / "away").mkdir()
    (tmp_path / "away" / "policy.safetensors").write_bytes(policy.read_bytes())
    (zoo / "inner" / "linked").symlink_to(tmp_path / "away")
    monkeypatch.setenv("LC_ZOO", str(zoo / "inner"))
    for spec in ("zoo:..", "zoo:../inner/..", "zoo:.", "zoo:linked", "safety-layer:zoo:.."):
        with pytest.raises(ValueError, match=r"no zoo policy|leads out of"):
            resolve_policy_spec(spec)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:  # the zoo name is checked where argparse reads it
        eval_main(["zoo:..", "--episodes", "1", "--no-record"])
    errors = [line for line in capsys.readouterr().err.splitlines() if ": error:" in line]
    assert exit_.value.code == 2 and len(errors) == 1 and "no zoo policy '..'" in errors[0]
