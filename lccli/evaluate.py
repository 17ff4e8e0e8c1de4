"""``lc-eval``: a policy or a built-in driver on fixed held-out seeds; and the held-out arguments the
analysis tools share."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import shlex
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lccli.common import (
    add_executor_arguments,
    add_lookahead_arguments,
    fail,
    int_at_least,
    lookahead_options,
    positive_int,
    zoo_spec,
)

if TYPE_CHECKING:
    from lcsim.config import ScenarioConfig

def format_eval(ev: dict) -> str:
    """One line: the outcome rates and means of an evaluation summary, each with its 95% interval."""
    def rate(k: str) -> str:
        lo, hi = ev[f"{k}_rate_ci95"]
        return f"{k} {100 * ev[f'{k}_rate']:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}]"

    lo, hi = ev["mean_safe_forward_m_ci95"]
    rlo, rhi = ev["mean_return_ci95"]
    return (f"held-out evaluation, {ev['episodes']} episodes: " + ", ".join(rate(k) for k in
            ("success", "collision", "off_road", "timeout")) +
            f"; safe forward {ev['mean_safe_forward_m']:.1f} m [{lo:.1f}, {hi:.1f}]"
            f"; return {ev['mean_return']:.1f} [{rlo:.1f}, {rhi:.1f}]")


EVAL_EPILOG = """examples:
  lc-eval runs/hybrid-ppo/policy.safetensors --episodes 200 --seed 0 --json-out runs/hybrid-ppo/eval200.json
  lc-eval rule --episodes 200 --out runs/rule-eval
  lc-eval zoo:pure-ppo --scenario dense --episodes 200 --no-record   # a policy on another road of the suite
  lc-eval lookahead-blind:runs/hybrid-ppo/policy.safetensors --lookahead-follow runs/ppo-pure/policy.safetensors \\
      --lookahead-horizon 32 --no-record     # Hybrid-PPO behind the planner, imagining 16 s with the pure policy
  lc-eval lookahead-blind:zoo:hybrid-ppo --lookahead-follow zoo:pure-ppo --lookahead-perceived \\
      --lookahead-horizon 32 --lookahead-samples 3 --episodes 1000 --seed 9 --workers 2   # its card's figure

Evaluation episode i uses the user seed 1000000000 + 100000 * SEED + i (SEED < 20000), disjoint from training
seeds and from the benchmark's sealed test episodes, which only lc-bench --final runs.
Prints outcome rates (fractions) and means with 95% intervals; --json-out writes them as JSON; every
episode is recorded to MCAP under --out (actions, reward components, predictions the policy saw).
"""


def heldout_driver(args: argparse.Namespace) -> tuple[Any, ScenarioConfig]:
    """The driver and scenario named by :func:`add_heldout_arguments`' ``policy`` and ``--predictor``
    (a built-in driver runs the paper scenario without the image). ``ValueError`` with a one-line message
    for a checkpoint that is missing, unreadable or does not fit its predictor."""
    from lcmodels.policy.evaluate import driver_for
    from lcsim.config import paper_scenario

    try:
        driver, config = driver_for(args.policy, predictor=args.predictor, lookahead=lookahead_options(args),
                                    follow=args.lookahead_follow)
    except (ValueError, OSError) as exc:
        raise ValueError(str(exc).splitlines()[0]) from exc
    return driver, config or paper_scenario(render_image=False)


def predictor_unused(policy: str, follow: str | None, predictor: Path) -> str:
    """Why ``--predictor`` makes no sense for the policies named (none reads a prediction), or "" when one
    does or a policy file cannot be read (loading it reports that)."""
    from lcmodels.policy.checkpoint import read_meta
    from lcmodels.policy.evaluate import policy_path_of
    from lcmodels.policy.obs import OBS_MODES, needs_predictor
    from lcsim.registry import DRIVER_NAMES

    modes = []
    for spec in (policy, follow):
        if spec is None or spec in DRIVER_NAMES:
            continue
        try:
            modes.append(str(read_meta(policy_path_of(spec)).get("obs_mode")))
        except ValueError:
            return ""
    if any(needs_predictor(m) for m in modes if m in OBS_MODES):
        return ""
    what = f"observation mode {', '.join(modes)}" if modes else "a built-in driver"
    return f"--predictor {predictor}: {policy} reads no prediction ({what}); drop --predictor"


def add_heldout_arguments(p: argparse.ArgumentParser, episodes: int = 200) -> None:
    """Who drives which held-out episodes: ``policy``, ``--episodes``, ``--seed``, ``--predictor``, ``--batch``
    (lc-eval's arguments, shared by the tools that run the same episodes)."""
    p.add_argument("policy", type=zoo_spec,
                   help="policy checkpoint (policy.safetensors), zoo:NAME (a shipped policy: zoo/), or a built-in "
                   "driver: rule / lookahead / "
                   "lookahead-blind / oracle (planners, upper references) / keep / random, or lookahead:POLICY / "
                   "lookahead-blind:POLICY (the lookahead following a policy without image in its imagined futures; "
                   "see --lookahead-follow)")
    p.add_argument("--episodes", type=positive_int, default=episodes, help="episodes (default %(default)s)")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="evaluation seed (default %(default)s)")
    p.add_argument("--predictor", type=Path, default=None,
                   help="predictor checkpoint (default: the one the policy was trained with)")
    p.add_argument("--batch", type=positive_int, default=20, help="episodes simulated together (default 20)")
    add_lookahead_arguments(p)
    p.add_argument("--lookahead-follow", metavar="DRIVER", default=None, type=zoo_spec,
                   help="with lookahead:POLICY / lookahead-blind:POLICY: the policy proposes each decision and the "
                   "imagined futures follow DRIVER (a built-in driver or a policy.safetensors without image), which "
                   "lets the lookahead guard a policy that reads the image (default: the policy itself)")


