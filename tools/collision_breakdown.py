#!/usr/bin/env python
"""Why a driver crashes: each collision of lc-eval's held-out episodes, classified at the moment of contact.

For a policy checkpoint or a non-learning driver, runs the same held-out episodes as ``lc-eval`` and sorts
every collision into one of:

- ``trapped``: the ego rear-ends its leader while keeping lane, and in the last ``--window-s`` seconds no
  allowed side lane had a gap of ``--front-gap-m`` ahead and ``--rear-gap-m`` behind (the trap closed
  before; avoiding it takes planning further ahead);
- ``missed_gap``: the same, but such a side gap was there in that window;
- ``late_change``: the ego hits a vehicle of the lane it is leaving while changing lanes (it started late);
- ``short_gap``: the ego hits a vehicle of its target lane while changing lanes (the gap was too short);
- ``hit_from_behind``: a vehicle runs into the ego while the ego keeps lane.

    python tools/collision_breakdown.py runs/hybrid-ppo/policy.safetensors --episodes 100
    python tools/collision_breakdown.py rule --episodes 200 --json
"""

from __future__ import annotations

import argparse
import collections
import json
import sys

import numpy as np

from lccli.common import fail
from lccli.evaluate import add_heldout_arguments, heldout_driver
from lcmodels.policy.evaluate import eval_user_seeds
from lcsim.core import KEEP, RUNNING, LaneChangeCore
from lcsim.envs import episode_seed

KINDS = ("trapped", "missed_gap", "late_change", "short_gap", "hit_from_behind")


def side_gap_open(core: LaneChangeCore, front_gap_m: float, rear_gap_m: float) -> np.ndarray:
    """``(E,)`` whether an allowed lane change would land in a gap of the given size right now."""
    gaps = core.lane_gaps()
    ok = (gaps["front_gap"] >= front_gap_m) & (gaps["rear_gap"] >= rear_gap_m) & core.action_mask()
    ok[:, KEEP] = False
    return ok.any(axis=1)


def classify(core: LaneChangeCore, e: int, was_changing: bool, recent_gap: bool) -> str:
    """The kind of environment ``e``'s collision (see the module docstring), from the state at contact."""
    sim = core.sim
    other = int(sim.collision_with[e])
    changing = was_changing or bool(sim.ego_lc_active[e])
    if changing:
        return "short_gap" if sim.lane[e, other] == sim.target_lane[e, 0] else "late_change"
    if sim.x[e, other] < sim.x[e, 0]:
        return "hit_from_behind"
    return "missed_gap" if recent_gap else "trapped"


def breakdown(driver, config, *, episodes: int, seed: int, batch: int, window_decisions: int,
              front_gap_m: float, rear_gap_m: float) -> dict[str, int]:
    """Counts of outcomes and collision kinds over ``episodes`` held-out episodes."""
    counts: collections.Counter[str] = collections.Counter()
    seeds = eval_user_seeds(episodes, seed)
    for start in range(0, episodes, batch):
        chunk = seeds[start:start + batch]
        e = len(chunk)
        core = LaneChangeCore(config, e)
        core.reset(np.arange(e), [episode_seed(s) for s in chunk])
        recent: list[collections.deque[bool]] = [collections.deque(maxlen=window_decisions) for _ in range(e)]
        while (core.outcome == RUNNING).any():
            running = core.outcome == RUNNING
            obs = core.observe()
            for i, is_open in enumerate(side_gap_open(core, front_gap_m, rear_gap_m)):
                recent[i].append(bool(is_open))
            actions = np.asarray(driver(obs, core.action_mask(), core), dtype=np.int64).reshape(e)
            changing = core.sim.ego_lc_active.copy()
            res = core.step(actions)
            for i in np.flatnonzero(running & (res.outcome != RUNNING)):
                counts[str(res.outcome[i])] += 1
                if res.outcome[i] == "collision":
                    counts[classify(core, i, bool(changing[i]), any(list(recent[i])[:-1]))] += 1
    return {k: counts.get(k, 0) for k in ("success", "collision", "off_road", "timeout", *KINDS)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="collision_breakdown", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    add_heldout_arguments(parser, episodes=100)
    gaps = parser.add_argument_group("what counts as a side gap")
    gaps.add_argument("--window-s", type=float, default=5.0, help="how far back it counts (default 5)")
    gaps.add_argument("--front-gap-m", type=float, default=12.0, help="gap ahead (default 12)")
    gaps.add_argument("--rear-gap-m", type=float, default=5.0, help="gap behind (default 5)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    if args.window_s <= 0:
        parser.error("--window-s must be > 0")
    try:
        driver, config = heldout_driver(args)
    except ValueError as exc:
        return fail(parser.prog, str(exc))
    window = max(1, round(args.window_s / config.decision_period_s)) + 1  # + the decision of the contact
    counts = breakdown(driver, config, episodes=args.episodes, seed=args.seed, batch=args.batch,
                       window_decisions=window, front_gap_m=args.front_gap_m, rear_gap_m=args.rear_gap_m)
    if args.json:
        print(json.dumps({"driver": args.policy, "episodes": args.episodes, **counts}))
    else:
        print(f"{args.policy}: {args.episodes} held-out episodes: " +
              ", ".join(f"{k} {counts[k]}" for k in ("success", "collision", "off_road", "timeout")))
        for kind in KINDS:
            print(f"  {kind:16s} {counts[kind]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
