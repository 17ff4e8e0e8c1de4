"""Traffic: no overlaps at spawn, no traffic collisions, lane changes happen, the road ahead never empties."""

import numpy as np
import pytest

from lcsim.collision import obb_overlap
from lcsim.config import EgoConfig, ScenarioConfig, TrafficConfig
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


def _brute_force_index(sim, e):
    """The neighbour index of environment ``e`` by all-pairs search: the sorted order by (x, index), each body's
    lanes (its lateral extent plus a 0.1 m margin, and a changing traffic vehicle's target lane), each vehicle's
    leader (the nearest vehicle ahead sharing a lane), and the nearest member of every lane ahead and behind."""
    n, num_lanes, lw = sim.num_vehicles, sim.road.num_lanes, sim.road.lane_width
    x, y, yaw, length, width = sim.x[e], sim.y[e], sim.yaw[e], sim.length[e], sim.width[e]
    sy = np.abs(np.sin(yaw))
    half = 0.5 * (sy * length + np.sqrt(1.0 - sy * sy) * width) + 0.1
    lo, hi = np.floor((y - half) / lw), np.floor((y + half) / lw)
    extra = np.where(sim.lc_active[e], sim.target_lane[e], -1)
    lanes = np.arange(num_lanes)[:, None]
    member = ((lanes >= lo) & (lanes <= hi)) | (lanes == extra)  # (L, N)
    order = np.lexsort((np.arange(n), x))
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    ahead_of = rank[None, :] > rank[:, None]  # [v, u]: u is ahead of v
    share = (member[:, :, None] & member[:, None, :]).any(axis=0)

    def nearest(candidates):  # (N, N) mask -> the candidate nearest in the sorted order, -1 when none
        r = np.where(candidates, rank[None, :], n)
        best = r.min(axis=1)
        return np.where(best < n, order[np.minimum(best, n - 1)], -1)

    def nearest_behind(candidates):
        r = np.where(candidates, rank[None, :], -1)
        best = r.max(axis=1)
        return np.where(best >= 0, order[np.maximum(best, 0)], -1)

    lead = nearest(ahead_of & share)
    in_lane = {(lane, True): nearest(ahead_of & member[lane][None, :]) for lane in range(num_lanes)}
    in_lane |= {(lane, False): nearest_behind(~ahead_of & member[lane][None, :] & (rank[None, :] != rank[:, None]))
                for lane in range(num_lanes)}
    return order, lead, in_lane


