"""Command-line pieces of lcsim: ``make demo`` and argument types shared by the project's commands.

``python -m lcsim.cli`` is ``make demo``: the main job, end to end, on the built-in simulator.

Today it drives one episode of the paper's scenario with the rule-based lane-change driver, records it
to MCAP, and prints the outcome and the file's path. (The full pipeline, ``lc-experiment --preset
quick``, takes over this target once it exists.)
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from lcsim.config import ScenarioConfig


def int_at_least(minimum: int):
    """An argparse ``type`` accepting integers >= ``minimum`` with a one-line message otherwise."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    parse.__name__ = f"int>={minimum}"
    return parse


def add_lookahead_arguments(p: argparse.ArgumentParser) -> None:
    """``--lookahead-horizon``, ``--lookahead-samples`` and ``--lookahead-perceived``: how the lookahead
    planners imagine (``lc-eval``, ``lc-record`` and the tools that run the same drivers)."""
    p.add_argument("--lookahead-horizon", type=int_at_least(1), default=None,
                   help="lookahead drivers: decisions imagined after each candidate one (default 16, i.e. 8 s)")
    p.add_argument("--lookahead-samples", type=int_at_least(1), default=None,
                   help="lookahead-blind drivers: redrawn futures imagined per candidate decision (default 1)")
    p.add_argument("--lookahead-perceived", action="store_true",
                   help="lookahead-blind drivers: imagine each future from what the ego's sensors show (no traffic "
                   "beyond the scenario's sensing range, each vehicle's unseen desired speed read from its motion): "
                   "the planner needs no privileged state, only the traffic's rules")


def lookahead_options(args: argparse.Namespace) -> dict[str, int]:
    """The ``--lookahead-*`` options given (``LookaheadConfig`` fields, for ``driver_for``)."""
    given = {"horizon_decisions": args.lookahead_horizon, "samples": args.lookahead_samples,
             "perceived": args.lookahead_perceived or None}
    return {k: v for k, v in given.items() if v is not None}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lcsim.cli", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/demo"), help="output directory (default runs/demo)")
    parser.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    from lcdata.record import record_episode

    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"demo: cannot create {args.out}: {exc.strerror}", file=sys.stderr)
        return 2
    config = ScenarioConfig()
    path = args.out / f"demo_rule_s{args.seed:07d}.mcap"
    t0 = time.perf_counter()
    res = record_episode(config, args.seed, "rule", path, scenario="lane-change", overwrite=True)
    wall = time.perf_counter() - t0
    print(f"rule-based driver, paper scenario, seed {args.seed}: {res.outcome} after "
          f"{res.steps * config.dt_s:.1f} s simulated ({res.decisions} decisions), return {res.total_reward:.1f}")
    print(f"recorded {res.path} ({res.messages} messages, {res.bytes / 1e6:.1f} MB) in {wall:.1f} s")
    print(f"view it with: lc-view {res.path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
