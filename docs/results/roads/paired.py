"""Two methods paired seed with seed on every validation episode of an lc-bench output folder's cached cells.

    python docs/results/roads/paired.py runs/roads-bench A_SEED0,A_SEED1 B_SEED0,B_SEED1

Each argument after the folder lists one method's policies (as lc-bench was given them) in training-seed order;
the i-th policy of A is paired with the i-th of B on the same episodes of every scenario both were run on.
Prints the episodes won by A alone and by B alone, and McNemar's exact test (lcmodels.stats.mcnemar).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from lcmodels.stats import mcnemar


def main() -> int:
    folder, a, b = Path(sys.argv[1]), sys.argv[2].split(","), sys.argv[3].split(",")
    cells: dict[tuple[str, str, str], dict] = {}
    for f in sorted((folder / "cells").glob("*.json")):
        c = json.loads(f.read_text())
        cells[(c["label"], c["scenario"], c["split"])] = c
    won_a: list[bool] = []
    won_b: list[bool] = []
    for pa, pb in zip(a, b, strict=True):
        for (label, scenario, split), ca in sorted(cells.items()):
            cb = cells.get((pb, scenario, split))
            if label != pa or cb is None:
                continue
            assert ca["user_seeds"] == cb["user_seeds"], "not the same episodes"
            won_a += [o == "s" for o in ca["outcomes"]]
            won_b += [o == "s" for o in cb["outcomes"]]
    t = mcnemar(won_a, won_b)
    print(f"{len(won_a)} pairs: {t.only_a} won by A alone, {t.only_b} by B alone; McNemar p = {t.p_value:.2g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
