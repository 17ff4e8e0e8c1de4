"""CARLA's ``VehiclePIDController`` law and a kinematic bicycle model, batched over environments.

The PID law follows CARLA's ``PIDLongitudinalController`` / ``PIDLateralController``: errors are kept
in a window of the last ``pid_window`` values (CARLA's ``deque(maxlen=10)``), the integral is
``sum(window) * dt`` and the derivative ``(e[-1] - e[-2]) / dt`` once two errors exist; the speed error
is in km/h; the lateral error is the signed angle between the heading and the vector to the target
waypoint. ``VehiclePIDController.run_step`` then caps throttle and brake, rate-limits the steering
command by ``max_steer_change`` per step and clips it to ``max_steer``.

The longitudinal and lateral controllers of E vehicles are stepped together as ``(E, 2)`` arrays.
"""

from __future__ import annotations

import math
import operator
from functools import reduce

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


def split_throttle_brake(u: np.ndarray, cfg: EgoConfig) -> tuple[np.ndarray, np.ndarray]:
    """CARLA: a non-negative output is throttle (<= max_throttle), a negative one brake (<= max_brake)."""
    return np.minimum(np.maximum(u, 0.0), cfg.max_throttle), np.minimum(np.maximum(-u, 0.0), cfg.max_brake)


def limit_steer(steer: np.ndarray, past: np.ndarray, cfg: EgoConfig) -> np.ndarray:
    """Rate-limit to ``past +- max_steer_change`` then clip to ``+-max_steer``."""
    lo = np.maximum(past - cfg.max_steer_change, -cfg.max_steer)
    hi = np.minimum(past + cfg.max_steer_change, cfg.max_steer)
    return np.minimum(np.maximum(steer, lo), hi)


def heading_error(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Signed angle (rad) from the heading to the vector (target - position); positive to the left."""
    return (np.arctan2(ty - y, tx - x) - yaw + math.pi) % (2 * math.pi) - math.pi


def longitudinal_accel(throttle: np.ndarray, brake: np.ndarray, speed: np.ndarray, cfg: EgoConfig) -> np.ndarray:
    """Acceleration (m/s^2) from pedal commands, with rolling resistance and drag (none at standstill)."""
    resist = (cfg.rolling_resistance_mps2 + cfg.drag_per_speed2 * speed * speed) * (speed > 0.0)
    return throttle * cfg.max_accel_mps2 - brake * cfg.max_brake_decel_mps2 - resist


def bicycle_step(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, speed: np.ndarray, accel: np.ndarray,
                 steer: np.ndarray, cfg: EgoConfig, dt: float) -> tuple[np.ndarray, ...]:
    """One Euler step of the kinematic bicycle model about the centre of gravity (mid-wheelbase).

    Shapes (E,); ``steer`` in [-1, 1] maps to ``steer * max_steer_angle_deg`` at the front wheels.
    Returns the new ``x, y, yaw, speed``.
    """
    beta = np.arctan(0.5 * np.tan(steer * math.radians(cfg.max_steer_angle_deg)))
    heading = yaw + beta
    vdt = speed * dt
    x = x + vdt * np.cos(heading)
    y = y + vdt * np.sin(heading)
    yaw = yaw + vdt * (2.0 / cfg.wheelbase_m) * np.sin(beta)
    speed = np.maximum(speed + accel * dt, 0.0)
    return x, y, yaw, speed
