"""How repeatable is the planner's keep label? For each state with a choice, imagine keep + 16 s of the
follower policy in K redrawn futures; report how often the K futures agree.

A one-off experiment of the window-critic study (see ../NOTE.md), kept to reproduce its figures:

    python docs/results/window-critic/scripts/noise.py POLICY FIRST_USER_SEED EPISODES FUTURES
"""
import json
import sys
import time

import numpy as np
import torch

from lcmodels.policy.evaluate import driver_for
from lcsim.core import KEEP, RUNNING, LaneChangeCore
from lcsim.envs import episode_seed
from lcsim.planning import LookaheadDriver, SafetyLayerConfig

torch.set_num_threads(1)
policy, first, n, K = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
drv, cfg = driver_for(policy)
planner = LookaheadDriver(SafetyLayerConfig(horizon_decisions=32, perceived=False), rule=drv)
shares, t0 = [], time.perf_counter()
for start in range(first, first + n, 20):
    seeds = list(range(start, min(start + 20, first + n)))
    core = LaneChangeCore(cfg, len(seeds))
    core.reset(np.arange(len(seeds)), [episode_seed(u) for u in seeds])
    while (core.outcome == RUNNING).any():
        obs, mask = core.observe(), core.action_mask()
        actions = drv(obs, mask, core)
        choice = (mask.sum(axis=1) > 1) & (core.outcome == RUNNING) & (actions == KEEP)
        if choice.any():
            keep = np.full(len(seeds), KEEP)
            alive = np.stack([planner.survives(core, keep, salt) for salt in range(1, K + 1)], axis=1)
            shares.extend(alive[choice].mean(axis=1).tolist())
        core.step(actions)
    print(f"{start - first + len(seeds)}/{n} episodes, {len(shares)} keep states, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
s = np.array(shares)
print(json.dumps({"policy": policy, "first_seed": first, "episodes": n, "futures": K, "keep_states": len(s),
                  "share_hist": {f"{k}/{K}": int((np.round(s * K) == k).sum()) for k in range(K + 1)}}))
