"""The compiled core indexes nothing out of bounds: its checks are off in normal runs (speed), so a rollout that
reaches every compiled function runs here once with numba's bounds checking on, compiled afresh."""

import os
import subprocess
import sys
import textwrap

_ROLLOUT = textwrap.dedent("""
    import numpy as np
    from lcsim.config import EgoConfig, ScenarioConfig, TrafficConfig
    from lcsim.core import LaneChangeCore
    from lcsim.envs import LaneChangeVectorEnv
    from lcsim.planning import LookaheadDriver, SafetyLayerConfig

    import lcsim.threads
    lcsim.threads.CHUNK_ALIGN = 1  # (chunks of one environment: three environments on two threads)
    rng = np.random.default_rng(0)
    for cfg in (ScenarioConfig(), ScenarioConfig(render_image=False, neighbour_selection="nearest",
                                                 observe_acceleration=True, invalid_lane_change="leave_road",
                                                 ego=EgoConfig(adaptive_cruise=True),
                                                 traffic=TrafficConfig(human_like=False))):
        env = LaneChangeVectorEnv(3, cfg, threads=2)  # (two threads: the shards' ranges are checked too)
        obs, info = env.reset(seed=1)
        for _ in range(250):  # several episodes end (autoreset) within it
            actions = np.where(rng.random(3) < 0.3, rng.integers(0, 3, 3), 1)
            obs, _, term, trunc, info = env.step(actions)
    core = LaneChangeCore(ScenarioConfig(render_image=False), 2, autopilot_ego=True)
    core.reset([0, 1], [3, 4])
    core.sim.log_hooks.append(lambda sim, log, counts: None)  # the logged call and the log rows
    for _ in range(40):
        core.step(np.ones(2, dtype=np.int64))
    core.sim.advance(70)  # more than one logged call
    core.sim.log_row(1)
    env = LaneChangeVectorEnv(1, ScenarioConfig(render_image=False))
    obs, info = env.reset(seed=2)
    driver = LookaheadDriver(SafetyLayerConfig(samples=2))
    for _ in range(3):
        obs, *_, info = env.step(driver(obs, info["action_mask"], env.core))
    index = env.core.sim.index
    n = env.core.sim.num_vehicles
    lanes = np.tile(np.arange(-1, 6), (1, n // 7 + 1))[:, :n]
    for ahead in (True, False):
        index.neighbour_in_lane(lanes, ahead)
        index.neighbour_flat(np.arange(n), lanes[0], ahead)
        for lane in range(-1, 6):
            index.lane_members_one(0, lane, ahead, 3)
            index.lane_members_one(n - 1, lane, ahead, 200)
    print("rollout done")
""")


def test_a_rollout_with_bounds_checking_on(tmp_path):
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp_path))
    res = subprocess.run([sys.executable, "-c", _ROLLOUT], env=env, capture_output=True, text=True, timeout=900,
                         check=False)
    assert res.returncode == 0 and "rollout done" in res.stdout, res.stderr[-3000:]


def test_advance_freezes_an_environment_at_its_event_with_hooks_or_without():
    """``advance(stop_on_event=True)`` freezes an environment at the step its ego passes the route's end, whether
    the steps run in one compiled call or one by one for the hooks, and the two give the same state."""
    import numpy as np

    from lcsim.config import ScenarioConfig, TrafficConfig
    from lcsim.sim import HighwaySim

    cfg = ScenarioConfig(render_image=False, route_length_m=10.0, traffic=TrafficConfig(num_vehicles=6))
    sims = []
    for hooked in (False, True):
        sim = HighwaySim(cfg, 2)
        sim.reset([0, 1], [1, 2])
        if hooked:
            sim.hooks.append(lambda s: None)
        sim.advance(40, stop_on_event=True)
        assert sim.frozen.all() and (sim.x[:, 0] >= 10.0).all()
        steps = sim.step.copy()
        sim.advance(5)  # frozen environments stay where they are
        assert np.array_equal(sim.step, steps)
        sims.append(sim)
    for block in ("vf", "vi", "vb", "ef", "ei", "eb"):
        assert np.array_equal(getattr(sims[0], block), getattr(sims[1], block), equal_nan=True), block


def test_log_hooks_see_the_rows_of_every_step_the_per_step_hooks_see():
    """The step log of the compiled call (``log_hooks``) holds, row for row, the state a per-step hook sees after each
    step an environment runs (none once it is frozen), and logging changes nothing in the simulation: batches of
    three, the PID ego and the autopilot ego, decisions that end in events, an advance longer than one logged call."""
    import numpy as np

    from lcsim.core import LaneChangeCore
    from lcsim.registry import make_driver
    from lcsim.sim import LOG_STEPS
    from tests.conftest import small_config

    for autopilot in (False, True):
        cores = [LaneChangeCore(small_config(), 3, autopilot_ego=autopilot) for _ in range(2)]
        seen: list[list[np.ndarray]] = [[], [], []]
        logged: list[list[np.ndarray]] = [[], [], []]

        def per_step(sim, seen=seen) -> None:
            for e in range(3):
                if not sim.frozen[e]:
                    seen[e].append(sim.log_row(e))

        def per_call(sim, log, counts, logged=logged) -> None:
            for e in range(3):
                logged[e] += list(log[e, : counts[e]].copy())

        for core in cores:
            core.reset([0, 1, 2], [11, 12, 13])
        cores[0].sim.hooks.append(per_step)
        cores[1].sim.log_hooks.append(per_call)
        drivers = [make_driver("random", 5) for _ in cores]
        for _ in range(60):
            for core, driver in zip(cores, drivers, strict=True):
                core.step(driver(core.observe(), core.action_mask(), core))
        for core in cores:
            core.sim.frozen[:] = False
            core.sim.advance(LOG_STEPS + 6)
        for block in ("vf", "vi", "vb", "ef", "ei", "eb", "hist"):
            assert np.array_equal(getattr(cores[0].sim, block), getattr(cores[1].sim, block)), block
        for e in range(3):
            assert len(seen[e]) == len(logged[e]) > LOG_STEPS
            assert np.array_equal(np.stack(seen[e]), np.stack(logged[e]))
        assert any(len(rows) < 60 * 10 + LOG_STEPS + 6 for rows in seen)  # an environment was frozen for a while
