"""Quick experiment: average the action probabilities of several policies (a policy ensemble).

A one-off experiment of the window-critic study (see ../NOTE.md), kept to reproduce its figures:

    python docs/results/window-critic/scripts/ensemble.py SEED POLICY [POLICY ...]
"""
import json
import sys
import time

import numpy as np
import torch

from lcmodels.policy.checkpoint import load_policy
from lcmodels.policy.evaluate import evaluate
from lcmodels.policy.obs import build_observation, scenario_for_mode


class Ensemble:
    name = "ensemble"
    def __init__(self, policies):
        self.policies = policies
    def probs(self, p, obs):
        pobs = build_observation(obs, p.obs_mode, p.predictor)
        t, _ = p.model.policy.obs_to_tensor(pobs)
        with torch.no_grad():
            return p.model.policy.get_distribution(t).distribution.probs.numpy()
    def __call__(self, obs, mask, core):
        pr = np.mean([self.probs(p, obs) for p in self.policies], axis=0)
        return pr.argmax(axis=1)

torch.set_num_threads(1)
seed, paths = int(sys.argv[1]), sys.argv[2:]
pols = [load_policy(p, predictor="runs/predictor/predictor.pt") for p in paths]
cfg = scenario_for_mode(pols[0].scenario, "hybrid" if any(p.obs_mode in ("hybrid", "image") for p in pols) else "pure")
t = time.perf_counter()
s, _ = evaluate(Ensemble(pols), cfg, episodes=200, seed=seed)
print(json.dumps({"members": paths, "seed": seed, "success": s["success_rate"], "collision": s["collision_rate"],
                  "timeout": s["timeout_rate"], "wall_s": round(time.perf_counter() - t, 1)}))
