"""Model config, forward pass, and the batched policy-time API (frames, masks, NaN safety)."""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lcdata.corpus import Corpus, WindowOptions, from_frame, to_frame
from lcmodels.predictor import Predictor, PredictorConfig, TrajectoryTransformer, load_model
from lcmodels.predictor.baselines import constant_velocity, constant_velocity_fit
from lcmodels.predictor.checkpoint import save_model
from lcmodels.predictor.synthetic import synthetic_tracks


def _predictor(h: int = 10, f: int = 10, seed: int = 0) -> Predictor:
    torch.manual_seed(seed)
    model = TrajectoryTransformer(PredictorConfig(history_steps=h, future_steps=f, d_model=32, ff_dim=64))
    torch.nn.init.normal_(model.head[-1].weight, std=0.3)  # a non-trivial residual
    return Predictor(model)


def _moving_histories(b: int, k: int, h: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    start = rng.uniform(-40, 40, (b, k, 1, 2))
    vel = np.stack((rng.uniform(0.2, 0.4, (b, k)), rng.uniform(-0.03, 0.03, (b, k))), -1)[:, :, None]
    return start + np.arange(h)[None, None, :, None] * vel


def test_config_validation_and_json() -> None:
    for bad, field in (
        ({"history_steps": 2}, "history_steps"),
        ({"future_steps": 0}, "future_steps"),
        ({"d_model": 30, "num_heads": 4}, "num_heads"),
        ({"dropout": 1.5}, "dropout"),
        ({"num_layers": 1.0}, "num_layers"),
    ):
        with pytest.raises(ValueError, match=field):
            PredictorConfig(**bad)
    cfg = PredictorConfig(history_steps=20, future_steps=60)
    assert PredictorConfig.from_dict(json.loads(cfg.to_json())) == cfg
    with pytest.raises(ValueError, match="unknown"):
        PredictorConfig.from_dict({"bogus": 1})


def test_untrained_model_is_the_cv_baseline() -> None:
    model = TrajectoryTransformer(PredictorConfig(d_model=32, ff_dim=64)).eval()
    hist = _moving_histories(4, 9, 10)
    pos = torch.from_numpy(hist.astype(np.float32))
    mask = torch.ones(4, 9, 10, dtype=torch.bool)
    with torch.no_grad():
        out = model(pos, mask).numpy()
    np.testing.assert_allclose(out, constant_velocity(hist[:, 0], 10), atol=1e-4)


@pytest.mark.parametrize(("h", "f"), [(10, 10), (20, 60)])
def test_predict_neighbours_shapes_and_masked_never_nan(h: int, f: int) -> None:
    pred = _predictor(h, f)
    b, k = 16, 8
    hist = _moving_histories(b, k, h)
    mask = np.random.default_rng(1).random((b, k, h)) > 0.3
    mask[0] = False  # an observation with no neighbours at all
    mask[1, :, -1] = False  # nobody present now
    hist[~mask] = np.nan  # garbage behind the mask must not leak
    out = pred.predict_neighbours(hist, mask)
    assert out.shape == (b, k, f, 2) and out.dtype == np.float32
    assert np.isfinite(out).all()
    assert np.all(out[~mask[:, :, -1]] == 0.0)
    assert np.isfinite(
        pred.predict_neighbours(hist, mask, ego_history=_moving_histories(b, 1, h)[:, 0])
    ).all()


def test_predict_neighbours_is_frame_equivariant() -> None:
    pred = _predictor()
    hist = _moving_histories(8, 8, 10, seed=2)
    mask = np.ones((8, 8, 10), dtype=bool)
    mask[:, 5:, :3] = False
    out = pred.predict_neighbours(hist, mask)
    origin, heading = np.array([12.0, -3.0]), np.array(0.7)
    moved = to_frame(hist.reshape(-1, 10, 2), origin, heading).reshape(hist.shape)
    out_moved = pred.predict_neighbours(moved, mask)
    back = from_frame(out_moved.reshape(-1, 10, 2).astype(np.float64), origin, heading).reshape(out.shape)
    np.testing.assert_allclose(back, out, atol=2e-3)


def test_predict_neighbours_matches_corpus_windows() -> None:
    """The policy-time path and the corpus path see the same tokens and give the same prediction."""
    pred = _predictor()
    corpus = Corpus.from_tracks(synthetic_tracks(seed=5, num_vehicles=12, num_steps=60), WindowOptions())
    batch = corpus.gather()
    full = batch.neighbour_mask.all(axis=(1, 2))
    assert full.sum() > 10
    sel = np.flatnonzero(full)[:32]
    expected = pred.predict_windows(batch._replace(**{k: v[sel] for k, v in batch._asdict().items()}))
    # Observation frame: an arbitrary rigid transform of each window's agent frame.
    origin, heading = np.array([3.0, 1.0]), np.array(-0.4)
    agent = batch.history[sel].astype(np.float64)
    nbs = batch.neighbours[sel].astype(np.float64)
    hist = np.concatenate((agent[:, None], nbs[:, :7]), axis=1)  # slot 0: the agent
    obs = to_frame(hist.reshape(len(sel), -1, 2), origin, heading).reshape(hist.shape)
    ego = to_frame(nbs[:, 7], origin, heading)  # the 8th neighbour plays the ego
    out = pred.predict_neighbours(obs, np.ones(hist.shape[:3], dtype=bool), ego_history=ego)
    got = from_frame(out[:, 0].astype(np.float64), origin, heading)
    np.testing.assert_allclose(got, expected, atol=2e-3)


def test_forward_ignores_garbage_behind_the_mask() -> None:
    model = _predictor().model
    pos = torch.from_numpy(_moving_histories(3, 9, 10).astype(np.float32))
    mask = torch.ones(3, 9, 10, dtype=torch.bool)
    mask[:, 4:, :5] = False
    clean = pos.clone()
    clean[~mask] = 0.0
    dirty = pos.clone()
    dirty[~mask] = float("nan")
    with torch.no_grad():
        torch.testing.assert_close(model(dirty, mask), model(clean, mask))


def _window_tokens(h: int = 10, f: int = 10) -> tuple[torch.Tensor, torch.Tensor]:
    corpus = Corpus.from_tracks(synthetic_tracks(episode="c", seed=7, num_vehicles=8, num_steps=80),
                                WindowOptions(history_steps=h, future_steps=f, stride=3))  # fmt: skip
    pos, mask = corpus.gather().tokens()
    return torch.from_numpy(pos), torch.from_numpy(mask)


def test_correction_config_and_stored_configs_without_it() -> None:
    with pytest.raises(ValueError, match="correction must be one of"):
        PredictorConfig(correction="clipped")
    with pytest.raises(ValueError, match="correction_accel_mps2"):
        PredictorConfig(correction_accel_mps2=0.0)
    # A config stored before the choice existed is the plain residual, whatever today's default is.
    old = {k: v for k, v in PredictorConfig().to_dict().items() if not k.startswith(("correction", "dt_s"))}
    assert PredictorConfig.from_dict(old).correction == "plain"
    stored = {k: v for k, v in old.items() if k != "velocity_window"}  # nor the fitted velocity: the last step's
    assert PredictorConfig.from_dict(stored).velocity_window == 1 and PredictorConfig().velocity_window == 10
    with pytest.raises(ValueError, match="velocity_window"):
        PredictorConfig(velocity_window=0)
    assert PredictorConfig.from_dict({**old, "correction": "gated"}).correction == "gated"
    cfg = PredictorConfig(future_steps=60, correction="bounded")
    bound = cfg.correction_bound_m()
    assert len(bound) == 60 and bound[-1] == pytest.approx(1.0 * 3.0 + 0.5 * 3.0 * 9.0)
    assert all(b1 < b2 for b1, b2 in itertools.pairwise(bound))


def test_plain_model_keeps_the_checkpoint_layout() -> None:
    plain = TrajectoryTransformer(PredictorConfig(correction="plain"))
    gated = TrajectoryTransformer(PredictorConfig(correction="bounded-gated"))
    assert not any(k.startswith("gate") for k in plain.state_dict())
    assert set(gated.state_dict()) - set(plain.state_dict()) == {"gate.weight", "gate.bias", "familiar_limit"}


def test_a_checkpoint_from_before_the_choices_loads_as_the_plain_one_step_model(tmp_path: Path) -> None:
    """A checkpoint whose stored config predates the correction and velocity-window fields (the zoo's first
    predictor was one) loads as the plain residual over one-step constant velocity, and computes what the
    same weights compute in a model built with that config explicitly."""
    torch.manual_seed(0)
    old_style = TrajectoryTransformer(PredictorConfig(d_model=32, ff_dim=64, correction="plain", velocity_window=1))
    torch.nn.init.normal_(old_style.head[-1].weight, std=0.3)
    path = save_model(old_style, tmp_path / "old.pt")
    payload = torch.load(path, weights_only=True)
    config = json.loads(payload["config"])
    for name in ("correction", "correction_speed_mps", "correction_accel_mps2", "dt_s", "velocity_window"):
        del config[name]
    payload["config"] = json.dumps(config)
    torch.save(payload, path)
    model, _ = load_model(path)
    assert model.config.correction == "plain" and model.gate is None and model.config.velocity_window == 1
    twin = TrajectoryTransformer(model.config)
    twin.load_state_dict(model.state_dict())
    twin.eval()
    model.eval()
    pos, mask = _window_tokens()
    with torch.no_grad():
        assert torch.equal(model(pos, mask), twin(pos, mask))
        assert torch.equal(model(pos, mask), old_style.eval()(pos, mask))


def test_a_checkpoint_tensor_of_another_dtype_is_refused_not_cast(tmp_path: Path) -> None:
    path = save_model(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1)), tmp_path / "p.pt")
    payload = torch.load(path, weights_only=True)
    name = next(iter(payload["state_dict"]))
    payload["state_dict"][name] = payload["state_dict"][name].to(torch.int32)
    torch.save(payload, path)
    with pytest.raises(ValueError, match=rf"tensor {name} is stored as torch.int32, the network holds torch.float32"):
        load_model(path)


