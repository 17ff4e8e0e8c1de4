"""Convert a legacy policy (a stable-baselines3 ``.zip`` written by lc-toolkit before policies became
data) into the ``.safetensors`` policy format, once, for a file you trust.

Loading a ``.zip`` unpickles objects stored in it, which runs whatever code its author put there; the
converted file holds only tensors and a JSON card, and every command loads it without ``--trust-pickle``.
The converted policy acts exactly as the original (same tensors).

    python tools/convert_policy.py runs/old/policy.zip runs/old/policy.safetensors --trust-pickle
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lcmodels.policy.checkpoint import card_path, convert_legacy_policy


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="convert_policy.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path, help="the legacy policy .zip")
    p.add_argument("dest", type=Path, help="the .safetensors policy to write")
    p.add_argument("--predictor", type=Path, default=None,
                   help="the predictor the policy was trained with, when it is no longer where the file says")
    p.add_argument("--trust-pickle", action="store_true",
                   help="required: say that you trust the file's source (loading it runs code stored in it)")
    p.add_argument("--overwrite", action="store_true", help="replace DEST when it exists")
    args = p.parse_args(argv)
    try:
        dest = convert_legacy_policy(args.src, args.dest, predictor=args.predictor, trust_pickle=args.trust_pickle,
                                     overwrite=args.overwrite)
    except (ValueError, OSError) as exc:
        print(f"convert_policy.py: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    print(f"wrote {dest} (and its card {card_path(dest)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
