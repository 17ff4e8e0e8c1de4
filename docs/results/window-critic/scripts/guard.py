"""Quick experiment: an observation-only guard from the window features in front of a policy.

A one-off experiment of the window-critic study (see ../NOTE.md), kept to reproduce its figures:

    python docs/results/window-critic/scripts/guard.py POLICY SEED RESCUE_S|none veto PREDICTOR
"""
import json
import sys
import time

import numpy as np
import torch

from lcmodels.policy.evaluate import driver_for, evaluate
from lcmodels.policy.extractor import WindowFeatures


class Guard:
    def __init__(self, driver, slots, rescue_s=None, veto=True):
        self.driver, self.wf = driver, WindowFeatures(slots)
        self.rescue_s, self.veto = rescue_s, veto
        self.name = getattr(driver, "name", "d") + "+guard"
        self.n_veto = self.n_rescue = self.n = 0
    @property
    def last_prediction(self):
        return getattr(self.driver, "last_prediction", None)
    def __call__(self, obs, mask, core):
        a = np.asarray(self.driver(obs, mask, core)).copy()
        with torch.no_grad():
            f = self.wf(torch.as_tensor(obs["current"], dtype=torch.float32)).numpy()
        trap = f[:, 0] * 16.0
        can = {0: f[:, 1] > 0.5, 2: f[:, 6] > 0.5}
        closes = {0: f[:, 3], 2: f[:, 8]}
        choice = mask[:, 0] | mask[:, 2]
        self.n += int(choice.sum())
        for i in np.flatnonzero(choice):
            if self.veto and a[i] != 1 and not can[a[i]][i]:
                a[i] = 1
                self.n_veto += 1
            if self.rescue_s is not None and a[i] == 1 and trap[i] < self.rescue_s:
                sides = [s for s in (0, 2) if mask[i, s] and can[s][i]]
                if sides:
                    a[i] = max(sides, key=lambda s: closes[s][i])
                    self.n_rescue += 1
        return a

spec, seed = sys.argv[1], int(sys.argv[2])
rescue = None if sys.argv[3] == "none" else float(sys.argv[3])
veto = sys.argv[4] == "veto"
torch.set_num_threads(1)
drv, cfg = driver_for(spec, predictor=sys.argv[5] if len(sys.argv) > 5 else None)
g = Guard(drv, cfg.num_neighbours, rescue, veto)
t = time.perf_counter()
s, _ = evaluate(g, cfg, episodes=200, seed=seed, images=False)
print(json.dumps({"spec": spec, "seed": seed, "rescue": rescue, "veto": veto, "success": s["success_rate"],
                  "collision": s["collision_rate"], "timeout": s["timeout_rate"], "decisions": g.n,
                  "vetoes": g.n_veto, "rescues": g.n_rescue, "wall_s": round(time.perf_counter() - t, 1)}))
