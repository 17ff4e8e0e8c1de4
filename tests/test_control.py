"""Control laws against hand-computed values, and a lane change end to end."""

import numpy as np
import pytest

from lcsim import kernel
from lcsim.config import (
    SWAPPED_LATERAL,
    SWAPPED_LONGITUDINAL,
    EgoConfig,
    PIDGains,
    ScenarioConfig,
    TrafficConfig,
)
from lcsim.control import pid_reference
from lcsim.core import KEEP, LEFT, LaneChangeCore
from lcsim.traffic import idm_accel


def test_idm_against_hand_computed_values():
    cfg = TrafficConfig()  # a=1.5, b=2.0, T=2 s, s0=2 m, delta=4
    # Free road at the desired speed: no acceleration.
    assert idm_accel(np.array(6.0), np.array(6.0), np.array(np.inf), np.array(0.0), cfg) == pytest.approx(0.0)
    # v=5, v0=10, gap=20, dv=1: s* = 2 + 5*2 + 5*1/(2*sqrt(3)) = 13.4434; a = 1.5*(1 - 0.0625 - (13.4434/20)^2)
    s_star = 2 + 10 + 5 / (2 * np.sqrt(3.0))
    expected = 1.5 * (1 - (5 / 10) ** 4 - (s_star / 20) ** 2)
    assert idm_accel(np.array(5.0), np.array(10.0), np.array(20.0), np.array(1.0), cfg) == pytest.approx(expected)
    # Far too close: braking is clipped at max_decel.
    assert idm_accel(np.array(8.0), np.array(8.0), np.array(0.5), np.array(3.0), cfg) == -cfg.max_decel_mps2


def _params(ego: EgoConfig, **overrides: float) -> np.ndarray:
    """The compiled core's parameters of a scenario with this ego, some replaced (by name)."""
    p, _ = kernel.kernel_params(ScenarioConfig(ego=ego), autopilot_ego=False)
    for name, value in overrides.items():
        p[kernel.P_NAMES.index(name)] = value
    return p


def _law(p, window, slot, count, *, x=0.0, y=0.0, yaw=0.0, speed=8.0, lead_gap=100.0, path=(0.0, 10.0, 0.0, 0.0),
         steer_past=0.0, accel_past=0.0, adaptive_cruise=False):
    return dict(zip(("x", "y", "yaw", "speed", "accel", "steer", "throttle", "brake"),
                    kernel.ego_law(p, x, y, yaw, speed, lead_gap, *path, steer_past, accel_past, adaptive_cruise,
                                   window, slot, count), strict=True))


def test_the_compiled_pid_is_carlas_law():
    """Random states for 25 steps through the compiled law: its commands are CARLA's PID law (written as CARLA
    writes it) of the errors it pushed, capped and rate-limited as VehiclePIDController.run_step does."""
    ego = EgoConfig(longitudinal_pid=PIDGains(kp=0.3, ki=0.05, kd=0.02, dt_s=0.05),
                    lateral_pid=PIDGains(kp=1.95, ki=0.2, kd=0.07, dt_s=0.05))
    p = _params(ego)
    window = np.zeros((10, 2))
    rng = np.random.default_rng(0)
    errs: list[list[float]] = [[], []]
    gains = (ego.longitudinal_pid, ego.lateral_pid)
    for k in range(25):
        slot = (k + 1) % 10
        steer_past = float(rng.uniform(-0.8, 0.8))
        r = _law(p, window, slot, k + 1, x=float(rng.uniform(0, 50)), y=float(rng.uniform(-1, 1)),
                 yaw=float(rng.normal(0, 0.1)), speed=float(rng.uniform(5, 12)), steer_past=steer_past)
        for c in range(2):
            errs[c].append(float(window[slot, c]))
        u_long, u_lat = (pid_reference(errs[c], g.kp, g.ki, g.kd, g.dt_s) for c, g in enumerate(gains))
        assert r["throttle"] == pytest.approx(min(max(u_long, 0.0), 0.75), abs=1e-12), k
        assert r["brake"] == pytest.approx(min(max(-u_long, 0.0), 0.3), abs=1e-12), k
        lo, hi = max(steer_past - 0.1, -0.8), min(steer_past + 0.1, 0.8)
        assert r["steer"] == pytest.approx(min(max(u_lat, lo), hi), abs=1e-12), k
    # Hand values: the first error has no integral or derivative; the second adds them (a window of two).
    p = _params(ego, kp_long=0.0, kp_lat=1.95, kd_dt_lat=0.07 / 0.1, ki_dt_lat=0.2 * 0.1, max_steer_change=2.0)
    window = np.zeros((10, 2))
    assert _law(p, window, 1, 1, yaw=-0.1)["steer"] == pytest.approx(1.95 * 0.1)
    expected = 1.95 * 0.2 + 0.07 * (0.2 - 0.1) / 0.1 + 0.2 * (0.1 + 0.2) * 0.1
    assert _law(p, window, 2, 2, yaw=-0.2)["steer"] == pytest.approx(expected)


