"""The ego's control: CARLA's ``VehiclePIDController`` law and a kinematic bicycle model (:func:`ego_step`).

The PID law follows CARLA's ``PIDLongitudinalController`` / ``PIDLateralController``: errors are kept
in a window of the last ``pid_window`` values (CARLA's ``deque(maxlen=10)``), the integral is
``sum(window) * dt`` and the derivative ``(e[-1] - e[-2]) / dt`` once two errors exist; the speed error
is in km/h; the lateral error is the signed angle between the heading and the vector to the target
waypoint. ``VehiclePIDController.run_step`` then caps throttle and brake, rate-limits the steering
command by ``max_steer_change`` per step and clips it to ``max_steer``.

The longitudinal and lateral controllers of E vehicles are stepped together as ``(E, 2)`` arrays. The law
is written once (:func:`ego_step`) and runs on arrays for a batch or on floats for one environment.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from functools import reduce
from typing import Any, NamedTuple

import numpy as np

from lcsim.config import EgoConfig


class PIDBank:
    """E x C independent PID controllers (C = 2: longitudinal, lateral) with CARLA's error window."""

    def __init__(self, num_envs: int, gains: list, window: int) -> None:
        self.kp = np.array([g.kp for g in gains])
        self.ki = np.array([g.ki for g in gains])
        self.kd = np.array([g.kd for g in gains])
        self.dt = np.array([g.dt_s for g in gains])
        self.kd_over_dt = self.kd / self.dt
        self.ki_dt = self.ki * self.dt
        self._kp, self._kd_over_dt, self._ki_dt = self.kp.tolist(), self.kd_over_dt.tolist(), self.ki_dt.tolist()
        self.window = window
        self.errors = np.zeros((num_envs, window, len(gains)))
        self.count = np.zeros((num_envs, 1), dtype=np.int64)
        self.ptr = 0  # ring position shared by all controllers (they are stepped together)

    def reset(self, idx: np.ndarray) -> None:
        self.errors[idx] = 0.0
        self.count[idx] = 0

    def step(self, error: np.ndarray) -> np.ndarray:
        """Push ``error`` (E, C) and return ``clip(kp e + ki sum(window) dt + kd de/dt, -1, 1)``, (E, C).

        Integral and derivative are zero until a controller has seen two errors, as in CARLA.
        """
        prev = self.errors[:, self.ptr]
        self.ptr = (self.ptr + 1) % self.window
        self.errors[:, self.ptr] = error
        self.count += 1
        has_two = self.count >= 2
        d_term = np.where(has_two, (error - prev) * self.kd_over_dt, 0.0)
        i_term = np.where(has_two, self.errors.sum(axis=1) * self.ki_dt, 0.0)
        return np.minimum(np.maximum(self.kp * error + d_term + i_term, -1.0), 1.0)

    def step_one(self, error: tuple[float, ...]) -> list[float]:
        """:meth:`step` for a single environment (E = 1) on Python floats, bit-identical to it.

        A dozen numpy calls on 1-element arrays cost ~20x the same arithmetic on floats. The window
        sum adds the ring slots in index order, one after the other, which is the order numpy's
        ``sum(axis=1)`` in :meth:`step` uses (tested).
        """
        errors = self.errors
        rows = errors[0].tolist()  # the window by ring slot, before this push
        prev = rows[self.ptr]
        self.ptr = ptr = (self.ptr + 1) % self.window
        errors[0, ptr] = error
        rows[ptr] = error
        count = self.count.item(0) + 1
        self.count[0, 0] = count
        has_two = count >= 2
        out = []
        if has_two:
            totals = [reduce(operator.add, column) for column in zip(*rows, strict=True)]  # ((w0 + w1) + w2) ...
            for c, e in enumerate(error):
                u = self._kp[c] * e + (e - prev[c]) * self._kd_over_dt[c] + totals[c] * self._ki_dt[c]
                out.append(min(max(u, -1.0), 1.0))
        else:
            for c, e in enumerate(error):
                out.append(min(max(self._kp[c] * e + 0.0 + 0.0, -1.0), 1.0))
        return out


def pid_reference(errors: list[float], kp: float, ki: float, kd: float, dt: float, window: int = 10) -> float:
    """CARLA's PID law for one controller, written as CARLA writes it (a deque); for tests and docs."""
    buf = errors[-window:]
    if len(buf) >= 2:
        de, ie = (buf[-1] - buf[-2]) / dt, sum(buf) * dt
    else:
        de = ie = 0.0
    return min(max(kp * buf[-1] + kd * de + ki * ie, -1.0), 1.0)


class ArrayOps:
    """The operations of :func:`ego_step` on ``(E,)`` arrays (many environments)."""

    minimum = staticmethod(np.minimum)
    maximum = staticmethod(np.maximum)
    ceil = staticmethod(np.ceil)
    remainder = staticmethod(np.remainder)
    arctan2 = staticmethod(np.arctan2)
    arctan = staticmethod(np.arctan)
    tan = staticmethod(np.tan)
    cos = staticmethod(np.cos)
    sin = staticmethod(np.sin)

    @staticmethod
    def positive(v: np.ndarray) -> np.ndarray:
        return v > 0.0


