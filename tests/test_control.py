"""Control laws against hand-computed values, and a lane change end to end."""

import numpy as np
import pytest

from lcsim.config import (
    SWAPPED_LATERAL,
    SWAPPED_LONGITUDINAL,
    EgoConfig,
    PIDGains,
    ScenarioConfig,
    TrafficConfig,
)
from lcsim.control import ArrayOps, FloatOps, PIDBank, ego_step, pid_reference
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


def test_pid_bank_matches_carla_law_and_hand_values():
    gains = [PIDGains(kp=1.0, ki=0.0, kd=0.75, dt_s=0.1), PIDGains(kp=1.95, ki=0.2, kd=0.07, dt_s=0.1)]
    bank = PIDBank(1, gains, window=10)
    rng = np.random.default_rng(0)
    errs: list[list[float]] = [[], []]
    for k in range(25):
        e = rng.normal(0, 0.3, size=2)
        out = bank.step(e[None, :])[0]
        for c in range(2):
            errs[c].append(float(e[c]))
            g = gains[c]
            assert out[c] == pytest.approx(pid_reference(errs[c], g.kp, g.ki, g.kd, g.dt_s), abs=1e-12), (k, c)
    # Hand values: first step has no I/D; second step adds them (window of two).
    bank = PIDBank(1, gains[1:], window=10)
    assert bank.step(np.array([[0.1]]))[0, 0] == pytest.approx(1.95 * 0.1)
    expected = 1.95 * 0.2 + 0.07 * (0.2 - 0.1) / 0.1 + 0.2 * (0.1 + 0.2) * 0.1
    assert bank.step(np.array([[0.2]]))[0, 0] == pytest.approx(expected)
    assert bank.step(np.array([[5.0]]))[0, 0] == 1.0  # clipped


def test_pid_step_one_is_bit_identical_to_the_batched_step():
    """The single-environment path on floats gives exactly what the batched array path gives, including
    after a reset, with errors spanning many magnitudes (which would expose another summation order) and
    small enough that the output is not clipped."""
    gains = [PIDGains(kp=1.0, ki=0.05, kd=0.75, dt_s=0.05), PIDGains(kp=1.95, ki=0.2, kd=0.07, dt_s=0.05)]
    one, batch = PIDBank(1, gains, window=10), PIDBank(3, gains, window=10)
    rng = np.random.default_rng(1)
    for k in range(60):
        if k == 30:
            one.reset(np.array([0]))
            batch.reset(np.array([0]))
        e = 0.02 * rng.standard_normal((3, 2)) * 10.0 ** rng.integers(-9, 1, size=(3, 2))
        got = one.step_one(tuple(e[0].tolist()))
        want = batch.step(e)[0].tolist()
        assert got == want, k
        assert max(abs(u) for u in got) < 1.0
    assert one.count.item(0) == batch.count[0, 0]
    np.testing.assert_array_equal(one.errors[0], batch.errors[0])


def _step(ops, cfg, n, rng, pid):
    """One ego_step on ``n`` random states (arrays for ArrayOps, the first state's floats for FloatOps)."""
    state = dict(x=rng.uniform(0, 500, n), y=rng.uniform(0, 14, n), yaw=rng.normal(0, 0.1, n),
                 speed=rng.uniform(0, 12, n), lead_gap=rng.uniform(0, 60, n), steer_past=rng.uniform(-0.8, 0.8, n),
                 accel_past=rng.normal(0, 1, n))
    path = (rng.uniform(0, 500, n), rng.uniform(2, 20, n), rng.uniform(0, 14, n), rng.uniform(0, 14, n))
    if ops is FloatOps:
        state = {k: float(v[0]) for k, v in state.items()}
        path = tuple(float(v[0]) for v in path)
    return ego_step(ops, cfg, **state, target_speed=30 / 3.6, path=path, lag_alpha=0.25, dt=0.05, pid=pid)


@pytest.mark.parametrize("cfg", [EgoConfig(), EgoConfig(adaptive_cruise=True)], ids=["plain", "adaptive-cruise"])
def test_the_control_law_gives_the_same_bits_on_floats_and_on_arrays(cfg):
    """Written once, run two ways: one environment's floats and a batch's arrays agree bit for bit."""
    def pid(e_speed, e_head):  # a stand-in controller: any function of the errors will do
        return np.tanh(0.3 * e_speed), np.tanh(2.0 * e_head)

    def pid_float(e_speed, e_head):
        u, v = pid(np.array([e_speed]), np.array([e_head]))
        return float(u[0]), float(v[0])

    for seed in range(200):
        batch = _step(ArrayOps, cfg, 3, np.random.default_rng(seed), pid)
        one = _step(FloatOps, cfg, 3, np.random.default_rng(seed), pid_float)
        for field in ("x", "y", "yaw", "speed", "accel", "steer", "throttle", "brake"):
            assert getattr(one, field) == getattr(batch, field)[0], (seed, field)


def test_throttle_brake_and_steer_limits():
    """VehiclePIDController.run_step: throttle <= 0.75, brake <= 0.3, steering within 0.1 of the last and +-0.8."""
    cfg = EgoConfig()
    u_long, u_lat = np.array([0.5, 0.9, -0.1, -0.9]), np.array([0.9, -0.9, 0.05, 0.0])
    r = ego_step(ArrayOps, cfg, x=np.zeros(4), y=np.zeros(4), yaw=np.zeros(4), speed=np.full(4, 8.0),
                 target_speed=8.0, lead_gap=np.full(4, 100.0), path=(np.zeros(4), np.full(4, 10.0), np.zeros(4),
                                                                      np.zeros(4)),
                 steer_past=np.array([0.75, 0.0, 0.0, 0.0]), accel_past=np.zeros(4), lag_alpha=1.0, dt=0.05,
                 pid=lambda e_speed, e_head: (u_long, u_lat))  # fmt: skip
    np.testing.assert_allclose(r.throttle, [0.5, 0.75, 0.0, 0.0])
    np.testing.assert_allclose(r.brake, [0.0, 0.0, 0.1, 0.3])
    np.testing.assert_allclose(r.steer, [0.8, -0.1, 0.05, 0.0])


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
