#!/usr/bin/env python
"""Instructions per decision of one environment, counted by valgrind (callgrind): a speed figure that a
busy or throttled machine does not move, for comparing two versions of the simulator.

Runs a fixed workload (the paper scenario with its image, seed 0, keep lane with a valid lane change
15% of the time) for 0 and for ``--decisions`` decisions under ``valgrind --tool=callgrind`` and prints
the difference divided by the number of decisions (start-up and imports cancel out). It takes about a
minute per 40 decisions. Needs valgrind (Debian package ``valgrind``).

    python tools/bench_sim_instructions.py                 # 40 decisions
    python tools/bench_sim_instructions.py --decisions 80 --json
"""

from __future__ import annotations

import argparse
import json

from callgrind import instructions, require_valgrind

_WORKLOAD = """
import sys
import numpy as np
from lcsim.config import ScenarioConfig
from lcsim.envs import LaneChangeEnv
env = LaneChangeEnv(ScenarioConfig())
env.reset(seed=0)
rng = np.random.default_rng(0)
for _ in range(5):
    env.step(1)
for _ in range(int(sys.argv[1])):
    mask = env.action_masks()
    action = int(rng.choice(np.flatnonzero(mask))) if rng.random() < 0.15 else 1
    _, _, terminated, truncated, _ = env.step(action)
    if terminated or truncated:
        env.reset()
"""


def _instructions(decisions: int) -> int:
    return instructions(_WORKLOAD, str(decisions))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--decisions", type=int, default=40, help="decisions measured (default 40)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    if args.decisions < 1:
        parser.error(f"--decisions must be >= 1, got {args.decisions}")
    require_valgrind()
    per_decision = (_instructions(args.decisions) - _instructions(0)) / args.decisions
    if args.json:
        print(json.dumps({"instructions_per_decision": round(per_decision), "decisions": args.decisions}))
    else:
        print(f"one env, paper scenario with image: {per_decision / 1e6:.2f} M instructions per decision "
              f"({args.decisions} decisions, callgrind)")


if __name__ == "__main__":
    main()
