#!/usr/bin/env python
"""Publish a recipe's trained policy from an lc-experiment directory into the zoo (zoo/NAME/), with its card.

    python tools/publish_zoo.py runs/paper hybrid-ppo pure-ppo [--seed 0] [--overwrite]

A recipe with a safety layer is published with the policy its layer followed (same run and seed) or refused:
its card's safety-layer figure holds for that pair only, and the zoo's layer follows the zoo's entry.
Each entry: policy.safetensors (weights and the policy's card), policy.card.json, zoo.json (recipe, commit,
training time, validation / test / safety-layer figures, the experiment's command, and the outcomes of a few
test episodes re-run now); the predictor the prediction and hybrid policies read goes to zoo/predictor/. A packaged
recipe published into this checkout's zoo also gets lcmodels/recipes/<name>.reached.json: what it reached, with
which command and commit (a zoo elsewhere, --zoo DIR, leaves those records alone).
--reached-only writes that record alone, for a recipe whose policy the zoo does not ship (the paper-faithful ones):

    python tools/publish_zoo.py runs/paper-best paper-hybrid-ppo paper-a2c --reached-only
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("run", type=Path, help="lc-experiment directory")
    ap.add_argument("recipes", nargs="+", help="recipe names whose final policies to publish")
    ap.add_argument("--seed", type=int, default=0, help="training seed of the runs to publish (default 0)")
    ap.add_argument("--zoo", type=Path, default=None, help="zoo directory (default: zoo/ of this checkout)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace zoo entries that exist (publishing into this checkout's zoo always rewrites the recipe's "
                         ".reached.json, a record in git)")
    ap.add_argument("--commit", default="",
                    help="the commit the experiment ran at, where its invocations.json does not record it (older "
                         "directories; default: this checkout's HEAD)")
    ap.add_argument("--reached-only", action="store_true",
                    help="write only lcmodels/recipes/<name>.reached.json, no zoo entry (packaged recipes)")
    args = ap.parse_args(argv)
    if args.reached_only and (args.zoo is not None or args.overwrite):
        ap.error("--zoo and --overwrite apply to zoo entries; --reached-only writes none")
    from lcmodels.bench.ledger import git_commit
    from lcmodels.experiment.entries import experiment_card, publish_from_experiment
    from lcmodels.experiment.recipe import RECIPES_DIR, recipe_path
    from lcmodels.fileio import write_json
    from lcmodels.zoo import CHECKOUT_ZOO, weights_sha256, zoo_dir

    commit = args.commit or git_commit()[0] or ""
    # the records describe what this checkout's own zoo/ ships, whatever LC_ZOO says
    own_zoo = (args.zoo if args.zoo is not None else zoo_dir()).resolve() == CHECKOUT_ZOO
    if not args.reached_only:  # a safety layer's figure holds only for the follower it was measured with
        try:
            for name in args.recipes:
                follow = (experiment_card(args.run, name, seed=args.seed)[0].get("safety_layer") or {}).get("follow")
                if not follow or follow["recipe"] in args.recipes:
                    continue
                root = args.zoo if args.zoo is not None else zoo_dir()
                shipped = root / follow["recipe"] / "policy.safetensors"
                if not shipped.is_file() or weights_sha256(shipped) != follow["weights_sha256"]:
                    raise ValueError(f"{name}'s safety layer was measured following {follow['recipe']} training seed "
                                     f"{args.seed}, which the zoo does not hold: publish both, "
                                     f"{name} {follow['recipe']} --seed {args.seed}")
        except ValueError as exc:
            print(f"publish_zoo: error: {str(exc).splitlines()[0]}", file=sys.stderr)
            return 2
    for name in args.recipes:
        try:
            reached = recipe_path(name).with_suffix(".reached.json")
            packaged = reached.parent == RECIPES_DIR
            if args.reached_only and not packaged:
                raise ValueError(f"{name} is not a packaged recipe: --reached-only writes lcmodels/recipes/ records")
            if args.reached_only:
                card = experiment_card(args.run, name, seed=args.seed, commit=commit)[0]
            else:
                entry = publish_from_experiment(args.run, name, seed=args.seed, root=args.zoo, commit=commit,
                                                overwrite=args.overwrite)  # fmt: skip
                card = entry.card
        except ValueError as exc:
            print(f"publish_zoo: error: {str(exc).splitlines()[0]}", file=sys.stderr)
            return 2
        t = card["heldout"]
        if packaged and own_zoo:  # a packaged recipe records what this checkout ships of it, next to it
            keep = ("recipe_version", "preset", "experiment_command", "commit", "training_seed", "training_wall_s",
                    "heldout", "validation", "safety_layer")
            write_json(reached, {"recipe": name, "published": time.strftime("%Y-%m-%d"),
                                 **{k: card.get(k) for k in keep}})  # fmt: skip
        where = reached if args.reached_only else f"zoo:{entry.name}: {entry.policy}"
        print(f"{where} (held-out success {100 * t['success_rate']:.1f}% of {t['episodes']}; sealed test: lc-bench --final)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
