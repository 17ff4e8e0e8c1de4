"""``lc-experiment``: the paper's tables and figures end to end, resumable."""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

from lccli.common import add_executor_arguments, fail, positive_int, setup_logging

EXPERIMENT_EPILOG = """stages (each skipped when complete, redone when missing or stale):
  corpus      autopilot trajectory corpus (MCAP)                 DIR/corpus/
  predictor   transformer + constant velocity/acceleration        DIR/predictor/metrics.json  (Table II)
  demos       demonstrations (the oracle's) for the warm start    DIR/demos/
  rule        rule-based reference on the held-out seeds          DIR/rule/metrics.json
  policies    A2C, DQN, PPO pure/image/prediction/hybrid, Hybrid-PPO + warm start, K seeds each
                                                                  DIR/policies/<method>/seed<k>/
  report      DIR/REPORT.md, DIR/fig5_safe_forward.png, DIR/fig6_total_reward.png

presets: tiny (seconds, for tests), quick (about 15 min on 2 cores, what `make demo` runs),
paper (the budgets each method needs to converge: hours).

examples:
  lc-experiment --preset quick --out runs/demo
  lc-experiment --preset paper --seeds 3 --jobs 2 --out runs/paper   # stop any time; rerun to continue
"""


def experiment_parser() -> argparse.ArgumentParser:
    from lcmodels.experiment import PRESETS

    p = argparse.ArgumentParser(
        prog="lc-experiment",
        description="Reproduce the paper's tables and figures end to end: record the trajectory corpus, train "
        "the predictor, record rule-based warm-start episodes, train every policy with K seeds, evaluate on "
        "held-out seeds and write DIR/REPORT.md. Resumable: a rerun skips what is complete.",
        epilog=EXPERIMENT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--preset", choices=list(PRESETS), default="quick", help="budgets (default %(default)s)")
    p.add_argument("--seeds", type=positive_int, default=1, help="training seeds per method (default 1)")
    p.add_argument("--out", type=Path, required=True, help="experiment directory (resumed when it holds one)")
    p.add_argument("--threads", type=positive_int, default=1,
                   help="torch threads (default 1: on a shared 2-core machine 1 is often fastest; results do "
                   "not depend on it beyond float rounding, and changing it does not make stages stale)")
    p.add_argument("--jobs", type=positive_int, default=1,
                   help="policies trained at once, each in its own process with --threads torch threads "
                   "(default 1; on 2 cores --jobs 2 --threads 1 keeps both busy; results do not depend on it)")
    add_executor_arguments(p, "every independent stage a Ray task (each policy x seed, each evaluation shard, "
                           "each recorded episode)", "this machine, --jobs processes")
    p.add_argument("--skip-train", action="store_true",
                   help="do not train policies; report what the directory already holds")
    p.add_argument("--dry-run", action="store_true",
                   help="only say which stages are complete and which would run (and why)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def experiment_main(argv: list[str] | None = None) -> int:
    import shlex

    parser = experiment_parser()
    args = parser.parse_args(argv)

    error = functools.partial(fail, "lc-experiment")

    from lcmodels.experiment import PRESETS, Experiment

    words = sys.argv[1:] if argv is None else list(argv)
    command = shlex.join(["lc-experiment", *words])
    t0 = time.perf_counter()

    def show(msg: str) -> None:
        print(f"{(time.perf_counter() - t0) / 60:6.1f} min  {msg}", flush=True)

    exp = Experiment(PRESETS[args.preset], args.out, seeds=args.seeds, command=command, threads=args.threads,
                     progress=None if args.quiet else show, executor=args.executor,
                     ray_address=args.ray_address)  # fmt: skip
    try:
        exp.check_out()
    except ValueError as exc:
        return error(str(exc))
    setup_logging("lc-experiment", verbose=False)
    if args.dry_run:
        if not args.out.exists():
            print(f"{args.out} does not exist: every stage would run")
            return 0
        stages = exp.plan()
        print(f"{sum(s.status == 'skipped' for s in stages)} stages complete, "
              f"{sum(s.status != 'skipped' for s in stages)} would run")
        return 0
    try:
        res = exp.run(skip_train=args.skip_train, jobs=args.jobs)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    done = sum(s.status == "done" for s in res.stages)
    skipped = sum(s.status == "skipped" for s in res.stages)
    print(f"{done} stages computed, {skipped} complete and skipped, {res.wall_s / 60:.1f} min")
    print(f"report: {res.report}")
    return 0
