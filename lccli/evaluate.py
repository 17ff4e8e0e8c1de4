"""``lc-eval``: a policy or a built-in driver on fixed held-out seeds; and the held-out arguments the
analysis tools share."""

from __future__ import annotations

import argparse
import contextlib
import functools
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from lccli.common import (
    add_safety_layer_arguments,
    add_setting_aliases,
    fail,
    int_at_least,
    positive_int,
    safety_layer_from_args,
    safety_settings,
    zoo_spec,
)
from lckit.config import (
    JsonConfig,
    check_field,
    check_limits,
    read_data_file,
    require_non_negative,
    require_positive,
)

if TYPE_CHECKING:
    from lcmodels.policy.driverspec import DriverSpec
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


@dataclass(frozen=True, slots=True, kw_only=True)
class EvalSettings(JsonConfig):
    """What ``lc-eval --config FILE`` (a TOML or JSON table of these fields, and a ``[safety]`` table of the safety
    layer's) and ``--set KEY=VALUE`` set; its flags set the rest."""

    LIMITS: ClassVar[dict[str, float]] = {"batch": 10_000, "threads": 1_024, "shards": 100_000}

    predictor: str = ""
    """A predictor checkpoint ('': the one the policy was trained with)."""
    batch: int = 20
    """Episodes simulated together."""
    threads: int = 1
    """Torch threads (more collapse when another process shares the cores)."""
    executor: str = "local"
    """``local`` (this machine: this process, or ``--workers`` processes) or ``ray``: the episodes cut into
    ``shards`` Ray tasks, the same figures (needs ``pip install -e ".[ray]"``)."""
    ray_address: str = ""
    """A running Ray cluster ('': RAY_ADDRESS, else a local instance started for the run)."""
    shards: int = 4
    """Ray tasks the episodes are cut into."""
    breakdown: bool = False
    """Also sort every collision at contact: trapped, missed_gap, late_change, short_gap, hit_from_behind
    (:mod:`lcmodels.analysis`)."""
    window_s: float = 5.0
    """With ``breakdown``: how far back a side gap counts as missed."""
    front_gap_m: float = 12.0
    """With ``breakdown``: a side gap's room ahead."""
    rear_gap_m: float = 5.0
    """With ``breakdown``: a side gap's room behind."""
    bound: bool = False
    """With the oracle: prove, episode by episode, whether it can be won at all (the search's winning decisions
    replayed from a fresh reset): the ceiling of any policy's success rate."""
    memory: int = 8
    """With ``bound``: decisions after which the ego's last lane change is forgotten when the search merges states
    (more merges less)."""
    max_nodes: int = 200_000
    """With ``bound``: give up on an episode after this many simulated decisions."""
    only: tuple[int, ...] = ()
    """With ``bound``: only these episode indices (0-based; a JSON list, ``[3, 7]``)."""

    def __post_init__(self) -> None:
        from lcdata.executors import EXECUTORS

        check_limits(self)
        require_positive(self, "batch", "threads", "shards", "window_s", "memory", "max_nodes")
        require_non_negative(self, "front_gap_m", "rear_gap_m")
        check_field(self.executor in EXECUTORS, self, "executor", f"must be one of {', '.join(EXECUTORS)}",
                    self.executor)  # fmt: skip
        check_field(all(i >= 0 for i in self.only), self, "only", "must be episode indices >= 0", self.only)


HELDOUT_ALIASES = {"--predictor": "predictor", "--batch": "batch"}
"""Older flags of :func:`add_heldout_arguments` that are settings now (still accepted)."""
EVAL_SETTING_ALIASES = {"--threads": "threads",
                        "--executor": "executor", "--ray-address": "ray_address", "--shards": "shards",
                        "--breakdown": "breakdown", "--window-s": "window_s", "--front-gap-m": "front_gap_m",
                        "--rear-gap-m": "rear_gap_m", "--bound": "bound", "--memory": "memory",
                        "--max-nodes": "max_nodes", "--only": "only"}  # fmt: skip
"""lc-eval's other older flags and the settings they are now (still accepted)."""


