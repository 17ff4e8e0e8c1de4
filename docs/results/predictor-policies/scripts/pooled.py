"""Pool the paired A/B tests of the bench files beside this script's folder: McNemar's exact test on every episode pair.

    python docs/results/predictor-policies/scripts/pooled.py
"""

import json
import pathlib
from math import comb

here = pathlib.Path(__file__).resolve().parent.parent
won_old = won_new = 0
for name in ("bench-seed0", "bench-seed1", "bench-train1-seed0", "bench-train1-seed1"):
    data = json.loads((here / f"{name}.json").read_text())
    for row in data["drivers"]:
        test = row.get("mcnemar_vs_first")
        if test and "ab-new" in row["driver"]:
            print(f"{name}: in-domain alone {test['only_a']}, transferring alone {test['only_b']}, p = {test['p_value']:.2g}")
            won_old, won_new = won_old + test["only_a"], won_new + test["only_b"]
n, k = won_old + won_new, min(won_old, won_new)
p = min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2**n)
print(f"pooled: in-domain alone {won_old}, transferring alone {won_new}, McNemar p = {p:.2g}")
