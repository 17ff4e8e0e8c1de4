#!/usr/bin/env python
"""What the compiled core costs at start: the first call's compilation, once per machine, and a later process's
start from numba's on-disk cache.

Runs a fresh interpreter that imports lcsim, makes the paper scenario's single environment, resets it and takes
one decision (every compiled function a decision reaches: the simulation step, the observation, the image, the
decision's scoring), first with an empty cache directory (``NUMBA_CACHE_DIR`` pointed at a new temporary one:
everything compiles) and then again with that directory filled (everything loads). Prints the wall time of the
import and of the first decision in each case, the median of ``--repeat`` runs.

    python tools/bench_compile.py            # human-readable
    python tools/bench_compile.py --json     # one JSON object
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

_PROBE = """
import time
t0 = time.perf_counter()
from lcsim.config import ScenarioConfig
from lcsim.envs import LaneChangeEnv
t1 = time.perf_counter()
env = LaneChangeEnv(ScenarioConfig())
env.reset(seed=0)
env.step(1)
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def _probe(cache_dir: str) -> tuple[float, float]:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, check=True)
    import_s, first_s = (float(v) for v in out.stdout.split())
    return import_s, first_s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="runs of each case (median; default 3)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    cold, warm = [], []
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory() as cache:
            cold.append(_probe(cache))
            warm.append(_probe(cache))
    result = {
        "cold_import_s": statistics.median(c[0] for c in cold), "cold_first_decision_s": statistics.median(c[1] for c in cold),
        "cached_import_s": statistics.median(w[0] for w in warm),
        "cached_first_decision_s": statistics.median(w[1] for w in warm),
    }
    if args.json:
        print(json.dumps({k: round(v, 3) for k, v in result.items()}))
    else:
        print(f"empty cache (compiles): import {result['cold_import_s']:.2f} s, first decision "
              f"{result['cold_first_decision_s']:.2f} s")
        print(f"filled cache (loads):   import {result['cached_import_s']:.2f} s, first decision "
              f"{result['cached_first_decision_s']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
