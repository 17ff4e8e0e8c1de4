"""lc-tune's sweep file: every trial a valid config or the file refused, naming the problem; a rerun skips
the finished trials."""

import json

import pytest

from lccli.tune import main as tune_main
from lcmodels.sweep import Sweep

BASE = '[base]\nobs = "pure"\nscenario = "tiny"\ntimesteps = 64\nn_envs = 2\nn_steps = 32\nbatch_size = 64\n' \
       'n_epochs = 1\neval_episodes = 2\neval_batch = 2\nrecord_eval = false\n'


def test_the_grid_times_the_seeds_are_the_trials(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text("seeds = [3, 4]\n" + BASE + "[grid]\ngamma = [0.9, 0.99]\nwindow_features = [false, true]\n")
    trials = Sweep.from_file(path).trials()
    assert len(trials) == 8 and trials[0][0] == "gamma=0.9_window_features=false_seed3"
    assert {(c.gamma, c.window_features, c.seed) for _, c in trials} == {
        (g, w, s) for g in (0.9, 0.99) for w in (False, True) for s in (3, 4)}


@pytest.mark.parametrize(("text", "message"), [
    ("[grid]\ngama = [0.9]\n", "unknown field"),
    ("[grid]\ngamma = []\n", "non-empty list"),
    ("[grid]\ngamma = [2.0]\n", "gamma must be in"),
    ("seeds = [-1]\n", "seeds must be"),
    ("[sweep]\n", "unknown top-level key"),
    ("gamma = \n", "not valid TOML"),
])
def test_a_bad_sweep_file_is_one_error_naming_it(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        Sweep.from_file(path)
    assert tune_main([str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-tune: error:") and len(err.strip().splitlines()) == 1 and message in err


def test_a_local_sweep_writes_its_table_and_a_rerun_skips_the_finished_trials(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text("seeds = [0]\n" + BASE + "[grid]\ngamma = [0.9, 0.95]\n")
    assert tune_main([str(path), "--out", str(tmp_path / "out"), "-q"]) == 0
    first = json.loads((tmp_path / "out" / "sweep.json").read_text())["trials"]
    table = (tmp_path / "out" / "SWEEP.md").read_text()
    assert len(first) == 2 and table.count("\n| 0.9 |") == table.count("\n| 0.95 |") == 1
    policies = {p: p.stat().st_mtime_ns for p in (tmp_path / "out" / "trials").rglob("policy.safetensors")}
    assert len(policies) == 2
    assert tune_main([str(path), "--out", str(tmp_path / "out"), "-q"]) == 0
    assert {p: p.stat().st_mtime_ns for p in policies} == policies  # finished trials are not trained again
    again = json.loads((tmp_path / "out" / "sweep.json").read_text())["trials"]
    assert [r["success_rate"] for r in again] == [r["success_rate"] for r in first]


def test_a_sweep_without_evaluation_still_writes_its_table(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text("seeds = [0]\n" + BASE.replace("eval_episodes = 2", "eval_episodes = 0") + "[grid]\ngamma = [0.9]\n")
    assert tune_main([str(path), "--out", str(tmp_path / "out"), "-q"]) == 0
    assert "—" in (tmp_path / "out" / "SWEEP.md").read_text()
