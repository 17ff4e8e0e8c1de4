"""Kinematic baselines from backward differences of the history (no future data).

Positions are ``(N, H, 2)`` with an optional ``(N, H)`` validity mask; predictions are ``(N, F, 2)``
in the same frame. Velocities are per step (metres per step), so no ``dt`` is needed.
"""

from __future__ import annotations

import numpy as np

__all__ = ["constant_acceleration", "constant_velocity", "constant_velocity_fit", "last_velocity"]


def last_velocity(history: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Backward-difference velocity at the last step, metres per step.

    Uses the most recent earlier valid position ``j``: ``(p[H-1] - p[j]) / (H-1-j)``; zero when the
    last position or every earlier one is invalid.

    Args:
        history: ``(N, H, 2)``.
        mask: ``(N, H)`` bool or None (all valid).

    Returns:
        ``(N, 2)``.
    """
    history = np.asarray(history, dtype=np.float64)
    h = history.shape[-2]
    if mask is None:
        return history[..., -1, :] - history[..., -2, :]
    mask = np.asarray(mask, dtype=bool)
    earlier = mask[..., :-1][..., ::-1]  # reversed: index 0 is step H-2
    back = np.argmax(earlier, axis=-1) + 1  # steps between the last point and the chosen one
    ok = earlier.any(axis=-1) & mask[..., -1]
    j = h - 1 - back
    pj = np.take_along_axis(history, j[..., None, None].repeat(2, axis=-1), axis=-2)[..., 0, :]
    v = (history[..., -1, :] - pj) / back[..., None]
    return np.where(ok[..., None], v, 0.0)


def constant_velocity(history: np.ndarray, future_steps: int, mask: np.ndarray | None = None) -> np.ndarray:
    """Constant-velocity extrapolation ``p[H-1] + k v``, ``k = 1..F``.

    Args:
        history: ``(N, H, 2)``.
        future_steps: F.
        mask: ``(N, H)`` bool or None.

    Returns:
        ``(N, F, 2)``.
    """
    history = np.asarray(history, dtype=np.float64)
    v = last_velocity(history, mask)
    k = np.arange(1, future_steps + 1, dtype=np.float64)[:, None]
    return history[..., -1:, :] + k * v[..., None, :]


def constant_acceleration(
    history: np.ndarray, future_steps: int, mask: np.ndarray | None = None
) -> np.ndarray:
    """Constant-acceleration extrapolation from the last three positions.

    With backward differences ``v = p[H-1] - p[H-2]`` and ``a = p[H-1] - 2 p[H-2] + p[H-3]``, the
    prediction ``p[H-1] + k v + a k (k + 1) / 2`` is exact for motion with constant acceleration.
    Falls back to constant velocity where the last three positions are not all valid or ``H < 3``.

    Args:
        history: ``(N, H, 2)``.
        future_steps: F.
        mask: ``(N, H)`` bool or None.

    Returns:
        ``(N, F, 2)``.
    """
    history = np.asarray(history, dtype=np.float64)
    cv = constant_velocity(history, future_steps, mask)
    if history.shape[-2] < 3:
        return cv
    a = history[..., -1, :] - 2 * history[..., -2, :] + history[..., -3, :]
    if mask is not None:
        ok = np.asarray(mask, dtype=bool)[..., -3:].all(axis=-1)
        a = np.where(ok[..., None], a, 0.0)
    k = np.arange(1, future_steps + 1, dtype=np.float64)[:, None]
    return cv + (k * (k + 1) / 2) * a[..., None, :]


def constant_velocity_fit(history: np.ndarray, future_steps: int, mask: np.ndarray | None = None,
                          window: int = 10) -> np.ndarray:
    """Constant velocity from the last position with the least-squares velocity of the last ``window`` steps.

    Robust to positions measured with noise, where a one-step difference jitters; the one-step velocity
    where fewer than 3 of those steps are valid, zero velocity where the last one is not.

    Args:
        history: ``(N, H, 2)``.
        future_steps: F.
        mask: ``(N, H)`` bool or None.
        window: W, 1 <= W <= H (1: :func:`constant_velocity`).

    Returns:
        ``(N, F, 2)``.
    """
    history = np.asarray(history, dtype=np.float64)
    h = history.shape[-2]
    if not 1 <= window <= h:
        raise ValueError(f"window must be in [1, {h}], got {window}")
    m = np.ones(history.shape[:-1], dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    v = last_velocity(history, mask)
    if window > 1:
        w = m[:, -window:, None].astype(np.float64)
        t = np.arange(window, dtype=np.float64)[None, :, None]
        cnt = w.sum(axis=1, keepdims=True)
        t_mean = (w * t).sum(axis=1, keepdims=True) / np.maximum(cnt, 1.0)
        p = history[:, -window:]
        p_mean = (w * p).sum(axis=1, keepdims=True) / np.maximum(cnt, 1.0)
        dt = (t - t_mean) * w
        slope = (dt * (p - p_mean)).sum(axis=1) / np.maximum((dt * (t - t_mean)).sum(axis=1), 1e-12)
        fit = (cnt[:, 0] >= 3) & m[:, -1:]
        v = np.where(fit, slope, v)
    k = np.arange(1, future_steps + 1, dtype=np.float64)[:, None]
    return history[..., -1:, :] + k * v[..., None, :]
