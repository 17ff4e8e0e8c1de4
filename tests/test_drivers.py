"""Non-learning drivers: the rule-based driver completes most episodes; an ACC lane keeper times out; the
safety layer only ever overrides the rule with a decision that survives its horizon."""

import collections
import copy

import numpy as np
import pytest

from lcsim import rng
from lcsim.config import EgoConfig, ScenarioConfig, TrafficConfig
from lcsim.core import KEEP, LaneChangeCore
from lcsim.envs import LaneChangeVectorEnv
from lcsim.planning import (
    LookaheadDriver,
    SafetyLayerConfig,
    estimated_desired_speeds,
    imagined_copy,
    perceive,
    redraw_future,
)
from lcsim.registry import make_driver
from tests.conftest import small_config


def _outcomes(driver_name: str, cfg: ScenarioConfig, n: int, seed: int) -> collections.Counter:
    env = LaneChangeVectorEnv(n, cfg)
    obs, info = env.reset(seed=seed)
    driver = make_driver(driver_name, seed)
    outcome: list[str | None] = [None] * n
    mask = info["action_mask"]
    while any(o is None for o in outcome):
        obs, _, term, trunc, info = env.step(driver(obs, mask, env.core))
        mask = info["action_mask"]
        for i in np.flatnonzero(term | trunc):
            outcome[i] = outcome[i] or info["outcome"][i]
    return collections.Counter(outcome)


def test_rule_driver_completes_a_good_share_of_episodes():
    res = _outcomes("rule", ScenarioConfig(render_image=False), 24, seed=500)
    assert res["success"] >= 7, res  # measured 46% over 96 episodes of human-like traffic (49% of exact IDM)


def test_adaptive_cruise_lane_keeper_cannot_make_the_time_limit():
    cfg = ScenarioConfig(render_image=False, ego=EgoConfig(adaptive_cruise=True))
    res = _outcomes("keep", cfg, 16, seed=900)
    assert res["timeout"] >= 12 and res["collision"] == 0, res


def test_random_driver_respects_the_mask():
    driver = make_driver("random", 3)
    mask = np.array([[False, True, False], [True, True, False], [True, True, True]])
    acts = np.stack([driver({}, mask, None) for _ in range(50)])
    assert (acts[:, 0] == 1).all() and set(acts[:, 1]) <= {0, 1} and set(acts[:, 2]) == {0, 1, 2}


def test_lookahead_picks_a_surviving_decision_and_leaves_the_simulator_untouched():
    # Dense traffic on a short route, so that some decisions are traps.
    cfg = small_config(traffic=TrafficConfig(num_vehicles=24, spawn_behind_m=40.0, spawn_ahead_m=140.0))
    core = LaneChangeCore(cfg, 4)
    core.reset(range(4), [11, 12, 13, 14])
    calls = []
    core.sim.hooks.append(lambda sim: calls.append(int(sim.step[0])))
    driver = LookaheadDriver(SafetyLayerConfig(horizon_decisions=6, blind=False, perceived=False))
    decisions = 0
    while (core.outcome == "").all() and decisions < 40:
        mask = core.action_mask()
        before = (core.sim.x.copy(), core.sim.y.copy(), core.sim.step.copy(), len(calls))
        actions = driver({}, mask, core)
        assert np.array_equal(core.sim.x, before[0]) and np.array_equal(core.sim.y, before[1])
        assert np.array_equal(core.sim.step, before[2]) and len(calls) == before[3]  # hooks saw nothing
        ok = np.stack([driver.survives(core, np.where(mask[:, a], a, KEEP)) & mask[:, a] for a in range(3)], 1)
        rows = np.arange(4)
        assert mask[rows, actions].all()
        assert (ok[rows, actions] | ~ok.any(1)).all(), (actions, ok)  # never a doomed choice if one survives
        core.step(actions)
        decisions += 1
    assert decisions > 5 and len(calls) == decisions * cfg.steps_per_decision


@pytest.mark.parametrize("blind", [False, True])
def test_lookahead_driver_is_deterministic_and_named(blind: bool):
    name = "lookahead-blind" if blind else "lookahead"
    assert make_driver(name).name == name
    runs = []
    for _ in range(2):
        core = LaneChangeCore(small_config(render_image=False), 2)
        core.reset([0, 1], [7, 8])
        driver, actions = LookaheadDriver(SafetyLayerConfig(horizon_decisions=4, blind=blind, perceived=False)), []
        while (core.outcome == "").all():
            actions.append(driver({}, core.action_mask(), core))
            core.step(actions[-1])
        runs.append((np.stack(actions), core.sim.x.copy(), core.outcome.copy()))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    assert list(runs[0][2]) == list(runs[1][2])


