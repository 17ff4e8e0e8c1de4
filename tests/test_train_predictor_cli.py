"""lc-train-predictor in-process on a tiny corpus recorded by lc-record."""

import json

import pytest
import torch

from lccli.predictor import train_predictor_main
from lccli.record import record_main


@pytest.fixture(scope="module")
def corpus_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("corpus")
    rc = record_main(["--scenario", "corpus", "--episodes", "4", "--seed", "3", "--vehicles", "6",
                      "--steps", "160", "--out", str(out)])
    assert rc == 0
    return out


def test_trains_and_writes_checkpoint_and_metrics(corpus_dir, tmp_path, capsys):
    out = tmp_path / "pred"
    rc = train_predictor_main(["--data", str(corpus_dir), "--out", str(out), "--epochs", "2", "-q"])
    assert rc == 0
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("model", "constant_velocity", "constant_acceleration"):
        assert metrics[key]["ade"] >= 0 and metrics[key]["fde"] >= metrics[key]["ade"] * 0.5
        assert len(metrics[key]["curve"]) == 10
    assert metrics["corpus"]
    state = torch.load(out / "predictor.pt", weights_only=True)
    assert state
    printed = capsys.readouterr().out
    assert "constant velocity" in printed and "ADE" in printed
    # Nothing already written is overwritten silently.
    assert train_predictor_main(["--data", str(corpus_dir), "--out", str(out), "-q"]) == 2
    assert "already exists" in capsys.readouterr().err


def test_bad_inputs_give_one_line_errors(tmp_path, capsys):
    assert train_predictor_main(["--data", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a directory" in err
    (tmp_path / "empty").mkdir()
    assert train_predictor_main(["--data", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-train-predictor: error:") and err.count("\n") == 1
    with pytest.raises(SystemExit):
        train_predictor_main(["--data", str(tmp_path), "--history", "0"])


def test_absurd_sizes_and_unfit_folders_are_refused_before_training(corpus_dir, tmp_path, monkeypatch, capsys):
    """The predictor is written after the whole training: an --out it cannot go to (the filesystem root, the
    home directory, under a file) and sizes no network can have are refused first, in one line."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    (tmp_path / "a_file").write_text("x")
    cases = [
        (["--history", str(10**9), "--out", str(tmp_path / "p1")], "history_steps must be at most"),
        (["--future", str(10**9), "--out", str(tmp_path / "p1")], "future_steps must be at most"),
        (["--out", "/"], "filesystem root"),
        (["--out", str(home)], "home directory"),
        (["--out", str(tmp_path / "a_file" / "p")], "cannot create output directory"),
    ]
    for argv, message in cases:
        assert train_predictor_main(["--data", str(corpus_dir), "-q", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("lc-train-predictor: error:") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "p1").exists() and not list(home.iterdir())


def test_the_lane_aware_base_is_a_training_option(corpus_dir, tmp_path):
    from lcmodels.predictor import load_model

    out = tmp_path / "lane"
    rc = train_predictor_main(["--data", str(corpus_dir), "--out", str(out), "--epochs", "1", "--base", "lane-aware", "-q"])
    assert rc == 0
    assert json.loads((out / "metrics.json").read_text())["config"]["model"]["base"] == "lane-aware"
    model, _ = load_model(out / "predictor.pt")
    assert model.config.base == "lane-aware"
    with pytest.raises(SystemExit):
        train_predictor_main(["--data", str(corpus_dir), "--base", "map"])


def test_gate_cost_is_a_training_option(corpus_dir, tmp_path, capsys):
    out = tmp_path / "costly"
    assert train_predictor_main(["--data", str(corpus_dir), "--out", str(out), "--epochs", "1", "--gate-cost", "1.5", "-q"]) == 0
    assert json.loads((out / "metrics.json").read_text())["config"]["gate_cost"] == 1.5
    assert train_predictor_main(["--data", str(corpus_dir), "--out", str(tmp_path / "bad"), "--gate-cost", "-1", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-train-predictor: error:") and err.count("\n") == 1 and "gate_cost" in err, err
