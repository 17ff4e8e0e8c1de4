"""CARLA's ``VehiclePIDController`` law and a kinematic bicycle model, batched over environments.

The PID law follows CARLA's ``PIDLongitudinalController`` / ``PIDLateralController``: errors are kept
in a window of the last ``pid_window`` values (CARLA's ``deque(maxlen=10)``), the integral is
``sum(window) * dt`` and the derivative ``(e[-1] - e[-2]) / dt`` once two errors exist; the speed error
is in km/h; the lateral error is the signed angle between the heading and the vector to the target
waypoint. ``VehiclePIDController.run_step`` then caps throttle and brake, rate-limits the steering
command by ``max_steer_change`` per step and clips it to ``max_steer``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lcsim.config import EgoConfig, PIDGains


@dataclass(slots=True)
class PIDState:
    """Error windows of E controllers: ``errors`` (E, W), ``count`` (E,) errors seen (capped at W)."""

    errors: np.ndarray
    count: np.ndarray

    @classmethod
    def zeros(cls, num_envs: int, window: int) -> PIDState:
        return cls(np.zeros((num_envs, window)), np.zeros(num_envs, dtype=np.int64))

    def reset(self, idx: np.ndarray) -> None:
        self.errors[idx] = 0.0
        self.count[idx] = 0


def pid_step(state: PIDState, error: np.ndarray, gains: PIDGains) -> np.ndarray:
    """Push ``error`` (E,) into each window and return the clipped PID output in [-1, 1], shape (E,).

    The window is kept newest-last, as a deque, so ``errors[:, -1]`` is the current error.
    """
    errs = state.errors
    errs[:, :-1] = errs[:, 1:]
    errs[:, -1] = error
    np.minimum(state.count + 1, errs.shape[1], out=state.count)
    has_two = state.count >= 2
    de = np.where(has_two, (errs[:, -1] - errs[:, -2]) / gains.dt_s, 0.0)
    ie = np.where(has_two, errs.sum(axis=1) * gains.dt_s, 0.0)
    return np.clip(gains.kp * error + gains.kd * de + gains.ki * ie, -1.0, 1.0)


def split_throttle_brake(u: np.ndarray, cfg: EgoConfig) -> tuple[np.ndarray, np.ndarray]:
    """CARLA: a non-negative output is throttle (<= max_throttle), a negative one brake (<= max_brake)."""
    throttle = np.where(u >= 0.0, np.minimum(u, cfg.max_throttle), 0.0)
    brake = np.where(u < 0.0, np.minimum(-u, cfg.max_brake), 0.0)
    return throttle, brake


def limit_steer(steer: np.ndarray, past: np.ndarray, cfg: EgoConfig) -> np.ndarray:
    """Rate-limit to ``past +- max_steer_change`` then clip to ``+-max_steer``."""
    steer = np.clip(steer, past - cfg.max_steer_change, past + cfg.max_steer_change)
    return np.clip(steer, -cfg.max_steer, cfg.max_steer)


def heading_error(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Signed angle (rad) from the heading to the vector (target - position); positive to the left."""
    err = np.arctan2(ty - y, tx - x) - yaw
    return (err + math.pi) % (2 * math.pi) - math.pi


def longitudinal_accel(throttle: np.ndarray, brake: np.ndarray, speed: np.ndarray, cfg: EgoConfig) -> np.ndarray:
    """Acceleration (m/s^2) from pedal commands, with rolling resistance and drag that never reverse."""
    resist = np.where(speed > 0.0, cfg.rolling_resistance_mps2 + cfg.drag_per_speed2 * speed * speed, 0.0)
    return throttle * cfg.max_accel_mps2 - brake * cfg.max_brake_decel_mps2 - resist


def bicycle_step(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, speed: np.ndarray, accel: np.ndarray,
                 steer: np.ndarray, cfg: EgoConfig, dt: float) -> tuple[np.ndarray, ...]:
    """One Euler step of the kinematic bicycle model about the centre of gravity (mid-wheelbase).

    Shapes (E,); ``steer`` in [-1, 1] maps to ``steer * max_steer_angle_deg`` at the front wheels.
    Returns the new ``x, y, yaw, speed``.
    """
    delta = steer * math.radians(cfg.max_steer_angle_deg)
    beta = np.arctan(0.5 * np.tan(delta))
    heading = yaw + beta
    x = x + speed * np.cos(heading) * dt
    y = y + speed * np.sin(heading) * dt
    yaw = yaw + speed / (0.5 * cfg.wheelbase_m) * np.sin(beta) * dt
    speed = np.maximum(speed + accel * dt, 0.0)
    return x, y, yaw, speed
