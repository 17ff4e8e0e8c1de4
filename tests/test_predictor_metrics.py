"""Metric functions on hand-made cases; baselines exact on their own motion models."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lcmodels.predictor.baselines import (
    constant_acceleration,
    constant_velocity,
    constant_velocity_fit,
    lane_aware_velocity,
    last_velocity,
)
from lcmodels.predictor.metrics import (
    ade,
    at_horizon,
    displacement_errors,
    error_curve,
    fde,
    horizons,
    miss_rate,
    summary,
)
from lcmodels.predictor.model import cv_extrapolate, lane_extrapolate


def test_metrics_hand_made() -> None:
    target = np.zeros((2, 3, 2))
    pred = np.zeros((2, 3, 2))
    pred[0, :, 0] = [3.0, 0.0, 0.0]  # errors 3, 0, 0
    pred[1, :, :] = [[0.0, 0.0], [3.0, 4.0], [6.0, 8.0]]  # errors 0, 5, 10
    np.testing.assert_allclose(displacement_errors(pred, target), [[3, 0, 0], [0, 5, 10]])
    assert ade(pred, target) == pytest.approx(18 / 6)
    assert fde(pred, target) == pytest.approx(5.0)
    np.testing.assert_allclose(error_curve(pred, target), [1.5, 2.5, 5.0])
    assert miss_rate(pred, target, 2.0) == pytest.approx(0.5)
    assert miss_rate(pred, target, 10.0) == 0.0  # strictly greater than the threshold
    s = summary(pred, target, miss_threshold_m=2.0)
    assert s["ade"] == pytest.approx(3.0) and s["curve"] == [1.5, 2.5, 5.0] and s["count"] == 2


def test_metric_input_checks() -> None:
    with pytest.raises(ValueError, match="N, F, 2"):
        ade(np.zeros((2, 3, 2)), np.zeros((2, 4, 2)))
    with pytest.raises(ValueError, match="threshold_m"):
        miss_rate(np.zeros((1, 1, 2)), np.zeros((1, 1, 2)), 0.0)


def test_metrics_at_horizons_hand_made() -> None:
    # Two trajectories, 60 steps at 20 Hz: errors grow by 0.1 m and 0.3 m per step along y.
    k = np.arange(1, 61, dtype=np.float64)
    target = np.zeros((2, 60, 2))
    pred = np.zeros((2, 60, 2))
    pred[0, :, 1] = 0.1 * k
    pred[1, :, 1] = 0.3 * k
    h = horizons(pred, target)
    assert list(h) == ["0.5s", "1s", "3s"]
    assert [h[key]["step"] for key in h] == [10, 20, 60]
    assert h["0.5s"]["fde"] == pytest.approx((1.0 + 3.0) / 2)
    assert h["0.5s"]["ade"] == pytest.approx(0.2 * 5.5)  # mean of 0.2 k over k = 1..10
    assert h["1s"]["rmse"] == pytest.approx(np.sqrt((2.0**2 + 6.0**2) / 2))
    assert h["3s"]["fde"] == pytest.approx(fde(pred, target)) and h["3s"]["ade"] == pytest.approx(
        ade(pred, target)
    )
    # RMSE weighs the larger error more: never below the FDE.
    assert all(h[key]["rmse"] >= h[key]["fde"] for key in h)
    # Only the horizons the future reaches; another step length moves the steps.
    assert list(horizons(pred[:, :10], target[:, :10])) == ["0.5s"]
    assert list(horizons(pred[:, :19], target[:, :19])) == ["0.5s"]
    assert horizons(pred, target, dt_s=0.1)["3s"]["step"] == 30
    assert summary(pred, target, miss_threshold_m=1.0)["horizons"] == h
    assert np.isnan(at_horizon(pred[:0], target[:0], 0.5)["fde"])


def test_horizon_input_checks() -> None:
    z = np.zeros((1, 20, 2))
    with pytest.raises(ValueError, match="beyond the 20 future steps"):
        at_horizon(z, z, 3.0)
    with pytest.raises(ValueError, match="whole number"):
        at_horizon(z, z, 0.52)
    with pytest.raises(ValueError, match="> 0"):
        at_horizon(z, z, 0.0)


def _track(h: int, f: int, v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(-h + 1, f + 1, dtype=np.float64)[:, None]
    p = np.array([5.0, -2.0]) + k * v + 0.5 * k**2 * a
    return p[None, :h], p[None, h:]


def test_constant_velocity_exact() -> None:
    hist, fut = _track(10, 60, np.array([0.33, 0.05]), np.zeros(2))
    np.testing.assert_allclose(constant_velocity(hist, 60), fut, atol=1e-12)
    np.testing.assert_allclose(constant_acceleration(hist, 60), fut, atol=1e-12)


def test_constant_acceleration_exact() -> None:
    hist, fut = _track(10, 20, np.array([0.3, -0.02]), np.array([0.004, 0.001]))
    np.testing.assert_allclose(constant_acceleration(hist, 20), fut, atol=1e-10)
    assert np.abs(constant_velocity(hist, 20) - fut).max() > 0.1  # CV is not exact here


def test_last_velocity_with_gaps_and_torch_twin() -> None:
    hist, _ = _track(6, 1, np.array([1.0, 0.5]), np.zeros(2))
    mask = np.array([[True, True, True, False, False, True]])
    np.testing.assert_allclose(last_velocity(hist, mask), [[1.0, 0.5]])
    np.testing.assert_allclose(last_velocity(hist, np.array([[False] * 5 + [True]])), [[0.0, 0.0]])
    rng = np.random.default_rng(0)
    h = rng.normal(size=(50, 8, 2))
    m = rng.random((50, 8)) > 0.4
    ours = cv_extrapolate(torch.from_numpy(h), torch.from_numpy(m), 5).numpy()
    np.testing.assert_allclose(ours, constant_velocity(h, 5, m), atol=1e-12)


def test_fitted_velocity_is_exact_on_straight_motion_robust_to_measurement_noise_and_has_a_torch_twin() -> None:
    hist, fut = _track(20, 60, np.array([0.33, 0.05]), np.zeros(2))
    np.testing.assert_allclose(constant_velocity_fit(hist, 60, window=10), fut, atol=1e-10)
    np.testing.assert_array_equal(constant_velocity_fit(hist, 60, window=1), constant_velocity(hist, 60))
    # positions rounded to the centimetre, as SUMO writes them: the one-step velocity jitters, the fit does not
    rng = np.random.default_rng(1)
    v = rng.uniform(5.0, 8.0, size=(200, 1)) * 0.05 * np.array([[1.0, 0.0]])  # 5-8 m/s along x, per step
    x0 = rng.uniform(0.0, 1.0, size=(200, 1, 2))
    steps = np.arange(80, dtype=np.float64)[None, :, None]
    track = x0 + steps * v[:, None, :]
    noisy = np.round(track * 100.0) / 100.0
    truth = track[:, 20:]
    err = {w: np.linalg.norm(constant_velocity_fit(noisy[:, :20], 60, window=w)[:, -1] - truth[:, -1], axis=-1).mean()
           for w in (1, 10)}
    assert err[10] < 0.3 * err[1], err
    with pytest.raises(ValueError, match="window"):
        constant_velocity_fit(hist, 5, window=21)
    # the torch twin, with gaps: where fewer than 3 of the window are valid, the one-step velocity
    h = rng.normal(size=(80, 12, 2))
    m = rng.random((80, 12)) > 0.4
    m[:5, :-1] = False  # the last step alone
    m[5:10, :-2] = False  # the last two steps
    for w in (1, 4, 10):
        ours = cv_extrapolate(torch.from_numpy(h), torch.from_numpy(m), 7, w).numpy()
        np.testing.assert_allclose(ours, constant_velocity_fit(h, 7, m, window=w), atol=1e-10)
    np.testing.assert_allclose(constant_velocity_fit(h, 7, m, window=10)[5:10], constant_velocity(h, 7, m)[5:10])


def _road_scene(lateral_step: float, phi: float = 0.15, neighbours: bool = True) -> tuple[np.ndarray, ...]:
    """An agent 1 m left of its lane's centre moving ``lateral_step`` m per step across a road of 3.5 m lanes
    whose direction is ``phi``, and four neighbours holding their lanes' centres: history (1, 20, 2), future
    (1, 60, 2) of the agent if it ends a lane change at the next centre, settling over the last 0.8 m (else
    holds its lateral position), neighbours (1, 4, 20, 2) and their mask, all in a frame rotated by ``phi`` from
    the road's."""
    k = np.arange(-19, 61, dtype=np.float64)
    along = 10.0 + 0.3 * k
    lateral = 1.0 + lateral_step * np.minimum(k, 0.0)  # the future holds the lateral position ...
    if abs(lateral_step) * 20 > 0.2:  # ... unless it is a lane change, which ends at the next centre
        distance, v = (2.5 if lateral_step > 0 else 1.0), abs(lateral_step)
        straight = np.minimum(v * k, distance - 0.8)
        settle = 0.8 * (1 - np.exp(-np.maximum(k - (distance - 0.8) / v, 0.0) * v / 0.8))
        lateral = np.where(k > 0, 1.0 + np.sign(lateral_step) * (straight + settle), lateral)
    c, s = np.cos(phi), np.sin(phi)

    def world(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.stack((c * a - s * b, s * a + c * b), -1)

    agent = world(along, lateral)
    hist = world(along[:20], 1.0 + lateral_step * k[:20])[None]
    lanes = np.array([0.0, 3.5, -3.5, 7.0])
    speeds = np.array([0.28, 0.31, 0.3, 0.33])
    nb = np.stack([world(-5.0 + 8.0 * i + speeds[i] * k[:20], np.full(20, lanes[i])) for i in range(4)])[None]
    mask = np.full((1, 4, 20), neighbours)
    return hist, agent[None, 20:], nb, mask


@pytest.mark.parametrize("lateral_step", [0.06, -0.06, 0.003])
def test_lane_aware_base_ends_a_lane_change_at_the_next_lane_centre_and_holds_the_lane_otherwise(
        lateral_step: float) -> None:  # fmt: skip
    hist, fut, nb, mask = _road_scene(lateral_step)
    pred = lane_aware_velocity(hist, nb, mask, 60)
    if abs(lateral_step) * 20 > 0.2:  # the fitted velocity alone would carry on across the road
        assert np.linalg.norm(constant_velocity_fit(hist, 60)[0, -1] - fut[0, -1]) > 1.0
        np.testing.assert_allclose(pred, fut, atol=1e-9)
    else:  # a slow drift (0.06 m/s) within the lane is not extrapolated: the lateral position is held
        np.testing.assert_allclose(pred, fut, atol=1e-9)
    # rotation and translation of the frame move the prediction with it
    rot = np.array([[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]])
    shift = np.array([3.0, -7.0])
    moved = lane_aware_velocity(hist @ rot.T + shift, nb @ rot.T + shift, mask, 60)
    np.testing.assert_allclose(moved, pred @ rot.T + shift, atol=1e-9)


def test_lane_aware_base_without_a_road_is_the_fitted_velocity_and_has_a_torch_twin() -> None:
    hist, _, nb, mask = _road_scene(0.06, neighbours=False)
    np.testing.assert_allclose(lane_aware_velocity(hist, nb, mask, 60), constant_velocity_fit(hist, 60), atol=1e-9)
    # along the road: a short window on a smooth track (no lag behind its acceleration), the long one on
    # positions rounded to the centimetre (the jitter a short one would read as speed)
    k = np.arange(-19, 11, dtype=np.float64)[:, None]
    track = (np.array([0.0, 1.0]) + k * np.array([0.3, 0.0]) + 0.5 * k**2 * np.array([0.0025, 0.0]))[None]  # 1 m/s²
    err = {w: np.abs(constant_velocity_fit(track[:, :20], 10, window=w)[0, -1, 0] - track[0, -1, 0]) for w in (3, 10)}
    assert err[3] + 0.05 < err[10]  # 0.5 s ahead: the long fit lags 4.5 steps of acceleration, the short one 1
    ours = lane_aware_velocity(track[:, :20], nb[:, :, :20], mask, 10)
    np.testing.assert_allclose(ours, constant_velocity_fit(track[:, :20], 10, window=3), atol=1e-9)
    rounded = np.round(track * 100) / 100
    np.testing.assert_allclose(lane_aware_velocity(rounded[:, :20], nb, mask, 10),
                               constant_velocity_fit(rounded[:, :20], 10, window=10), atol=1e-9)  # fmt: skip
    with pytest.raises(ValueError, match="lateral_window"):
        lane_aware_velocity(hist, nb, mask, 60, lateral_window=1)
    still = nb.copy()
    still[:] = still[:, :, -1:]  # parked neighbours give no direction
    np.testing.assert_allclose(lane_aware_velocity(hist, still, ~mask, 60), constant_velocity_fit(hist, 60))
    with pytest.raises(ValueError, match="window"):
        lane_aware_velocity(hist, nb, mask, 60, window=2)
    with pytest.raises(ValueError, match="neighbours must be"):
        lane_aware_velocity(hist, nb[:, :, :5], mask[:, :, :5], 60)
    # random scenes with gaps and garbage behind the mask: numpy and torch agree
    rng = np.random.default_rng(3)
    n, k, h = 300, 6, 12
    hist = np.cumsum(rng.normal([0.3, 0.0], [0.02, 0.03], size=(n, h, 2)), axis=1)
    nb = rng.normal(0.0, 6.0, size=(n, k, 1, 2)) + np.cumsum(rng.normal([0.3, 0.0], [0.02, 0.01], size=(n, k, h, 2)), axis=2)
    nmask = rng.random((n, k, h)) > 0.2
    nb = np.where(nmask[..., None], nb, np.nan)
    ours = lane_aware_velocity(hist, nb, nmask, 9, window=6)
    assert np.isfinite(ours).all()
    pos = torch.from_numpy(np.concatenate((hist[:, None], nb), 1))
    mask = torch.from_numpy(np.concatenate((np.ones((n, 1, h), dtype=bool), nmask), 1))
    np.testing.assert_allclose(lane_extrapolate(pos, mask, 9, 6).numpy(), ours, atol=1e-9)
    moved = (np.abs(ours - constant_velocity_fit(hist, 9, window=6)).max(axis=(1, 2)) > 1e-6).mean()
    assert 0.2 < moved < 1.0  # most scenes have a road; the lateral drift is held or a lane change ends


def test_an_analytic_predictor_is_its_lane_aware_base_and_loads_as_a_checkpoint(tmp_path) -> None:
    from lcmodels.predictor import Predictor, PredictorConfig, analytic_model, save_model

    config = PredictorConfig(d_model=16, num_heads=2, num_layers=1, ff_dim=32, base="lane-aware")
    rng = np.random.default_rng(5)
    n, k, h = 64, 8, config.history_steps
    agent = np.cumsum(rng.normal([0.3, 0.0], [0.02, 0.03], size=(n, 1, h, 2)), axis=2)
    nb = rng.normal(0.0, 6.0, size=(n, k, 1, 2)) + np.cumsum(rng.normal([0.3, 0.0], [0.02, 0.01], size=(n, k, h, 2)), axis=2)
    pos = torch.from_numpy(np.concatenate((agent, nb), 1)).float()
    mask = torch.from_numpy(rng.random((n, k + 1, h)) > 0.2)
    mask[:, 0] = True
    expected = lane_extrapolate(pos, mask, config.future_steps, config.velocity_window,
                                smooth_window=config.lane_smooth_window, smooth_jitter_m=config.lane_smooth_jitter_m,
                                lateral_window=config.lane_lateral_window, lane_width_m=config.lane_width_m,
                                margin_m=config.lane_margin_m, approach_m=config.lane_approach_m,
                                move_mps=config.lane_change_mps, still_mps=config.lane_hold_mps, dt_s=config.dt_s)  # fmt: skip
    loaded = Predictor.load(save_model(analytic_model(config), tmp_path / "predictor.pt"))
    with torch.no_grad():
        got = loaded.model(pos, mask)
    np.testing.assert_allclose(got.numpy(), expected.numpy(), atol=1e-5)
    assert not np.allclose(got.numpy(), cv_extrapolate(pos[:, 0], mask[:, 0], config.future_steps, 10).numpy())
    with pytest.raises(ValueError, match="analytic predictor needs base"):
        analytic_model(PredictorConfig())