def test_the_law_is_the_same_after_a_window_wraps():
    """Two windows that hold the same errors at other ring slots give the same commands (the sum is over all
    slots, the derivative from the slot before)."""
    p = _params(EgoConfig())
    a, b = np.zeros((10, 2)), np.zeros((10, 2))
    rng = np.random.default_rng(1)
    for k in range(30):
        state = dict(x=float(rng.uniform(0, 50)), yaw=float(rng.normal(0, 0.05)), speed=float(rng.uniform(5, 12)))
        ra, rb = _law(p, a, (k + 1) % 10, k + 1, **state), _law(p, b, (k + 4) % 10, k + 1, **state)
        assert ra == pytest.approx(rb, abs=1e-12), k


def test_throttle_brake_and_steer_limits():
    """VehiclePIDController.run_step: throttle <= 0.75, brake <= 0.3, steering within 0.1 of the last and +-0.8."""
    # A proportional law (kp 1/3.6 on the speed error in km/h: the command is the speed error in m/s; kp 1 on the
    # heading error, which is -yaw on a straight path) makes the commands what we choose.
    p = _params(EgoConfig(), kp_long=1 / 3.6, kd_dt_long=0.0, ki_dt_long=0.0, kp_lat=1.0, kd_dt_lat=0.0,
                ki_dt_lat=0.0, target_speed=8.0)
    cases = [(0.5, 0.9, 0.75), (0.9, -0.9, 0.0), (-0.1, 0.05, 0.0), (-0.9, 0.0, 0.0)]  # (u_long, u_lat, steer_past)
    got = [_law(p, np.zeros((10, 2)), 1, 2, speed=8.0 - u_long, yaw=-u_lat, steer_past=past)
           for u_long, u_lat, past in cases]
    np.testing.assert_allclose([r["throttle"] for r in got], [0.5, 0.75, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose([r["brake"] for r in got], [0.0, 0.0, 0.1, 0.3], atol=1e-12)
    np.testing.assert_allclose([r["steer"] for r in got], [0.8, -0.1, 0.05, 0.0], atol=1e-12)


@pytest.mark.parametrize("ego", [EgoConfig(start_lane=1),
                                 EgoConfig(start_lane=1, lateral_pid=SWAPPED_LATERAL,
                                           longitudinal_pid=SWAPPED_LONGITUDINAL)],
                         ids=["paper-gains", "swapped-gains"])
def test_lane_change_reaches_target_lane_without_overshoot(ego):
    cfg = ScenarioConfig(traffic=TrafficConfig(num_vehicles=0), ego=ego, render_image=False)
    core = LaneChangeCore(cfg, 1)
    core.reset([0], [0])
    sim = core.sim
    for _ in range(4):
        core.step(np.array([KEEP]))
    assert abs(sim.speed[0, 0] * 3.6 - 30.0) < 0.2  # cruise settles at the target speed
    ys, ts = [], []
    sim.hooks.append(lambda s: (ys.append(s.y[0, 0]), ts.append(s.t_s[0])))
    t0 = sim.t_s[0]
    core.step(np.array([LEFT]))
    assert core.action_mask()[0].tolist() == [False, True, False]  # change in progress: keep only
    for _ in range(12):
        core.step(np.array([KEEP]))
    ys_a, ts_a = np.array(ys), np.array(ts) - t0
    target = 2.5 * cfg.road.lane_width_m
    reached = ts_a[np.argmax(np.abs(ys_a - target) < 0.3)]
    assert reached <= ego.lane_change_time_s + 1.5, reached  # about lane_change_time
    assert ys_a.max() - target < 0.3  # bounded overshoot
    assert abs(ys_a[-1] - target) < 0.05
    assert sim.lane[0, 0] == 2 and not sim.ego_lc_active[0]
    assert core.action_mask()[0].all()
