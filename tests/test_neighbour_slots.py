"""The observation's vehicle slots: lane slots against a brute-force search, and the nearest-K variant."""

import dataclasses

import numpy as np
import pytest

from lcsim.config import LANE_SLOTS, ScenarioConfig, TrafficConfig
from lcsim.core import LaneChangeCore

from .conftest import small_config


def _dense() -> ScenarioConfig:
    # Dense, lane-changing traffic: slots are often filled, sometimes twice by a vehicle changing lanes.
    return small_config(traffic=TrafficConfig(num_vehicles=40, spawn_behind_m=60.0, spawn_ahead_m=200.0,
                                              random_lane_change_rate_per_min=3.0))


def _brute_force_slots(core: LaneChangeCore, e: int) -> list[int]:
    """Slot vehicles of environment e from the lanes each body touches and the sorted order, one by one."""
    sim, index = core.sim, core.sim.index
    lo, hi = index.lohi[0, e], index.lohi[1, e]
    extra, pos = index.extra[e], index.pos_of[e]
    ego_lane, ego_pos = int(sim.target_lane[e, 0]), int(pos[0])
    out = []
    for offset, ahead, rank in LANE_SLOTS[: core.k]:
        lane = ego_lane + offset
        members = [v for v in range(1, sim.num_vehicles) if lo[v] <= lane <= hi[v] or extra[v] == lane]
        side = [v for v in members if (pos[v] > ego_pos if ahead else pos[v] < ego_pos)]
        side.sort(key=lambda v: pos[v] if ahead else -pos[v])
        v = side[rank - 1] if 0 <= lane < sim.road.num_lanes and len(side) >= rank else -1
        if v >= 0 and np.hypot(sim.x[e, v] - sim.x[e, 0], sim.y[e, v] - sim.y[e, 0]) > core.config.sensing_range_m:
            v = -1
        out.append(v)
    return out


@pytest.mark.parametrize("k", [8, 16])  # the paper's count of slots, and the wider view
@pytest.mark.parametrize("num_envs", [1, 3])  # the single-environment path and the batched one
def test_lane_slots_match_a_brute_force_search(num_envs, k):
    cfg = dataclasses.replace(_dense(), num_neighbours=k)
    assert cfg.neighbour_selection == "lanes"
    core = LaneChangeCore(cfg, num_envs)
    envs = np.arange(num_envs)
    core.reset(envs, [13] if num_envs == 1 else [11, 12, 13])
    rng = np.random.default_rng(0)
    filled = straddling = 0
    for _ in range(60):
        actions = np.where(rng.random(num_envs) < 0.2, rng.integers(0, 3, num_envs), 1)
        core.step(actions)
        slots = core.neighbours(envs)
        for e in envs:
            assert slots[e].tolist() == _brute_force_slots(core, e)
        assert (core.neighbours(envs[::-1]) == slots[::-1]).all()  # environments in another order
        filled += int((slots >= 0).sum())
        lo, hi = core.sim.index.lohi
        for e in envs:
            shown = slots[e][slots[e] >= 0]
            straddling += int((lo[e, shown] != hi[e, shown]).sum())
    assert filled > 60 * num_envs * k // 2  # the test exercises full slots, not empty ones
    assert straddling > 0  # and vehicles that touch two lanes (changing lanes)


def test_lane_slots_are_in_the_observation():
    core = LaneChangeCore(_dense(), 1)
    core.reset([0], [5])
    for _ in range(4):
        core.step(np.array([1]))
    obs, nb = core.observe(), core.neighbours(np.array([0]))[0]
    cur = obs["current"][0]
    assert (cur[1:, -1] == (nb >= 0)).all()  # presence column
    lead, follow = nb[0], nb[1]
    if lead >= 0:
        assert cur[1, 0] > 0  # the leader is ahead in the ego frame
    if follow >= 0:
        assert cur[2, 0] < 0


def test_nearest_selection_orders_by_distance():
    cfg = dataclasses.replace(_dense(), neighbour_selection="nearest")
    core = LaneChangeCore(cfg, 1)
    core.reset([0], [5])
    core.step(np.array([1]))
    nb = core.neighbours(np.array([0]))[0]
    sim = core.sim
    d = np.hypot(sim.x[0] - sim.x[0, 0], sim.y[0] - sim.y[0, 0])
    shown = nb[nb >= 0]
    assert len(shown) == core.k
    assert (np.diff(d[shown]) >= 0).all()
    others = np.setdiff1d(np.arange(1, sim.num_vehicles), shown)
    assert d[others].min() >= d[shown].max()


@pytest.mark.parametrize("selection", ["lanes", "nearest"])
def test_both_selections_are_deterministic(selection):
    cfg = dataclasses.replace(_dense(), neighbour_selection=selection)
    runs = []
    for _ in range(2):
        core = LaneChangeCore(cfg, 2)
        core.reset([0, 1], [3, 4])
        for _ in range(5):
            core.step(np.array([2, 1]))
        runs.append(core.observe())
    for k in runs[0]:
        assert np.array_equal(runs[0][k], runs[1][k])


def test_wider_slots_extend_the_paper_slots():
    """The first 8 of 16 slots are the 8-slot observation; the ninth is the leader's leader."""
    cores = [LaneChangeCore(dataclasses.replace(_dense(), num_neighbours=k), 2) for k in (8, 16)]
    for core in cores:
        core.reset([0, 1], [21, 22])
    for _ in range(30):
        for core in cores:
            core.step(np.array([1, 2]))
        narrow, wide = (core.neighbours(np.arange(2)) for core in cores)
        assert np.array_equal(wide[:, :8], narrow)
        assert np.array_equal(cores[1].observe()["current"][:, :9], cores[0].observe()["current"])
        sim = cores[1].sim
        for e in range(2):
            lead, second = wide[e, 0], wide[e, 8]
            if second >= 0:
                assert lead >= 0 and sim.x[e, second] > sim.x[e, lead]
