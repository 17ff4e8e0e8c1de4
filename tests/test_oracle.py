"""The omniscient search: what it finds wins on replay, a boxed-in ego has no winning plan, and the oracle
driver plays its plans bit for bit inside a batch."""

import numpy as np
import pytest

from lcsim.config import RoadConfig, TrafficConfig
from lcsim.core import RUNNING, LaneChangeCore
from lcsim.drivers import RuleBasedDriver
from lcsim.planning import OracleDriver, replay, search_episode, search_from
from lcsim.registry import make_driver
from tests.conftest import small_config

# 12 vehicles on the 150 m route: the rule-based driver crashes in episode 1 and wins episode 0.
BUSY = small_config(traffic=TrafficConfig(num_vehicles=12, spawn_behind_m=40.0, spawn_ahead_m=120.0),
                    render_image=False)
# Two lanes packed with traffic at 6 km/h and no lane changes: the ego (30 km/h, no brakes) cannot get past.
BOXED = small_config(road=RoadConfig(num_lanes=2), render_image=False,
                     traffic=TrafficConfig(num_vehicles=10, spawn_behind_m=0.0, spawn_ahead_m=120.0, speed_kmh=6.0,
                                           speed_spread_kmh=0.0, lane_changes=False))


def _drive(config, seeds, driver):
    core = LaneChangeCore(config, len(seeds))
    core.reset(range(len(seeds)), seeds)
    actions = []
    while (core.outcome == RUNNING).any():
        actions.append(driver({}, core.action_mask(), core))
        core.step(actions[-1])
    return core.outcome.tolist(), np.array(actions)


def test_search_wins_an_episode_the_rule_driver_crashes_and_its_plan_replays_to_success():
    assert _drive(BUSY, [1], RuleBasedDriver())[0] == ["collision"]
    result = search_episode(BUSY, 1)
    assert result.winnable is True and result.outcomes.get("collision", 0) > 0  # it had to back out of crashes
    assert len(result.actions) == result.deepest == len(result.ego_xy)
    assert replay(BUSY, 1, result.actions) == "success"
    assert replay(BUSY, 1, result.actions[:-1]) == RUNNING  # the last decision is the one that reaches the end
    again = search_episode(BUSY, 1)
    assert again.actions == result.actions and again.nodes == result.nodes  # deterministic


def test_search_reports_no_winning_plan_when_the_ego_is_boxed_in():
    result = search_episode(BOXED, 0)
    assert result.winnable is False and set(result.outcomes) == {"collision"}
    # The longest-surviving branch is kept: it survives up to its end, and one more decision of any kind crashes.
    assert 0 < result.deepest == len(result.actions) < BOXED.time_limit_s / BOXED.decision_period_s
    assert replay(BOXED, 0, result.actions) == RUNNING
    assert {replay(BOXED, 0, [*result.actions, a]) for a in (0, 1, 2)} <= {"collision", "off_road"}
    stopped = search_episode(BOXED, 0, max_nodes=3)
    assert stopped.winnable is None and stopped.nodes == 3


def test_oracle_driver_plays_its_plans_inside_a_batch_and_refuses_an_episode_it_did_not_drive():
    seeds = [1, 0, 5]
    outcomes, actions = _drive(BUSY, seeds, make_driver("oracle"))
    assert outcomes == ["success"] * 3
    for i, seed in enumerate(seeds):
        plan = search_episode(BUSY, seed).actions
        assert actions[: len(plan), i].tolist() == plan  # the batch follows each single-episode plan exactly
    core = LaneChangeCore(BUSY, 1)
    core.reset([0], [1])
    driver = OracleDriver()
    mask = core.action_mask()
    first = int(driver({}, mask, core)[0])
    core.step(np.array([next(a for a in (0, 1, 2) if a != first and mask[0, a])]))  # leave the plan
    with pytest.raises(RuntimeError, match="oracle's plan"):
        driver({}, core.action_mask(), core)


def test_search_from_a_state_mid_episode_continues_it_and_leaves_the_state_untouched():
    core = LaneChangeCore(BUSY, 1)
    core.reset([0], [1])
    prefix, rule = [], RuleBasedDriver()
    for _ in range(6):
        prefix.append(int(rule({}, core.action_mask(), core)[0]))
        core.step(np.array(prefix[-1:]))
    before = (core.sim.x.copy(), core.sim.step.copy(), core.outcome.copy())
    result = search_from(core)
    assert np.array_equal(core.sim.x, before[0]) and np.array_equal(core.sim.step, before[1])
    assert (core.outcome == before[2]).all()
    assert result.winnable is True and replay(BUSY, 1, prefix + result.actions) == "success"


def test_search_rejects_bad_settings():
    with pytest.raises(ValueError, match="single-environment"):
        search_from(LaneChangeCore(BUSY, 2))
    with pytest.raises(ValueError, match="memory_decisions"):
        search_episode(BUSY, 0, memory_decisions=0)
    with pytest.raises(ValueError, match="max_nodes"):
        search_episode(BUSY, 0, max_nodes=0)
