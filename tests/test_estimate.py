"""The drivers' estimator of the perceived planner, and the known-drivers diagnostic."""

import subprocess
import sys

import numpy as np
import pytest

from lcsim.config import TrafficConfig
from lcsim.core import KEEP, RUNNING, LaneChangeCore
from lcsim.planning import LookaheadConfig, LookaheadDriver
from lcsim.planning.estimate import LONGITUDINAL, DriverEstimator
from lcsim.planning.perception import imagined_copy, perceive
from lcsim.registry import make_driver, scenario
from lcsim.traffic import DriverParams
from tests.conftest import small_config


def _paper_run(decisions: int, envs: int = 8) -> tuple[LaneChangeCore, DriverEstimator]:
    cfg = scenario("paper")
    core = LaneChangeCore(cfg, envs)
    core.reset(np.arange(envs), list(range(100, 100 + envs)))
    est = DriverEstimator(cfg.traffic, cfg.dt_s, cfg.steps_per_decision, cfg.sensing_range_m)
    rule = make_driver("rule")
    for _ in range(decisions):
        est.observe(core)
        core.step(rule(core.observe(), core.action_mask(), core))
        assert (core.outcome == RUNNING).any()
    est.observe(core)
    return core, est


def test_the_estimate_of_each_driver_beats_the_prior_where_the_motion_tells():
    """Reaction time and desired speed show in the motion (rule-based ego on the paper scenario, 8 episodes,
    30 s): the posterior mean is much closer to each vehicle's truth than the traffic's median."""
    core, est = _paper_run(60)
    seen = est.evidence
    assert seen.sum() >= 30 and not seen[:, 0].any()  # vehicles in sight, never the ego
    post = est.posterior()[seen]
    sim = core.sim
    for name, factor in (("lag", 0.6), ("time_headway", 0.95), ("max_accel", 0.95)):
        cand, true = getattr(est.candidates, name), getattr(sim.drivers, name)[seen]
        prior = np.sqrt(np.mean((np.log(cand.mean()) - np.log(true)) ** 2))
        mean = np.sqrt(np.mean((np.log((post * cand).sum(-1)) - np.log(true)) ** 2))
        assert mean < factor * prior, (name, mean, prior)
    v0_prior = np.sqrt(np.mean((np.exp(est.log_prior) @ est.v0 - sim.v0[seen]) ** 2))
    v0_post = np.sqrt(np.mean(((post * est.v0).sum(-1) - sim.v0[seen]) ** 2))
    assert v0_post < 0.7 * v0_prior, (v0_post, v0_prior)


def test_a_new_episode_forgets_and_draws_are_reproducible():
    core, est = _paper_run(6, envs=2)
    assert est.evidence[0].any() and est.evidence[1].any()
    rows, salt, step = np.array([0, 0, 1]), np.array([1, 2, 1]), np.array([7, 7, 7])
    a, v0a, seen = est.draw(rows, salt, step)
    b, v0b, _ = est.draw(rows, salt, step)
    assert np.array_equal(seen, est.evidence[rows]) and np.isnan(v0a[~seen]).all()  # drawn only where observed
    assert np.array_equal(v0a, v0b, equal_nan=True) and all(np.array_equal(getattr(a, n), getattr(b, n)) for n in LONGITUDINAL)
    assert not np.array_equal(v0a[0][seen[0]], v0a[1][seen[1]])  # another salt, other plausible drivers
    core.reset([1], [999])
    est.observe(core)
    assert est.evidence[0].any() and not est.evidence[1].any()
    assert np.allclose(est.posterior(np.array([1]))[0], np.exp(est.log_prior))


def test_perceive_keeps_the_known_driver_parameters_and_nothing_else():
    cfg = small_config(render_image=False, traffic=TrafficConfig(num_vehicles=24, spawn_behind_m=40.0,
                                                                 spawn_ahead_m=140.0, human_like=True))
    core = LaneChangeCore(cfg, 2)
    core.reset([0, 1], [3, 4])
    for _ in range(3):
        core.step(np.full(2, KEEP))
    true = {n: getattr(core.sim.drivers, n).copy() for n in DriverParams.__slots__}
    copy_ = imagined_copy(core)
    perceive(copy_.sim, 1e4, known_drivers=("lag", "time_headway"))
    traffic = core.sim.is_traffic.copy()
    traffic[:, 0] = False
    drivers = copy_.sim.drivers
    assert np.array_equal(drivers.lag[traffic], true["lag"][traffic])
    assert np.array_equal(drivers.time_headway[traffic], true["time_headway"][traffic])
    assert np.ptp(drivers.max_accel[traffic]) == 0.0 != np.ptp(true["max_accel"][traffic])  # the median driver
    with pytest.raises(ValueError, match="known_drivers"):
        perceive(imagined_copy(core).sim, 1e4, known_drivers=("reaction",))


def test_lookahead_config_checks_the_estimator_and_known_drivers():
    with pytest.raises(ValueError, match="estimate_drivers"):
        LookaheadConfig(blind=True, estimate_drivers=True)
    with pytest.raises(ValueError, match="known_drivers"):
        LookaheadConfig(blind=True, known_drivers=("lag",))
    with pytest.raises(ValueError, match="known_drivers"):
        LookaheadConfig(blind=True, perceived=True, known_drivers=("reaction",))
    assert LookaheadConfig(blind=True, perceived=True, known_drivers=["lag"]).known_drivers == ("lag",)  # from JSON


def test_estimating_planner_is_deterministic_and_only_picks_surviving_decisions():
    cfg = small_config(render_image=False, traffic=TrafficConfig(num_vehicles=24, spawn_behind_m=40.0,
                                                                 spawn_ahead_m=140.0, human_like=True))
    runs = []
    for _ in range(2):
        core = LaneChangeCore(cfg, 3)
        core.reset(range(3), [21, 22, 23])
        driver = LookaheadDriver(LookaheadConfig(horizon_decisions=6, blind=True, perceived=True, samples=2,
                                                 estimate_drivers=True))
        seen = []
        for _ in range(12):
            if (core.outcome != RUNNING).any():
                break
            actions = driver({}, core.action_mask(), core)
            seen.append(actions)
            core.step(actions)
        assert driver._estimator is not None and driver._estimator.evidence.any()
        runs.append(np.stack(seen))
    assert np.array_equal(runs[0], runs[1])


def test_lc_eval_names_a_bad_driver_parameter_in_one_line():
    out = subprocess.run([sys.executable, "-c", "import sys; from lccli.evaluate import eval_main; sys.exit(eval_main())", "rule", "--lookahead-known-drivers", "lag,reaction"],
                         capture_output=True, text=True)  # fmt: skip
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert "Traceback" not in out.stderr and "'reaction' is not a driver parameter" in lines[-1]
