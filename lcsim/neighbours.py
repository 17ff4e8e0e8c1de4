"""The neighbour index of the simulator's current state, and searches in it.

The compiled core (:mod:`lcsim.kernel`) keeps it up to date at every simulation step: the vehicles of each
environment sorted by ``x`` (ties by index), the lanes each body touches (its lateral extent accounts for its yaw,
plus a 0.1 m margin) and, for a traffic vehicle changing lanes, its target lane; each vehicle's leader (the nearest
vehicle ahead that is a member of one of its lanes), the gap to it and its speed. A search for the nearest member
of a lane ahead of or behind a vehicle walks the sorted order from the vehicle's place.
"""

from __future__ import annotations

import numpy as np

from lcsim import kernel as K


class LaneIndex:
    """The neighbour index of E environments, views of the simulator's state blocks (always current).

    Attributes:
        order: ``(E, N)`` vehicle index at each sorted position (ascending x).
        pos_of: ``(E, N)`` sorted position of each vehicle (the inverse of ``order``).
        lo, hi: ``(E, N)`` lowest and highest lane each body touches (may lie beyond the road's lanes).
        extra: ``(E, N)`` the target lane of a traffic vehicle changing lanes, -1 otherwise.
        gap: ``(E, N)`` bumper-to-bumper gap to the leader along x (m), inf when none.
        lead_speed: ``(E, N)`` leader speed (m/s), 0 when none.
        lead: ``(E, N)`` each vehicle's leader, -1 when none.
    """

    __slots__ = ("_vi", "extra", "gap", "hi", "lead", "lead_speed", "lo", "num_lanes", "order", "pos_of")

    def __init__(self, vf: np.ndarray, vi: np.ndarray, num_lanes: int) -> None:
        self._vi, self.num_lanes = vi, num_lanes
        self.gap, self.lead_speed = vf[K.GAP], vf[K.LEAD_SPEED]
        self.order, self.pos_of, self.lo, self.hi = vi[K.ORDER], vi[K.POS_OF], vi[K.LO], vi[K.HI]
        self.extra, self.lead = vi[K.EXTRA], vi[K.LEAD]

    @property
    def lead_flat(self) -> np.ndarray:
        """``(E, N)`` the leader's flat index into an ``(E, N)`` array; ``E * N`` when none."""
        e, n = self.lead.shape
        return np.where(self.lead >= 0, self.lead + np.arange(e)[:, None] * n, e * n)

    @property
    def lohi(self) -> np.ndarray:
        """``(2, E, N)``: ``lo`` and ``hi``."""
        return np.stack((self.lo, self.hi))

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
        lane = np.asarray(lane, dtype=np.int64)
        e, k = lane.shape
        veh = np.arange(k, dtype=np.int64) if vehicles is None else np.asarray(vehicles, dtype=np.int64)
        n = self.order.shape[1]
        if e != self.order.shape[0] or veh.shape != (k,) or (k and (veh.min() < 0 or veh.max() >= n)):
            raise IndexError(f"lane must be (E={self.order.shape[0]}, K) and vehicles K indices in [0, {n})")
        envs = np.repeat(np.arange(e, dtype=np.int64), k)
        out = K.nearest_many(self._vi, self.num_lanes, envs, np.tile(veh, e), lane.ravel(), ahead)
        return out.reshape(e, k)

    def neighbour_flat(self, flat: np.ndarray, lane: np.ndarray, ahead: bool) -> np.ndarray:
        """As :meth:`neighbour_in_lane` for a few vehicles given by flat index ``flat`` (into E x N).

        Returns the neighbours' flat indices (-1 when none or the lane does not exist).
        """
        n = self.order.shape[1]
        flat = np.asarray(flat, dtype=np.int64)
        if flat.size and (flat.min() < 0 or flat.max() >= self.order.size):
            raise IndexError(f"flat indices must be in [0, {self.order.size})")
        envs = flat // n
        out = K.nearest_many(self._vi, self.num_lanes, envs, flat - envs * n, np.asarray(lane, dtype=np.int64),
                             ahead)
        return np.where(out >= 0, out + envs * n, -1)

    def lane_members_one(self, vehicle: int, lane: int, ahead: bool, count: int, env: int = 0) -> list[int]:
        """The ``count`` members of ``lane`` nearest ahead of (behind) ``vehicle`` of environment ``env``, nearest
        first, as vehicle indices; fewer when there are fewer, none when the lane does not exist."""
        if not (0 <= env < self.order.shape[0] and 0 <= vehicle < self.order.shape[1]):
            raise IndexError(f"no vehicle {vehicle} in environment {env}")
        return K.lane_members(self._vi, self.num_lanes, env, vehicle, lane, ahead, count).tolist()

