"""experiments/imagined_drivers: the drivers' estimator, and the safety layer imagining drawn, known or estimated
drivers or a longer ego, on small real episodes."""

import subprocess
import sys

import numpy as np
import pytest

from lcsim.config import ScenarioConfig, TrafficConfig
from lcsim.core import KEEP, RUNNING, LaneChangeCore
from lcsim.planning import LookaheadDriver, SafetyLayerConfig
from lcsim.registry import make_driver, scenario
from lcsim.traffic import DriverParams

from .estimate import LONGITUDINAL, DriverEstimator
from .imagined_drivers import ImaginedDriversLayer, main


def small_config(**overrides) -> ScenarioConfig:
    """A 150 m route (the traffic as given): fast, with traffic around the ego."""
    return ScenarioConfig(**{"route_length_m": 150.0, "time_limit_s": 25.0, **overrides})


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


def _human_core(envs: int, seeds: list[int]) -> LaneChangeCore:
    cfg = small_config(render_image=False, traffic=TrafficConfig(num_vehicles=24, spawn_behind_m=40.0,
                                                                 spawn_ahead_m=140.0, human_like=True))
    core = LaneChangeCore(cfg, envs)
    core.reset(range(envs), seeds)
    return core


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


def test_known_drivers_keep_those_parameters_true_in_the_imagined_future_and_nothing_else():
    core = _human_core(2, [3, 4])
    for _ in range(3):
        core.step(np.full(2, KEEP))
    true = {n: getattr(core.sim.drivers, n).copy() for n in DriverParams.__slots__}
    layer = ImaginedDriversLayer(SafetyLayerConfig(), known=("lag", "time_headway"))
    rows = np.arange(2)
    future = core.replicate(rows)
    layer.imagine(future, 1, rows)
    traffic = core.sim.is_traffic.copy()
    traffic[:, 0] = False
    drivers = future.sim.drivers
    assert np.array_equal(drivers.lag[traffic], true["lag"][traffic])
    assert np.array_equal(drivers.time_headway[traffic], true["time_headway"][traffic])
    assert np.ptp(drivers.max_accel[traffic]) == 0.0 != np.ptp(true["max_accel"][traffic])  # the median driver
    with pytest.raises(ValueError, match="'reaction' is not a driver parameter"):
        ImaginedDriversLayer(SafetyLayerConfig(), known=("reaction",))


def test_the_variants_need_the_layer_they_change():
    with pytest.raises(ValueError, match="perceived"):
        ImaginedDriversLayer(SafetyLayerConfig(perceived=False), estimate=True)
    with pytest.raises(ValueError, match="perceived"):
        ImaginedDriversLayer(SafetyLayerConfig(perceived=False), draw=True)
    with pytest.raises(ValueError, match="blind"):
        ImaginedDriversLayer(SafetyLayerConfig(blind=False, perceived=False), margin_m=1.0)
    with pytest.raises(ValueError, match=r"\[0, 10\]"):
        ImaginedDriversLayer(SafetyLayerConfig(), margin_m=-0.5)


def test_without_a_variant_it_decides_as_the_product_safety_layer():
    runs = []
    for cls in (LookaheadDriver, ImaginedDriversLayer):
        core = _human_core(3, [31, 32, 33])
        driver = cls(SafetyLayerConfig(horizon_decisions=4, samples=2))
        seen = []
        for _ in range(12):
            if (core.outcome != RUNNING).any():
                break
            seen.append(driver({}, core.action_mask(), core))
            core.step(seen[-1])
        runs.append((np.stack(seen), driver.overrides))
    assert np.array_equal(runs[0][0], runs[1][0]) and runs[0][1] == runs[1][1]


@pytest.mark.parametrize("variant", [{"estimate": True}, {"draw": True}])
def test_the_estimating_and_drawing_layers_are_deterministic(variant):
    runs = []
    for _ in range(2):
        core = _human_core(3, [21, 22, 23])
        driver = ImaginedDriversLayer(SafetyLayerConfig(horizon_decisions=6, samples=2), **variant)
        seen = []
        for _ in range(12):
            if (core.outcome != RUNNING).any():
                break
            seen.append(driver({}, core.action_mask(), core))
            core.step(seen[-1])
        if variant.get("estimate"):
            assert driver._estimator is not None and driver._estimator.evidence.any()
        runs.append(np.stack(seen))
    assert np.array_equal(runs[0], runs[1])


