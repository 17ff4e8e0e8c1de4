"""Autopilot behaviour: IDM car following with a Traffic-Manager-like gap, and smooth lane changes."""

from __future__ import annotations

import math

import numpy as np

from lcsim.config import TrafficConfig


def idm_accel(v: np.ndarray, v0: np.ndarray, gap: np.ndarray, dv: np.ndarray, cfg: TrafficConfig) -> np.ndarray:
    """Intelligent Driver Model acceleration (m/s^2), clipped to [-max_decel, max_accel].

    Args:
        v: own speed (m/s); v0: desired speed; gap: bumper-to-bumper gap to the leader (m, inf when
            none); dv: approach rate v - v_leader (m/s). All broadcastable.

    ``s* = s0 + v T + v dv / (2 sqrt(a b))`` with s0 = idm_min_gap_m and T = idm_time_headway_s, so
    in steady following the gap is about ``2 s * v + 2 m`` as Traffic Manager keeps it.
    """
    a, b = cfg.idm_max_accel_mps2, cfg.idm_comfort_decel_mps2
    # In-place steps where the operand is a fresh array (a numpy scalar when the inputs are 0-d).
    s_star = v * dv
    s_star /= 2.0 * math.sqrt(a * b)  # (IEEE sqrt either way; math's costs no numpy call)
    s_star += v * cfg.idm_time_headway_s
    s_star = np.maximum(s_star, 0.0)
    s_star += cfg.idm_min_gap_m
    ratio = v / np.maximum(v0, 0.1)
    delta = cfg.idm_delta
    if delta in (2, 4):  # powers by squaring: several times faster than pow
        free = ratio * ratio
        if delta == 4:
            free *= free
    else:
        free = ratio ** delta
    interaction = s_star / np.maximum(gap, 0.1)
    interaction *= interaction
    acc = 1.0 - free
    acc -= interaction
    acc *= a
    return np.minimum(np.maximum(acc, -cfg.max_decel_mps2), a)


def smoothstep5(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-jerk profile ``10t^3 - 15t^4 + 6t^5`` on [0, 1] and its derivative."""
    t = np.minimum(np.maximum(tau, 0.0), 1.0)
    t2 = t * t
    u = 1.0 - t
    u *= u
    d = 30.0 * t2
    d *= u
    return t2 * t * (10.0 - 15.0 * t + 6.0 * t2), d
