"""Per-lane sorted-order neighbour search, O(E * L * N) after one sort per environment.

Vehicles are sorted by ``x`` once per step. A vehicle is a *member* of every lane its body overlaps
(its lateral extent accounts for its yaw) and, while a traffic vehicle changes lanes, of its target
lane. For every lane and sorted position, the next member ahead (and, on demand, the previous member
behind) comes from one cumulative min (max) scan, so leaders, followers and side gaps for all vehicles
cost a handful of array operations and no all-pairs work.
"""

from __future__ import annotations

import numpy as np


class LaneIndex:
    """Neighbour structure of one simulation step for E environments.

    Attributes:
        order: ``(E, N)`` vehicle index at each sorted position (ascending x).
        member: ``(E, L, N)`` lane membership in sorted order.
        ahead: ``(E, L, N)`` sorted position of the next member of lane l strictly ahead of position
            p, or N when none.
        lead: ``(E, N)`` each vehicle's leader (nearest vehicle ahead in any lane it belongs to), -1.
        gap: ``(E, N)`` bumper-to-bumper gap to the leader along x (m), inf when none.
        lead_speed: ``(E, N)`` leader speed (m/s), 0 when none.
    """

    __slots__ = ("_behind", "ahead", "gap", "lead", "lead_speed", "member", "order", "rows")

    def __init__(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, speed: np.ndarray, length: np.ndarray,
                 width: np.ndarray, extra_lane: np.ndarray, lane_width: float, num_lanes: int,
                 rows: np.ndarray, margin: float = 0.1) -> None:
        e, n = x.shape
        self.rows = rows
        self.order = order = np.argsort(x, axis=1, kind="stable")
        xs, ys = x[rows, order], y[rows, order]
        ls, ws, ss = length[rows, order], width[rows, order], speed[rows, order]
        sy = np.abs(np.sin(yaw[rows, order]))
        half_lat = 0.5 * (sy * ls + np.sqrt(1.0 - sy * sy) * ws) + margin  # lateral half extent of the body
        inv = 1.0 / lane_width
        lo = np.floor((ys - half_lat) * inv)[:, None, :]
        hi = np.floor((ys + half_lat) * inv)[:, None, :]
        lanes = np.arange(num_lanes, dtype=np.float64)[None, :, None]
        member = (lanes >= lo) & (lanes <= hi)
        member |= lanes == extra_lane[rows, order][:, None, :]
        self.member = member
        pos = np.arange(n)
        ahead = np.empty((e, num_lanes, n), dtype=np.int64)
        ahead[..., -1] = n
        ahead[..., :-1] = np.minimum.accumulate(np.where(member, pos, n)[..., :0:-1], axis=-1)[..., ::-1]
        self.ahead = ahead
        self._behind: np.ndarray | None = None
        lead_pos = np.where(member, ahead, n).min(axis=1)  # (E, N) sorted position of the leader
        # Leader fields gathered from sorted arrays padded with a "no vehicle" column at position N.
        pad = lambda a, v: np.concatenate([a, np.full((e, 1), v, dtype=a.dtype)], axis=1)  # noqa: E731
        lead_s = pad(order, -1)[rows, lead_pos]
        gap_s = pad(xs, np.inf)[rows, lead_pos] - xs - 0.5 * (ls + pad(ls, 0.0)[rows, lead_pos])
        lv_s = pad(ss, 0.0)[rows, lead_pos]
        self.lead = np.empty_like(lead_s)
        self.gap = np.empty_like(gap_s)
        self.lead_speed = np.empty_like(lv_s)
        self.lead[rows, order] = lead_s
        self.gap[rows, order] = gap_s
        self.lead_speed[rows, order] = lv_s

    @property
    def behind(self) -> np.ndarray:
        """``(E, L, N)`` sorted position of the previous member of lane l strictly behind p, or -1."""
        if self._behind is None:
            n = self.order.shape[1]
            idx = np.where(self.member, np.arange(n), -1)
            behind = np.empty_like(idx)
            behind[..., 0] = -1
            behind[..., 1:] = np.maximum.accumulate(idx, axis=-1)[..., :-1]
            self._behind = behind
        return self._behind

    def neighbour_in_lane(self, lane: np.ndarray, ahead: bool) -> np.ndarray:
        """``(E, N)`` nearest vehicle ahead of (or behind) each vehicle in lane ``lane`` (E, N); -1.

        ``lane`` may hold lanes that do not exist (< 0 or >= L); those give -1.
        """
        rows, order = self.rows, self.order
        _e, num_lanes, n = self.member.shape
        valid = (lane >= 0) & (lane < num_lanes)
        lane_s = np.clip(lane, 0, num_lanes - 1)[rows, order]
        table = self.ahead if ahead else self.behind
        pos = table[rows, lane_s, np.arange(n)[None, :]]
        found = (pos >= 0) & (pos < n)
        veh_s = np.where(found, order[rows, np.clip(pos, 0, n - 1)], -1)
        out = np.empty_like(veh_s)
        out[rows, order] = veh_s
        return np.where(valid, out, -1)


def gather(values: np.ndarray, idx: np.ndarray, rows: np.ndarray, fill: float) -> np.ndarray:
    """``values[e, idx[e, i]]`` with ``fill`` where idx < 0. Shapes (E, N) -> (E, N)."""
    return np.where(idx >= 0, values[rows, np.maximum(idx, 0)], fill)