def test_redraw_future_keeps_the_present_and_redraws_the_traffics_coming_choices():
    core = LaneChangeCore(small_config(render_image=False), 3)
    core.reset(range(3), [21, 22, 23])
    for _ in range(3):
        core.step(np.full(3, KEEP))
    seen, blind, blind_again = imagined_copy(core), imagined_copy(core), imagined_copy(core)
    redraw_future(blind.sim, 1)
    redraw_future(blind_again.sim, 1)
    for name in ("x", "y", "speed", "lane", "step"):
        assert np.array_equal(getattr(blind.sim, name), getattr(core.sim, name)), name  # the present is kept

    def draws(sim):  # the lane-change stream's draws of the next 50 steps, as the simulator makes them
        return np.stack([rng.uniform(sim.key, sim.step + k, sim.num_vehicles, stream=1, base=sim.lane_change_base)
                         for k in range(50)])

    assert np.array_equal(draws(seen.sim), draws(core.sim))
    assert not np.isclose(draws(blind.sim), draws(core.sim)).any()
    for future in (blind, blind_again):
        for _ in range(20):
            future.step(np.full(3, KEEP))
    assert np.array_equal(blind.sim.x, blind_again.sim.x) and np.array_equal(blind.sim.lane, blind_again.sim.lane)
    with pytest.raises(ValueError, match="salt"):
        redraw_future(blind.sim, 0)


def _dense_core(human_like: bool = True) -> LaneChangeCore:
    """Four unrendered environments in dense traffic on a short route, so that some decisions are traps."""
    cfg = small_config(render_image=False, traffic=TrafficConfig(num_vehicles=24, spawn_behind_m=40.0,
                                                                 spawn_ahead_m=140.0, human_like=human_like))
    core = LaneChangeCore(cfg, 4)
    core.reset(range(4), [11, 12, 13, 14])
    return core


@pytest.mark.slow
def test_blind_lookahead_with_several_futures_keeps_a_decision_that_survives_the_most_of_them():
    core = _dense_core()
    driver = LookaheadDriver(SafetyLayerConfig(horizon_decisions=6, perceived=False, samples=3))
    overridden = 0
    for _ in range(30):
        if (core.outcome != "").any():
            break
        mask = core.action_mask()
        actions = driver({}, mask, core)
        alive = np.stack([sum(driver.survives(core, np.where(mask[:, a], a, KEEP), salt) & mask[:, a]
                              for salt in (1, 2, 3)) for a in range(3)], axis=1)
        rows, choice = np.arange(4), mask.sum(axis=1) > 1
        assert (alive[rows, actions] == alive.max(axis=1))[choice].all(), (actions, alive)
        overridden += int((choice & (actions != driver.rule({}, mask, core))).sum())
        core.step(actions)
    assert overridden > 0  # the traffic is dense enough for the planner to overrule the rule


def test_lookahead_with_a_proposer_keeps_its_decision_unless_that_future_crashes():
    core = _dense_core()
    proposer = make_driver("random", 5)
    proposer.last_prediction = np.zeros((4, 1, 1, 2))  # what a policy that predicts would expose
    driver = LookaheadDriver(SafetyLayerConfig(horizon_decisions=6, perceived=False), proposer=proposer)
    assert driver.name == "random+lookahead-blind-rule" and driver.last_prediction is None  # nothing decided yet
    kept = vetoed = choices = 0
    for _ in range(30):
        if (core.outcome != "").any():
            break
        mask = core.action_mask()
        proposed = make_driver("random", 5)  # the same draws as the proposer's next one
        proposed.rng = copy.deepcopy(proposer.rng)
        wanted = proposed({}, mask, core)
        actions = driver({}, mask, core)
        assert driver.last_prediction is proposer.last_prediction  # what the proposer decided on
        ok = np.stack([driver.survives(core, np.where(mask[:, a], a, KEEP)) & mask[:, a] for a in range(3)], 1)
        rows = np.arange(4)
        stands = ok[rows, wanted] | ~ok.any(axis=1)  # the proposal survives, or nothing does
        assert np.array_equal(actions[stands], wanted[stands]) and ok[rows, actions][~stands].all()
        kept, vetoed = kept + int(stands.sum()), vetoed + int((~stands).sum())
        choices += int((mask.sum(axis=1) > 1).sum())
        core.step(actions)
    assert kept > 0 and vetoed > 0  # random lane changes in dense traffic: some are doomed
    assert (driver.overrides, driver.choices) == (vetoed, choices)  # what lc-eval reports of a planner


def test_lookahead_never_returns_a_decision_the_mask_refuses():
    """A proposer that always wants the right lane, where there is none or a change is under way: its
    proposal counts as the keep the core would make of it, so the planner still checks that keep."""
    core = _dense_core()

    def always_right(obs, mask, core):
        return np.zeros(len(mask), dtype=np.int64)

    driver = LookaheadDriver(SafetyLayerConfig(horizon_decisions=6, perceived=False), proposer=always_right)
    refused = 0
    for _ in range(30):
        if (core.outcome != "").any():
            break
        mask = core.action_mask()
        actions = driver({}, mask, core)
        assert mask[np.arange(4), actions].all(), (actions, mask)
        refused += int((~mask[:, 0]).sum())
        core.step(actions)
    assert refused > 0  # the case arose: a lane change under way, or the ego in the rightmost lane


