"""The cost per decision of the safety layer and of its multiple-base-policy variant on the same states.

Drives ``--envs`` validation episodes of a suite road with the safety layer for ``--decisions`` decisions and, before
each, lets the layer and the variant decide on copies of the same state; prints (and with ``--json-out`` writes) the
CPU milliseconds of each per decision and per decision with a choice (one torch thread: one core's time)::

    python -m experiments.multi_rollout.cost safety-layer:zoo:roads-ppo --set safety.horizon_decisions=32 \\
        --set safety.samples=3 --bases follow,rule,forced --progress-gain-m 5
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from lccli.common import add_safety_layer_arguments, safety_layer_from_args

from .multi_rollout import MultiRolloutLayer, TimedLayer, _bases, base_drivers


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="multi_rollout.cost", description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("policy", help="a driver behind the safety layer, as lc-bench names it (safety-layer:zoo:NAME)")
    add_safety_layer_arguments(p)
    p.add_argument("--bases", type=_bases, default=("follow", "rule", "forced"), metavar="NAMES",
                   help="the variant's base policies (default follow,rule,forced)")
    p.add_argument("--progress-gain-m", type=float, default=None, metavar="M", help="the variant's tie-break")
    p.add_argument("--scenario", default="paper", help="a road of the highway suite (default paper)")
    p.add_argument("--envs", type=int, default=20, help="validation episodes of evaluation seed 0 (default 20)")
    p.add_argument("--decisions", type=int, default=40, help="decisions timed (default 40)")
    p.add_argument("--json-out", type=Path, default=None, help="write the figures as JSON here (not over a file)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)

    def error(msg: str) -> int:
        print(f"multi_rollout.cost: error: {' '.join(str(msg).split())}", file=sys.stderr)
        return 2

    import torch

    from lcmodels.bench.run import resolve_driver
    from lcmodels.policy.evaluate import driver_for, eval_user_seeds
    from lcsim.core import RUNNING, LaneChangeCore
    from lcsim.suite import SUITE_SCENARIOS

    torch.set_num_threads(1)
    if args.scenario not in SUITE_SCENARIOS:
        return error(f"unknown suite scenario {args.scenario!r}; choose {', '.join(SUITE_SCENARIOS)}")
    if not 1 <= args.envs <= 1000 or not 1 <= args.decisions <= 10_000:
        return error("--envs must be in 1..1000 and --decisions in 1..10000")
    if args.json_out is not None and args.json_out.exists():
        return error(f"--json-out {args.json_out} exists: name another file")
    try:
        bench = resolve_driver(args.policy, safety=safety_layer_from_args(args.policy, args))
        if bench.spec.layer is None:
            return error(f"{args.policy} drives behind no safety layer: name it safety-layer:{args.policy}")
        config = SUITE_SCENARIOS[args.scenario].make()
        plain, own = driver_for(bench.spec, predictor=bench.predictor, scenario=config)
        layers = {"layer": TimedLayer(plain.config, plain.rule, plain.proposer),
                  "multi-rollout": MultiRolloutLayer(plain.config, plain.rule, plain.proposer,
                                                     bases=base_drivers(args.bases),
                                                     progress_gain_m=args.progress_gain_m)}  # fmt: skip
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    core = LaneChangeCore(own or config, args.envs)
    core.reset(np.arange(args.envs), eval_user_seeds(args.envs, 0))
    everyone = np.arange(args.envs)
    for i in range(args.decisions + 1):  # the first decision compiles what the planners run: not timed
        if not (core.outcome == RUNNING).any():
            break
        obs, mask = core.observe(), core.action_mask()
        decided = {name: layer(obs, mask, core.replicate(everyone)) for name, layer in layers.items()}
        if i == 0:
            for layer in layers.values():
                layer.cpu_s, layer.decisions, layer.choices = 0.0, 0, 0
        core.step(decided["layer"])
    out = {"driver": args.policy, "scenario": args.scenario, "envs": args.envs, "decisions": args.decisions,
           "safety_layer": bench.spec.layer.to_dict(), "bases": list(args.bases), "progress_gain_m": args.progress_gain_m,
           **{name: layer.cost() for name, layer in layers.items()}}  # fmt: skip
    for name in layers:
        print(f"{name}: {out[name]['ms_per_decision']:.1f} ms of CPU per decision, {out[name]['ms_per_choice']:.1f} "
              f"per decision with a choice ({out[name]['decisions']} decisions)")
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