def eval_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lc-eval",
        description="Evaluate a trained policy (or a non-learning driver) on fixed held-out seeds.",
        epilog=EVAL_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_heldout_arguments(p)
    p.add_argument("--scenario", default=None, metavar="NAME|FILE",
                   help="where to drive: a registered scenario (paper, three-lane, dense, ...; lc-bench --list) or a "
                   "scenario file (.toml/.json of ScenarioConfig fields); default: a policy's own, paper for a "
                   "built-in driver. A policy drives elsewhere when its observation keeps its shapes there")
    p.add_argument("--out", type=Path, default=None,
                   help="record every episode here (default: eval-<name>-s<seed> next to the checkpoint, "
                   "or runs/eval-<driver> for a driver)")
    p.add_argument("--no-record", action="store_true", help="do not record episodes")
    p.add_argument("--overwrite", action="store_true", help="replace existing episode files")
    p.add_argument("--json-out", type=Path, default=None, help="write the summary as JSON here")
    p.add_argument("--threads", type=positive_int, default=1,
                   help="torch threads (default 1: more collapse when another process shares the cores)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    why = p.add_argument_group("why it crashes (--breakdown)")
    why.add_argument("--breakdown", action="store_true",
                     help="also sort every collision at contact: trapped, missed_gap, late_change, short_gap, "
                     "hit_from_behind (see lcmodels.analysis)")
    why.add_argument("--window-s", type=float, default=5.0,
                     help="how far back a side gap counts as missed (default 5)")
    why.add_argument("--front-gap-m", type=float, default=12.0, help="a side gap's room ahead (default 12)")
    why.add_argument("--rear-gap-m", type=float, default=5.0, help="a side gap's room behind (default 5)")
    where = p.add_argument_group("where the episodes run")
    add_executor_arguments(where, "the episodes cut into --shards parts, each a Ray task", "this process")
    where.add_argument("--shards", type=positive_int, default=4, help="Ray tasks the episodes are cut into (4)")
    where.add_argument("--workers", type=positive_int, default=None,
                       help="processes at once on this machine: the episodes cut over them, whole batches each, "
                       "the same figures (default 1); with --bound, the searches (default 2)")
    bound = p.add_argument_group("what the scenario allows (lc-eval oracle --bound)")
    bound.add_argument("--bound", action="store_true",
                       help="with the oracle: prove, episode by episode, whether it can be won at all (the search's "
                       "winning decisions replayed from a fresh reset): the ceiling of any policy's success rate")
    bound.add_argument("--memory", type=positive_int, default=8,
                       help="decisions after which the ego's last lane change is forgotten when the search merges "
                       "states (default 8; more merges less)")
    bound.add_argument("--max-nodes", type=positive_int, default=200_000,
                       help="give up on an episode after this many simulated decisions (default 200000)")
    bound.add_argument("--only", type=int, nargs="+", metavar="I", help="only these episode indices (0-based)")
    return p


def eval_main(argv: list[str] | None = None) -> int:
    args = eval_parser().parse_args(argv)
    command = "lc-eval " + shlex.join(sys.argv[1:] if argv is None else argv)

    error = functools.partial(fail, "lc-eval")

    import numpy as np
    import torch

    from lcmodels.policy.checkpoint import read_meta
    from lcmodels.policy.evaluate import driver_for, evaluate, policy_path_of
    from lcsim.planning import LookaheadDriver
    from lcsim.registry import DRIVER_NAMES, scenario
    from lcsim.registry import scenario_label as registry_label

    is_driver = args.policy in DRIVER_NAMES
    ckpt = policy_path_of(args.policy)
    if not is_driver and not ckpt.is_file():
        what = "is a directory" if ckpt.is_dir() else "does not exist"
        return error(f"{args.policy} {what} (expected a policy.safetensors, or {' / '.join(DRIVER_NAMES)})")
    from lcsim.suite import MAX_VALIDATION_SEED

    if args.seed >= MAX_VALIDATION_SEED:
        return error(f"--seed must be below {MAX_VALIDATION_SEED}: the seeds above are the benchmark's sealed test "
                     "episodes, which only lc-bench --final runs")
    if args.json_out is not None and args.json_out.exists() and not args.overwrite:
        return error(f"{args.json_out} already exists; pass --overwrite or choose another --json-out")
    from lcdata.fileio import check_output_file, check_output_folder

    try:  # the summary is written after the whole evaluation: a place it cannot go is refused first
        if args.json_out is not None:
            check_output_file(args.json_out, "--json-out")
        if args.out is not None and not args.no_record:
            check_output_folder(args.out)
    except ValueError as exc:
        return error(str(exc))
    if args.predictor is not None:
        problem = predictor_unused(args.policy, args.lookahead_follow, args.predictor)
        if problem:
            return error(problem)
    if args.bound:
        return _bound_main(args, error)
    if args.window_s <= 0:
        return error(f"--window-s must be > 0, got {args.window_s}")
    torch.set_num_threads(args.threads)
    try:
        target = scenario(args.scenario) if args.scenario is not None else None
    except ValueError as exc:
        return error(str(exc))
    try:
        driver, config = driver_for(args.policy, predictor=str(args.predictor) if args.predictor else None,
                                    lookahead=lookahead_options(args), follow=args.lookahead_follow,
                                    scenario=target)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    if config is None:
        config = target if target is not None else scenario("paper")
    out = None
    if not args.no_record:
        if args.out is not None:
            out = args.out
        elif is_driver:
            out = Path("runs") / f"eval-{args.policy}-s{args.seed}"
        else:
            out = ckpt.parent / f"eval-{ckpt.stem}-s{args.seed}"
    train_seeds = None
    if not is_driver:
        seeds_file = ckpt.parent / "train_episode_seeds.npy"
        train_seeds = np.load(seeds_file) if seeds_file.exists() else None
    if is_driver or args.scenario is not None:
        scenario_label = registry_label(args.scenario or "paper")
    else:
        scenario_label = str(read_meta(ckpt).get("scenario_name") or "paper")
    show = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", flush=True))
    start = time.perf_counter()
    if args.workers is not None and args.executor == "ray":
        return error("--workers is for this machine; with --executor ray, --shards says how the episodes are cut")
    sharded = args.executor == "local" and (args.workers or 1) > 1
    hooks = []
    if args.breakdown:
        from lcmodels.analysis import CollisionBreakdown

        hooks.append(CollisionBreakdown(window_s=args.window_s, front_gap_m=args.front_gap_m,
                                        rear_gap_m=args.rear_gap_m))  # fmt: skip
    try:
        if args.executor == "ray" or sharded:
            if hooks:
                return error("--breakdown runs in this process only (no --executor ray, no --workers)")
            from lcdata.executors import ray_session
            from lcdata.procs import closing_pool
            from lcmodels.policy.evaluate import evaluate_sharded, shard_pool

            where = ray_session(args.ray_address) if args.executor == "ray" else contextlib.nullcontext()
            pooled = closing_pool(shard_pool(args.workers, args.threads)) if sharded else contextlib.nullcontext()
            with pooled as pool, where:
                summary, results = evaluate_sharded(
                    args.policy, config if is_driver or target is not None else None, episodes=args.episodes, seed=args.seed,
                    shards=args.shards if args.executor == "ray" else args.workers, executor=args.executor,
                    pool=pool, predictor=str(args.predictor) if args.predictor else None,
                    lookahead=lookahead_options(args), follow=args.lookahead_follow,
                    out_dir=out, scenario=scenario_label, batch=args.batch,
                    overwrite=args.overwrite, train_seeds=train_seeds, progress=show,
                    driver_name=str(getattr(driver, "name", type(driver).__name__)))  # fmt: skip
        else:
            summary, results = evaluate(driver, config, episodes=args.episodes, seed=args.seed, out_dir=out,
                                        batch=args.batch, overwrite=args.overwrite, train_seeds=train_seeds,
                                        progress=show, hooks=hooks, scenario=scenario_label)  # fmt: skip
    except OSError as exc:  # a full disk under --out
        where = f" under {out}" if out is not None else ""
        return error(f"the evaluation stopped: writing{where} failed: {exc.strerror or exc}; episodes not finished "
                     "are left as .partial files")
    except ValueError as exc:
        return error(str(exc).splitlines()[0])
    except KeyboardInterrupt:
        print("lc-eval: interrupted; nothing summarised (episodes recorded so far are kept; --overwrite to redo "
              "them)", file=sys.stderr)  # fmt: skip
        return 130
    if hooks:
        summary["collision_kinds"] = hooks[0].counts
    summary["wall_s"] = round(time.perf_counter() - start, 3)
    summary["decisions"] = sum(r.length for r in results)
    if isinstance(driver, LookaheadDriver) and args.executor != "ray" and not sharded:  # how often it overrode
        summary["planner_choices"], summary["planner_overrides"] = driver.choices, driver.overrides
    if isinstance(driver, LookaheadDriver):  # what the planner imagined: the file says how it was made
        summary["lookahead"] = dataclasses.asdict(driver.config) | {"follow": args.lookahead_follow}
    summary["command"] = command
    print(format_eval(summary))
    processes = f", {args.workers} processes" if sharded else ""
    print(f"{summary['decisions']} decisions in {summary['wall_s']} s ({args.batch} episodes at a time, "
          f"{args.threads} torch threads{processes})")
    if "planner_overrides" in summary:
        print(f"the planner overrode {summary['planner_overrides']} of {summary['planner_choices']} decisions "
              "with a choice")
    if "overlap_with_training" in summary:
        print(f"evaluation episodes also seen in training: {summary['overlap_with_training']}")
    if "collision_kinds" in summary:
        print("collisions by kind: " + ", ".join(f"{k} {v}" for k, v in summary["collision_kinds"].items()))
    if out is not None:
        print(f"recorded {args.episodes} episodes in {out}")
    if args.json_out is not None:
        return _write_summary(args.json_out, summary, error)
    return 0


def _write_summary(path: Path, data: object, error: Callable[[str], int]) -> int:
    """Write ``--json-out`` (atomically); a write that fails still (a disk filled during the evaluation) is one
    line, after the figures were printed."""
    from lcdata.fileio import write_json

    try:
        write_json(path, data)
    except OSError as exc:
        return error(f"--json-out {path} could not be written: {exc.strerror or exc} (the figures are printed above)")
    print(f"wrote {path}")
    return 0


def _bound_main(args: argparse.Namespace, error: Callable[[str], int]) -> int:
    """``lc-eval oracle --bound``: the share of the held-out episodes that can be won at all."""
    from lcmodels.analysis import oracle_bound
    from lcmodels.policy.evaluate import eval_user_seeds
    from lcsim.registry import scenario

    if args.policy != "oracle":
        return error(f"--bound applies to the oracle (lc-eval oracle --bound), not to {args.policy}")
    if args.out is not None or args.breakdown:
        return error("--bound records no episodes and sorts no collisions; write its figures with --json-out")
    try:
        config = scenario(args.scenario or "paper")
        users = eval_user_seeds(args.episodes, args.seed)
    except ValueError as exc:
        return error(str(exc))
    show = None if args.quiet else (lambda k, n: print(f"\rsearching: {k}/{n} episodes", end="", flush=True))
    try:
        summary, rows = oracle_bound(config, users, indices=args.only, memory_decisions=args.memory,
                                     max_nodes=args.max_nodes, workers=args.workers or 2, progress=show)
    except ValueError as exc:
        return error(str(exc))
    if show is not None:
        print()
    summary.update(scenario=args.scenario or "paper", eval_seed=args.seed)
    won, n = summary["winnable"], summary["episodes"]
    lo, hi = summary["winnable_rate_ci95"]
    print(f"winnable: {won}/{n} = {100 * won / n:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}] "
          f"(every winning sequence replayed to success: {summary['replayed_success']}/{won})")
    print(f"no winning sequence: episodes {summary['not_winnable_episodes'] or 'none'}; undecided (--max-nodes): "
          f"{summary['undecided_episodes'] or 'none'}")
    print(f"search: {summary['nodes_total']} decisions simulated, {summary['cpu_s_total']} s CPU, "
          f"{summary['wall_s']} s wall on {args.workers or 2} workers")
    if args.json_out is not None and _write_summary(args.json_out, {"summary": summary, "episodes": rows}, error):
        return 2
    return 0 if summary["replayed_success"] == won else 1
