"""Does the critic see a doomed keep better with 16 lane slots than with 8? Drive an 8-slot policy in a
16-slot scenario (its first 8 slots are the 8-slot layout), label every state with a choice by the blind
16 s planner following the same policy, and keep the 16-slot ``current`` (slice ``[:, :9]`` for 8 slots).

A one-off experiment of the window-critic study (see ../NOTE.md), kept to reproduce its figures:

    python docs/results/window-critic/scripts/collect16.py POLICY FIRST_USER_SEED EPISODES OUT.npz
"""
import dataclasses
import sys
import time

import numpy as np
import torch

from lcmodels.policy.evaluate import driver_for
from lcsim.core import RUNNING, LaneChangeCore
from lcsim.envs import episode_seed
from lcsim.planning import LookaheadDriver, SafetyLayerConfig


class FirstSlots:
    """The policy, shown only the first 8 slots of a 16-slot observation."""
    needs_observation = True

    def __init__(self, driver):
        self.driver, self.name = driver, driver.name

    def __call__(self, obs, mask, core):
        return self.driver({**obs, "current": obs["current"][:, :9]}, mask, core)


torch.set_num_threads(1)
policy, first, n, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
drv, cfg = driver_for(policy)
cfg = dataclasses.replace(cfg, num_neighbours=16)
pol = FirstSlots(drv)
planner = LookaheadDriver(SafetyLayerConfig(horizon_decisions=32, perceived=False), rule=pol)
current, alive, actions, t0 = [], [], [], time.perf_counter()
for start in range(first, first + n, 20):
    seeds = list(range(start, min(start + 20, first + n)))
    core = LaneChangeCore(cfg, len(seeds))
    core.reset(np.arange(len(seeds)), [episode_seed(u) for u in seeds])
    while (core.outcome == RUNNING).any():
        obs, mask = core.observe(), core.action_mask()
        a = pol(obs, mask, core)
        planner(obs, mask, core)  # labels only: the policy drives
        choice = ~np.isnan(planner.last_alive[:, 1])
        current.append(obs["current"][choice])
        alive.append(planner.last_alive[choice])
        actions.append(a[choice])
        core.step(a)
    print(f"{start - first + len(seeds)}/{n} episodes, {sum(map(len, actions))} states, "
          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
np.savez_compressed(out, current=np.concatenate(current), alive=np.concatenate(alive),
                    actions=np.concatenate(actions))