def test_bounded_correction_stays_within_its_bound() -> None:
    torch.manual_seed(0)
    cfg = PredictorConfig(d_model=32, ff_dim=64, correction="bounded")
    model = TrajectoryTransformer(cfg).eval()
    torch.nn.init.constant_(model.head[-1].bias, 1e4)  # a wild correction
    pos, mask = _window_tokens()
    with torch.no_grad():
        pred = model(pos, mask)
    cv = torch.from_numpy(constant_velocity_fit(pos[:, 0].double().numpy(), cfg.future_steps,
                                              window=cfg.velocity_window)).float()  # the base
    bound = torch.tensor(cfg.correction_bound_m()).view(1, -1, 1)
    dev = (pred - cv).abs()
    assert (dev <= bound * (1 + 1e-5)).all() and (dev >= bound * 0.99).all()  # saturated, not beyond


@pytest.mark.parametrize("correction", ["gated", "bounded-gated"])
def test_gate_moves_between_cv_and_the_full_correction(correction: str) -> None:
    torch.manual_seed(0)
    cfg = PredictorConfig(d_model=32, ff_dim=64, correction=correction)
    model = TrajectoryTransformer(cfg).eval()
    torch.nn.init.normal_(model.head[-1].weight, std=0.3)
    pos, mask = _window_tokens()
    cv = torch.from_numpy(constant_velocity_fit(pos[:, 0].double().numpy(), cfg.future_steps,
                                              window=cfg.velocity_window)).float()  # the base
    ungated = TrajectoryTransformer(dataclasses.replace(cfg, correction=correction.replace("gated", "plain")
                                                        .replace("bounded-plain", "bounded"))).eval()  # fmt: skip
    ungated.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith(("gate", "familiar"))})
    with torch.no_grad():
        _pred, gate = model.predict_with_gate(pos, mask)
        assert gate is not None and gate.shape == (len(pos), cfg.future_steps)
        assert torch.allclose(gate, torch.full_like(gate, 0.5))  # starts half open
        torch.nn.init.constant_(model.gate.bias, -40.0)
        torch.testing.assert_close(model(pos, mask), cv, atol=1e-5, rtol=0)  # closed: constant velocity
        torch.nn.init.constant_(model.gate.bias, 40.0)
        torch.testing.assert_close(model(pos, mask), ungated(pos, mask))  # open: the full correction


