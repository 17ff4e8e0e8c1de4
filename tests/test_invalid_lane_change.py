"""A change towards a lane that does not exist: refused (default) or carried off the road."""

from __future__ import annotations

import numpy as np

from lcsim.core import KEEP, LEFT, RIGHT, RUNNING, LaneChangeCore
from tests.conftest import small_config


def _edge_core(mode: str) -> tuple[LaneChangeCore, int]:
    core = LaneChangeCore(small_config(invalid_lane_change=mode, render_image=False), 1)
    core.reset([0], [3])
    lane = int(core.sim.target_lane[0, 0])
    return core, lane


def _towards_nothing(lane: int, num_lanes: int) -> int:
    if lane == 0:
        return RIGHT
    assert lane == num_lanes - 1, "walk the ego to an edge lane first"
    return LEFT


def _drive_to_edge(core: LaneChangeCore) -> None:
    while core.sim.target_lane[0, 0] > 0:
        if core.action_mask()[0, RIGHT]:
            core.step(np.array([RIGHT]))
        else:
            core.step(np.array([KEEP]))
        assert core.outcome[0] == RUNNING
    while core.sim.ego_lc_active[0]:
        core.step(np.array([KEEP]))


def test_refused_change_is_penalised_and_the_episode_goes_on() -> None:
    core, _ = _edge_core("refuse")
    _drive_to_edge(core)
    y = float(core.sim.y[0, 0])
    res = core.step(np.array([_towards_nothing(0, core.sim.road.num_lanes)]))
    assert res.outcome[0] == RUNNING and not res.terminated[0]
    assert res.components["off_road"][0] == core.config.reward.off_road == -10.0
    assert int(core.sim.target_lane[0, 0]) == 0 and not core.sim.ego_lc_active[0]
    assert abs(float(core.sim.y[0, 0]) - y) < 0.2  # stayed in its lane
    # a valid decision afterwards carries no penalty
    assert core.step(np.array([KEEP])).components["off_road"][0] == 0.0


def test_leave_road_mode_drives_off_and_ends_the_episode() -> None:
    core, _ = _edge_core("leave_road")
    _drive_to_edge(core)
    action = _towards_nothing(0, core.sim.road.num_lanes)
    outcome = RUNNING
    for _ in range(20):
        res = core.step(np.array([action if core.action_mask()[0, KEEP] and not core.sim.ego_lc_active[0]
                                  else KEEP]))
        outcome = res.outcome[0]
        if outcome != RUNNING:
            break
    assert outcome == "off_road"
    assert res.components["off_road"][0] == -10.0 and res.terminated[0]
