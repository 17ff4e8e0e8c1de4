"""Autopilot behaviour: IDM car following with a Traffic-Manager-like gap, smooth lane changes, and the
per-driver parameters and random processes that make the traffic human-like (``TrafficConfig.human_like``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lcsim import kernel
from lcsim.config import WANDER_CLIP_SIGMAS, TrafficConfig

__all__ = ["WANDER_CLIP_SIGMAS", "DriverParams", "idm_accel"]


@dataclass(slots=True)
class DriverParams:
    """Per-driver car-following parameters, arrays shaped like the vehicles (``(E, N)`` in the simulator).

    ``time_headway`` (s), ``max_accel`` (m/s^2), ``inv_2sqrt_ab`` (``1 / (2 sqrt(a b))``, s^2/m), the reaction
    lag factor ``lag`` (``dt / reaction time``, at most 1: the share of the gap between commanded and applied
    acceleration closed per step), ``lc_inv_duration`` (1/s), ``eagerness`` (probability of acting on a
    blocked leader at a check).
    """

    time_headway: np.ndarray
    max_accel: np.ndarray
    inv_2sqrt_ab: np.ndarray
    lag: np.ndarray
    lc_inv_duration: np.ndarray
    eagerness: np.ndarray

    @classmethod
    def nominal(cls, cfg: TrafficConfig, shape: tuple[int, ...], dt: float) -> DriverParams:
        """Every driver at the medians of the configured distributions."""
        a, b = cfg.idm_max_accel_mps2, cfg.idm_comfort_decel_mps2
        lag = min(1.0, dt / cfg.reaction_time_s) if cfg.human_like and cfg.reaction_time_s > 0 else 1.0
        eagerness = 0.5 * (cfg.lane_change_eagerness_min + 1.0) if cfg.human_like else 1.0
        return cls(np.full(shape, cfg.idm_time_headway_s), np.full(shape, a), np.full(shape, 0.5 / math.sqrt(a * b)),
                   np.full(shape, lag), np.full(shape, 1.0 / cfg.lane_change_duration_s), np.full(shape, eagerness))

    def draw(self, rows: tuple[int, slice] | int, gen: np.random.Generator, cfg: TrafficConfig, dt: float,
             n: int) -> None:
        """Draw ``n`` drivers into ``rows`` of the arrays (an episode's reset), from ``gen``."""
        z = np.clip(gen.standard_normal((5, n)), -2.5, 2.5) * cfg.driver_spread
        e_duration = np.exp(np.clip(gen.standard_normal(n), -2.5, 2.5) * cfg.lane_change_spread)
        eagerness = gen.uniform(cfg.lane_change_eagerness_min, 1.0, n)
        medians = np.array([cfg.idm_time_headway_s, cfg.idm_max_accel_mps2, cfg.idm_comfort_decel_mps2,
                            cfg.reaction_time_s, cfg.lane_change_duration_s, dt])
        values = kernel.driver_values(np.exp(z[0]), np.exp(z[1]), np.exp(z[2]), np.exp(z[3]), e_duration,
                                      eagerness, medians)
        for name, row in zip(self.__slots__, values, strict=True):
            getattr(self, name)[rows] = row

    def set_nominal(self, mask: np.ndarray, cfg: TrafficConfig, dt: float) -> None:
        """Put the drivers where ``mask`` is set at the medians (what a planner that cannot see them assumes)."""
        self.set_where(mask, DriverParams.nominal(cfg, (1,), dt))

    def set_where(self, mask: np.ndarray, other: DriverParams) -> None:
        """Take ``other``'s drivers (arrays broadcasting to ours) where ``mask`` is set, in place (the simulator's
        drivers are views of its state)."""
        for name in self.__slots__:
            getattr(self, name)[...] = np.where(mask, getattr(other, name), getattr(self, name))


def idm_accel(v: np.ndarray, v0: np.ndarray, gap: np.ndarray, dv: np.ndarray, cfg: TrafficConfig,
              drivers: DriverParams | None = None) -> np.ndarray:
    """Intelligent Driver Model acceleration (m/s^2), clipped to [-max_decel, max_accel]: the simulator's own
    (:func:`lcsim.kernel.idm`), on arrays.

    Args:
        v: own speed (m/s); v0: desired speed; gap: bumper-to-bumper gap to the leader (m, inf when
            none); dv: approach rate v - v_leader (m/s). All broadcastable.
        drivers: per-driver time gap, acceleration and deceleration (shaped like ``v``); None: the
            configured values for every vehicle.

    ``s* = s0 + v T + v dv / (2 sqrt(a b))`` with s0 = idm_min_gap_m and T = idm_time_headway_s, so
    in steady following the gap is about ``2 s * v + 2 m`` as Traffic Manager keeps it.
    """
    v, v0, gap, dv = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (v, v0, gap, dv)))
    shape = v.shape
    if drivers is None:
        a = np.full(shape, cfg.idm_max_accel_mps2)
        headway = np.full(shape, cfg.idm_time_headway_s)
        term = np.full(shape, 2.0 * math.sqrt(cfg.idm_max_accel_mps2 * cfg.idm_comfort_decel_mps2))
    else:
        a, headway, term = (np.broadcast_to(np.asarray(arr, dtype=np.float64), shape)
                            for arr in (drivers.max_accel, drivers.time_headway, drivers.inv_2sqrt_ab))
    delta = cfg.idm_delta
    out = kernel.idm_array(*(np.ascontiguousarray(arr).ravel() for arr in (v, v0, gap, dv, a, headway, term)),
                           drivers is not None, cfg.idm_min_gap_m, int(delta) if delta in (2, 4) else 0,
                           float(delta), cfg.max_decel_mps2)
    return out.reshape(shape) if shape else out[0]

