"""``lc-experiment``: the paper's tables and figures end to end, resumable."""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

from lccli.common import add_executor_arguments, fail, positive_int, setup_logging

EXPERIMENT_EPILOG = """stages (each skipped when complete, redone when missing or stale, resumed when interrupted):
  corpus      autopilot trajectory corpus (MCAP)                        DIR/corpus/
  predictor   transformer + constant velocity/acceleration (Table II)   DIR/predictor/
  demos       demonstrations a recipe clones, shared between recipes    DIR/demos/<driver>-s<seed>-n<episodes>/
  recipes     per recipe and training seed: clone, dagger, train, shielded (as the recipe says; shielded:
              more PPO behind the safety layer, once the policy it follows is trained), then eval on the
              validation and held-out episodes, and safety (behind the safety layer) where it asks
                                                                        DIR/policies/<recipe>/seed<k>/<stage>/
  rule, oracle  the references on the same episodes                    DIR/rule/, DIR/oracle/
  zoo         (quick) the shipped policies on the held-out episodes (and behind their safety layer), a few
              recorded                                          DIR/zoo/, DIR/zoo-safety/, DIR/showcase/
  report      DIR/REPORT.md, DIR/fig5_safe_forward.png, DIR/fig6_total_reward.png
A stage runs once the stages it reads are complete; --dry-run lists every stage: complete, would run (why), or
would run after a stage it reads.

recipes: lcmodels/recipes/*.toml (paper-*: the paper's methods as it trains them; hybrid-ppo, pure-ppo, ...:
the project's best per method; quick-pure: make demo's), or a .toml file of your own (--recipe FILE). A preset
runs the recipes whose files say its kinds (kind = "paper", "best", ...), in the order the files say (order).

presets: tiny (seconds, for tests: every recipe with tiny budgets), quick (make demo: the zoo, one quick
recipe, minutes on 2 cores), paper (every paper and best recipe at its own budget but those whose files say
optional = true, which run when named, hybrid-ppo with 2 training seeds, 1000 held-out episodes: hours),
ablation (the controlled input ablation: five inputs, 3 training seeds each, on the paper's road and every road
of the suite, every run measured on every road: a night and more on 2 cores).

episodes: validation (evaluation seeds 0 and 1, what recipes are chosen on) and held-out (evaluation seed 9,
which no recipe here is chosen on); both are validation episodes in the benchmark's sense. The sealed test
episodes run only through lc-bench --final, which appends them to the ledger; the report quotes them from it.

examples:
  lc-experiment --preset quick --out runs/demo
  lc-experiment --preset paper --jobs 2 --out runs/paper   # stop any time; rerun to continue
  lc-experiment --preset paper --seeds 3 --jobs 2 --out runs/paper   # every recipe with 3 training seeds
  lc-experiment --preset paper --recipe hybrid-ppo --recipe pure-ppo --jobs 2 --out runs/best
"""


def experiment_parser() -> argparse.ArgumentParser:
    from lcmodels.experiment import PRESETS

    p = argparse.ArgumentParser(
        prog="lc-experiment",
        description="Reproduce the paper's tables and figures end to end from recipes: record the trajectory "
        "corpus, train the predictor, run every recipe's stages (demonstrations, cloning, DAgger, RL) with K "
        "training seeds, evaluate on validation and held-out episodes and write DIR/REPORT.md. Resumable: a rerun "
        "skips what is complete.",
        epilog=EXPERIMENT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--preset", choices=list(PRESETS), default="quick", help="budgets (default %(default)s)")
    p.add_argument("--recipe", action="append", default=None, metavar="NAME_OR_FILE",
                   help="run this recipe (a name in lcmodels/recipes/ or a .toml file) instead of the preset's; "
                   "repeat for several")
    p.add_argument("--seeds", type=positive_int, default=1,
                   help="training seeds per recipe (default 1; the paper preset trains hybrid-ppo, and "
                   "pure-ppo that its safety layer follows, with 2)")
    p.add_argument("--out", type=Path, required=True, help="experiment directory (resumed when it holds one)")
    p.add_argument("--threads", type=positive_int, default=1,
                   help="torch threads (default 1: on a shared 2-core machine 1 is often fastest; results do "
                   "not depend on it beyond float rounding, and changing it does not make stages stale)")
    p.add_argument("--jobs", type=positive_int, default=1,
                   help="training stages at once, each in its own process with --threads torch threads, and "
                   "processes an evaluation's episodes are cut over (default 1; on 2 cores --jobs 2 --threads 1 "
                   "keeps both busy; results do not depend on it)")
    add_executor_arguments(p, "every independent stage a Ray task (each training stage, each evaluation shard, "
                           "each recorded episode)", "this machine, --jobs processes")
    p.add_argument("--skip-train", action="store_true",
                   help="do not train policies; report what the directory already holds")
    p.add_argument("--dry-run", action="store_true",
                   help="only say which stages are complete and which would run (and why, or after which stage)")
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

    preset = PRESETS[args.preset]
    if args.recipe:
        import dataclasses

        from lcmodels.experiment.recipe import load_recipe

        try:
            for r in args.recipe:
                load_recipe(r)
        except ValueError as exc:
            return error(str(exc).splitlines()[0])
        preset = dataclasses.replace(preset, recipes=tuple(args.recipe))
    exp = Experiment(preset, args.out, seeds=args.seeds, command=command, threads=args.threads,
                     progress=None if args.quiet else show, executor=args.executor,
                     ray_address=args.ray_address)  # fmt: skip
    try:
        exp.check_out()
        exp.graph()  # every recipe and follower reads and no stages wait on each other, before anything is written
    except ValueError as exc:
        return error(str(exc).splitlines()[0])
    setup_logging("lc-experiment", verbose=False)
    if args.dry_run:  # a query of the stage graph against DIR's records: nothing is written
        try:
            stages = exp.plan()
        except (ValueError, OSError) as exc:
            return error(str(exc).splitlines()[0])
        print(f"{sum(s.status == 'skipped' for s in stages)} stages complete, "
              f"{sum(s.status != 'skipped' for s in stages)} would run")
        return 0
    try:
        res = exp.run(skip_train=args.skip_train, jobs=args.jobs)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    except KeyboardInterrupt:
        print(f"\nlc-experiment: interrupted; the stages that finished are kept: rerun the same command to resume "
              f"{args.out}", file=sys.stderr)
        return 130
    done = sum(s.status == "done" for s in res.stages)
    skipped = sum(s.status == "skipped" for s in res.stages)
    print(f"{done} stages computed, {skipped} complete and skipped, {res.wall_s / 60:.1f} min")
    print(f"report: {res.report}")
    return 0
