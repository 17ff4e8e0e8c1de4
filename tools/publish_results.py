#!/usr/bin/env python
"""Copy an lc-experiment directory's report and small result files to a folder meant for git.

    python tools/publish_results.py runs/paper docs/results/paper [--overwrite]

Copies ``REPORT.md``, the figures, ``experiment.json``, ``invocations.json``, the complete stage records (``stages/*.json``)
and, per stage, ``metrics.json`` / ``run.json`` / ``progress.csv`` / ``warm_start.json``: every file
the report's *Files* table names, and nothing large (no checkpoints, TensorBoard logs or MCAP episodes).
Refuses when the run has no report or has unfinished stages, and when the destination exists (unless
``--overwrite``, which replaces it).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from lcmodels.experiment import INVOCATIONS, MARKER, REPORT_NAME, RULE_KEY, STAGES_DIR

TOP = (REPORT_NAME, MARKER)
OPTIONAL_TOP = (INVOCATIONS,)  # runs of lc-toolkit versions before it have none
PER_STAGE = ("metrics.json", "run.json", "progress.csv", "warm_start.json")


def published_files(run: Path) -> list[Path]:
    """Paths (relative to ``run``) of the files to publish."""
    files = [Path(n) for n in TOP] + [Path(n) for n in OPTIONAL_TOP if (run / n).is_file()] + sorted(p.relative_to(run) for p in run.glob("*.png"))
    files += sorted(p.relative_to(run) for p in (run / STAGES_DIR).glob("*.json") if not p.name.endswith(".pending.json"))
    stage_dirs = [run / "predictor", run / RULE_KEY, *sorted(run.glob("policies/*/seed*"))]
    for d in stage_dirs:
        files += [(d / n).relative_to(run) for n in PER_STAGE if (d / n).is_file()]
    return files


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="an lc-experiment --out directory")
    ap.add_argument("dest", type=Path, help="destination folder (created)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing destination")
    args = ap.parse_args(argv)
    run, dest = args.run, args.dest
    if not all((run / n).is_file() for n in TOP):
        print(f"error: {run} is not an lc-experiment directory with a {REPORT_NAME}", file=sys.stderr)
        return 2
    pending = sorted(p.name for p in (run / STAGES_DIR).glob("*.pending.json"))
    if pending:
        print(f"error: {run} has {len(pending)} unfinished stage(s) ({pending[0]}); finish the run first",
              file=sys.stderr)  # fmt: skip
        return 2
    if dest.exists():
        if not args.overwrite:
            print(f"error: {dest} exists; pass --overwrite to replace it", file=sys.stderr)
            return 2
        shutil.rmtree(dest)
    files = published_files(run)
    for rel in files:
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(run / rel, dest / rel)
    size = sum((dest / rel).stat().st_size for rel in files)
    print(f"copied {len(files)} files ({size / 1e6:.1f} MB) from {run} to {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
