#!/usr/bin/env python
"""A gap shield in front of a driver: lc-eval's held-out episodes with unsafe lane changes vetoed.

An experiment, not a method of record: before each decision the shield looks at the exact gaps of the
lane the driver wants to change into (``LaneChangeCore.lane_gaps``, privileged perception) and keeps
lane instead when the gap ahead is under ``max(--front-gap-m, --headway-s x closing speed)`` or the gap
behind under ``max(--rear-gap-m, --headway-s x the follower's closing speed)``. ``--front-gap-m -1``
runs the driver without the shield (the reference). Prints one JSON object per run.

    python -m experiments.gap_shield.gap_shield runs/ppo/policy.safetensors --front-gap-m 1 --rear-gap-m 1
    python -m experiments.gap_shield.gap_shield rule --front-gap-m -1
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from lccli.common import fail
from lccli.evaluate import add_heldout_arguments, eval_settings, heldout_driver
from lcmodels.policy.evaluate import evaluate
from lcsim.core import KEEP, LaneChangeCore


class GapShield:
    """``driver(obs, mask, core)`` with lane changes into short gaps replaced by keep."""

    def __init__(self, driver, *, front_gap_m: float, rear_gap_m: float, headway_s: float) -> None:
        self.driver, self.front_gap_m, self.rear_gap_m, self.headway_s = driver, front_gap_m, rear_gap_m, headway_s
        self.name = f"{getattr(driver, 'name', 'driver')}+shield"
        self.changes = self.vetoed = 0  # lane changes asked for (where allowed) and vetoed

    @property
    def last_prediction(self) -> np.ndarray | None:
        return getattr(self.driver, "last_prediction", None)

    def __call__(self, obs: dict[str, np.ndarray], mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        actions = np.array(self.driver(obs, mask, core), dtype=np.int64).reshape(-1)
        rows = np.arange(len(actions))
        g = core.lane_gaps()
        v = core.sim.speed[:, 0]
        front_need = np.maximum(self.front_gap_m, self.headway_s * np.maximum(v - g["front_speed"][rows, actions], 0.0))
        rear_need = np.maximum(self.rear_gap_m, self.headway_s * np.maximum(g["rear_speed"][rows, actions] - v, 0.0))
        asked = (actions != KEEP) & mask[rows, actions]
        veto = asked & ((g["front_gap"][rows, actions] < front_need) | (g["rear_gap"][rows, actions] < rear_need))
        self.changes += int(asked.sum())
        self.vetoed += int(veto.sum())
        actions[veto] = KEEP
        return actions


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="eval_shield", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    add_heldout_arguments(parser)
    parser.add_argument("--front-gap-m", type=float, default=1.0, help="least gap ahead (m, default 1; -1: no shield)")
    parser.add_argument("--rear-gap-m", type=float, default=1.0, help="least gap behind (m, default 1)")
    parser.add_argument("--headway-s", type=float, default=0.0,
                        help="least time to close either gap (s, default 0: distance only)")
    args = parser.parse_args(argv)
    if args.rear_gap_m < 0 or args.headway_s < 0:
        parser.error("--rear-gap-m and --headway-s must be >= 0")
    try:
        driver, config = heldout_driver(args)
        batch = eval_settings(args)[0].batch
    except ValueError as exc:
        return fail(parser.prog, str(exc))
    shield = None
    if args.front_gap_m >= 0:
        shield = driver = GapShield(driver, front_gap_m=args.front_gap_m, rear_gap_m=args.rear_gap_m,
                                    headway_s=args.headway_s)
    t0 = time.perf_counter()
    summary, _ = evaluate(driver, config, episodes=args.episodes, seed=args.seed, batch=batch)
    print(json.dumps({
        "driver": args.policy, "shield": shield is not None, "front_gap_m": args.front_gap_m,
        "rear_gap_m": args.rear_gap_m, "headway_s": args.headway_s, "episodes": args.episodes,
        **{k: summary[k] for k in ("success_rate", "collision_rate", "off_road_rate", "timeout_rate")},
        "changes_asked": shield.changes if shield else None, "changes_vetoed": shield.vetoed if shield else None,
        "wall_s": round(time.perf_counter() - t0, 1),
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