EVAL_EPILOG = """examples:
  lc-eval runs/hybrid-ppo/policy.safetensors --episodes 200 --seed 0 --json-out runs/hybrid-ppo/eval200.json
  lc-eval rule --episodes 200 --out runs/rule-eval
  lc-eval zoo:pure-ppo --scenario dense --episodes 200 --no-record   # a policy on another road of the suite
  lc-eval safety-layer:zoo:hybrid-ppo --follow zoo:pure-ppo --set safety.horizon_decisions=32 \\
      --set safety.samples=3 --episodes 1000 --seed 9 --workers 2 --no-record   # behind its safety layer
  lc-eval safety-layer:rule --set safety.perceived=false --no-record   # the rule-based driver behind a blind layer
  lc-eval zoo:hybrid-ppo --set breakdown=true --no-record   # why it crashes
  lc-eval oracle --set bound=true --episodes 200 --json-out bound.json   # what the scenario allows at all

settings (--config FILE: a TOML or JSON table of them, its [safety] table the safety layer's; then each
--set KEY=VALUE in order):
  predictor ('': the policy's own)  batch (20)  threads (1)  executor (local|ray)  ray_address  shards (4)
  breakdown (false)  window_s (5.0)  front_gap_m (12.0)  rear_gap_m (5.0)       # sorting the collisions
  bound (false)  memory (8)  max_nodes (200000)  only ([]: every episode)      # oracle's bound
  safety.follow  safety.horizon_decisions (16)  safety.samples (1)  safety.perceived (true)  safety.blind (true)
The safety layer: safety-layer:POLICY or safety-layer:rule; blind = false is a privileged layer, an upper
reference. Older spellings still work: lookahead-blind:POLICY (blind, not perceived), lookahead:POLICY
(privileged), --lookahead-follow, --lookahead-horizon/-samples/-perceived, and --batch, --threads, --predictor,
--breakdown, --window-s, --front-gap-m, --rear-gap-m, --executor, --ray-address, --shards, --bound, --memory,
--max-nodes, --only for the settings of the same names.

Evaluation episode i uses the user seed 1000000000 + 100000 * SEED + i (SEED < 20000), disjoint from training
seeds and from the benchmark's sealed test episodes, which only lc-bench --final runs.
Prints outcome rates (fractions) and means with 95% intervals; --json-out writes them as JSON; every
episode is recorded to MCAP under --out (actions, reward components, predictions the policy saw).
"""


def eval_settings(args: argparse.Namespace) -> tuple[EvalSettings, DriverSpec]:
    """The settings of :func:`add_heldout_arguments`' command line: :class:`EvalSettings`' defaults, ``--config``,
    then ``--set`` in order; and the driver, parsed once with the safety layer it drives behind (its settings from
    the spelling, ``[safety]``, ``--follow`` and ``--set safety.KEY=VALUE``). ``ValueError`` in one line naming the
    file or the setting."""
    from lcmodels.policy.driverspec import parse_driver_spec

    data: dict[str, Any] = {}
    config = getattr(args, "config", None)
    if config is not None:
        data = read_data_file(config, "config file")
    table = data.pop("safety", None)
    if table is not None and not isinstance(table, dict):
        raise ValueError(f"{config}: [safety] must be a table of the safety layer's settings")
    _, rest = safety_settings(args.settings)
    try:
        opts = EvalSettings.from_dict(data, stored=False)
    except ValueError as exc:
        raise ValueError(f"{config}: {exc}") from None
    layer = safety_layer_from_args(args.policy, args, table)
    return opts.with_settings(rest), parse_driver_spec(args.policy, safety_table=layer)


def heldout_driver(args: argparse.Namespace) -> tuple[Any, ScenarioConfig]:
    """The driver and scenario named by :func:`add_heldout_arguments`' ``policy`` and settings
    (a built-in driver runs the paper scenario without the image). ``ValueError`` with a one-line message
    for a checkpoint that is missing, unreadable or does not fit its predictor."""
    from lcmodels.policy.evaluate import driver_for
    from lcsim.config import paper_scenario

    opts, spec = eval_settings(args)
    try:
        driver, config = driver_for(spec, predictor=opts.predictor or None)
    except (ValueError, OSError) as exc:
        raise ValueError(str(exc).splitlines()[0]) from exc
    return driver, config or paper_scenario(render_image=False)


def predictor_unused(spec: DriverSpec, predictor: Path) -> str:
    """Why a predictor makes no sense for the policies ``spec`` names (none reads a prediction, nor the one its
    layer follows), or "" when one does or a policy file cannot be read (loading it reports that)."""
    from lcmodels.policy.checkpoint import read_meta
    from lcmodels.policy.obs import OBS_MODES, needs_predictor

    modes = []
    for each in (spec, spec.follow):
        if each is None or each.kind != "policy":
            continue
        try:
            modes.append(str(read_meta(each.path).get("obs_mode")))
        except ValueError:
            return ""
    if any(needs_predictor(m) for m in modes if m in OBS_MODES):
        return ""
    what = f"observation mode {', '.join(modes)}" if modes else "a built-in driver"
    return f"predictor {predictor}: {spec.text} reads no prediction ({what}); drop it"


