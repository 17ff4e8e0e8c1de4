"""One-off robustness check (the perceived-planner study): the perceived planner with a noisy perception.

    python docs/results/perceived/scripts/noisy.py SIGMA_X SIGMA_V SIGMA_A LC-EVAL-ARGS...

Runs ``lc-eval`` (LC-EVAL-ARGS must include ``--lookahead-perceived``) with Gaussian errors added, in every
imagined copy, to each traffic vehicle's position along the road (SIGMA_X m), speed (SIGMA_V m/s) and
acceleration (SIGMA_A m/s^2) before the desired speeds are estimated and the future imagined. The errors
are drawn afresh for each copy, from a generator seeded by the episode's key, the step and a counter, so a
run is repeatable. The ego's own state and the real traffic are exact.
"""

import sys

import numpy as np

from lccli.evaluate import eval_main
from lcsim.sim import HighwaySim

sx, sv, sa, args = float(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), sys.argv[4:]
full = HighwaySim.perceive
calls = [0]


def perceive(self: HighwaySim, range_m: float) -> None:
    calls[0] += 1
    gen = np.random.default_rng([int(self.key[0] % (2**32)), int(self.step[0]), calls[0]])
    traffic = self.is_traffic.copy()
    traffic[:, 0] = False
    noise = lambda s: np.where(traffic, gen.normal(0.0, s, self.x.shape) if s > 0 else 0.0, 0.0)  # noqa: E731
    self.x = self.x + noise(sx)
    self.speed = np.maximum(self.speed + noise(sv), 0.0)
    self.accel = self.accel + noise(sa)
    self.rebuild_index()
    full(self, range_m)


HighwaySim.perceive = perceive
sys.exit(eval_main(args))
