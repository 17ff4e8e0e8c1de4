"""One-off ablation (the perceived-planner study): which half of ``HighwaySim.perceive`` costs the perceived planner its points.

    python docs/results/perceived/scripts/ablate.py range  LC-EVAL-ARGS...   # only the sensing range
    python docs/results/perceived/scripts/ablate.py speeds LC-EVAL-ARGS...   # only the desired-speed estimate
    python docs/results/perceived/scripts/ablate.py crude  LC-EVAL-ARGS...   # the first, cruder estimate

Runs ``lc-eval`` with ``--lookahead-perceived`` given in LC-EVAL-ARGS, with ``perceive`` cut down to one of its
two parts: ``range`` parks the traffic beyond the range but keeps every vehicle's true desired speed;
``speeds`` estimates the desired speeds but keeps every vehicle wherever it is; ``crude`` is the whole of
``perceive`` with the first estimate tried: the larger of the nominal desired speed and the present speed.
"""

import sys

import numpy as np

from lccli.evaluate import eval_main
from lcsim.sim import HighwaySim

part, args = sys.argv[1], sys.argv[2:]
full = HighwaySim.perceive


def perceive(self: HighwaySim, range_m: float) -> None:
    if part == "range":
        v0 = self.v0.copy()
        full(self, range_m)
        self.v0 = v0
    elif part == "speeds":
        full(self, np.inf)  # nothing is farther than infinity: only the speeds change
    elif part == "crude":
        full(self, range_m)
        traffic = self.is_traffic.copy()
        traffic[:, 0] = False
        self.v0 = np.where(traffic, np.maximum(self.speed, self.config.traffic.speed_kmh / 3.6), self.v0)
    else:
        raise SystemExit(f"part must be range, speeds or crude, not {part}")


HighwaySim.perceive = perceive
sys.exit(eval_main(args))
