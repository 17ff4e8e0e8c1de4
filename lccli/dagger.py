"""``lc-dagger``: DAgger with the oracle (or another expert) as the expert, from an lc-train-policy run.

Each round the policy drives new training episodes; the oracle (lcsim.planning.oracle, which sees the future)
labels every state the policy reaches with the decision of a winning plan from there; the policy is
cloned again on the demonstrations plus every labelled state, saved and evaluated on lc-eval's held-out
episodes. See lcmodels.policy.dagger.

    lc-record --driver oracle --episodes 200 --out runs/oracle-demos --workers 2
    lc-train-policy --obs hybrid --predictor P.pt --warm-start runs/oracle-demos --timesteps 0 --out runs/bc
    lc-dagger runs/bc --rounds 2 --episodes 100 --out runs/bc-dagger
    lc-dagger runs/bc --rounds 4 --episodes 100 --out runs/bc-dagger --resume   # rounds 3 and 4
    lc-dagger runs/ppo --expert safety-layer:runs/ppo/policy.safetensors --out runs/ppo-improved
    lc-dagger runs/ppo --expert safety-layer:runs/ppo/policy.safetensors --set safety.horizon_decisions=32 \\
        --out runs/ppo-improved-16s    # the safety layer imagining 16 s instead of 8 s
    lc-eval runs/bc-dagger/round4/policy.safetensors --episodes 200

Outputs in --out: round<r>/policy.safetensors (loadable by lc-eval and lc-record --driver policy:...),
round<r>/metrics.json (collection, training and held-out evaluation), round<r>/states.npz (the states
the policy drove into and their labels, for --resume), dagger.json (all rounds).
"""

from __future__ import annotations

import argparse

from lccli.common import (
    add_safety_layer_arguments,
    fail,
    non_negative_int,
    positive_int,
    safety_layer_from_args,
)


def dagger_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="lc-dagger", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))  # fmt: skip
    ap.add_argument("run", help="lc-train-policy run directory (warm-started: its demonstrations stay in the data)")
    ap.add_argument("--out", required=True, help="directory for the rounds: a new one, or one to --resume")
    ap.add_argument("--rounds", type=positive_int, default=2, help="DAgger rounds (2)")
    ap.add_argument("--episodes", type=positive_int, default=100, help="episodes the policy drives per round (100)")
    ap.add_argument("--epochs", type=positive_int, default=10, help="behaviour-cloning epochs per round over all states (10)")
    ap.add_argument("--seed", type=non_negative_int, default=100_000, help="first training user seed of the rounds (100000)")
    ap.add_argument("--workers", type=positive_int, default=2, help="processes that drive and label episodes (2)")
    ap.add_argument("--eval-episodes", type=non_negative_int, default=200, help="held-out episodes after each round, 0 to skip")
    ap.add_argument("--eval-seed", type=non_negative_int, default=0, help="evaluation seed, as lc-eval --seed (0)")
    ap.add_argument("--labels", choices=("plan", "winning"), default="plan",
                    help="plan: the oracle's decision at every state; winning: keep the policy's own decision "
                    "where the episode can still be won after it, correct only the losing ones (plan)")
    ap.add_argument("--expert", default="oracle",
                    help="who labels the states: oracle (sees the whole future; default), or a driver as lc-eval "
                    "names it, e.g. safety-layer:runs/pure/policy.safetensors (that policy behind the safety layer, "
                    "which does not foresee the traffic's random lane changes)")
    add_safety_layer_arguments(ap)  # how an expert behind the safety layer imagines
    ap.add_argument("--correction-weight", type=float, default=1.0,
                    help="weight in training of a state whose label differs from the policy's own decision, "
                    "against 1 for one where they agree (1)")
    ap.add_argument("--no-action-balance", dest="balance_actions", action="store_false",
                    help="train every state alike (times its correction weight); by default a state counts by the "
                    "inverse square root of its label's frequency, so that rare lane changes are heard, as in cloning")
    ap.add_argument("--threads", type=positive_int, default=1,
                    help="torch threads for training (default 1: more collapse when another process shares the cores)")
    ap.add_argument("--demonstrations", default=None, metavar="DIR",
                    help="where the run's demonstrations are now, when they have moved since it was trained "
                    "(default: the directory its run.json names)")
    ap.add_argument("--resume", action="store_true",
                    help="continue the rounds already in --out (same run, --episodes, --seed, --labels) up to "
                    "--rounds in all")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = dagger_parser().parse_args(argv)
    import torch

    from lcmodels.policy.dagger import dagger

    torch.set_num_threads(args.threads)
    try:
        layer = safety_layer_from_args(args.expert, args) if args.expert != "oracle" else None
        if args.expert == "oracle" and (args.follow or args.settings):
            raise ValueError("--follow and --set safety.KEY=VALUE apply to an expert behind the safety layer")
        dagger(args.run, args.out, rounds=args.rounds, episodes=args.episodes, epochs=args.epochs, seed=args.seed,
               workers=args.workers, eval_episodes=args.eval_episodes, eval_seed=args.eval_seed, labels=args.labels,
               expert=args.expert, correction_weight=args.correction_weight,
               balance_actions=args.balance_actions, resume=args.resume,
               expert_safety=layer, demonstrations=args.demonstrations,
               progress=lambda msg: print(msg, flush=True))  # fmt: skip
    except (ValueError, OSError) as exc:
        return fail("lc-dagger", str(exc).splitlines()[0])
    return 0