def test_gate_closes_on_motion_unlike_the_training_windows() -> None:
    """Familiarity: fitted on smooth synthetic traffic, the gate stays open on more of it and falls back
    to constant velocity where centimetre jitter makes the accelerations unlike anything seen."""
    torch.manual_seed(0)
    cfg = PredictorConfig(d_model=32, ff_dim=64, correction="gated")
    model = TrajectoryTransformer(cfg).eval()
    torch.nn.init.normal_(model.head[-1].weight, std=0.3)
    pos, mask = _window_tokens()
    corpus = Corpus.from_tracks(synthetic_tracks(episode="c", seed=7, num_vehicles=8, num_steps=80),
                                WindowOptions(stride=3))  # fmt: skip
    model.fit_normalisation(pos, mask, torch.from_numpy(corpus.gather().future))
    assert torch.isfinite(model.familiar_limit)
    familiar = model.familiarity(pos, mask)
    assert (familiar == 1.0).float().mean() > 0.99
    noisy = pos + 0.01 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(1))
    assert model.familiarity(noisy, mask).max() == 0.0
    with torch.no_grad():
        pred = model(noisy, mask)
    cv = torch.from_numpy(constant_velocity_fit(noisy[:, 0].double().numpy(), cfg.future_steps,
                                              window=cfg.velocity_window)).float()  # the base
    torch.testing.assert_close(pred, cv, atol=1e-5, rtol=0)


