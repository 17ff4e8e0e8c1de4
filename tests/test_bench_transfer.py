"""The SUMO transfer check end to end: SUMO highway episodes generated, imported, and a predictor evaluated
on them next to the baselines (tools/sumo_highway.py, tools/bench_transfer.py)."""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np
import pytest

TOOLS = pathlib.Path(__file__).resolve().parent.parent / "tools"
sys.path.insert(0, str(TOOLS))

import bench_transfer  # noqa: E402
import sumo_highway  # noqa: E402

from lcdata.corpus import Corpus, WindowOptions, load_tracks  # noqa: E402
from lcmodels.predictor import PredictorConfig, TrainConfig, train_predictor  # noqa: E402
from lcmodels.predictor.baselines import constant_acceleration, constant_velocity  # noqa: E402
from lcmodels.predictor.metrics import summary  # noqa: E402

needs_sumo = pytest.mark.skipif(not sumo_highway.sumo_available(),
                                reason='eclipse-sumo is not installed (pip install -e ".[sumo]")')  # fmt: skip
TINY = sumo_highway.HighwayOptions(road_length_m=500.0, initial_vehicles=14, duration_s=20.0)


def test_configs_and_bad_input_give_one_line_errors(tmp_path, capsys) -> None:
    assert bench_transfer.parse_config("20+60") == (20, 60, 5)
    assert bench_transfer.parse_config("10+10") == (10, 10, 1)
    assert bench_transfer.parse_config("20+60/3") == (20, 60, 3)
    with pytest.raises(ValueError, match="HISTORY"):
        bench_transfer.parse_config("20x60")
    assert bench_transfer.parse_variant("gated") == ("gated", 0.0, None, None)
    assert bench_transfer.parse_variant("gated:0.003:1") == ("gated", 0.003, 1, None)
    assert bench_transfer.parse_variant("gated:0.003::lane-aware") == ("gated", 0.003, None, "lane-aware")
    for argv, words in (
        (["--out", str(tmp_path), "--configs", "ten"], "HISTORY+FUTURE"),
        (["--out", str(tmp_path), "--variants", "magic"], "unknown correction"),
        (["--out", str(tmp_path), "--variants", "gated:-1"], "noise"),
        (["--out", str(tmp_path), "--variants", "gated:0::map"], "unknown base"),
        (["--out", str(tmp_path), "--checkpoint", str(tmp_path / "none.pt")], "does not exist"),
        (["--out", str(tmp_path), "--sumo", str(tmp_path)], "not a folder of .mcap"),
        (["--out", str(tmp_path), "--lcsim-episodes", "0"], "must be >= 1"),
    ):
        assert bench_transfer.main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("bench_transfer.py: error:") and err.count("\n") == 1 and words in err, err
    with pytest.raises(ValueError, match="initial_vehicles"):
        sumo_highway.HighwayOptions(initial_vehicles=-1)
    assert bench_transfer.main(["--help"]) == 0
    assert "SUMO" in capsys.readouterr().out


@pytest.fixture(scope="module")
def sumo_corpus(tmp_path_factory) -> pathlib.Path:
    if not sumo_highway.sumo_available():
        pytest.skip('eclipse-sumo is not installed (pip install -e ".[sumo]")')
    out = tmp_path_factory.mktemp("sumo")
    files = sumo_highway.generate(out / "sumo", 2, 7, TINY)
    sumo_highway.import_fcd(files, out / "corpus")
    return out


@pytest.mark.slow
@needs_sumo
def test_sumo_highway_episodes(sumo_corpus: pathlib.Path) -> None:
    tracks = load_tracks(sumo_corpus / "corpus")
    assert len(tracks) == 2
    for t in tracks:
        assert t["vehicle_id"].nunique() >= TINY.initial_vehicles
        assert set(t["lane"].unique()) <= {0, 1, 2, 3} and t["lane"].nunique() >= 3
        np.testing.assert_allclose(t["length"], 5.37)
        np.testing.assert_allclose(t["width"], 1.80)
        assert abs(t["speed"].mean() * 3.6 - 24.0) < 3.0  # near 24 km/h, with the speed factor's spread
        assert t["speed"].std() > 0.1  # not a frozen conveyor belt
        for _, car in t.sort_values("step").groupby("vehicle_id"):  # a lane change moves sideways, no jump
            assert np.abs(np.diff(car["y"].to_numpy())).max() < 0.2
    # Episodes differ by seed, and a seed is repeatable.
    a, b = (t.sort_values(["vehicle_id", "step"])[["x", "y"]].to_numpy() for t in tracks)
    assert a.shape != b.shape or not np.allclose(a, b)
    again = sumo_highway.generate(sumo_corpus / "again", 1, 7, TINY)[0]
    first = (sumo_corpus / "sumo" / again.name).read_text()
    assert again.read_text().split("<fcd-export")[1] == first.split("<fcd-export")[1]