def add_heldout_arguments(p: argparse.ArgumentParser, episodes: int = 200) -> None:
    """Who drives which held-out episodes, and how: ``policy``, ``--episodes``, ``--seed``, the safety layer's
    ``--follow``, ``--config`` and ``--set`` (:class:`EvalSettings`, :func:`eval_settings`), and the older flags
    that are settings now (lc-eval's arguments, shared by the tools that run the same episodes)."""
    p.add_argument("policy", type=zoo_spec,
                   help="policy checkpoint (policy.safetensors), zoo:NAME (a shipped policy: zoo/), a built-in "
                   "driver (rule, oracle, keep, random, and lookahead / lookahead-blind: the rule-based driver behind a privileged / blind safety layer), or "
                   "safety-layer:POLICY / safety-layer:rule: that driver behind the safety layer (older spellings: "
                   "lookahead-blind:POLICY, lookahead:POLICY)")
    p.add_argument("--episodes", type=positive_int, default=episodes, help="episodes (default %(default)s)")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="evaluation seed (default %(default)s)")
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="a TOML or JSON table of settings (below), its [safety] table the safety layer's")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting (below; safety.KEY for the safety layer's), after --config; repeatable")
    add_safety_layer_arguments(p, with_set=False)
    add_setting_aliases(p, HELDOUT_ALIASES)


def eval_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lc-eval",
        description="Evaluate a trained policy (or a non-learning driver), alone or behind the safety layer, on "
        "fixed held-out seeds.",
        epilog=EVAL_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_heldout_arguments(p)
    add_setting_aliases(p, EVAL_SETTING_ALIASES, flags=("--breakdown", "--bound"), lists=("--only",))
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
    p.add_argument("--workers", type=positive_int, default=None,
                   help="processes at once on this machine: the episodes cut over them, whole batches each, "
                   "the same figures (default 1); with bound, the searches (default 2)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def eval_main(argv: list[str] | None = None) -> int:
    args = eval_parser().parse_args(argv)
    command = "lc-eval " + shlex.join(sys.argv[1:] if argv is None else argv)

    error = functools.partial(fail, "lc-eval")

    import torch

    from lcmodels.policy.checkpoint import read_meta
    from lcmodels.policy.evaluate import driver_for, evaluate
    from lcsim.planning import LookaheadDriver
    from lcsim.registry import DRIVER_NAMES, scenario
    from lcsim.registry import scenario_label as registry_label

    try:
        opts, spec = eval_settings(args)
    except ValueError as exc:
        return error(str(exc))
    predictor = Path(opts.predictor) if opts.predictor else None
    is_driver = spec.kind == "driver"
    ckpt = Path(spec.name)
    if not is_driver and not ckpt.is_file():
        what = "is a directory" if ckpt.is_dir() else "does not exist"
        return error(f"{args.policy} {what} (expected a policy.safetensors, or {' / '.join(DRIVER_NAMES)})")
    from lcsim.suite import MAX_VALIDATION_SEED

    if args.seed >= MAX_VALIDATION_SEED:
        return error(f"--seed must be below {MAX_VALIDATION_SEED}: the seeds above are the benchmark's sealed test "
                     "episodes, which only lc-bench --final runs")
    if args.json_out is not None and args.json_out.exists() and not args.overwrite:
        return error(f"{args.json_out} already exists; pass --overwrite or choose another --json-out")
    from lckit.fileio import check_output_file, check_output_folder, check_target

    try:  # the summary is written after the whole evaluation: a place it cannot go is refused first
        if args.json_out is not None:
            check_output_file(args.json_out, "--json-out")
            check_target(args.json_out)  # never written through a link
        if args.out is not None and not args.no_record:
            check_output_folder(args.out)
    except (ValueError, OSError) as exc:
        return error(str(exc))
    if predictor is not None:
        problem = predictor_unused(spec, predictor)
        if problem:
            return error(problem)
    if opts.bound:
        return _bound_main(args, opts, error)
    torch.set_num_threads(opts.threads)
    try:
        target = scenario(args.scenario) if args.scenario is not None else None
    except ValueError as exc:
        return error(str(exc))
    try:
        driver, config = driver_for(spec, predictor=str(predictor) if predictor else None, scenario=target)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    if config is None:
        config = target if target is not None else scenario("paper")
    out = None
    if not args.no_record:
        if args.out is not None:
            out = args.out
        elif is_driver:
            out = Path("runs") / f"eval-{args.policy.replace(':', '-')}-s{args.seed}"
        else:
            out = ckpt.parent / f"eval-{ckpt.stem}-s{args.seed}"
    train_seeds = None
    if not is_driver:
        from lcmodels.fileio import read_train_seeds

        try:
            train_seeds = read_train_seeds(ckpt.parent)
        except ValueError as exc:
            return error(str(exc))
    if is_driver or args.scenario is not None:
        scenario_label = registry_label(args.scenario or "paper")
    else:
        scenario_label = str(read_meta(ckpt).get("scenario_name") or "paper")
    show = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", flush=True))
    start = time.perf_counter()
    if args.workers is not None and opts.executor == "ray":
        return error("--workers is for this machine; with executor ray, the setting shards says how the episodes "
                     "are cut")  # fmt: skip
    sharded = opts.executor == "local" and (args.workers or 1) > 1
    hooks = []
    if opts.breakdown:
        from lcmodels.analysis import CollisionBreakdown

        hooks.append(CollisionBreakdown(window_s=opts.window_s, front_gap_m=opts.front_gap_m,
                                        rear_gap_m=opts.rear_gap_m))  # fmt: skip
    try:
        if opts.executor == "ray" or sharded:
            if hooks:
                return error("breakdown runs in this process only (no executor ray, no --workers)")
            from lcdata.executors import ray_session
            from lcmodels.policy.evaluate import evaluate_sharded, shard_pool

            where = ray_session(opts.ray_address or None) if opts.executor == "ray" else contextlib.nullcontext()
            pooled = shard_pool(args.workers, opts.threads) if sharded else contextlib.nullcontext()
            with pooled as pool, where:
                summary, results = evaluate_sharded(
                    spec, config if is_driver or target is not None else None, episodes=args.episodes, seed=args.seed,
                    shards=opts.shards if opts.executor == "ray" else args.workers, executor=opts.executor,
                    pool=pool, predictor=str(predictor) if predictor else None,
                    out_dir=out, scenario=scenario_label, batch=opts.batch,
                    overwrite=args.overwrite, train_seeds=train_seeds, progress=show,
                    driver_name=str(getattr(driver, "name", type(driver).__name__)))  # fmt: skip
        else:
            summary, results = evaluate(driver, config, episodes=args.episodes, seed=args.seed, out_dir=out,
                                        batch=opts.batch, overwrite=args.overwrite, train_seeds=train_seeds,
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
    if isinstance(driver, LookaheadDriver) and opts.executor != "ray" and not sharded:  # how often it overrode
        summary["planner_choices"], summary["planner_overrides"] = driver.choices, driver.overrides
    if isinstance(driver, LookaheadDriver):  # how the safety layer imagined: the file says how it was made
        summary["safety_layer"] = driver.config.to_dict()
    summary["command"] = command
    print(format_eval(summary))
    processes = f", {args.workers} processes" if sharded else ""
    print(f"{summary['decisions']} decisions in {summary['wall_s']} s ({opts.batch} episodes at a time, "
          f"{opts.threads} torch threads{processes})")
    if "planner_overrides" in summary:
        print(f"the safety layer overrode {summary['planner_overrides']} of {summary['planner_choices']} decisions "
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
    from lckit.fileio import write_json

    try:
        write_json(path, data)
    except OSError as exc:
        return error(f"--json-out {path} could not be written: {exc.strerror or exc} (the figures are printed above)")
    print(f"wrote {path}")
    return 0


def _bound_main(args: argparse.Namespace, opts: EvalSettings, error: Callable[[str], int]) -> int:
    """``lc-eval oracle --set bound=true``: the share of the held-out episodes that can be won at all."""
    from lcmodels.analysis import oracle_bound
    from lcmodels.policy.evaluate import eval_user_seeds
    from lcsim.registry import scenario

    if args.policy != "oracle":
        return error(f"bound applies to the oracle (lc-eval oracle --set bound=true), not to {args.policy}")
    if args.out is not None or opts.breakdown:
        return error("bound records no episodes and sorts no collisions; write its figures with --json-out")
    try:
        config = scenario(args.scenario or "paper")
        users = eval_user_seeds(args.episodes, args.seed)
    except ValueError as exc:
        return error(str(exc))
    show = None if args.quiet else (lambda k, n: print(f"\rsearching: {k}/{n} episodes", end="", flush=True))
    try:
        summary, rows = oracle_bound(config, users, indices=list(opts.only) or None, memory_decisions=opts.memory,
                                     max_nodes=opts.max_nodes, workers=args.workers or 2, progress=show)
    except ValueError as exc:
        return error(str(exc))
    if show is not None:
        print()
    summary.update(scenario=args.scenario or "paper", eval_seed=args.seed)
    won, n = summary["winnable"], summary["episodes"]
    lo, hi = summary["winnable_rate_ci95"]
    print(f"winnable: {won}/{n} = {100 * won / n:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}] "
          f"(every winning sequence replayed to success: {summary['replayed_success']}/{won})")
    print(f"no winning sequence: episodes {summary['not_winnable_episodes'] or 'none'}; undecided (max_nodes): "
          f"{summary['undecided_episodes'] or 'none'}")
    print(f"search: {summary['nodes_total']} decisions simulated, {summary['cpu_s_total']} s CPU, "
          f"{summary['wall_s']} s wall on {args.workers or 2} workers")
    if args.json_out is not None and _write_summary(args.json_out, {"summary": summary, "episodes": rows}, error):
        return 2
    return 0 if summary["replayed_success"] == won else 1