def test_the_safety_layer_config_refuses_samples_without_blindness():
    with pytest.raises(ValueError, match="samples > 1 needs blind"):
        SafetyLayerConfig(blind=False, perceived=False, samples=2)
    with pytest.raises(ValueError, match="samples must be >= 1"):
        SafetyLayerConfig(samples=0)


def test_perceive_keeps_what_the_sensors_show_and_parks_the_rest():
    core = _dense_core()
    for _ in range(4):
        core.step(np.full(4, KEEP))
    sim = core.sim
    copy_ = imagined_copy(core)
    before = {k: getattr(sim, k).copy() for k in ("x", "y", "speed", "v0")}
    perceive(copy_.sim, 30.0)
    dist = np.hypot(before["x"] - before["x"][:, :1], before["y"] - before["y"][:, :1])
    near, far = dist <= 30.0, dist > 30.0
    assert near[:, 1:].any() and far.any()  # both kinds are there to check
    after = copy_.sim
    assert np.array_equal(after.x[near], before["x"][near]) and np.array_equal(after.speed, before["speed"])
    assert ((after.x - before["x"][:, :1])[far] < -9.9e4).all()
    # the desired speeds are what the motion tells, from the leaders left in view; the ego's own is known
    assert np.array_equal(after.v0[:, 1:], estimated_desired_speeds(after)[:, 1:])
    assert after.v0[0, 0] == before["v0"][0, 0]
    # the observation's slots show the same vehicles, less those beyond the range; the original is untouched
    ids = np.arange(4)
    shown = core.neighbours(ids)
    seen = np.where(near[ids[:, None], np.maximum(shown, 0)] & (shown >= 0), shown, -1)
    assert (seen >= 0).any() and (seen != shown).any()
    assert np.array_equal(copy_.neighbours(ids), seen)
    for k, v in before.items():
        assert np.array_equal(getattr(sim, k), v), k
    with pytest.raises(ValueError, match="range_m"):
        perceive(copy_.sim, 0.0)


def test_desired_speeds_are_recovered_from_the_motion_they_cause():
    """Exactly where every driver follows IDM with the configured parameters (human-like drivers add noise,
    a reaction lag and their own parameters, which the estimate cannot see: it stays within the spread)."""
    core = _dense_core(human_like=False)
    for _ in range(6):
        core.step(np.full(4, KEEP))
    sim = core.sim
    est = estimated_desired_speeds(sim)
    err_kmh = np.abs(est - sim.v0)[:, 1:] * 3.6
    assert np.mean(err_kmh < 0.1) >= 0.9, np.sort(err_kmh.ravel())[-10:]  # 99.9% within 0.5 km/h on the paper scenario
    tc = core.config.traffic
    spread = 2.5 * tc.speed_spread_kmh / 3.6
    assert (est >= tc.speed_kmh / 3.6 - spread - 1e-9).all() and (est <= tc.speed_kmh / 3.6 + spread + 1e-9).all()


def test_perceived_lookahead_is_deterministic_and_only_picks_surviving_decisions():
    runs = []
    for _ in range(2):
        core = _dense_core()
        driver = LookaheadDriver(SafetyLayerConfig(horizon_decisions=6))
        assert driver.name == "lookahead-perceived"
        actions_seen = []
        for _ in range(20):
            if (core.outcome != "").any():
                break
            mask = core.action_mask()
            actions = driver({}, mask, core)
            ok = np.stack([driver.survives(core, np.where(mask[:, a], a, KEEP)) & mask[:, a] for a in range(3)], 1)
            rows, choice = np.arange(4), mask.sum(axis=1) > 1
            assert (ok[rows, actions] | ~ok.any(axis=1))[choice].all(), (actions, ok)
            actions_seen.append(actions)
            core.step(actions)
        runs.append(np.stack(actions_seen))
    assert np.array_equal(runs[0], runs[1])


def test_the_safety_layer_config_refuses_perception_without_blindness():
    with pytest.raises(ValueError, match="perceived needs blind"):
        SafetyLayerConfig(blind=False)
    with pytest.raises(TypeError):  # a research option is no field of the product's layer
        SafetyLayerConfig(driver_draws=True)  # type: ignore[call-arg]


def test_the_planner_reports_the_prediction_its_driver_decided_on():
    """A driver followed in the imagined futures also runs on their batch; the planner's ``last_prediction`` is
    still the one the driver had when it made the decision (one row per environment), not the last imagined one."""

    class Tagging:
        name = "tagging"
        needs_observation = False

        def __call__(self, obs, action_mask, core):
            self.last_prediction = np.full((core.num_envs, 1), float(core.num_envs))
            return np.full(core.num_envs, KEEP, dtype=np.int64)

    env = LaneChangeVectorEnv(4, ScenarioConfig(render_image=False))
    obs, info = env.reset(seed=3)
    driver = LookaheadDriver(SafetyLayerConfig(perceived=False, horizon_decisions=2, samples=2), rule=Tagging())
    for _ in range(3):
        actions = driver(obs, info["action_mask"], env.core)
        assert driver.last_prediction.shape == (4, 1) and (driver.last_prediction == 4.0).all()
        obs, *_, info = env.step(actions)
