"""``lc-bench``: any policy or driver on every scenario of the benchmark suite, next to each scenario's
ceiling (the oracle) and floor (the rule-based driver)."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from lccli.common import (
    add_executor_arguments,
    add_safety_layer_arguments,
    fail,
    int_at_least,
    positive_int,
    safety_layer_from_args,
)

EPILOG = """examples:
  lc-bench --list                                          # the suites and their scenarios
  lc-bench zoo:hybrid-ppo zoo:pure-ppo --episodes 100      # validation episodes (evaluation seed 0), 2 policies
  lc-bench zoo:hybrid-ppo zoo:pure-ppo rule oracle --final --workers 2   # the sealed test episodes
  lc-bench zoo:hybrid-ppo safety-layer:zoo:hybrid-ppo --follow zoo:pure-ppo --set safety.horizon_decisions=32 \\
      --set safety.samples=3 --suite paper --final --workers 2   # alone and behind its safety layer
  lc-bench mypkg.policies:act --episodes 50                # your own policy: act(obs[, action_mask]) -> actions
  lc-bench --verify                                        # replay 10 episodes of every ledger line, compare
  lc-bench --verify --verify-episodes all 7c68e9a44fc1      # one line, every episode of it

Validation (default): --episodes episodes of evaluation seed --seed on every scenario, cached under
--out/cells/, so a rerun resumes. Use them for every choice.
--final: each scenario's sealed test episodes (2000 on paper, 500 elsewhere), which no other command runs.
Each result is looked up in the ledger (docs/results/benchmark/ledger.jsonl; LC_LEDGER or --ledger
elsewhere) and, when missing, run and appended to it with the commit, the date and every episode's outcome:
a policy is measured once, a changed one gets a new entry. Quote test figures from the ledger, and decide
nothing on them. Every figure is derived from the line's outcome letters (a line whose stored figures or key
disagree with them is refused); with another ledger than the committed one, every figure printed says so.

--verify: replay ledger lines (all, or the KEYs named in place of POLICY) with the weights each names and
compare every replayed episode's outcome with the line's letter: a deterministic random sample of
--verify-episodes per line (default 10; `all` replays every episode), drawn with --verify-seed. A line
prints `checked K/N episodes, ok`, `MISMATCH` (the first episode that differs; the command then exits 1
with one line per mismatching line), or `not checkable` with the reason (weights not present, a road whose
config changed since). A file whose weights differ from the line's digest is refused.

