"""Small deterministic multi-lane traffic for tests and benchmarks (not the project simulator).

Vehicles follow their leader with IDM on a straight road, and change lanes (a smooth cosine lateral
move) when a slower leader blocks them and the side lane has room. The output is a long-form tracks
DataFrame with the columns of docs/INTERFACES.md, so the corpus and predictor code can be developed
and tested without ``lcsim``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = ["synthetic_tracks"]


def synthetic_tracks(
    *,
    episode: str = "ep0",
    seed: int = 0,
    num_vehicles: int = 12,
    num_steps: int = 400,
    num_lanes: int = 3,
    dt_s: float = 0.05,
    lane_width_m: float = 3.5,
    mean_speed_mps: float = 6.7,
    lane_change_time_s: float = 2.0,
    lane_changes: bool = True,
) -> pd.DataFrame:
    """Simulate ``num_vehicles`` cars for ``num_steps`` steps; vehicle 0 is the ego.

    Returns:
        Long-form DataFrame, ``num_vehicles * num_steps`` rows, columns ``episode, step, t,
        vehicle_id, x, y, yaw, speed, accel, lane, target_lane, length, width, is_ego``.
    """
    rng = np.random.default_rng(seed)
    n = num_vehicles
    lane = rng.integers(0, num_lanes, n)
    x = np.zeros(n)
    for k in range(num_lanes):  # spread vehicles along each lane with gaps of 12-30 m
        idx = np.flatnonzero(lane == k)
        x[idx] = np.cumsum(rng.uniform(12.0, 30.0, len(idx)))
    desired = mean_speed_mps * rng.uniform(0.8, 1.25, n)
    speed = desired * rng.uniform(0.85, 1.0, n)
    length = np.full(n, 4.5)
    width = np.full(n, 1.9)
    target = lane.copy()
    lc_progress = np.full(n, -1.0)  # -1: no change; else fraction of the manoeuvre done
    lc_from = lane.astype(float)
    y = (lane + 0.5) * lane_width_m
    cooldown = rng.uniform(0, 5.0, n)

    rows_x, rows_y, rows_v, rows_a, rows_l, rows_tl, rows_yaw = [], [], [], [], [], [], []
    prev_y = y.copy()
    for _ in range(num_steps):
        # Leader per vehicle in its current lane (and target lane while changing).
        occ = np.where(lc_progress >= 0, target, lane)
        gap = np.full(n, np.inf)
        lead_v = speed.copy()
        dx = x[None, :] - x[:, None]  # (n, n): j ahead of i when > 0
        same = (occ[None, :] == occ[:, None]) | (lane[None, :] == occ[:, None])
        cand = same & (dx > 0)
        np.fill_diagonal(cand, False)
        dmask = np.where(cand, dx, np.inf)
        j = np.argmin(dmask, axis=1)
        has = np.isfinite(dmask[np.arange(n), j])
        gap[has] = dmask[np.arange(n), j][has] - length[j][has]
        lead_v[has] = speed[j][has]
        # IDM
        s0, th, a_max, b = 2.0, 1.5, 1.5, 2.0
        s_star = s0 + speed * th + speed * (speed - lead_v) / (2 * np.sqrt(a_max * b))
        acc = a_max * (1 - (speed / desired) ** 4 - (np.maximum(s_star, 0) / np.maximum(gap, 0.1)) ** 2)
        acc = np.clip(acc, -6.0, a_max)
        # Lane-change decisions
        cooldown -= dt_s
        if lane_changes:
            want = (lc_progress < 0) & (cooldown <= 0) & (gap < 25.0) & (lead_v < desired - 0.5)
            for i in np.flatnonzero(want):
                for side in (1, -1) if rng.random() < 0.5 else (-1, 1):
                    tl = lane[i] + side
                    if not 0 <= tl < num_lanes:
                        continue
                    others = (lane == tl) | (target == tl)
                    others[i] = False
                    if np.all(np.abs(x[others] - x[i]) > 15.0):
                        target[i] = tl
                        lc_progress[i] = 0.0
                        lc_from[i] = lane[i]
                        cooldown[i] = 8.0
                        break
        speed = np.maximum(speed + acc * dt_s, 0.0)
        x = x + speed * dt_s
        moving = lc_progress >= 0
        lc_progress[moving] += dt_s / lane_change_time_s
        frac = np.clip(lc_progress, 0, 1)
        shape = 0.5 - 0.5 * np.cos(np.pi * frac)
        y = np.where(
            moving, (lc_from + (target - lc_from) * shape + 0.5) * lane_width_m, (lane + 0.5) * lane_width_m
        )
        lane = np.where(moving & (frac >= 0.5), target, lane)
        done = moving & (lc_progress >= 1.0)
        lc_progress[done] = -1.0
        yaw = np.arctan2((y - prev_y) / dt_s, np.maximum(speed, 1e-6))
        prev_y = y.copy()
        rows_x.append(x.copy())
        rows_y.append(y.copy())
        rows_v.append(speed.copy())
        rows_a.append(acc.copy())
        rows_l.append(lane.copy())
        rows_tl.append(target.copy())
        rows_yaw.append(yaw)

    steps = np.repeat(np.arange(num_steps), n)
    return pd.DataFrame(
        {
            "episode": episode,
            "step": steps.astype(np.int64),
            "t": steps * dt_s,
            "vehicle_id": np.tile(np.arange(n), num_steps).astype(np.int64),
            "x": np.concatenate(rows_x),
            "y": np.concatenate(rows_y),
            "yaw": np.concatenate(rows_yaw),
            "speed": np.concatenate(rows_v),
            "accel": np.concatenate(rows_a),
            "lane": np.concatenate(rows_l).astype(np.int64),
            "target_lane": np.concatenate(rows_tl).astype(np.int64),
            "length": np.tile(length, num_steps),
            "width": np.tile(width, num_steps),
            "is_ego": np.tile(np.arange(n) == 0, num_steps),
        }
    )
