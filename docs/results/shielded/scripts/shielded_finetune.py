#!/usr/bin/env python
"""Hybrid-PPO fine-tuned behind its safety layer: PPO steps in which the perceived lookahead layer executes the
decision and a proposal it overrides costs the policy a penalty (post-posed shielding with punishment).

The lab script of the shielded study's first runs (docs/results/shielded/NOTE.md); the recipe stage that does
the same is lcmodels.policy.shield (recipe hybrid-ppo-shielded):

    python docs/results/shielded/scripts/shielded_finetune.py --timesteps 150000 --penalty 100 --out runs/shielded
    lc-eval lookahead-blind:runs/shielded/policy.safetensors --lookahead-follow zoo:pure-ppo --lookahead-perceived \\
        --lookahead-horizon 32 --lookahead-samples 3 --episodes 200 --seed 0 --no-record
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

import lcmodels.policy.train as train_module
from lcmodels.policy.evaluate import driver_for
from lcmodels.policy.train import PolicyConfig, train_policy
from lcsim.planning import LookaheadDriver, SafetyLayerConfig
from lcsim.sb3 import LaneChangeSB3VecEnv

ROOT = Path(__file__).resolve().parents[4]


class ShieldedVecEnv(LaneChangeSB3VecEnv):
    """The simulator's SB3 view with the safety layer between the policy and the road."""

    layer: LookaheadDriver
    penalty: float = 0.0
    counts: ClassVar[dict[str, int]] = {"choices": 0, "overrides": 0}

    def step_wait(self):  # type: ignore[override]
        proposed = np.asarray(self._actions, dtype=np.int64).reshape(-1)
        core = self.venv.core
        self.layer.proposer = lambda obs, mask, c: proposed
        before = (self.layer.choices, self.layer.overrides)
        executed = self.layer({}, core.action_mask(), core)
        type(self).counts["choices"] += self.layer.choices - before[0]
        type(self).counts["overrides"] += self.layer.overrides - before[1]
        self._actions = executed
        obs, reward, dones, infos = super().step_wait()
        return obs, reward - self.penalty * (executed != proposed), dones, infos


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", default=str(ROOT / "zoo/hybrid-ppo/policy.safetensors"))
    ap.add_argument("--follow", default=str(ROOT / "zoo/pure-ppo/policy.safetensors"))
    ap.add_argument("--predictor", default=str(ROOT / "zoo/predictor/predictor.pt"))
    ap.add_argument("--timesteps", type=int, default=150_000)
    ap.add_argument("--penalty", type=float, default=100.0, help="raw reward per overridden proposal (collision: 500)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(1)
    card = json.loads(Path(args.policy).with_name("policy.card.json").read_text())
    cfg = PolicyConfig.from_dict({**card["train_config"], "init_policy": args.policy, "timesteps": args.timesteps,
                                  "checkpoint_every": 10_000})
    follower, _ = driver_for(args.follow)
    ShieldedVecEnv.layer = LookaheadDriver(SafetyLayerConfig(horizon_decisions=32, samples=3),
                                           rule=follower)
    ShieldedVecEnv.penalty = args.penalty
    train_module.LaneChangeSB3VecEnv = ShieldedVecEnv  # the training environments only
    t0 = time.perf_counter()

    def show(row: dict) -> None:
        c = ShieldedVecEnv.counts
        print(f"step {int(row['timesteps'])}: success {row['success_rate']:.2f} overrides {c['overrides']}/"
              f"{c['choices']} ({time.perf_counter() - t0:.0f} s)", flush=True)

    train_policy(cfg, args.out, predictor=args.predictor, progress=show)
    (args.out / "shield.json").write_text(json.dumps({**ShieldedVecEnv.counts, "penalty": args.penalty,
                                                      "timesteps": args.timesteps,
                                                      "wall_s": round(time.perf_counter() - t0, 1)}) + "\n")


if __name__ == "__main__":
    main()
