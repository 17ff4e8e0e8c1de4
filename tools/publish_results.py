#!/usr/bin/env python
"""Copy an lc-experiment directory's report and small result files to a folder meant for git
(:func:`lcmodels.publish.publish`).

    python tools/publish_results.py runs/paper docs/results/paper [--overwrite] [--weights]

With --weights the folder also holds each stage's final weights and resumes as an experiment directory:
`cp -r docs/results/paper runs/paper` and the same lc-experiment command goes on where the run stopped
(the recordings are re-made, the same bytes; finished stages are skipped).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lcmodels.publish import publish


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="an lc-experiment --out directory")
    ap.add_argument("dest", type=Path, help="destination folder (created)")
    ap.add_argument("--overwrite", action="store_true", help="replace the published files in an existing destination")
    ap.add_argument("--allow-pending", action="store_true",
                    help="publish a run stopped on purpose with unfinished stages (their finished parts are copied)")
    ap.add_argument("--weights", action="store_true",
                    help="also copy each stage's policy.safetensors and the predictor.pt, so the folder resumes")
    args = ap.parse_args(argv)
    try:
        files = publish(args.run, args.dest, overwrite=args.overwrite, allow_pending=args.allow_pending,
                        weights=args.weights)
    except (ValueError, OSError) as exc:
        print(f"publish_results.py: error: {exc}", file=sys.stderr)
        return 2
    size = sum((args.dest / rel).stat().st_size for rel in files)
    print(f"copied {len(files)} files ({size / 1e6:.1f} MB) from {args.run} to {args.dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
