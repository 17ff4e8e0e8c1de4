"""One-off robustness check (the perceived-planner study): the perceived planner with a traffic model that is off.

    python docs/results/perceived/scripts/misspecified.py 0.8 LC-EVAL-ARGS...   # parameters 20% low
    python docs/results/perceived/scripts/misspecified.py 1.2 LC-EVAL-ARGS...   # parameters 20% high

Runs ``lc-eval`` (LC-EVAL-ARGS must include ``--lookahead-perceived``) with the imagined futures simulated,
and the desired speeds estimated, under a traffic model whose car-following and lane-change parameters are
all scaled by the factor: IDM time headway and minimum gap, the gaps a traffic lane change needs ahead and
behind, its rear headway, and the speed margin under which a vehicle counts as blocked. Below 1 the planner
takes the traffic for more aggressive than it is; above 1, for more cautious. The real traffic is unchanged.
"""

import dataclasses
import sys

from lccli.evaluate import eval_main
from lcsim.sim import HighwaySim

factor, args = float(sys.argv[1]), sys.argv[2:]
SCALED = ("idm_time_headway_s", "idm_min_gap_m", "lane_change_front_gap_m", "lane_change_rear_gap_m",
          "lane_change_rear_headway_s", "blocked_speed_margin_kmh")
full = HighwaySim.perceive


def perceive(self: HighwaySim, range_m: float) -> None:
    tc = self.config.traffic
    model = dataclasses.replace(tc, **{k: getattr(tc, k) * factor for k in SCALED})
    self.config = dataclasses.replace(self.config, traffic=model)  # this imagined copy's own model of the traffic
    full(self, range_m)


HighwaySim.perceive = perceive
sys.exit(eval_main(args))