@pytest.mark.slow
@needs_sumo
def test_transfer_evaluation_end_to_end(sumo_corpus: pathlib.Path, tmp_path: pathlib.Path, capsys) -> None:
    from lccli.record import record_main

    lcsim = tmp_path / "lcsim"
    assert record_main(["--scenario", "corpus", "--episodes", "4", "--seed", "5", "--vehicles", "8",
                        "--steps", "300", "--out", str(lcsim)]) == 0  # fmt: skip
    cfg = TrainConfig(model=PredictorConfig(d_model=32, ff_dim=64, num_layers=1, correction="gated"), stride=2,
                      max_epochs=3, batch_size=128, progress=False, tensorboard=False, num_threads=1)  # fmt: skip
    train_predictor(load_tracks(lcsim), cfg, tmp_path / "model")
    ckpt = tmp_path / "model" / "predictor.pt"

    e = bench_transfer.evaluate_checkpoint(ckpt, sumo_corpus / "corpus", stride=4, max_windows=None)
    assert e["windows"] > 100 and e["correction"] == "gated"
    # The baselines in the report are the baseline functions on the very same windows.
    corpus = Corpus.from_tracks(load_tracks(sumo_corpus / "corpus"), WindowOptions(stride=4))
    batch = corpus.gather()
    assert len(batch.history) == e["windows"] == e["model"]["count"]
    for name, fn in (("constant_velocity", constant_velocity), ("constant_acceleration", constant_acceleration)):
        assert e[name] == summary(fn(batch.history, 10), batch.future, miss_threshold_m=0.5)
    for name in ("model", "constant_velocity", "constant_acceleration"):
        h = e[name]["horizons"]
        assert list(h) == ["0.5s"] and all(np.isfinite(v) and v >= 0 for v in h["0.5s"].values())
    # An evaluation-only run of the command: the table, the JSON and the file agree.
    out = tmp_path / "bench"
    argv = ["--out", str(out), "--checkpoint", str(ckpt), "--lcsim-test", str(lcsim), "--sumo",
            str(sumo_corpus / "corpus"), "--max-eval-windows", "500", "-q"]  # fmt: skip
    assert bench_transfer.main(argv) == 0
    table = capsys.readouterr().out
    assert "| sumo | 10+10 | CV |" in table and "| lcsim | 10+10 | model |" in table
    assert bench_transfer.main([*argv, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["models"] == json.loads((out / "transfer.json").read_text())["models"]
    assert printed["models"]["model"]["sumo"]["windows"] == 500


def test_sumo_highway_bad_input(tmp_path, capsys) -> None:
    for argv, words in ((["--out", str(tmp_path), "--episodes", "x"], "invalid int"),
                        (["--out", str(tmp_path), "--episodes", "0"], "must be >= 1"),
                        (["--out", str(tmp_path), "--sigma", "3"], "sigma")):  # fmt: skip
        assert sumo_highway.main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("sumo_highway.py: error:") and err.count("\n") == 1 and words in err, err


def test_recording_keeps_stdout_for_the_figures(tmp_path, capsys) -> None:
    """--json prints the figures on stdout: the recording's summary goes to stderr."""
    out = bench_transfer.record_lcsim(tmp_path / "rec", 3, 1, quiet=True)
    assert len(list(out.glob("*.mcap"))) == 3
    captured = capsys.readouterr()
    assert captured.out == "" and "recorded 3 episodes" in captured.err


def test_the_training_corpus_can_mix_two_driving_styles(tmp_path) -> None:
    """exact_episodes more episodes with exact-IDM traffic: their configs say so; a rerun records nothing."""
    from lcdata.offline import episode_config
    from lcdata.reader import read_episode

    out = bench_transfer.record_lcsim(tmp_path / "rec", 2, 1, quiet=True, exact_episodes=2)
    files = sorted(out.glob("*.mcap"))
    styles = sorted(episode_config(read_episode(f)).traffic.human_like for f in files)
    assert styles == [False, False, True, True]
    mtimes = [f.stat().st_mtime_ns for f in files]
    bench_transfer.record_lcsim(tmp_path / "rec", 2, 1, quiet=True, exact_episodes=2)
    assert [f.stat().st_mtime_ns for f in sorted(out.glob("*.mcap"))] == mtimes
