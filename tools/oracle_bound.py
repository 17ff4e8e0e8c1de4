#!/usr/bin/env python
"""What the scenario allows: the share of held-out episodes an omniscient driver can win.

For each of ``lc-eval``'s held-out evaluation episodes (the same seeds, so the figure sits beside the
policies' success rates), :func:`lcsim.oracle.search_episode` searches the decision tree with the exact
future for a sequence that reaches the end of the route without a collision. Every sequence it finds is
replayed from a fresh reset and must end in success, so "winnable" is proven; "not winnable" means every
branch of the merged tree crashed (see ``lcsim.oracle``: rerun those with a larger ``--memory`` to
merge less). No policy can beat the winnable share; it is the ceiling for the success targets.

    python tools/oracle_bound.py                       # 200 episodes of evaluation seed 0, 2 workers
    python tools/oracle_bound.py --episodes 50 --json  # one JSON object
    python tools/oracle_bound.py --only 79 191 --memory 40   # re-check two episodes, merging less
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

from lcdata.record import episode_seed
from lcmodels.policy.evaluate import eval_user_seeds, wilson_interval
from lcsim.planning import replay, search_episode
from lcsim.registry import TASK_SCENARIOS, scenario


def _one(job: tuple[str, int, int, int, int]) -> dict:
    scenario_name, index, user_seed, memory, max_nodes = job
    config = scenario(scenario_name)
    seed = episode_seed(user_seed)
    t0 = time.process_time()
    r = search_episode(config, seed, memory_decisions=memory, max_nodes=max_nodes)
    replayed = replay(config, seed, r.actions) if r.winnable else None
    return {"episode": index, "user_seed": user_seed, "seed": seed, "winnable": r.winnable,
            "replay_outcome": replayed, "nodes": r.nodes, "deepest_decision": r.deepest,
            "pruned": r.outcomes, "actions": r.actions if r.winnable else None,
            "cpu_s": round(time.process_time() - t0, 3)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))  # fmt: skip
    ap.add_argument("--episodes", type=int, default=200, help="held-out episodes, as lc-eval --episodes (200)")
    ap.add_argument("--seed", type=int, default=0, help="evaluation seed, as lc-eval --seed (0)")
    ap.add_argument("--scenario", default="paper", choices=TASK_SCENARIOS, help="scenario (paper)")
    ap.add_argument("--memory", type=int, default=8,
                    help="decisions after which the ego's last lane change is forgotten when merging states (8)")
    ap.add_argument("--max-nodes", type=int, default=200_000, help="give up on an episode after this many decisions")
    ap.add_argument("--only", type=int, nargs="+", metavar="I", help="only these episode indices (0-based)")
    ap.add_argument("--workers", type=int, default=2, help="processes (2)")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    ap.add_argument("--out", help="also write the per-episode results (winning decisions included) to this JSON file")
    args = ap.parse_args(argv)

    def fail(msg: str) -> int:
        print(f"oracle_bound: error: {msg}", file=sys.stderr)
        return 2

    if args.episodes < 1 or args.workers < 1 or args.memory < 1 or args.max_nodes < 1:
        return fail("--episodes, --workers, --memory and --max-nodes must be >= 1")
    try:
        users = eval_user_seeds(args.episodes, args.seed)
    except ValueError as exc:
        return fail(str(exc))
    picked = args.only if args.only is not None else list(range(args.episodes))
    if any(not 0 <= i < args.episodes for i in picked):
        return fail(f"--only indices must be in [0, {args.episodes})")
    if args.out and os.path.exists(args.out):  # checked now, not after the search
        return fail(f"--out {args.out} already exists; choose another file")
    jobs = [(args.scenario, i, users[i], args.memory, args.max_nodes) for i in picked]
    t0 = time.perf_counter()
    rows = []
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.workers, mp_context=ctx) as pool:
        for row in pool.map(_one, jobs):
            rows.append(row)
            if not args.json:
                print(f"\repisodes: {len(rows)}/{len(jobs)}", end="", file=sys.stderr, flush=True)
    if not args.json:
        print(file=sys.stderr)
    wall = time.perf_counter() - t0
    n = len(rows)
    won = sum(r["winnable"] is True for r in rows)
    replay_ok = sum(r["replay_outcome"] == "success" for r in rows)
    lost = [r["episode"] for r in rows if r["winnable"] is False]
    undecided = [r["episode"] for r in rows if r["winnable"] is None]
    lo, hi = wilson_interval(won, n)
    summary = {
        "scenario": args.scenario, "eval_seed": args.seed, "episodes": n, "memory_decisions": args.memory,
        "winnable": won, "winnable_rate": won / n, "winnable_rate_ci95": [lo, hi],
        "replayed_success": replay_ok, "not_winnable_episodes": lost, "undecided_episodes": undecided,
        "nodes_total": sum(r["nodes"] for r in rows), "cpu_s_total": round(sum(r["cpu_s"] for r in rows), 1),
        "wall_s": round(wall, 1), "workers": args.workers,
    }  # fmt: skip
    if args.out:
        with open(args.out, "x") as f:  # one line per episode
            f.write('{"summary": ' + json.dumps(summary, indent=1) + ',\n "episodes": [\n  ')
            f.write(",\n  ".join(json.dumps(r) for r in rows) + "\n ]\n}\n")
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"winnable: {won}/{n} = {100 * won / n:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}] "
              f"(every winning sequence replayed to success: {replay_ok}/{won})")
        print(f"no winning sequence: episodes {lost or 'none'}; undecided (--max-nodes): {undecided or 'none'}")
        print(f"search: {summary['nodes_total']} decisions simulated, {summary['cpu_s_total']} s CPU, "
              f"{summary['wall_s']} s wall on {args.workers} workers")
    return 0 if replay_ok == won else 1


if __name__ == "__main__":
    sys.exit(main())
