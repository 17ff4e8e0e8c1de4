"""The ego's control: CARLA's ``VehiclePIDController`` law and a kinematic bicycle model.

The law itself is compiled with the rest of the simulator's step (:func:`lcsim.kernel.ego_law`); this module
holds the controllers' state (:class:`PIDBank`) and CARLA's PID law as CARLA writes it (:func:`pid_reference`),
which the tests hold the compiled law to.

The PID law follows CARLA's ``PIDLongitudinalController`` / ``PIDLateralController``: errors are kept
in a window of the last ``pid_window`` values (CARLA's ``deque(maxlen=10)``), the integral is
``sum(window) * dt`` and the derivative ``(e[-1] - e[-2]) / dt`` once two errors exist; the speed error
is in km/h; the lateral error is the signed angle between the heading and the vector to the target
waypoint. ``VehiclePIDController.run_step`` then caps throttle and brake, rate-limits the steering
command by ``max_steer_change`` per step and clips it to ``max_steer``.
"""

from __future__ import annotations

import numpy as np

from lcsim.kernel import ego_law

__all__ = ["PIDBank", "ego_law", "pid_reference"]


class PIDBank:
    """The error windows of E x C PID controllers (C = 2: longitudinal, lateral), stepped together (their gains
    are the compiled core's parameters, :func:`lcsim.kernel.kernel_params`).

    ``errors`` ``(E, window, C)`` by ring slot, ``count`` ``(E, 1)`` errors pushed since the reset, ``ptr`` the
    ring slot of the latest error (shared: the controllers are stepped together).
    """

    def __init__(self, num_envs: int, controllers: int, window: int) -> None:
        self.window = window
        self.errors = np.zeros((num_envs, window, controllers))
        self.count = np.zeros((num_envs, 1), dtype=np.int64)
        self.ptr = 0

    def reset(self, idx: np.ndarray) -> None:
        self.errors[idx] = 0.0
        self.count[idx] = 0


def pid_reference(errors: list[float], kp: float, ki: float, kd: float, dt: float, window: int = 10) -> float:
    """CARLA's PID law for one controller, written as CARLA writes it (a deque); for tests and docs."""
    buf = errors[-window:]
    if len(buf) >= 2:
        de, ie = (buf[-1] - buf[-2]) / dt, sum(buf) * dt
    else:
        de = ie = 0.0
    return min(max(kp * buf[-1] + kd * de + ki * ie, -1.0), 1.0)
