"""Clone a policy again on the states a DAgger run labelled, with another correction weight.

    python docs/results/distil/scripts/reclone.py runs/distil runs/pure-start/policy.safetensors \
        --correction-weight 1 --epochs 10 --out runs/distil-reclone-cw1/policy.safetensors

Reads every ``round<r>/states.npz`` of the DAgger directory (the states its students reached, each expert label
and the student's own decision) and trains the starting policy on all of them at once, as DAgger's last round
does, with a state whose label differs from the student's decision weighted ``--correction-weight`` against 1.
The states stay those the run's students reached under its own weight: this isolates what the weight does to
cloning the same labels, not a DAgger run at that weight.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lccli.common import fail, positive_int


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("dagger_dir", type=Path, help="an lc-dagger --out directory")
    ap.add_argument("start", type=Path, help="the policy to train from (the DAgger run's starting policy)")
    ap.add_argument("--correction-weight", type=float, required=True, help="weight of a corrected state (against 1)")
    ap.add_argument("--epochs", type=positive_int, default=10, help="epochs over all states (10)")
    ap.add_argument("--seed", type=int, default=0, help="shuffling seed (0)")
    ap.add_argument("--no-balance", action="store_true",
                    help="every decision alike: no weighting of rare actions by the inverse square root of their "
                    "frequency (which cloning does by default)")
    ap.add_argument("--out", type=Path, required=True, help="the policy file to write (refused if it exists)")
    args = ap.parse_args(argv)
    if args.out.exists():
        return fail("reclone", f"{args.out} exists; choose another --out")
    if not args.correction_weight > 0:
        return fail("reclone", f"--correction-weight must be > 0, got {args.correction_weight}")
    import numpy as np
    import torch

    from lcmodels.policy.checkpoint import load_policy, save_policy
    from lcmodels.policy.obs import mode_keys
    from lcmodels.policy.warmstart import Demonstrations, RowChunks, pretrain

    torch.set_num_threads(1)
    try:
        rounds = sorted(args.dagger_dir.glob("round*/states.npz"), key=lambda p: int(p.parent.name[5:]))
        if not rounds:
            raise FileNotFoundError(f"{args.dagger_dir} holds no round*/states.npz")
        loaded = load_policy(args.start)
        keys = mode_keys(loaded.obs_mode)
        obs: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        labels, own = [], []
        for path in rounds:
            with np.load(path) as states:
                for k in keys:
                    obs[k].append(states[k])
                labels.append(states["labels"])
                own.append(states["actions"])
    except (ValueError, OSError, KeyError) as exc:
        return fail("reclone", str(exc).splitlines()[0])
    y, a = np.concatenate(labels), np.concatenate(own)
    weights = np.where(y != a, args.correction_weight, 1.0)
    if args.no_balance:  # cancel pretrain's 1/sqrt(frequency) weight of each label's action (constant factors aside)
        weights *= np.sqrt(np.bincount(y, minlength=3)[y] / len(y))
    weights = weights.astype(np.float32)
    data = Demonstrations({k: RowChunks(v) for k, v in obs.items()}, y, np.zeros(len(y), dtype=np.float32), 0, weights)
    t0 = time.perf_counter()
    losses = pretrain(loaded.model, data, epochs=args.epochs, value_coef=0.0, seed=args.seed,
                      progress=lambda e, loss: print(f"epoch {e}/{args.epochs}: loss {loss:.4f}", flush=True))
    train_s = time.perf_counter() - t0
    meta = {k: v for k, v in loaded.meta.items() if k not in ("format", "version")}
    meta["reclone"] = {"from": str(args.start), "dagger": str(args.dagger_dir), "states": len(y),
                       "corrections": int((y != a).sum()), "correction_weight": args.correction_weight,
                       "balance_actions": not args.no_balance}
    save_policy(loaded.model, args.out, meta)
    record = {**meta["reclone"], "rounds": [str(p) for p in rounds], "epochs": args.epochs, "epoch_losses": losses,
              "train_s": train_s}
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    print(f"{len(y)} states ({record['corrections']} corrections) in {train_s:.0f} s -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