@pytest.mark.parametrize("num_envs", [1, 2])
def test_the_neighbour_index_equals_a_brute_force_search(num_envs):
    """At every step of lane-changing traffic (and the ego's own lane changes): the sorted order, leaders, gaps,
    leader speeds and lane searches of the index the compiled core keeps are those of an all-pairs search."""
    cfg = ScenarioConfig(render_image=False, traffic=TrafficConfig(random_lane_change_rate_per_min=3.0))
    core = LaneChangeCore(cfg, num_envs)
    core.reset(list(range(num_envs)), [21 + k for k in range(num_envs)])
    sim = core.sim
    n, num_lanes = sim.num_vehicles, sim.road.num_lanes
    changes = 0
    for step in range(300):
        sim.substep()
        changes += int(sim.lc_active[:, 1:].sum())
        index = sim.index
        for e in range(num_envs):
            order, lead, in_lane = _brute_force_index(sim, e)
            np.testing.assert_array_equal(index.order[e], order, err_msg=f"order, step {step}")
            np.testing.assert_array_equal(index.lead[e], lead, err_msg=f"lead, step {step}")
            has = lead >= 0
            gap = sim.x[e, np.maximum(lead, 0)] - sim.x[e] - 0.5 * (sim.length[e] + sim.length[e, np.maximum(lead, 0)])
            np.testing.assert_allclose(index.gap[e][has], gap[has], rtol=0, atol=1e-9)
            assert np.isinf(index.gap[e][~has]).all() and (index.lead_speed[e][~has] == 0).all()
            np.testing.assert_array_equal(index.lead_speed[e][has], sim.speed[e, lead[has]])
        lanes = np.tile(np.arange(-1, num_lanes + 1), (num_envs, 1))
        for ahead in (True, False):
            got = index.neighbour_in_lane(np.repeat(lanes, n, axis=1).reshape(num_envs, -1), ahead,
                                          vehicles=np.tile(np.arange(n), lanes.shape[1]))
            got = got.reshape(num_envs, lanes.shape[1], n)
            for e in range(num_envs):
                _, _, in_lane = _brute_force_index(sim, e)
                for j, lane in enumerate(lanes[e]):
                    want = in_lane[(lane, ahead)] if 0 <= lane < num_lanes else np.full(n, -1)
                    np.testing.assert_array_equal(got[e, j], want, err_msg=f"lane {lane}, ahead {ahead}, step {step}")
        if step % 10 == 0:
            core.step(np.array([step // 10 % 3, 2 - step // 10 % 3][:num_envs]))
    assert changes > 50  # lane changers were in the index


@pytest.mark.parametrize(("num_envs", "autopilot_ego"), [(1, False), (1, True), (2, False)])
def test_lanes_follow_the_positions_after_every_substep(num_envs, autopilot_ego):
    """``lane`` is the lane of ``y``; ``target_lane`` is ``lane`` but during a change (the ego's: while its
    path runs). A single environment redoes only the vehicles that moved sideways: check both against the
    formula over every vehicle, through traffic and ego lane changes."""
    from lcsim.sim import HighwaySim

    cfg = ScenarioConfig(render_image=False, traffic=TrafficConfig(random_lane_change_rate_per_min=3.0))
    sim = HighwaySim(cfg, num_envs, autopilot_ego=autopilot_ego)
    sim.reset(np.arange(num_envs), [5 + k for k in range(num_envs)])
    changes = 0
    for step in range(400):
        if not autopilot_ego and step % 40 == 0:
            sim.start_lane_change(np.ones(num_envs, dtype=bool), np.where(sim.target_lane[:, 0] > 0, -1, 1))
        sim.substep()
        lane = np.clip(np.floor(sim.y / sim.road.lane_width), 0, sim.road.num_lanes - 1).astype(np.int64)
        np.testing.assert_array_equal(sim.lane, lane, err_msg=f"step {step}")
        changing = sim.lc_active.copy()
        if not autopilot_ego:
            changing[:, 0] = sim.ego_lc_active
        np.testing.assert_array_equal(sim.target_lane[~changing], lane[~changing], err_msg=f"step {step}")
        changes += int((sim.target_lane != sim.lane).sum())
    assert changes > 50, changes  # lane changes were under way


def _traffic(human_like: bool, **fields) -> ScenarioConfig:
    return ScenarioConfig(render_image=False, traffic=TrafficConfig(human_like=human_like, **fields))


def test_human_like_drivers_differ_wander_within_their_lane_and_vary_their_acceleration():
    """Per-driver parameters, a lateral wander that never leaves the lane, noisier acceleration than exact IDM,
    lane changes of varying duration; exact IDM has none of it. Statistics of 8 x 40 s of the paper's traffic."""
    from lcsim.stats import traffic_statistics

    human = traffic_statistics(_traffic(True), 8, 40.0)
    exact = traffic_statistics(_traffic(False), 8, 40.0)
    tc = TrafficConfig()
    assert 0.6 * tc.lane_wander_m < human["lateral_offset_sd_m"] < 1.2 * tc.lane_wander_m
    assert human["lateral_offset_max_m"] <= 2.5 * tc.lane_wander_m + 1e-9
    # exact IDM keeps the lane centre; only a lane change begun in the last moments, before it has covered a tenth
    # of a lane width (which the statistics cannot tell from lane keeping), shows at all
    assert exact["lateral_offset_sd_m"] < 0.02 and exact["lateral_offset_max_m"] < 0.1 * 3.5
    assert human["accel_sd_mps2"] > 2.0 * exact["accel_sd_mps2"]
    assert human["lane_change_duration_sd_s"] > 0.5 > exact["lane_change_duration_sd_s"]
    # the durations measured on the lateral position are the configured ones
    assert exact["lane_change_duration_mean_s"] == pytest.approx(tc.lane_change_duration_s, abs=0.02)
    assert human["lane_changes"] > 20 and human["traffic_collisions"] == exact["traffic_collisions"] == 0
    sim = LaneChangeCore(_traffic(True), 2).sim
    sim.reset([0, 1], [3, 4])
    for name in ("time_headway", "max_accel", "lag", "lc_inv_duration", "eagerness"):
        values = getattr(sim.drivers, name)[:, 1:]
        assert values.std() > 0.0 and np.isfinite(values).all(), name
    assert (sim.drivers.lag > 0).all() and (sim.drivers.lag <= 1).all()


def test_human_like_traffic_is_a_function_of_the_seed():
    """Same seed, same bits (the random processes draw from counter-based streams keyed by the seed); another
    seed, other drivers."""
    runs = []
    for seed in (7, 7, 8):
        core = LaneChangeCore(_traffic(True), 1, autopilot_ego=True)
        core.reset([0], [seed])
        for _ in range(60):
            core.step(np.full(1, KEEP))
        runs.append((core.sim.x.copy(), core.sim.y.copy(), core.sim.speed.copy(), core.sim.drivers.time_headway.copy()))
    assert all(np.array_equal(a, b) for a, b in zip(runs[0], runs[1], strict=True))
    assert not np.array_equal(runs[0][1], runs[2][1]) and not np.array_equal(runs[0][3], runs[2][3])


def test_configs_stored_before_human_like_drivers_keep_the_exact_traffic():
    stored = TrafficConfig(human_like=False).to_dict()
    del stored["human_like"]
    assert TrafficConfig.from_dict(stored).human_like is False  # a recording or a run of an earlier version
    assert TrafficConfig.from_dict(stored, stored=False).human_like is True  # a file a person writes
    with pytest.raises(ValueError, match="lane_wander_m"):
        LaneChangeCore(_traffic(True, lane_wander_m=0.5), 1)
    with pytest.raises(ValueError, match="lane_change_eagerness_min"):
        TrafficConfig(lane_change_eagerness_min=1.5)


def test_a_perceived_copy_sees_the_median_driver():
    """The planner's perceived copy cannot see a driver's own parameters: it gets the median driver's."""
    from lcsim.planning.perception import imagined_copy, perceive

    core = LaneChangeCore(_traffic(True), 2)
    core.reset([0, 1], [5, 6])
    copy_ = imagined_copy(core)
    perceive(copy_.sim, 60.0)
    tc = core.config.traffic
    assert (copy_.sim.drivers.time_headway[:, 1:] == tc.idm_time_headway_s).all()
    assert (copy_.sim.drivers.max_accel[:, 1:] == tc.idm_max_accel_mps2).all()
    assert core.sim.drivers.time_headway[:, 1:].std() > 0  # the original keeps its drivers


def test_a_perceived_copy_keeps_the_pace_of_lane_changes_under_way():
    """A change under way shows: the copy's changers go on at their own pace (no sideways jump)."""
    from lcsim.planning.perception import imagined_copy, perceive

    core = LaneChangeCore(_traffic(True, random_lane_change_rate_per_min=6.0), 2)
    core.reset([0, 1], [9, 10])
    for _ in range(20):
        core.step(np.full(2, KEEP))
        if core.sim.lc_active[:, 1:].sum() >= 2:
            break
    sim = core.sim
    assert sim.lc_active[:, 1:].any()
    copy_ = imagined_copy(core)
    perceive(copy_.sim, 1000.0)
    changing = copy_.sim.lc_active.copy()
    assert np.array_equal(copy_.sim.drivers.lc_inv_duration[changing], sim.drivers.lc_inv_duration[changing])
    y_before = copy_.sim.y.copy()
    copy_.sim.substep()
    assert np.abs(copy_.sim.y - y_before)[changing].max() < 0.05  # metres in one 50 ms step


def test_a_stored_config_without_a_traffic_table_keeps_the_exact_traffic():
    """Imported episodes store no traffic table: they read as the traffic of their time, not today's default."""
    cfg = ScenarioConfig.from_dict({"dt_s": 0.1})
    assert cfg.traffic.human_like is False
    assert ScenarioConfig.from_dict({"dt_s": 0.1}, stored=False).traffic.human_like is True
