"""Trajectory metrics as pure numpy functions (metres in, metres out).

Shapes: ``pred`` and ``target`` are ``(N, F, 2)``: N trajectories, F future steps, (x, y).

Metrics at a horizon of ``t`` seconds (:func:`at_horizon`, step ``k = round(t / dt)``): ADE over steps
``1..k``, FDE (mean error at step ``k``) and RMSE at step ``k`` (root of the mean squared error at that
step, as trajectory-prediction papers on highway data report it). :data:`HORIZONS_S` are the horizons
reported next to every model: 0.5 s, 1 s and 3 s (steps 10, 20 and 60 at the corpus's 20 Hz), each where
the future is long enough.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "DT_S",
    "HORIZONS_S",
    "ade",
    "at_horizon",
    "displacement_errors",
    "error_curve",
    "fde",
    "horizon_label",
    "horizons",
    "miss_rate",
    "summary",
]

#: Step of the corpus, seconds (20 Hz).
DT_S = 0.05
#: Horizons reported next to every model, seconds.
HORIZONS_S: tuple[float, ...] = (0.5, 1.0, 3.0)


def displacement_errors(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Euclidean error per trajectory and step.

    Args:
        pred: ``(N, F, 2)``.
        target: ``(N, F, 2)``.

    Returns:
        ``(N, F)`` float64 distances.
    """
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape or pred.ndim != 3 or pred.shape[-1] != 2:
        raise ValueError(f"pred and target must both be (N, F, 2), got {pred.shape} and {target.shape}")
    return np.linalg.norm(pred - target, axis=-1)


def ade(pred: np.ndarray, target: np.ndarray) -> float:
    """Average displacement error: mean over N and F of the step errors. ``(N, F, 2)`` x2 -> scalar."""
    return float(displacement_errors(pred, target).mean())


def fde(pred: np.ndarray, target: np.ndarray) -> float:
    """Final displacement error: mean over N of the error at the last step. ``(N, F, 2)`` x2 -> scalar."""
    return float(displacement_errors(pred, target)[:, -1].mean())


def error_curve(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Mean error at each future step. ``(N, F, 2)`` x2 -> ``(F,)``."""
    return displacement_errors(pred, target).mean(axis=0)


def miss_rate(pred: np.ndarray, target: np.ndarray, threshold_m: float) -> float:
    """Fraction of trajectories whose final error exceeds ``threshold_m``. ``(N, F, 2)`` x2 -> scalar."""
    if threshold_m <= 0:
        raise ValueError(f"threshold_m must be > 0, got {threshold_m}")
    return float((displacement_errors(pred, target)[:, -1] > threshold_m).mean())


def horizon_label(seconds: float) -> str:
    """``0.5 -> "0.5s"``, ``1.0 -> "1s"``, ``3.0 -> "3s"``: the keys of :func:`horizons`."""
    return f"{seconds:g}s"


def _horizon_step(seconds: float, dt_s: float) -> int:
    if not (seconds > 0 and dt_s > 0):
        raise ValueError(f"horizon and dt_s must be > 0, got {seconds} and {dt_s}")
    step = round(seconds / dt_s)
    if step < 1 or abs(step * dt_s - seconds) > 1e-6 * max(1.0, seconds):
        raise ValueError(f"a horizon of {seconds} s is not a whole number of {dt_s} s steps")
    return step


def at_horizon(
    pred: np.ndarray, target: np.ndarray, seconds: float, *, dt_s: float = DT_S
) -> dict[str, float]:
    """ADE, FDE and RMSE at one horizon. ``(N, F, 2)`` x2 -> dict.

    Args:
        pred, target: ``(N, F, 2)``; step ``j`` (0-based) of the future is ``(j + 1) * dt_s`` ahead.
        seconds: the horizon; ``k = seconds / dt_s`` must be a whole number ``<= F``.
        dt_s: step of the data.

    Returns:
        ``{"step": k, "ade": mean error over steps 1..k, "fde": mean error at step k,
        "rmse": sqrt(mean squared error at step k)}``, metres (NaN for N = 0).

    Raises:
        ValueError: the horizon is not a whole number of steps or beyond the future.
    """
    err = displacement_errors(pred, target)
    k = _horizon_step(seconds, dt_s)
    if k > err.shape[1]:
        raise ValueError(f"a horizon of {seconds} s is step {k}, beyond the {err.shape[1]} future steps")
    if err.shape[0] == 0:
        return {"step": k, "ade": float("nan"), "fde": float("nan"), "rmse": float("nan")}
    last = err[:, k - 1]
    return {
        "step": k,
        "ade": float(err[:, :k].mean()),
        "fde": float(last.mean()),
        "rmse": float(np.sqrt(np.mean(last**2))),
    }


def horizons(
    pred: np.ndarray,
    target: np.ndarray,
    *,
    dt_s: float = DT_S,
    horizons_s: tuple[float, ...] = HORIZONS_S,
) -> dict[str, dict[str, float]]:
    """:func:`at_horizon` at each horizon the future reaches, keyed by :func:`horizon_label` (``"0.5s"``, ...).

    A horizon beyond the ``F`` future steps is left out (a 10-step future at 20 Hz has 0.5 s only).
    """
    f = displacement_errors(pred, target).shape[1]
    return {
        horizon_label(t): at_horizon(pred, target, t, dt_s=dt_s)
        for t in horizons_s
        if _horizon_step(t, dt_s) <= f
    }


def summary(
    pred: np.ndarray, target: np.ndarray, *, miss_threshold_m: float, dt_s: float = DT_S
) -> dict[str, Any]:
    """All metrics in one JSON-ready dict: ``ade, fde, curve (F floats), miss_rate, miss_threshold_m, count,
    horizons`` (:func:`horizons`: ADE/FDE/RMSE at 0.5 s, 1 s, 3 s where the future reaches)."""
    err = displacement_errors(pred, target)
    return {
        "ade": float(err.mean()),
        "fde": float(err[:, -1].mean()),
        "curve": [float(v) for v in err.mean(axis=0)],
        "miss_rate": float((err[:, -1] > miss_threshold_m).mean()),
        "miss_threshold_m": float(miss_threshold_m),
        "count": int(err.shape[0]),
        "horizons": horizons(pred, target, dt_s=dt_s),
    }