class FloatOps:
    """The same operations on Python floats (one environment: a dozen numpy calls on 1-element arrays cost
    about 20x the same arithmetic on floats). IEEE arithmetic gives the same bits; the transcendental
    functions still come from numpy, whose SIMD versions can differ from ``math`` in the last bit."""

    minimum = staticmethod(min)
    maximum = staticmethod(max)

    @staticmethod
    def ceil(x: float) -> float:
        return float(math.ceil(x))

    @staticmethod
    def remainder(x: float, m: float) -> float:
        return x % m

    @staticmethod
    def arctan2(y: float, x: float) -> float:
        return float(np.arctan2(y, x))

    @staticmethod
    def arctan(x: float) -> float:
        return float(np.arctan(x))

    @staticmethod
    def tan(x: float) -> float:
        return float(np.tan(x))

    @staticmethod
    def cos(x: float) -> float:
        return float(np.cos(x))

    @staticmethod
    def sin(x: float) -> float:
        return float(np.sin(x))

    @staticmethod
    def positive(v: float) -> float:
        return 1.0 if v > 0.0 else 0.0


class EgoStep(NamedTuple):
    """What one control step gives: the new pose and speed, and the commands that led there."""

    x: Any
    y: Any
    yaw: Any
    speed: Any
    accel: Any
    steer: Any
    throttle: Any
    brake: Any


def ego_step(ops: type[ArrayOps] | type[FloatOps], cfg: EgoConfig, *, x: Any, y: Any, yaw: Any, speed: Any,
             target_speed: Any, lead_gap: Any, path: tuple[Any, Any, Any, Any], steer_past: Any, accel_past: Any,
             lag_alpha: float, dt: float, pid: Callable[[Any, Any], tuple[Any, Any]]) -> EgoStep:
    """The ego's control law, written once: CARLA's local planner and ``VehiclePIDController`` on the planned
    path, a first-order powertrain lag and the kinematic bicycle model, for ``(E,)`` arrays (``ArrayOps``)
    or one environment's floats (``FloatOps``), with the same operations in the same order, so both give
    the same bits.

    Args:
        path: ``(x0, length, y0, y1)`` of the planned path: the lateral move from ``y0`` to ``y1`` over
            ``length`` metres from ``x0`` (``length`` is the same lane when no change is under way).
        lead_gap: the gap to the leader (m), used with ``adaptive_cruise``.
        pid: ``(speed error in km/h, heading error in rad) -> (longitudinal, lateral) command in [-1, 1]``
            (a :class:`PIDBank`'s ``step`` or ``step_one``).
    """
    px0, plen, py0, py1 = path
    if cfg.adaptive_cruise:
        target_speed = ops.minimum(target_speed, ops.maximum((lead_gap - cfg.acc_min_gap_m) / cfg.acc_time_headway_s,
                                                             0.0))
    # Local planner: the first waypoint (every waypoint_spacing_m along the path) beyond the look-ahead.
    sp = cfg.waypoint_spacing_m
    tx = px0 + ops.ceil((x + (cfg.base_min_distance_m + cfg.distance_ratio * speed) - px0) / sp) * sp
    frac = ops.minimum(ops.maximum((tx - px0) / plen, 0.0), 1.0)
    ty = py0 + (py1 - py0) * frac
    # Errors: speed in km/h; heading: the signed angle from the heading to the waypoint, positive to the left.
    e_speed = (target_speed - speed) * 3.6
    e_head = ops.remainder(ops.arctan2(ty - y, tx - x) - yaw + math.pi, 2 * math.pi) - math.pi
    u_long, u_lat = pid(e_speed, e_head)
    # VehiclePIDController.run_step: throttle and brake capped, steering rate-limited and clipped.
    throttle = ops.minimum(ops.maximum(u_long, 0.0), cfg.max_throttle)
    brake = ops.minimum(ops.maximum(-u_long, 0.0), cfg.max_brake)
    lo = ops.maximum(steer_past - cfg.max_steer_change, -cfg.max_steer)
    hi = ops.minimum(steer_past + cfg.max_steer_change, cfg.max_steer)
    steer = ops.minimum(ops.maximum(u_lat, lo), hi)
    # Pedals to acceleration (rolling resistance and drag, none at standstill), through the powertrain lag.
    resist = (cfg.rolling_resistance_mps2 + cfg.drag_per_speed2 * speed * speed) * ops.positive(speed)
    drive = throttle * cfg.max_accel_mps2 - brake * cfg.max_brake_decel_mps2 - resist
    accel = accel_past + (drive - accel_past) * lag_alpha
    # Kinematic bicycle about the centre of gravity (mid-wheelbase), one Euler step.
    beta = ops.arctan(0.5 * ops.tan(steer * math.radians(cfg.max_steer_angle_deg)))
    heading = yaw + beta
    vdt = speed * dt
    return EgoStep(
        x=x + vdt * ops.cos(heading), y=y + vdt * ops.sin(heading),
        yaw=yaw + vdt * (2.0 / cfg.wheelbase_m) * ops.sin(beta), speed=ops.maximum(speed + accel * dt, 0.0),
        accel=accel, steer=steer, throttle=throttle, brake=brake,
    )  # fmt: skip
