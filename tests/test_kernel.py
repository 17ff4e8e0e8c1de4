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
    from lcsim.planning import LookaheadConfig, LookaheadDriver

    rng = np.random.default_rng(0)
    for cfg in (ScenarioConfig(), ScenarioConfig(render_image=False, neighbour_selection="nearest",
                                                 observe_acceleration=True, invalid_lane_change="leave_road",
                                                 ego=EgoConfig(adaptive_cruise=True),
                                                 traffic=TrafficConfig(human_like=False))):
        env = LaneChangeVectorEnv(3, cfg)
        obs, info = env.reset(seed=1)
        for _ in range(250):  # several episodes end (autoreset) within it
            actions = np.where(rng.random(3) < 0.3, rng.integers(0, 3, 3), 1)
            obs, _, term, trunc, info = env.step(actions)
    core = LaneChangeCore(ScenarioConfig(render_image=False), 2, autopilot_ego=True)
    core.reset([0, 1], [3, 4])
    for _ in range(40):
        core.step(np.ones(2, dtype=np.int64))
    env = LaneChangeVectorEnv(1, ScenarioConfig(render_image=False))
    obs, info = env.reset(seed=2)
    driver = LookaheadDriver(LookaheadConfig(blind=True, perceived=True))
    for _ in range(3):
        obs, *_, info = env.step(driver(obs, info["action_mask"], env.core))
    print("rollout done")
""")


def test_a_rollout_with_bounds_checking_on(tmp_path):
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp_path))
    res = subprocess.run([sys.executable, "-c", _ROLLOUT], env=env, capture_output=True, text=True, timeout=900,
                         check=False)
    assert res.returncode == 0 and "rollout done" in res.stdout, res.stderr[-3000:]
