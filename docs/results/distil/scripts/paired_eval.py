"""Evaluate drivers on the same validation episodes and compare each with the first, episode by episode.

    python docs/results/distil/scripts/paired_eval.py zoo:pure-ppo runs/distil/round4/policy.safetensors \
        --episodes 1000 --seed 9 --json-out docs/results/distil/paired-seed9.json
    python docs/results/distil/scripts/paired_eval.py zoo:pure-ppo safety-layer:zoo:pure-ppo \
        --set safety.horizon_decisions=32 --set safety.samples=3 --episodes 200 --seed 9

Each driver runs lc-eval's episodes of evaluation seed SEED (validation episodes: never the sealed test set);
``--set safety.KEY=VALUE`` applies to every driver behind the safety layer. Prints each driver's success with
its Wilson 95% interval over episodes and McNemar's exact test against the first driver; ``--json-out`` keeps
the summaries, the per-episode outcomes and the tests.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lccli.common import fail, non_negative_int, positive_int, zoo_spec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("drivers", nargs="+", type=zoo_spec, help="driver specs as lc-eval takes them (zoo:NAME, a policy file, safety-layer:...); the first is the reference")
    ap.add_argument("--episodes", type=positive_int, default=200, help="validation episodes (200)")
    ap.add_argument("--seed", type=non_negative_int, default=9, help="evaluation seed (9)")
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="safety.KEY=VALUE",
                    help="a setting of the safety layer of every driver behind it (repeatable)")
    ap.add_argument("--json-out", type=Path, default=None, help="write the results here (refused if it exists)")
    args = ap.parse_args(argv)
    if args.json_out is not None and args.json_out.exists():
        return fail("paired_eval", f"{args.json_out} exists; choose another --json-out")
    import torch

    from lcmodels.policy.driverspec import split_safety_layer
    from lcmodels.policy.evaluate import driver_for, evaluate
    from lcmodels.stats import mcnemar, wilson_interval
    from lcsim.config import paper_scenario

    torch.set_num_threads(1)
    rows = []
    try:
        for spec in args.drivers:
            _, layer = split_safety_layer(spec)
            safety = layer.with_named_settings(args.settings) if layer is not None and args.settings else None
            driver, config = driver_for(spec, safety=safety)
            t0 = time.perf_counter()
            summary, stats = evaluate(driver, config or paper_scenario(render_image=False), episodes=args.episodes, seed=args.seed,
                                      batch=20, progress=lambda d, n, s=spec: print(f"{s}: {d}/{n}", file=sys.stderr))
            won = [e.outcome == "success" for e in stats]
            rows.append({"driver": spec, "safety_layer": None if layer is None else (safety or layer).to_dict(),
                         "wall_s": time.perf_counter() - t0, "won": won, "summary": summary})
    except (ValueError, OSError) as exc:
        return fail("paired_eval", str(exc).splitlines()[0])
    first = rows[0]
    print(f"evaluation seed {args.seed}, {args.episodes} validation episodes")
    for row in rows:
        k, n = sum(row["won"]), len(row["won"])
        lo, hi = wilson_interval(k, n)
        line = f"{row['driver']}: success {100 * k / n:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}] ({row['wall_s']:.0f} s)"
        if row is not first:
            test = mcnemar(row["won"], first["won"])
            row["mcnemar_vs_first"] = test.as_dict()
            line += f"; against {first['driver']}: {test.only_a} won only here, {test.only_b} only there, {test.p_text}"
        row["success_wilson95"] = [lo, hi]
        print(line)
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps({"episodes": args.episodes, "eval_seed": args.seed, "drivers": rows},
                                            indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
