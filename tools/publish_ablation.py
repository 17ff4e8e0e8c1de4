"""Publish the controlled input ablation measured by ``lc-experiment --preset ablation --out RUN``.

    python tools/publish_ablation.py RUN [--dest docs/results/ablation]

Writes, from RUN's ``suite`` stages alone (every figure derived from the runs' outcome letters): per training
block (``paper``: trained on the paper's road; ``roads``: on every road of the suite) lc-bench's table with its
figures (``BLOCK/BENCH.md``, PNG and SVG), ``ablation.json`` (the verdict rows and the summaries) and
``VERDICT.md`` (one table per block: the hybrid input against each other input, the paper's Table IV beside).
Runs not measured yet are listed as such.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lcmodels.ablation import write_ablation

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="publish_ablation", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="the ablation's experiment directory (lc-experiment --preset ablation)")
    p.add_argument("--dest", type=Path, default=ROOT / "docs" / "results" / "ablation")
    args = p.parse_args(argv)
    if not (args.run / "experiment.json").is_file():
        p.error(f"{args.run} is no experiment directory (no experiment.json)")
    args.dest.mkdir(parents=True, exist_ok=True)
    written = write_ablation(args.run, args.dest)
    if not written:
        p.error(f"{args.run}: no block has its ceiling, floor and a hybrid run measured yet")
    for path in written:
        print(path.relative_to(args.dest))
    return 0


if __name__ == "__main__":
    sys.exit(main())