# -- crafted predictor files: sizes and types checked before a weight is allocated -------------------------------
@pytest.mark.parametrize(("fields", "message"), [
    ({"ff_dim": 10**10}, "ff_dim must be at most"),
    ({"d_model": 10**6, "num_heads": 1}, "d_model must be at most"),
    ({"num_layers": 10**9}, "num_layers must be at most"),
    ({"history_steps": 10**9}, "history_steps must be at most"),
    ({"num_layers": [2]}, "num_layers must be an int"),
    ({"dropout": "none"}, "dropout"),
    ({"correction": ["plain"]}, "correction must be one of"),
    ({"dt_s": 1e308}, "dt_s must be at most"),
    ({"d_model": 4096, "ff_dim": 16384, "num_layers": 64, "num_heads": 64}, "weights, more than"),
])
def test_absurd_predictor_configs_are_refused_before_building(fields: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PredictorConfig.from_dict({**PredictorConfig(d_model=16, ff_dim=32).to_dict(), **fields})


def _crafted(tmp_path: Path, name: str, change) -> Path:
    path = tmp_path / "good.pt"
    if not path.exists():
        torch.manual_seed(0)
        save_model(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1)), path)
    payload = torch.load(path, weights_only=True)
    change(payload)
    torch.save(payload, tmp_path / name)
    return tmp_path / name


def _config(**fields):
    def change(payload: dict) -> None:
        payload["config"] = json.dumps({**json.loads(payload["config"]), **fields})
    return change


