"""A short training run: loss goes down, artefacts are complete, checkpoints round-trip."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from lcdata.corpus import Corpus, WindowOptions
from lcmodels.predictor import Predictor, PredictorConfig, TrainConfig, load_model, train_predictor
from lcmodels.predictor.synthetic import synthetic_tracks
from lcmodels.predictor.train import CHECKPOINT_NAME, METRICS_NAME

SMALL = TrainConfig(
    model=PredictorConfig(d_model=32, ff_dim=64, num_layers=1),
    stride=2,
    max_epochs=3,
    batch_size=256,
    progress=False,
    seed=3,
)


def _tracks() -> list:
    return [synthetic_tracks(episode=f"ep{i}", seed=i, num_vehicles=10, num_steps=220) for i in range(5)]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("predictor")
    return out, train_predictor(_tracks(), SMALL, out)


def test_training_lowers_validation_loss_and_writes_metrics(run: tuple[Path, dict[str, Any]]) -> None:
    out, metrics = run
    assert metrics["val"]["best_ade"] < metrics["val"]["initial_ade"]
    on_disk = json.loads((out / METRICS_NAME).read_text())
    assert on_disk == json.loads(json.dumps(metrics))
    for name in ("model", "constant_velocity", "constant_acceleration"):
        entry = on_disk[name]
        assert set(entry) >= {"ade", "fde", "curve", "miss_rate"}
        assert len(entry["curve"]) == SMALL.model.future_steps
        assert entry["fde"] >= 0 and np.isfinite(entry["ade"])
    split = on_disk["corpus"]["split"]
    assert not set(split["train"]) & (set(split["val"]) | set(split["test"]))
    assert on_disk["corpus"]["test"]["windows"] == on_disk["model"]["count"]
    assert (out / "tensorboard").is_dir() and any((out / "tensorboard").iterdir())


def test_checkpoint_round_trip_identical_predictions(run: tuple[Path, dict[str, Any]]) -> None:
    out, _ = run
    raw = torch.load(out / CHECKPOINT_NAME, weights_only=True)
    assert raw["format"] == "lc-toolkit/predictor"
    pred = Predictor.load(out / CHECKPOINT_NAME, history_steps=10, future_steps=10)
    corpus = Corpus.from_tracks(
        synthetic_tracks(episode="x", seed=42, num_vehicles=8, num_steps=60), WindowOptions()
    )
    batch = corpus.gather()
    first = pred.predict_windows(batch)
    pred.save(out / "copy.pt")
    again = Predictor.load(out / "copy.pt").predict_windows(batch)
    np.testing.assert_array_equal(first, again)
    model, extra = load_model(out / CHECKPOINT_NAME)
    assert extra["train_config"]["seed"] == SMALL.seed
    assert not model.training


def test_wrong_horizon_and_corrupt_checkpoints(run: tuple[Path, dict[str, Any]], tmp_path: Path) -> None:
    out, _ = run
    with pytest.raises(ValueError, match=r"future_steps=10.*future_steps=60"):
        Predictor.load(out / CHECKPOINT_NAME, future_steps=60)
    with pytest.raises(ValueError, match="history_steps"):
        Predictor.load(out / CHECKPOINT_NAME, history_steps=20)
    data = (out / CHECKPOINT_NAME).read_bytes()
    (tmp_path / "trunc.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="corrupt"):
        Predictor.load(tmp_path / "trunc.pt")
    (tmp_path / "text.pt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="corrupt"):
        Predictor.load(tmp_path / "text.pt")
    torch.save({"hello": torch.zeros(1)}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not an lc-toolkit predictor"):
        Predictor.load(tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="does not exist"):
        Predictor.load(tmp_path / "missing.pt")


def test_training_is_deterministic(run: tuple[Path, dict[str, Any]], tmp_path: Path) -> None:
    _, metrics = run
    again = train_predictor(_tracks(), SMALL, tmp_path)
    assert again["model"]["ade"] == metrics["model"]["ade"]
    assert again["val"] == metrics["val"]


def test_train_config_validation_and_too_few_episodes(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="batch_size"):
        TrainConfig(batch_size=0)
    with pytest.raises(ValueError, match="val_fraction"):
        TrainConfig(val_fraction=0.0)
    cfg = TrainConfig(model=PredictorConfig(history_steps=20, future_steps=60))
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match="at least 3 episodes"):
        train_predictor(_tracks()[:2], SMALL, tmp_path)


def test_gated_training_with_input_noise_round_trips(tmp_path: Path) -> None:
    """A gated model trained on jittered positions: finite, its familiarity limit fitted, and the
    checkpoint gives the very same predictions and gates after loading."""
    cfg = dataclasses.replace(SMALL, model=dataclasses.replace(SMALL.model, correction="bounded-gated"),
                              input_noise_m=0.003, gate_cost=0.1, tensorboard=False)  # fmt: skip
    metrics = train_predictor(_tracks(), cfg, tmp_path)
    assert np.isfinite(metrics["model"]["ade"]) and metrics["config"]["input_noise_m"] == 0.003
    model, _ = load_model(tmp_path / CHECKPOINT_NAME)
    assert model.config.correction == "bounded-gated" and torch.isfinite(model.familiar_limit)
    corpus = Corpus.from_tracks(synthetic_tracks(episode="x", seed=42, num_vehicles=8, num_steps=60), WindowOptions())
    pos, mask = (torch.from_numpy(a) for a in corpus.gather().tokens())
    with torch.no_grad():
        pred, gate = model.predict_with_gate(pos, mask)
        again, gate_again = load_model(tmp_path / CHECKPOINT_NAME)[0].predict_with_gate(pos, mask)
    assert gate is not None and ((gate >= 0) & (gate <= 1)).all()
    assert torch.equal(pred, again) and torch.equal(gate, gate_again)
    with pytest.raises(ValueError, match="input_noise_m"):
        TrainConfig(input_noise_m=-0.1)


def test_a_time_limit_stops_after_the_epoch_that_crosses_it_and_says_so(
    run: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    _, metrics = run
    assert metrics["training"]["stopped_by"] in ("max_epochs", "patience")
    cut = train_predictor(_tracks(), dataclasses.replace(SMALL, time_limit_s=1e-9), tmp_path / "cut")
    assert cut["training"]["epochs"] == 1 and cut["training"]["stopped_by"] == "time_limit"
    assert cut["training"]["history"] == metrics["training"]["history"][:1]  # the same first epoch
