"""``lc-tune``: a sweep of policy-config values times training seeds, each trial a training run with its
held-out evaluation, one table sorted by held-out success (:mod:`lcmodels.sweep`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lccli.common import add_executor_arguments, fail, positive_int, setup_logging

EPILOG = """a sweep file (TOML or JSON):
  seeds = [0, 1]              # training seeds of every grid point
  [base]                      # PolicyConfig fields every trial shares (what lc-train-policy --set sets)
  obs = "pure"
  timesteps = 200000
  [grid]                      # each field: the values to try; every combination is a grid point
  gamma = [0.9, 0.95]
  window_features = [false, true]
A sweep holds at most {max_trials} trials (grid points x seeds). A trial's folder is named by its values
(trials/gamma=0.9_window_features=false_seed0); a value no folder name should hold (a path separator, ..)
is replaced and a hash of the values added.

examples:
  lc-tune sweep.toml --out runs/sweep                          # trials one after the other here
  lc-tune sweep.toml --out runs/sweep --executor ray           # Ray Tune trials, on a local Ray instance
  ray start --head && lc-tune sweep.toml --out /shared/sweep --executor ray --ray-address auto   # a cluster

outputs (in --out): trials/<name>/ (lc-train-policy run directories: a rerun skips the finished ones),
SWEEP.md and sweep.json (every trial's held-out success and collision rate with 95% intervals, sorted).
"""


def tune_parser() -> argparse.ArgumentParser:
    from lcmodels.sweep import MAX_TRIALS

    p = argparse.ArgumentParser(prog="lc-tune", description=__doc__.split("\n\n")[0],
                                epilog=EPILOG.format(max_trials=MAX_TRIALS),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sweep", type=Path, help="the sweep file (.toml or .json)")
    p.add_argument("--out", type=Path, required=True, help="the sweep's directory (resumed when rerun)")
    p.add_argument("--predictor", type=Path, default=None, help="predictor.pt for prediction and hybrid trials")
    p.add_argument("--threads", type=positive_int, default=1, help="torch threads (and Ray CPUs) per trial (1)")
    add_executor_arguments(p, "each trial a Ray Tune trial", "trials one after the other here")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def main(argv: list[str] | None = None) -> int:
    args = tune_parser().parse_args(argv)
    from lcmodels.sweep import SWEEP_MD, Sweep, run_sweep

    if args.predictor is not None and not args.predictor.is_file():
        return fail("lc-tune", f"--predictor {args.predictor} does not exist")
    setup_logging("lc-tune", verbose=False)
    try:
        sweep = Sweep.from_file(args.sweep)
        rows = run_sweep(sweep, args.out, predictor=None if args.predictor is None else str(args.predictor),
                         threads=args.threads, executor=args.executor, ray_address=args.ray_address,
                         progress=None if args.quiet else (lambda msg: print(msg, flush=True)))  # fmt: skip
    except (ValueError, OSError) as exc:
        return fail("lc-tune", str(exc).splitlines()[0])
    best = rows[0]
    if best["success_rate"] is None:
        print(f"{len(rows)} trials, none evaluated (eval_episodes = 0)")
    else:
        print(f"{len(rows)} trials; best {best['trial']}: success {100 * best['success_rate']:.1f}% "
              f"[{100 * best['success_rate_ci95'][0]:.1f}, {100 * best['success_rate_ci95'][1]:.1f}]")
    print(f"table: {args.out / SWEEP_MD}")
    return 0
