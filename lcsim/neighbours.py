"""Per-lane sorted-order neighbour search, O(E * L * N) after one sort per environment.

Vehicles are sorted by ``x`` once per step. A vehicle is a *member* of every lane its body overlaps
(and, while a traffic vehicle changes lanes, of its target lane). For every lane and every sorted
position, the next member ahead and the previous member behind come from one cumulative min/max
scan, so leaders, followers and side gaps for all vehicles cost a handful of array operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(slots=True)
class LaneIndex:
    """Neighbour structure of one simulation step.

    Attributes:
        order: ``(E, N)`` vehicle index at each sorted position (ascending x).
        rank: ``(E, N)`` sorted position of each vehicle (inverse of ``order``).
        member: ``(E, L, N)`` lane membership in sorted order.
        ahead: ``(E, L, N)`` sorted position of the next member of lane l strictly ahead of
            position p, or N when none.
        behind: ``(E, L, N)`` sorted position of the previous member of lane l strictly behind p, or -1.
    """

    order: np.ndarray
    rank: np.ndarray
    member: np.ndarray
    ahead: np.ndarray
    behind: np.ndarray

    def vehicle_at(self, pos: np.ndarray) -> np.ndarray:
        """Vehicle index at sorted positions ``pos`` (E, ...); -1 where pos is out of range."""
        n = self.order.shape[1]
        valid = (pos >= 0) & (pos < n)
        flat = np.clip(pos, 0, n - 1).reshape(pos.shape[0], -1)
        out = np.take_along_axis(self.order, flat, axis=1).reshape(pos.shape)
        return np.where(valid, out, -1)


def lane_membership(y: np.ndarray, half_width: np.ndarray, lane_width: float, num_lanes: int,
                    extra_lane: np.ndarray | None = None, margin: float = 0.1) -> np.ndarray:
    """``(E, L, N)`` bool: lanes overlapped by each body, plus ``extra_lane`` (E, N; -1 for none)."""
    lo = np.floor((y - half_width - margin) / lane_width)
    hi = np.floor((y + half_width + margin) / lane_width)
    lanes = np.arange(num_lanes, dtype=np.float64)[None, :, None]
    member = (lanes >= lo[:, None, :]) & (lanes <= hi[:, None, :])
    if extra_lane is not None:
        member |= lanes == extra_lane[:, None, :]
    return member


def build_index(x: np.ndarray, y: np.ndarray, half_width: np.ndarray, lane_width: float, num_lanes: int,
                extra_lane: np.ndarray | None = None) -> LaneIndex:
    """Sort by x and build the per-lane ahead/behind tables for all E environments at once."""
    e, n = x.shape
    order = np.argsort(x, axis=1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.broadcast_to(np.arange(n), (e, n)), axis=1)
    ys = np.take_along_axis(y, order, axis=1)
    hw = np.take_along_axis(half_width, order, axis=1)
    extra = None if extra_lane is None else np.take_along_axis(extra_lane, order, axis=1)
    member = lane_membership(ys, hw, lane_width, num_lanes, extra)
    pos = np.arange(n)
    idx = np.where(member, pos, n)
    suffix_min = np.minimum.accumulate(idx[..., ::-1], axis=-1)[..., ::-1]
    ahead = np.full_like(idx, n)
    ahead[..., :-1] = suffix_min[..., 1:]
    idx = np.where(member, pos, -1)
    prefix_max = np.maximum.accumulate(idx, axis=-1)
    behind = np.full_like(idx, -1)
    behind[..., 1:] = prefix_max[..., :-1]
    return LaneIndex(order, rank, member, ahead, behind)


def leaders(index: LaneIndex) -> np.ndarray:
    """``(E, N)`` index of each vehicle's leader: the nearest vehicle ahead in any lane it belongs to; -1."""
    n = index.order.shape[1]
    lead_pos = np.where(index.member, index.ahead, n).min(axis=1)  # (E, N) by sorted position
    lead = index.vehicle_at(lead_pos)
    out = np.empty_like(lead)
    np.put_along_axis(out, index.order, lead, axis=1)
    return out


def neighbour_in_lane(index: LaneIndex, lane: np.ndarray, ahead: bool) -> np.ndarray:
    """``(E, N)`` index of the nearest vehicle ahead of (or behind) each vehicle in lane ``lane`` (E, N).

    ``lane`` may hold invalid lanes (< 0 or >= L); those give -1.
    """
    num_lanes = index.member.shape[1]
    valid = (lane >= 0) & (lane < num_lanes)
    lane_sorted = np.take_along_axis(np.clip(lane, 0, num_lanes - 1), index.order, axis=1)
    table = index.ahead if ahead else index.behind
    pos = np.take_along_axis(table, lane_sorted[:, None, :], axis=1)[:, 0, :]
    veh_sorted = index.vehicle_at(pos)
    out = np.empty_like(veh_sorted)
    np.put_along_axis(out, index.order, veh_sorted, axis=1)
    return np.where(valid, out, -1)


def gather(values: np.ndarray, idx: np.ndarray, fill: float) -> np.ndarray:
    """``values[e, idx[e, i]]`` with ``fill`` where idx < 0. Shapes (E, N) -> (E, N)."""
    out = np.take_along_axis(values, np.maximum(idx, 0), axis=1)
    return np.where(idx >= 0, out, fill)
