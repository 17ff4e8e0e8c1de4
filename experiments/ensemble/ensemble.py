#!/usr/bin/env python
"""An ensemble of policies on lc-eval's held-out episodes: each decision the argmax of the members' mean
action probabilities.

An experiment, not a method of record (the ensemble study): do several PPO policies together, trained with other
seeds or taken at other points of one run (a snapshot ensemble, free in training time), make fewer of the
rare decisions that end in a collision than each alone? The members must share the observation mode, the
scenario and the predictor; PPO and A2C only (DQN has no action distribution). Prints one JSON object with
lc-eval's keys, the members and the wall time.

    python -m experiments.ensemble.ensemble runs/ppo-s0/policy.safetensors runs/ppo-s1/policy.safetensors --episodes 200 --seed 0
    python -m experiments.ensemble.ensemble runs/ppo/policy-600000.safetensors runs/ppo/policy-900000.safetensors runs/ppo/policy.safetensors \\
        --json-out ensemble.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from lccli.common import fail
from lcmodels.policy.checkpoint import LoadedPolicy, load_policy
from lcmodels.policy.evaluate import evaluate
from lcmodels.policy.obs import build_observation, scenario_for_mode
from lcsim.config import ScenarioConfig
from lcsim.core import LaneChangeCore


class EnsembleDriver:
    """``driver(obs, mask, core) -> actions``: the argmax of the members' mean action probabilities."""

    needs_observation = True

    def __init__(self, members: list[LoadedPolicy]) -> None:
        if not members:
            raise ValueError("an ensemble needs at least one policy")
        first = members[0]
        for m in members:
            if m.algo not in ("ppo", "a2c"):
                raise ValueError(f"ensemble members must be PPO or A2C policies (an action distribution), got {m.algo}")
            for what, a, b in (("observation mode", m.obs_mode, first.obs_mode),
                               ("scenario", m.scenario, first.scenario),
                               ("predictor", m.meta.get("predictor"), first.meta.get("predictor"))):  # fmt: skip
                if a != b:
                    raise ValueError(f"ensemble members differ in their {what}")
        self.members = members
        self.name = f"ensemble{len(members)}-{first.obs_mode}"
        self.last_prediction: np.ndarray | None = None

    @property
    def config(self) -> ScenarioConfig:
        return scenario_for_mode(self.members[0].scenario, self.members[0].obs_mode)

    def probabilities(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """``(E, A)`` the members' mean action probabilities (one observation for all: they share its mode and
        predictor)."""
        first = self.members[0]
        pobs = build_observation(obs, first.obs_mode, first.predictor)
        self.last_prediction = pobs.get("prediction")
        total = None
        for m in self.members:
            tensor, _ = m.model.policy.obs_to_tensor(pobs)
            with torch.no_grad():
                probs = m.model.policy.get_distribution(tensor).distribution.probs.cpu().numpy()
            total = probs if total is None else total + probs
        assert total is not None
        return total / len(self.members)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        return self.probabilities(obs).argmax(axis=1).astype(np.int64)


def load_ensemble(paths: list[Path], predictor: Path | None = None) -> EnsembleDriver:
    """The members loaded (each checked against its predictor) and checked against each other."""
    return EnsembleDriver([load_policy(p, predictor=predictor) for p in paths])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="eval_ensemble", description=__doc__.split("\n\n")[0],
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("policies", nargs="+", type=Path, help="policy checkpoints (policy.safetensors), one per member")
    ap.add_argument("--episodes", type=int, default=200, help="held-out episodes (default 200)")
    ap.add_argument("--seed", type=int, default=0, help="evaluation seed, as lc-eval --seed (default 0)")
    ap.add_argument("--batch", type=int, default=20, help="episodes simulated together (default 20)")
    ap.add_argument("--predictor", type=Path, default=None,
                    help="predictor checkpoint (default: the one the members were trained with)")
    ap.add_argument("--json-out", type=Path, default=None, help="also write the JSON object here")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = ap.parse_args(argv)
    if args.episodes < 1 or args.batch < 1 or args.seed < 0 or args.threads < 1:
        return fail(ap.prog, "--episodes, --batch and --threads must be >= 1 and --seed >= 0")
    torch.set_num_threads(args.threads)
    try:
        driver = load_ensemble(args.policies, args.predictor)
        t0 = time.perf_counter()
        summary, _ = evaluate(driver, driver.config, episodes=args.episodes, seed=args.seed, batch=args.batch)
    except (ValueError, OSError) as exc:
        return fail(ap.prog, str(exc).splitlines()[0])
    summary.update(members=[str(p) for p in args.policies], seed=args.seed, wall_s=round(time.perf_counter() - t0, 1))
    text = json.dumps(summary, indent=1)
    print(text)
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
