"""Traffic: no overlaps at spawn, no traffic collisions, lane changes happen, the road ahead never empties."""

import numpy as np

from lcsim.collision import obb_overlap
from lcsim.config import EgoConfig, ScenarioConfig
from lcsim.core import KEEP, LaneChangeCore


def test_spawn_has_no_overlaps_and_keeps_the_egos_spot_free():
    core = LaneChangeCore(ScenarioConfig(render_image=False), 8)
    core.reset(np.arange(8), list(range(8)))
    sim = core.sim
    n = sim.num_vehicles
    i, j = np.triu_indices(n, 1)
    for e in range(8):
        hit = obb_overlap(sim.x[e, i], sim.y[e, i], sim.yaw[e, i], sim.length[e, i], sim.width[e, i],
                          sim.x[e, j], sim.y[e, j], sim.yaw[e, j], sim.length[e, j], sim.width[e, j])
        assert not hit.any()
        gap = sim.index.gap[e, 0]  # the ego's leader, if any, starts beyond the clearance
        assert not np.isfinite(gap) or gap > 10.0


def test_long_autopilot_run_has_no_collisions_and_some_lane_changes():
    cfg = ScenarioConfig(render_image=False, ego=EgoConfig(adaptive_cruise=True))
    core = LaneChangeCore(cfg, 4, autopilot_ego=True)
    core.reset(np.arange(4), [10, 11, 12, 13])
    sim = core.sim
    changes = 0
    lanes = sim.lane.copy()
    for _ in range(120):  # 60 s
        core.step(np.full(4, KEEP))
        changes += int((sim.lane != lanes).sum())
        lanes = sim.lane.copy()
    assert sim.traffic_collisions.sum() == 0
    assert (core.outcome == "").all() or set(core.outcome) <= {"", "timeout", "success"}
    assert changes > 10
    speeds = sim.speed[:, 1:] * 3.6
    assert 18 < speeds.mean() < 26 and speeds.std() > 0.5  # about 24 km/h, not a frozen conveyor belt


def test_traffic_stays_ahead_of_the_ego_for_the_whole_route():
    cfg = ScenarioConfig(render_image=False, ego=EgoConfig(adaptive_cruise=True), time_limit_s=200.0)
    core = LaneChangeCore(cfg, 2)
    core.reset([0, 1], [5, 6])
    sim = core.sim
    while (sim.x[:, 0] < 0.9 * cfg.route_length_m).any() and sim.t_s[0] < 150:
        core.step(np.full(2, KEEP))
    ahead = (sim.x[:, 1:] > sim.x[:, :1]) & (sim.x[:, 1:] < sim.x[:, :1] + 150.0)
    assert (ahead.sum(axis=1) >= 5).all()
