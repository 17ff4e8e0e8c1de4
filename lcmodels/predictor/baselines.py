"""Kinematic baselines from backward differences of the history (no future data).

Positions are ``(N, H, 2)`` with an optional ``(N, H)`` validity mask; predictions are ``(N, F, 2)``
in the same frame. Velocities are per step (metres per step), so no ``dt`` is needed.
"""

from __future__ import annotations

import numpy as np

__all__ = ["constant_acceleration", "constant_velocity", "constant_velocity_fit", "lane_aware_velocity", "last_velocity"]


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


def _fit_slope(p: np.ndarray, m: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares velocity ``(..., 2)`` of the valid positions among the last ``window`` of ``(..., H, 2)``,
    and whether it is known ``(...,)`` (at least 3 of them valid, the last one included)."""
    w = m[..., -window:, None].astype(np.float64)
    p = np.where(w > 0, p[..., -window:, :], 0.0)
    t = np.arange(window, dtype=np.float64)[:, None]
    cnt = w.sum(-2, keepdims=True)
    t_mean = (w * t).sum(-2, keepdims=True) / np.maximum(cnt, 1.0)
    p_mean = (w * p).sum(-2, keepdims=True) / np.maximum(cnt, 1.0)
    dt = (t - t_mean) * w
    slope = (dt * (p - p_mean)).sum(-2) / np.maximum((dt * (t - t_mean)).sum(-2), 1e-12)
    return slope, (cnt[..., 0, 0] >= 3) & m[..., -1]


def lane_aware_velocity(history: np.ndarray, neighbours: np.ndarray, neighbour_mask: np.ndarray, future_steps: int,
                        *, window: int = 10, smooth_window: int = 3, smooth_jitter_m: float = 0.001,
                        lateral_window: int = 2, lane_width_m: float = 3.5, margin_m: float = 0.1,
                        approach_m: float = 0.8, move_mps: float = 0.2, still_mps: float = 0.1,
                        dt_s: float = 0.05) -> np.ndarray:
    """Fitted speed along the road, a lane change that ends at the next lane centre, no drift across otherwise.

    The road and its lanes are read from the neighbours, not from a map: the road's direction is the median
    direction of the neighbours' velocities (fitted to ``window`` steps), and a lane centre's lateral offset is
    the circular mean, modulo ``lane_width_m``, of the lateral offsets of the neighbours that hold their lane
    (lateral speed below ``still_mps``). In that road frame:

    - along the road the agent keeps its fitted speed: fitted to ``window`` steps where its positions jitter
      (measured positions: rounding, a tracker's noise), to ``smooth_window`` steps where they do not (the mean
      absolute deviation of its second differences from their mean over ``window`` steps below
      ``smooth_jitter_m``), so that a smooth track's acceleration does not make the fit lag;
    - across it, the agent's lateral speed over the last ``lateral_window`` steps: above ``move_mps`` it is
      changing lanes and goes on at that speed towards the first lane centre more than ``margin_m`` ahead,
      slowing down exponentially over the last ``approach_m`` (at the speed it had), so that it settles there;
      otherwise it holds its lateral position.

    Where no neighbour gives the road (none moving and present at the last step, or none holding its lane)
    the agent keeps its fitted velocity (the window chosen as above) in both axes: :func:`constant_velocity_fit`
    for jittering positions.

    Args:
        history: ``(N, H, 2)`` agent positions (every step valid), the agent frame of ``lcdata.corpus``.
        neighbours: ``(N, K, H, 2)`` in the same frame.
        neighbour_mask: ``(N, K, H)`` bool presence.
        future_steps: F.
        window: steps the velocities are fitted to, ``3 <= window <= H``.
        smooth_window: the agent's along-road window for smooth tracks, ``2 <= smooth_window <= window``.
        smooth_jitter_m: the jitter below which a track is smooth, metres.
        lateral_window: steps the agent's lateral speed is fitted to, ``2 <= lateral_window <= window``.
        lane_width_m: the lanes' width, metres.
        margin_m: a lane centre nearer than this ahead is the one being left, not the target.
        approach_m: the last stretch to the target centre, covered with an exponentially falling speed, metres.
        move_mps: lateral speed above which the agent counts as changing lanes, m/s.
        still_mps: lateral speed below which a neighbour counts as holding its lane, m/s.
        dt_s: the step, seconds.

    Returns:
        ``(N, F, 2)``.
    """
    history = np.asarray(history, dtype=np.float64)
    neighbours = np.asarray(neighbours, dtype=np.float64)
    neighbour_mask = np.asarray(neighbour_mask, dtype=bool)
    n, h, _ = history.shape
    if not 3 <= window <= h:
        raise ValueError(f"window must be in [3, {h}], got {window}")
    for name, value in (("smooth_window", smooth_window), ("lateral_window", lateral_window)):
        if not 2 <= value <= window:
            raise ValueError(f"{name} must be in [2, window={window}], got {value}")
    if neighbours.shape[:1] + neighbours.shape[2:] != (n, h, 2) or neighbour_mask.shape != neighbours.shape[:-1]:
        raise ValueError(f"neighbours must be (N, K, H, 2) and their mask (N, K, H) with N={n}, H={h}; got "
                         f"{neighbours.shape} and {neighbour_mask.shape}")
    every = np.ones((n, h), dtype=bool)
    second = np.diff(history[:, -window:], 2, axis=1)  # (N, W-2, 2)
    smooth = np.abs(second - second.mean(1, keepdims=True)).sum(-1).mean(1) < smooth_jitter_m
    v_agent = np.where(smooth[:, None], _fit_slope(history, every, smooth_window)[0], _fit_slope(history, every, window)[0])
    v_lateral, _ = _fit_slope(history, every, lateral_window)
    v_n, ok = _fit_slope(neighbours, neighbour_mask, window)  # (N, K, 2)
    ok &= np.hypot(v_n[..., 0], v_n[..., 1]) > 0.5 * dt_s  # moving at least 0.5 m/s
    angle = np.sort(np.where(ok, np.arctan2(v_n[..., 1], v_n[..., 0]), np.inf), axis=1)
    count = ok.sum(1)
    middle = np.stack((np.maximum(count - 1, 0) // 2, count // 2), 1)  # the median's one or two angles
    theta = np.where(count > 0, np.take_along_axis(angle, np.minimum(middle, angle.shape[1] - 1), axis=1).mean(1), 0.0)
    c, s = np.cos(theta), np.sin(theta)

    def to_road(v: np.ndarray) -> np.ndarray:  # rotate by -theta; v (N, ..., 2)
        cc, ss = c.reshape((n,) + (1,) * (v.ndim - 2)), s.reshape((n,) + (1,) * (v.ndim - 2))
        return np.stack((cc * v[..., 0] + ss * v[..., 1], cc * v[..., 1] - ss * v[..., 0]), -1)

    lateral_n = to_road(np.where(neighbour_mask[..., -1:], neighbours[:, :, -1] - history[:, None, -1], 0.0))[..., 1]
    holding = ok & (np.abs(to_road(v_n)[..., 1]) < still_mps * dt_s)
    phase_angle = 2 * np.pi * lateral_n / lane_width_m
    phase = np.arctan2(np.where(holding, np.sin(phase_angle), 0.0).sum(1),
                       np.where(holding, np.cos(phase_angle), 0.0).sum(1)) * lane_width_m / (2 * np.pi)  # fmt: skip
    road = holding.any(1)
    vy = to_road(v_lateral)[:, 1]
    sign = np.sign(vy)
    speed = np.maximum(np.abs(vy), 1e-9)
    changing = np.abs(vy) > move_mps * dt_s
    steps = (sign * margin_m - phase) / lane_width_m
    distance = np.abs(phase + lane_width_m * np.where(sign > 0, np.ceil(steps), np.floor(steps)))  # to the target
    last = np.minimum(distance, approach_m)  # covered with a falling speed
    k = np.arange(1, future_steps + 1, dtype=np.float64)[None, :]
    straight = np.minimum(speed[:, None] * k, (distance - last)[:, None])
    settle = last[:, None] * -np.expm1(-np.maximum(k - ((distance - last) / speed)[:, None], 0.0) * (speed / np.maximum(last, 1e-9))[:, None])
    across = np.where(changing[:, None], sign[:, None] * (straight + settle), 0.0)
    along = to_road(v_agent)[:, :1] * k
    cc, ss = c[:, None], s[:, None]
    lane = np.stack((cc * along - ss * across, ss * along + cc * across), -1)
    fitted = v_agent[:, None, :] * k[..., None]
    return history[:, -1:, :] + np.where(road[:, None, None], lane, fitted)