@pytest.mark.parametrize(("change", "message"), [
    (_config(ff_dim=10**10), "ff_dim must be at most"),
    (_config(num_layers=[2]), "num_layers must be an int"),
    (_config(bogus=1), "unknown PredictorConfig fields"),
    (lambda p: p.__setitem__("config", "[" * 5000 + "]" * 5000), "nested too deeply"),
    (lambda p: p.__setitem__("config", json.dumps([1, 2])), "JSON object"),
    (lambda p: p.__setitem__("config", 5), "wrong type"),
    (lambda p: p.__setitem__("state_dict", [1, 2]), "wrong type"),
    (lambda p: p.__setitem__("extra", "[1]"), "not a JSON object"),
    (lambda p: p["state_dict"].__setitem__("head.0.weight", torch.zeros(3)), "do not match the stored config"),
])
def test_a_crafted_predictor_file_is_one_line(tmp_path: Path, change, message: str) -> None:
    path = _crafted(tmp_path, "bad.pt", change)
    with pytest.raises(ValueError, match=message) as exc:
        load_model(path)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)


def test_a_file_larger_than_any_predictor_is_not_read(tmp_path: Path) -> None:
    from lcmodels.predictor.checkpoint import MAX_FILE_BYTES

    path = tmp_path / "huge.pt"
    with open(path, "wb") as f:  # sparse: nothing is written to the disk
        f.truncate(MAX_FILE_BYTES + 1)
    with pytest.raises(ValueError, match="more than a predictor checkpoint can be"):
        load_model(path)


def test_the_parameter_estimate_is_close_to_the_network() -> None:
    for config in (PredictorConfig(), PredictorConfig(d_model=16, ff_dim=32, num_layers=1, correction="plain"),
                   PredictorConfig(d_model=128, ff_dim=512, num_layers=3, num_context_layers=1, history_steps=30)):
        built = sum(p.numel() for p in TrajectoryTransformer(config).parameters())
        assert built <= config.parameter_estimate() <= 1.2 * built


def test_lane_aware_base_config_and_an_untrained_model_is_the_lane_aware_extrapolation(tmp_path: Path) -> None:
    from lcmodels.predictor.baselines import lane_aware_velocity

    with pytest.raises(ValueError, match="base must be one of"):
        PredictorConfig(base="map")
    with pytest.raises(ValueError, match="lane_width_m"):
        PredictorConfig(base="lane-aware", lane_width_m=0.0)
    with pytest.raises(ValueError, match="lane_lateral_window"):
        PredictorConfig(base="lane-aware", lane_lateral_window=1)
    old = {k: v for k, v in PredictorConfig().to_dict().items() if k != "base" and not k.startswith("lane_")}
    assert PredictorConfig.from_dict(old).base == "constant-velocity"  # stored before the choice existed
    cfg = PredictorConfig(d_model=32, ff_dim=64, base="lane-aware")
    torch.manual_seed(0)
    model = TrajectoryTransformer(cfg).eval()
    pos, mask = _window_tokens()
    nb = torch.where(mask[:, 1:].unsqueeze(-1), pos[:, 1:], torch.zeros(()))
    lane = lane_aware_velocity(pos[:, 0].double().numpy(), nb.double().numpy(), mask[:, 1:].numpy(),
                               cfg.future_steps, window=cfg.velocity_window)  # fmt: skip
    fitted = constant_velocity_fit(pos[:, 0].double().numpy(), cfg.future_steps, window=cfg.velocity_window)
    assert np.abs(lane - fitted).max() > 1e-3  # the two bases differ on these windows
    with torch.no_grad():
        np.testing.assert_allclose(model(pos, mask).numpy(), lane, atol=1e-4)  # the head starts at zero
        future = torch.from_numpy(lane).float() + 0.01
        model.fit_normalisation(pos, mask, future)  # residuals over the lane-aware base
        np.testing.assert_allclose(model.residual_mean.numpy(), 0.01, atol=1e-4)
    path = save_model(model, tmp_path / "lane.pt")
    loaded, _ = load_model(path)
    assert loaded.config.base == "lane-aware"
    with torch.no_grad():
        torch.testing.assert_close(loaded(pos, mask), model(pos, mask))
