"""Trajectory metrics as pure numpy functions (metres in, metres out).

Shapes: ``pred`` and ``target`` are ``(N, F, 2)``: N trajectories, F future steps, (x, y).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ade", "displacement_errors", "error_curve", "fde", "miss_rate", "summary"]


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


def summary(
    pred: np.ndarray, target: np.ndarray, *, miss_threshold_m: float
) -> dict[str, float | list[float]]:
    """All metrics in one JSON-ready dict: ``ade, fde, curve (F floats), miss_rate, miss_threshold_m, count``."""
    err = displacement_errors(pred, target)
    return {
        "ade": float(err.mean()),
        "fde": float(err[:, -1].mean()),
        "curve": [float(v) for v in err.mean(axis=0)],
        "miss_rate": float((err[:, -1] > miss_threshold_m).mean()),
        "miss_threshold_m": float(miss_threshold_m),
        "count": int(err.shape[0]),
    }
