#!/usr/bin/env python
"""The run committed under docs/results/paper-50k: lc-experiment's paper preset at 50k steps per policy.

    python -m experiments.paper_50k.run [--out runs/paper-50k]

Resumable like lc-experiment: rerunning skips complete stages.
"""

from __future__ import annotations

import argparse
import dataclasses

from lcmodels.experiment import PRESETS, run_experiment
from lcmodels.presets import PAPER_RECIPES

if __name__ == "__main__":  # the corpus stage records with worker processes (spawn)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/paper-50k")
    args = ap.parse_args()
    preset = dataclasses.replace(PRESETS["paper"], name="paper-50k", recipes=PAPER_RECIPES,
                                 caps=(("timesteps", 50_000),), predictor_time_limit_s=300.0)
    run_experiment(preset, args.out, seeds=1, command=f"python -m experiments.paper_50k.run --out {args.out}", threads=1,
                   progress=lambda m: print(m, flush=True))