Writes --out/BENCH.md and --out/bench.json (replacing those an earlier lc-bench wrote; any other file of
those names only with --overwrite): per scenario the ceiling, the floor and each driver's success
and collision with Wilson 95% intervals over episodes and the normalised score (success / ceiling's
success); per driver the suite's mean normalised score and McNemar's exact test against the first driver on
the same episodes; per method (a recipe's training seeds) the IQM with rliable's bootstrap interval and
McNemar's test against the first method, its runs paired training seed with training seed (in the
order given where a run's seed is unknown). Beside them, two figures (PNG
and SVG, embedded in BENCH.md): each method's normalised score per scenario with its interval
(bench_normalised), and rliable's interval estimates of the IQM and mean (bench_intervals).
"""


def bench_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lc-bench", epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Any policy or driver on every road of the benchmark suite, next to each road's ceiling (the "
        "oracle) and floor (the rule-based driver): validation episodes for choices, or the sealed test episodes "
        "through the ledger (--final).")
    p.add_argument("policies", nargs="*", metavar="POLICY",
                   help="zoo:NAME, a policy.safetensors, a built-in driver (rule, oracle, lookahead, keep, ...), "
                   "safety-layer:POLICY (behind the safety layer; older spelling lookahead-blind:POLICY), or "
                   "package.module:callable; with --verify, ledger keys (default: every line)")
    p.add_argument("--list", action="store_true", help="list the suites and their scenarios, then exit")
    p.add_argument("--suite", default=None, help="the suite (default highway; --list shows them)")
    p.add_argument("--scenario", action="append", default=None, metavar="NAME",
                   help="only this scenario of the suite (repeatable)")
    p.add_argument("--final", action="store_true",
                   help="the sealed test episodes, through the ledger (see below)")
    p.add_argument("--episodes", type=positive_int, default=None,
                   help="validation episodes per scenario (default 100; not with --final)")
    p.add_argument("--seed", type=int_at_least(0), default=None,
                   help="validation evaluation seed (default 0; not with --final)")
    p.add_argument("--ledger", type=Path, default=None, help="the ledger (default: LC_LEDGER, else the checkout's)")
    check = p.add_argument_group("verifying the ledger by replay")
    check.add_argument("--verify", action="store_true",
                       help="replay ledger lines' episodes and compare their outcome letters (see below)")
    check.add_argument("--verify-episodes", type=_episodes_or_all, default=None, metavar="N|all",
                       help="episodes replayed per line: a deterministic random sample, or all (default 10)")
    check.add_argument("--verify-seed", type=int_at_least(0), default=None, metavar="S",
                       help="the seed the sample of episodes is drawn with (default 0)")
    p.add_argument("--out", type=Path, default=None,
                   help="where the table and the cached cells go (default runs/bench, or runs/bench-final)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a BENCH.md or bench.json in --out that lc-bench did not write")
    add_safety_layer_arguments(p)
    p.add_argument("--batch", type=positive_int, default=20, help="episodes simulated together (default 20)")
    p.add_argument("--threads", type=positive_int, default=1, help="torch threads per process (default 1)")
    p.add_argument("-q", "--quiet", action="store_true", help="no episode counts while a cell runs (a line per cell stays)")
    p.add_argument("--no-figures", action="store_true",
                   help="do not draw bench_normalised and bench_intervals (PNG and SVG beside BENCH.md)")
    where = p.add_argument_group("where the episodes run")
    add_executor_arguments(where, "each cell's episodes cut into Ray tasks", "this machine")
    where.add_argument("--workers", type=positive_int, default=1,
                       help="processes on this machine, each cell's episodes cut over them (default 1)")
    return p


def _episodes_or_all(text: str) -> int | str:
    """``--verify-episodes``: a positive count, or ``all``."""
    return text if text == "all" else positive_int(text)


def _verify(args: argparse.Namespace) -> int:
    """``lc-bench --verify``: replay the ledger's lines (or those named) and compare their letters."""
    from lcmodels.bench.ledger import NOT_COMMITTED, is_committed, ledger_path, read_ledger
    from lcmodels.bench.run import FINAL_BATCH, Runner
    from lcmodels.bench.verify import DEFAULT_EPISODES, select_entries, verify_ledger

    error = lambda msg: fail("lc-bench", msg)  # noqa: E731
    used = [flag for flag, value in (("--final", args.final), ("--episodes", args.episodes), ("--seed", args.seed),
                                     ("--suite", args.suite), ("--scenario", args.scenario), ("--out", args.out),
                                     ("--follow", args.follow), ("--set", args.settings)) if value]  # fmt: skip
    if used:
        return error(f"--verify replays ledger lines as they were run: drop {', '.join(used)}")
    if args.workers > 1 and args.executor == "ray":
        return error("--workers is for this machine; with --executor ray the lines' episodes become Ray tasks")
    ledger = args.ledger or ledger_path()
    try:
        entries = select_entries(read_ledger(ledger), args.policies)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    episodes = None if args.verify_episodes == "all" else args.verify_episodes or DEFAULT_EPISODES
    mark = "" if is_committed(ledger) else f" ({NOT_COMMITTED})"
    print(f"lc-bench: verifying {len(entries)} line(s) of ledger {ledger}{mark} by replay, "
          f"{'every episode' if episodes is None else f'{episodes} episode(s) a line'}", flush=True)
    import torch

    torch.set_num_threads(args.threads)
    runner = Runner(workers=args.workers, executor=args.executor, threads=args.threads, batch=FINAL_BATCH,
                    ray_address=args.ray_address)  # fmt: skip
    verdicts = []
    try:
        with runner.session():
            for i, verdict in enumerate(verify_ledger(entries, runner, episodes=episodes,
                                                      seed=args.verify_seed or 0), 1):  # fmt: skip
                verdicts.append(verdict)
                print(f"[{i}/{len(entries)}] {verdict.line()}", flush=True)
    except KeyboardInterrupt:
        print("\nlc-bench: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    by = {s: [v for v in verdicts if v.status == s] for s in ("ok", "not checkable", "mismatch")}
    print(f"lc-bench: {len(by['ok'])} line(s) ok ({sum(v.checked for v in by['ok'])} episodes replayed, "
          f"{sum(v.wall_s for v in verdicts):.0f} s), {len(by['not checkable'])} not checkable, "
          f"{len(by['mismatch'])} mismatching")  # fmt: skip
    for v in by["mismatch"]:
        print(f"lc-bench: error: ledger line {v.key} ({v.what}): MISMATCH at {v.detail}", file=sys.stderr)
    return 1 if by["mismatch"] else 0


def _list() -> str:
    from lcsim.suite import SUITE_SCENARIOS, SUITES

    lines = []
    for name, members in SUITES.items():
        lines.append(f"suite {name}: {', '.join(members)}")
    lines.append("")
    for sc in SUITE_SCENARIOS.values():
        lines.append(f"  {sc.name:<11} {sc.test_episodes:>5} sealed test episodes  {sc.what}")
    return "\n".join(lines)


OUTPUTS = ("BENCH.md", "bench.json")
"""What lc-bench writes in --out besides its cells/ (each names the command that made it)."""


def written_by_bench(path: Path) -> bool:
    """Whether lc-bench wrote ``path``: a ``BENCH.md`` whose last line is the lc-bench command that made it, a
    ``bench.json`` whose ``command`` is one (what :func:`main` puts in both)."""
    from lckit.fileio import read_json

    if path.suffix == ".json":
        data = read_json(path)
        return isinstance(data, dict) and str(data.get("command", "")).startswith("lc-bench ")
    try:
        with path.open("rb") as f:
            f.seek(max(0, path.stat().st_size - 4096))
            tail = f.read().decode(errors="replace").rstrip().splitlines()
    except OSError:
        return False
    return bool(tail) and tail[-1].startswith("`lc-bench ") and tail[-1].endswith("`")


def check_out(out: Path, overwrite: bool) -> None:
    """``ValueError`` (or :class:`~lckit.fileio.UnsafePathError`) in one line, before anything runs, when lc-bench
    may not write in ``out``: a file, a ``cells/`` that leads out of it, a ``BENCH.md`` or ``bench.json`` that is
    a symbolic link, or one lc-bench did not write (unless ``overwrite``)."""
    from lckit.fileio import check_inside, check_target

    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a directory")
    check_inside(out / "cells", out)
    for name in OUTPUTS:
        path = check_target(out / name, out)
        if path.exists() and not overwrite and not written_by_bench(path):
            raise ValueError(f"{path} exists and lc-bench did not write it; pass --overwrite to replace it, or "
                             "choose another --out")


def main(argv: list[str] | None = None) -> int:
    args = bench_parser().parse_args(argv)
    error = lambda msg: fail("lc-bench", msg)  # noqa: E731
    if args.list:
        print(_list())
        return 0
    if args.verify:
        return _verify(args)
    if args.verify_episodes is not None or args.verify_seed is not None:
        return error("--verify-episodes and --verify-seed go with --verify")
    if not args.policies:
        return error("name at least one POLICY (or --list)")
    command = "lc-bench " + shlex.join(sys.argv[1:] if argv is None else argv)

    from lckit.fileio import write_file
    from lcmodels.bench.ledger import NOT_COMMITTED, is_committed, ledger_path, read_ledger
    from lcmodels.bench.run import Runner, bench_cell, resolve_driver
    from lcmodels.bench.table import CEILING, FLOOR, suite_markdown, suite_summary
    from lcsim.suite import DEFAULT_SUITE, MAX_VALIDATION_SEED, SUITE_SCENARIOS, suite

    if args.final and (args.episodes is not None or args.seed is not None):
        return error("--final runs each scenario's sealed test episodes, all of them: drop --episodes / --seed")
    episodes = args.episodes or 100
    seed = 0 if args.seed is None else args.seed
    if seed >= MAX_VALIDATION_SEED:
        return error(f"--seed must be below {MAX_VALIDATION_SEED} (above are the sealed test episodes: --final)")
    if args.workers > 1 and args.executor == "ray":
        return error("--workers is for this machine; with --executor ray the cells' episodes become Ray tasks")
    try:
        scenarios = suite(args.suite or DEFAULT_SUITE)
    except ValueError as exc:
        return error(str(exc))
    if args.scenario:
        unknown = [s for s in args.scenario if s not in SUITE_SCENARIOS]
        if unknown:
            return error(f"unknown suite scenario {unknown[0]!r}; choose {', '.join(SUITE_SCENARIOS)}")
        scenarios = [s for s in scenarios if s.name in args.scenario] if args.suite else \
            [SUITE_SCENARIOS[s] for s in dict.fromkeys(args.scenario)]
        if not scenarios:
            return error(f"none of {', '.join(args.scenario)} is in suite {args.suite}")
    ledger = args.ledger or ledger_path()
    try:
        read_ledger(ledger)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    out = args.out or Path("runs") / ("bench-final" if args.final else "bench")
    try:
        check_out(out, args.overwrite)
    except (ValueError, OSError) as exc:
        return error(str(exc))
    from lcmodels.policy.driverspec import parse_driver_spec, split_safety_layer

    try:
        behind = [p for p in args.policies if split_safety_layer(p)[1] is not None]
        if not behind and (args.follow or args.settings):
            return error("--follow and --set safety.KEY=VALUE apply to a driver behind the safety layer "
                         "(safety-layer:POLICY)")  # fmt: skip
        specs = [parse_driver_spec(p, safety_table=safety_layer_from_args(p, args) if p in behind else None)
                 for p in args.policies]  # fmt: skip
        drivers = [resolve_driver(s) for s in specs]
        references = {name: resolve_driver(parse_driver_spec(name)) for name in (CEILING, FLOOR)}
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    labels = [d.label for d in drivers]
    if len(set(labels)) != len(labels):
        return error("a POLICY is named twice")
    todo = [(d, sc) for sc in scenarios for d in [*(r for r in references.values() if r.label not in labels),
                                                  *drivers]]  # fmt: skip
    split = "test" if args.final else f"validation seed {seed}"
    mark = f" [{NOT_COMMITTED}]" if args.final and not is_committed(ledger) else ""
    print(f"lc-bench: {len(drivers)} driver(s) x {len(scenarios)} scenario(s) of suite {args.suite or DEFAULT_SUITE}, "
          f"{split} episodes; ceiling oracle, floor rule" + (f"; ledger {ledger}{mark}" if args.final else ""),
          flush=True)  # fmt: skip
    show = None if args.quiet else (lambda k, n: print(f"\r  {k}/{n} episodes", end="", flush=True))
    runner = Runner(workers=args.workers, executor=args.executor, threads=args.threads, batch=args.batch,
                    ray_address=args.ray_address, progress=show)  # fmt: skip
    cells: dict[tuple[str, str], dict] = {}
    sources: dict[str, int] = {}
    import torch

    torch.set_num_threads(args.threads)
    try:
        with runner.session():
            for i, (driver, sc) in enumerate(todo, 1):
                cell = bench_cell(driver, sc, runner, final=args.final, episodes=episodes, seed=seed,
                                  cache_dir=out / "cells", ledger=ledger, command=command)  # fmt: skip
                rec = cell.record
                where = {"ledger": "from the ledger", "ledger+": "appended to the ledger", "cache": "cached",
                         "run": "run"}[cell.source]  # fmt: skip
                if show is not None and cell.source in ("run", "ledger+"):
                    print("\r", end="")
                sources[cell.source] = sources.get(cell.source, 0) + 1
                print(f"[{i}/{len(todo)}] {driver.label} on {sc.name}: success {100 * rec['success_rate']:.1f}%, "
                      f"collision {100 * rec['collision_rate']:.1f}% of {rec['episodes']} ({where}"
                      + (f", {rec['wall_s']} s" if cell.source in ("run", "ledger+") else "") + ")" + mark, flush=True)
                cells[(driver.label, sc.name)] = rec
    except KeyboardInterrupt:
        print("\nlc-bench: interrupted; finished cells are kept (a rerun resumes)", file=sys.stderr)
        return 130
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    summary = suite_summary(cells, [(d.label, d.group) for d in drivers], scenarios,
                            suite=args.suite or DEFAULT_SUITE, split=split,
                            pair_keys={d.label: d.about.get("training_seed") for d in drivers})  # fmt: skip
    summary["command"] = command
    if args.final:
        summary["ledger"] = {"path": str(ledger), "committed": is_committed(ledger)}
    try:
        check_out(out, args.overwrite)  # again: the cells took a while
        figures = ""
        if not args.no_figures:
            from lcmodels.bench.figures import figures_markdown, write_figures

            write_figures(summary, out, root=out)
            figures = figures_markdown()
        markdown = suite_markdown(summary, command, figures=figures)
        write_file(out / "BENCH.md", markdown, root=out)
        write_file(out / "bench.json", json.dumps(summary, indent=1, sort_keys=True) + "\n", root=out)
    except (ValueError, OSError) as exc:
        return error(str(exc))
    print()
    print(markdown)
    names = {"run": "run", "cache": "cached", "ledger": "from the ledger", "ledger+": "appended to the ledger"}
    print(f"lc-bench: {len(todo)} cells: " + ", ".join(f"{n} {names[k]}" for k, n in sources.items()))
    print(f"lc-bench: wrote {out / 'BENCH.md'} and {out / 'bench.json'}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
