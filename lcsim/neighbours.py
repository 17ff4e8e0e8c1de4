"""Per-lane sorted-order neighbour search, O(E * L * N) after one sort per environment.

Vehicles are sorted by ``x`` once per step. A vehicle is a *member* of every lane its body overlaps
(its lateral extent accounts for its yaw) and, while a traffic vehicle changes lanes, of its target
lane. For every lane and sorted position, the nearest member ahead (and, on demand, behind) comes from
one running-max scan over the sorted positions, so leaders, followers and side gaps for all vehicles
cost a handful of array operations and no all-pairs work.

Speed notes (the index is rebuilt every simulation step): the sort re-uses the previous step's order
when it is still strictly increasing (vehicles rarely overtake within 50 ms) and re-sorts only the rows
where it is not; gathers and scatters use flat indices (``np.take`` / ``put`` on raveled arrays, about
twice as fast as 2-D fancy indexing); the lane tables are small integers in an ``(L, N, E)`` layout,
filled by multiplying the membership mask rather than by ``np.where`` (whose random mask defeats
branch prediction), and scanned by a log-step running max on large batches, where
``ufunc.accumulate`` is slow.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

_NO_POSITIONS = np.zeros(0, dtype=np.int64)

# Above this many table elements a log-step (Hillis-Steele) scan beats ``np.maximum.accumulate``.
_DOUBLING_SCAN_MIN = 4096
# From this many vehicles in all, the body extent is computed only where the yaw is not zero.
_SPARSE_YAW_MIN = 1024
# Below this many environments a fresh argsort is cheaper than checking the previous order.
_REUSE_ORDER_MIN_ENVS = 4


class _Consts:
    """Index arrays that depend only on (E, N, L)."""

    def __init__(self, e: int, n: int, num_lanes: int) -> None:
        self.dtype = np.int16 if 2 * n < np.iinfo(np.int16).max else np.int32  # (tables hold <= N; lookups add N)
        self.env = np.arange(e, dtype=np.int64)
        self.rn = self.env[:, None] * n  # row offsets into (E, N)
        self.pos = np.arange(n, dtype=np.int64)[:, None]
        # Ranks in (N, 1): the nearest member wins a running max.
        self.rank_ahead = (n - np.arange(n)).astype(self.dtype)[:, None]
        self.rank_behind = np.arange(1, n + 1).astype(self.dtype)[:, None]
        self.lanes = np.arange(num_lanes, dtype=np.float64)[:, None, None]
        self.sentinel = e * n  # flat index standing for "no vehicle"
        self.minus_plus = np.array([-1.0, 1.0])[:, None, None]
        self.half_offset = np.array([0, e * n])[:, None, None]  # flat offsets of the two halves of (2, E, N)


@lru_cache(maxsize=32)
def _consts(e: int, n: int, num_lanes: int) -> _Consts:
    return _Consts(e, n, num_lanes)


def _scan_max(w: np.ndarray, reverse: bool) -> None:
    """In-place inclusive running maximum along axis 1 of ``(L, N, E)`` (from the end when ``reverse``)."""
    if w.size < _DOUBLING_SCAN_MIN:
        v = w[:, ::-1] if reverse else w
        np.maximum.accumulate(v, axis=1, out=v)
        return
    n, s = w.shape[1], 1
    while s < n:
        if reverse:
            np.maximum(w[:, :-s], w[:, s:], out=w[:, :-s])
        else:
            np.maximum(w[:, s:], w[:, :-s], out=w[:, s:])
        s *= 2


def _half_lateral_extent(yaw: np.ndarray, length: np.ndarray, width: np.ndarray, margin: float) -> np.ndarray:
    """Half the lateral extent of each body plus ``margin``: ``0.5 (|sin| l + |cos| w) + margin``.

    On large batches the trigonometry is done only where the yaw is not zero (vehicles changing lanes
    and the ego); elsewhere the formula reduces exactly to ``0.5 w + margin``.
    """
    if yaw.size < _SPARSE_YAW_MIN:
        sy = np.abs(np.sin(yaw))
        return 0.5 * (sy * length + np.sqrt(1.0 - sy * sy) * width) + margin
    half = 0.5 * width + margin
    tilted = (yaw != 0.0).ravel().nonzero()[0]
    if tilted.size:
        sy = np.abs(np.sin(yaw.take(tilted)))
        half.put(tilted, 0.5 * (sy * length.take(tilted) + np.sqrt(1.0 - sy * sy) * width.take(tilted)) + margin)
    return half


def sorted_order(x: np.ndarray, previous: np.ndarray | None = None) -> np.ndarray:
    """``np.argsort(x, axis=1, kind="stable")``, cheaper when ``previous`` (a recent order) is given.

    Rows that ``previous`` still sorts strictly increasingly keep it (the stable order is then the
    unique one); the others, ties included, are sorted afresh. The result never depends on
    ``previous``, only the cost does.
    """
    e = x.shape[0]
    if previous is None or e < _REUSE_ORDER_MIN_ENVS or previous.shape != x.shape:
        return x.argsort(axis=1, kind="stable")  # (the method: less dispatch than np.argsort)
    xs = x.take(previous + _consts(e, x.shape[1], 1).rn)
    redo = (xs[:, 1:] <= xs[:, :-1]).any(axis=1).nonzero()[0]
    if redo.size == 0:
        return previous
    order = previous.copy()
    order[redo] = np.argsort(x[redo], axis=1, kind="stable")
    return order


def _swap_permutation(xs: np.ndarray) -> np.ndarray | None:
    """For positions ``xs`` (one environment, in the previous sorted order) that are out of order only
    where two neighbours swapped places (an overtaking within the step), the ``(N + 1,)`` permutation of
    sorted positions that sorts them (new position q holds the vehicle of old position ``perm[q]``; the
    last entry is the "no vehicle" row). None when disjoint neighbour swaps do not sort them strictly."""
    p = (xs[1:] <= xs[:-1]).nonzero()[0]
    if p.size > 1 and np.count_nonzero(p[1:] == p[:-1] + 1):  # a vehicle passed two: not a pair swap
        return None
    perm = np.arange(xs.size + 1)
    perm[p], perm[p + 1] = p + 1, p
    s = xs.take(perm[:-1])
    return None if np.count_nonzero(s[1:] <= s[:-1]) else perm


class LaneIndex:
    """Neighbour structure of one simulation step for E environments.

    Attributes:
        order: ``(E, N)`` vehicle index at each sorted position (ascending x).
        member: ``(L, N, E)`` lane membership by sorted position.
        gap: ``(E, N)`` bumper-to-bumper gap to the leader along x (m), inf when none.
        lead_speed: ``(E, N)`` leader speed (m/s), 0 when none.
        lead: ``(E, N)`` each vehicle's leader (nearest vehicle ahead in any lane it belongs to), -1.
    """

    __slots__ = ("_ahead", "_behind", "_c", "_flat", "_lead", "_lead_flat", "_lead_half_len", "_none_idx", "_pos_of",
                 "extra", "gap", "lead_speed", "lohi", "margin", "member", "num_lanes", "order")

    def __init__(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, speed: np.ndarray, length: np.ndarray,
                 width: np.ndarray, extra_lane: np.ndarray, lane_width: float, num_lanes: int,
                 rows: np.ndarray | None = None, margin: float = 0.1, previous_order: np.ndarray | None = None,
                 ) -> None:
        e, n = x.shape
        self.num_lanes = num_lanes
        self._c = c = _consts(e, n, num_lanes)
        self.order = order = sorted_order(x, previous_order)
        # Tables are (positions, environments): flat[p, e] is the flat index (into E x N) of the vehicle at
        # sorted position p, with a "no vehicle" row at position N.
        flat = np.empty((n + 1, e), dtype=np.int64)
        fi = flat[:n]
        np.add(order.T, c.rn.T, out=fi)
        flat[n] = c.sentinel
        self._flat = flat
        half_lat = _half_lateral_extent(yaw, length, width, margin)
        # Lowest and highest lane the body touches, both in one pass: y - h and y + h (negation is exact).
        self.lohi = lohi = np.floor((y + c.minus_plus * half_lat) * (1.0 / lane_width))  # (2, E, N)
        self.extra, self.margin = extra_lane, margin
        lo, hi = lohi.take(fi + c.half_offset)
        lanes = c.lanes
        member = (lanes >= lo) & (lanes <= hi)  # (L, N, E)
        member |= lanes == extra_lane.take(fi)
        self.member = member
        self._pos_of: np.ndarray | None = None
        self._link(x, speed, length)

    def _link(self, x: np.ndarray, speed: np.ndarray, length: np.ndarray) -> None:
        """The lane tables, leaders, gaps and leader speeds from ``order`` and ``member``."""
        c, member, flat = self._c, self.member, self._flat
        num_lanes, n, e = member.shape
        # ahead[l, p, e]: N - (sorted position of the first member of lane l at or after p), 0 when none.
        ahead = np.empty((num_lanes, n + 1, e), dtype=c.dtype)
        ahead[:, n] = 0
        np.multiply(member, c.rank_ahead, out=ahead[:, :n])
        _scan_max(ahead[:, :n], reverse=True)
        self._ahead = ahead
        self._behind: np.ndarray | None = None
        # The leader: the nearest member strictly ahead in any lane the vehicle belongs to.
        lead_pos = n - (member * ahead[:, 1:]).max(axis=0).astype(np.int64)  # (N, E); N when none
        lead_flat = np.empty(e * n, dtype=np.int64)
        lead_flat[flat[:n]] = flat.take(lead_pos * e + c.env if e > 1 else lead_pos)
        lead_flat = lead_flat.reshape(e, n)
        self._lead_flat = lead_flat
        self._lead: np.ndarray | None = None
        self._none_idx = (lead_flat == c.sentinel).ravel().nonzero()[0]  # flat indices of those without a leader
        self._lead_half_len = 0.5 * (length + length.take(lead_flat, mode="clip"))
        self._leader_gaps(x, speed)

    def _leader_gaps(self, x: np.ndarray, speed: np.ndarray) -> None:
        """``gap`` and ``lead_speed`` from the leaders (inf and 0 where none; the few are put afterwards)."""
        lead_flat, none = self._lead_flat, self._none_idx
        gap = x.take(lead_flat, mode="clip")
        gap -= x
        gap -= self._lead_half_len
        gap.put(none, np.inf)
        lead_speed = speed.take(lead_flat, mode="clip")
        lead_speed.put(none, 0.0)
        self.gap, self.lead_speed = gap, lead_speed

    def after_move(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, speed: np.ndarray, length: np.ndarray,
                   width: np.ndarray, extra_lane: np.ndarray, lane_width: float, moved: np.ndarray,
                   ) -> LaneIndex | None:
        """The index of the new state from this one, or None when the sorted order changed otherwise than
        by neighbours swapping places in one environment (build afresh).

        Valid when only the vehicles at flat indices ``moved`` (into E x N) can have changed ``y``, ``yaw``
        or ``extra_lane`` since this index was built (``x`` and ``speed`` may have changed everywhere).
        The lanes touched are recomputed for the moved vehicles only. If no lane membership changed and
        the order holds (most steps), every structure but the gaps is shared; otherwise the membership
        columns are permuted (swaps) and updated (moved vehicles), and the lane tables and leaders rebuilt
        from them. Either way the result is the one a full build gives, bit for bit (tested against it).
        """
        e = x.shape[0]
        xs = x.take(self._flat[:-1].T if e > 1 else self.order)  # positions in the previous sorted order
        perm = None
        if np.count_nonzero(xs[:, 1:] <= xs[:, :-1]):
            perm = _swap_permutation(xs[0]) if e == 1 else None
            if perm is None:
                return None
        # The moved vehicles on Python floats: the operations of _half_lateral_extent and of the build,
        # in the same order (IEEE arithmetic and sqrt; the sine still comes from numpy).
        sines = np.sin(yaw.take(moved)).tolist()
        lohi = self.lohi.reshape(2, -1)
        old_lo, old_hi = lohi.take(moved, axis=1).tolist()
        inv, margin = 1.0 / lane_width, self.margin
        new_extra, old_extra = extra_lane.take(moved).tolist(), self.extra.take(moved).tolist()
        changed = []
        for k, (s_m, l_m, w_m, y_m) in enumerate(zip(sines, length.take(moved).tolist(), width.take(moved).tolist(),
                                                     y.take(moved).tolist(), strict=True)):
            sy = abs(s_m)
            half = 0.5 * (sy * l_m + math.sqrt(1.0 - sy * sy) * w_m) + margin
            lo, hi = math.floor((y_m - half) * inv), math.floor((y_m + half) * inv)
            if lo != old_lo[k] or hi != old_hi[k] or new_extra[k] != old_extra[k]:
                changed.append((moved.item(k), lo, hi, new_extra[k]))
        new = object.__new__(LaneIndex)
        new._c, new.margin, new.num_lanes = self._c, self.margin, self.num_lanes
        new.extra, new.lohi = extra_lane, self.lohi
        if perm is None:
            new.order, new._flat, new._pos_of, member = self.order, self._flat, self._pos_of, self.member
        else:  # neighbours swapped places: the same tables with their positions permuted, then relinked
            new.order, new._flat, new._pos_of = self.order[:, perm[:-1]], self._flat[perm], None
            member = self.member[:, perm[:-1]]
        columns = []  # (sorted position, environment, lane membership) where the membership changes
        if changed:
            n = self.order.shape[1]
            new.lohi = self.lohi.copy()
            new_lohi = new.lohi.reshape(2, -1)
            pos_of = new.pos_of
            for f, lo, hi, lane_extra in changed:
                new_lohi[0, f], new_lohi[1, f] = lo, hi
                p, env = pos_of.item(f), f // n
                column = [lo <= lane <= hi or lane == lane_extra for lane in range(self.num_lanes)]
                if column != member[:, p, env].tolist():
                    columns.append((p, env, column))
        if not columns and perm is None:
            # Most steps; also a lane changer's body entering its target lane, already a member of it.
            new._ahead, new._behind, new._lead = self._ahead, self._behind, self._lead
            new._lead_flat, new._lead_half_len, new._none_idx = self._lead_flat, self._lead_half_len, self._none_idx
            new.member = member
            new._leader_gaps(x, speed)
            return new
        if columns:
            member = member.copy() if member is self.member else member
            for p, env, column in columns:
                member[:, p, env] = column
        new.member = member
        new._link(x, speed, length)
        return new

    @property
    def lead_flat(self) -> np.ndarray:
        """``(E, N)`` the leader's flat index into an ``(E, N)`` array; ``E * N`` when none."""
        return self._lead_flat

    @property
    def lead(self) -> np.ndarray:
        if self._lead is None:
            lf = self._lead_flat
            self._lead = np.where(lf == self._c.sentinel, -1, lf - self._c.rn)
        return self._lead

    @property
    def pos_of(self) -> np.ndarray:
        """``(E, N)`` sorted position of each vehicle (the inverse of ``order``)."""
        if self._pos_of is None:
            e, n = self.order.shape
            pos = np.empty(e * n, dtype=np.int64)
            pos[self._flat[:n]] = self._c.pos
            self._pos_of = pos.reshape(e, n)
        return self._pos_of

    def _behind_table(self) -> np.ndarray:
        """``(L, N + 1, E)``: at p, 1 + the sorted position of the last member of lane l before p, 0 when none."""
        if self._behind is None:
            num_lanes, n, e = self.member.shape
            behind = np.empty((num_lanes, n + 1, e), dtype=self._c.dtype)
            behind[:, 0] = 0
            np.multiply(self.member, self._c.rank_behind, out=behind[:, 1:])
            _scan_max(behind[:, 1:], reverse=False)
            self._behind = behind
        return self._behind

    def neighbour_in_lane(self, lane: np.ndarray, ahead: bool, vehicles: np.ndarray | None = None) -> np.ndarray:
        """Nearest vehicle ahead of (or behind) each vehicle in lane ``lane``; -1 when none.

        Args:
            lane: ``(E, N)`` a lane per vehicle, or ``(E, K)`` a lane per entry of ``vehicles``. Lanes that
                do not exist (< 0 or >= L) give -1.
            ahead: search ahead (larger x) or behind.
            vehicles: ``(K,)`` vehicle indices the columns of ``lane`` refer to (default: all N vehicles).

        Returns:
            Vehicle indices, shaped like ``lane``.
        """
        c = self._c
        pos = self.pos_of if vehicles is None else self.pos_of[:, vehicles]
        veh = self._nearest(lane, pos, c.env[:, None], ahead)
        out = veh - c.rn
        out[veh < 0] = -1
        return out

    def neighbour_flat(self, flat: np.ndarray, lane: np.ndarray, ahead: bool) -> np.ndarray:
        """As :meth:`neighbour_in_lane` for a few vehicles given by flat index ``flat`` (into E x N).

        Returns the neighbours' flat indices (-1 when none or the lane does not exist).
        """
        return self._nearest(lane, self.pos_of.take(flat), flat // self.order.shape[1], ahead)

    def lane_members_one(self, vehicle: int, lane: int, ahead: bool, count: int) -> list[int]:
        """One environment (E = 1): the ``count`` members of ``lane`` nearest ahead of (behind) ``vehicle``,
        nearest first, as vehicle indices; fewer when there are fewer, none when the lane does not exist.

        The first is what :meth:`neighbour_in_lane` gives, the next the neighbour of that one, and so on:
        scalar look-ups in the ahead table, and one search of the membership column behind (the behind
        table is not built for it).
        """
        if not 0 <= lane < self.num_lanes:
            return []
        p = self.pos_of.item(vehicle)
        if ahead:  # chained look-ups in the ahead table: the first member at or after q + 1, then after it
            n, table, order, out = self.order.shape[1], self._ahead, self.order, []
            q = p
            while len(out) < count:
                q = n - table.item(lane, q + 1, 0)
                if q >= n:
                    break
                out.append(order.item(q))
            return out
        pos = (p - 1) - np.flatnonzero(self.member[lane, p - 1::-1, 0])[:count] if p > 0 else _NO_POSITIONS
        return self.order[0].take(pos).tolist()

    def _nearest(self, lane: np.ndarray, pos: np.ndarray, env: np.ndarray, ahead: bool) -> np.ndarray:
        """Flat index of the nearest member of ``lane`` ahead of / behind sorted position ``pos``; -1."""
        c, num_lanes = self._c, self.num_lanes
        e, n = self.order.shape
        lane_c = np.minimum(np.maximum(lane, 0), num_lanes - 1)
        base = (lane_c * (n + 1) + pos) * e + env
        if ahead:  # the first member at or after p + 1
            nearest = np.subtract(n, self._ahead.take(base + e), dtype=np.int64)
        else:  # the last member at or before p - 1; 0 (none) maps to position N
            nearest = (self._behind_table().take(base).astype(np.int64) + n) % (n + 1)
        veh = self._flat.take(nearest * e + env)
        veh[(veh == c.sentinel) | (lane < 0) | (lane >= num_lanes)] = -1
        return veh


def gather(values: np.ndarray, idx: np.ndarray, rows: np.ndarray, fill: float) -> np.ndarray:
    """``values[e, idx[e, i]]`` with ``fill`` where idx < 0. Shapes (E, N) -> (E, N)."""
    n = values.shape[1]
    return np.where(idx >= 0, values.take(idx + rows * n, mode="clip"), fill)