def test_a_margin_makes_the_imagined_ego_longer_and_refuses_tight_decisions():
    cfg = small_config(render_image=False, traffic=TrafficConfig(num_vehicles=24, spawn_behind_m=40.0,
                                                                 spawn_ahead_m=140.0))
    core = LaneChangeCore(cfg, 4)
    core.reset(range(4), [11, 12, 13, 14])
    plain = ImaginedDriversLayer(SafetyLayerConfig(horizon_decisions=6, perceived=False))
    margin = ImaginedDriversLayer(SafetyLayerConfig(horizon_decisions=6, perceived=False), margin_m=3.0)
    length = core.sim.length.copy()
    survived = np.zeros(2, dtype=int)
    for _ in range(20):
        if (core.outcome != "").any():
            break
        mask = core.action_mask()
        for a in range(3):
            act = np.where(mask[:, a], a, KEEP)
            plain_ok, margin_ok = (d.survives(core, act) & mask[:, a] for d in (plain, margin))
            survived += (int(plain_ok.sum()), int(margin_ok.sum()))
        core.step(plain({}, mask, core))
    assert 0 < survived[1] < survived[0]  # 3 m more room at each end: fewer decisions survive, not none
    assert np.array_equal(core.sim.length, length)  # only the imagined copies are longer


def test_the_script_runs_a_variant_and_names_bad_input_in_one_line(capsys):
    assert main(["safety-layer:rule", "--set", "safety.horizon_decisions=2", "--known-drivers", "lag",
                 "--episodes", "2", "--batch", "2", "-q"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "held-out evaluation, 2 episodes" in out and "overrode" in out
    assert main(["rule", "--episodes", "2"]) == 2  # behind no safety layer
    assert capsys.readouterr().err.count("\n") == 1
    bad = subprocess.run([sys.executable, "-m", "experiments.imagined_drivers.imagined_drivers", "safety-layer:rule",
                          "--known-drivers", "lag,reaction"], capture_output=True, text=True)  # fmt: skip
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert "'reaction' is not a driver parameter" in bad.stderr.strip().splitlines()[-1]


def test_a_perceived_copy_can_draw_plausible_drivers_instead():
    """Drawn, the copy's unseen drivers come from the traffic's distribution: the same state and salt give the same
    drivers, another salt others, and the ego keeps its own parameters."""
    from lcsim.planning import imagined_copy, perceive, redraw_future

    from .imagined_drivers import draw_drivers

    core = LaneChangeCore(ScenarioConfig(render_image=False, traffic=TrafficConfig(human_like=True)), 2)
    core.reset([0, 1], [5, 6])
    drawn = []
    for salt in (1, 1, 2):
        copy_ = imagined_copy(core)
        redraw_future(copy_.sim, salt)
        perceive(copy_.sim, 1000.0)
        traffic = copy_.sim.is_traffic.copy()
        traffic[:, 0] = False
        draw_drivers(copy_.sim, traffic)
        drawn.append(copy_.sim.drivers.time_headway.copy())
        assert np.array_equal(copy_.sim.drivers.max_accel[:, 0], core.sim.drivers.max_accel[:, 0])
    assert np.array_equal(drawn[0], drawn[1])
    assert not np.array_equal(drawn[0][:, 1:], drawn[2][:, 1:])
    assert drawn[0][:, 1:].std() > 0  # not the median driver
    assert not np.array_equal(drawn[0][:, 1:], core.sim.drivers.time_headway[:, 1:])  # nor the true ones
    tc = core.config.traffic
    spread = np.log(drawn[0][:, 1:] / tc.idm_time_headway_s)
    assert np.abs(spread).max() <= 2.5 * tc.driver_spread + 1e-9  # within the distribution's clipped range
