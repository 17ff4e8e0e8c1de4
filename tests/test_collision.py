"""Oriented-rectangle collisions: exact where coarse or axis-aligned tests are wrong, and in the sim."""

import math

import numpy as np

from lcsim.collision import obb_overlap
from lcsim.config import EgoConfig, ScenarioConfig, TrafficConfig
from lcsim.core import COLLISION, KEEP, LaneChangeCore


def _aabb_overlap_unrotated(xa, ya, la, wa, xb, yb, lb, wb):
    """What a check that ignores yaw would say."""
    return abs(xb - xa) <= (la + lb) / 2 and abs(yb - ya) <= (wa + wb) / 2


def test_rotated_corner_contact_missed_by_yaw_free_check():
    # A car yawed by 30 degrees beside another: its corner reaches into the neighbour,
    # although the unrotated footprints are 0.3 m apart laterally.
    a = (0.0, 0.0, math.radians(30), 5.0, 2.0)
    b = (1.0, 2.3, 0.0, 5.0, 2.0)
    assert not _aabb_overlap_unrotated(a[0], a[1], a[3], a[4], b[0], b[1], b[3], b[4])
    assert obb_overlap(*map(np.array, a), *map(np.array, b))


def test_close_but_separated_rotated_boxes():
    # Bounding circles overlap (a coarse test says "close"), the rectangles do not touch.
    a = (0.0, 0.0, math.radians(45), 5.0, 1.0)
    b = (2.6, -2.6, math.radians(45), 5.0, 1.0)
    ra = rb = 0.5 * math.hypot(5.0, 1.0)
    assert math.hypot(b[0] - a[0], b[1] - a[1]) <= ra + rb
    assert not obb_overlap(*map(np.array, a), *map(np.array, b))
    # Touching edges count as contact.
    assert obb_overlap(np.array(0.0), np.array(0.0), np.array(0.0), np.array(4.0), np.array(2.0),
                       np.array(4.0), np.array(0.0), np.array(0.0), np.array(4.0), np.array(2.0))


def test_ego_without_brakes_hits_a_slow_leader():
    cfg = ScenarioConfig(traffic=TrafficConfig(num_vehicles=1, spawn_behind_m=0.0, spawn_ahead_m=40.0,
                                               speed_kmh=10.0, speed_spread_kmh=0.0, ego_clearance_m=10.0,
                                               min_spawn_gap_m=0.0, lane_changes=False),
                         ego=EgoConfig(start_lane=0), road=ScenarioConfig().road.__class__(num_lanes=2),
                         render_image=False)
    core = LaneChangeCore(cfg, 1)
    core.reset([0], [3])
    sim = core.sim
    sim.y[0, 1] = sim.y[0, 0]  # put the one traffic vehicle in the ego's lane, ahead
    sim.x[0, 1] = 30.0
    sim.lane[0, 1] = sim.target_lane[0, 1] = 0
    sim.rebuild_index()
    for _ in range(40):
        res = core.step(np.array([KEEP]))
        if res.terminated[0]:
            break
    assert res.outcome[0] == COLLISION
    assert sim.collision_with[0] == 1
    assert res.components["collision"][0] == cfg.reward.collision
    # Frozen at the contact: the bodies touch but have not driven through each other.
    gap = sim.x[0, 1] - sim.x[0, 0] - 0.5 * (sim.length[0, 0] + sim.length[0, 1])
    assert -0.5 < gap <= 0.0
