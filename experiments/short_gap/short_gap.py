"""What the other vehicle does in a short-gap collision behind the safety layer.

A *short-gap* collision (``lc-eval --breakdown``) is the ego hitting a vehicle of its target lane while it
changes lanes. Behind the perceived lookahead safety layer most of the collisions left are of this kind, though
every lane change the layer let through survived its imagined futures. This script drives held-out episodes
with a driver of ``lc-eval`` and, for every short-gap collision, reports what the partner did between the
start of the ego's lane change and the contact, next to what the imagined futures assumed:

- where the partner was when the change began (ahead or behind in the target lane, or in another lane and
  changing into the target lane: a merge into the same gap);
- its mean acceleration over the change, and the share of its drivers' parameters (headway, acceleration,
  reaction lag) that differ from the median driver the perceived layer imagines;
- the share of imagined futures in which the ego's change survived at its start.

Run from the repository root::

    python -m experiments.short_gap.short_gap lookahead-blind:zoo:hybrid-ppo --follow zoo:pure-ppo --seed 0
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from lccli.common import non_negative_int, positive_int, zoo_spec
from lcmodels.analysis import classify_collision
from lcmodels.policy.driverspec import safety_layer_of
from lcmodels.policy.evaluate import driver_for, eval_user_seeds
from lcsim.config import paper_scenario
from lcsim.core import COLLISION, KEEP, LaneChangeCore, StepResult
from lcsim.episodes import EpisodeHook, run_episodes
from lcsim.traffic import DriverParams

_PARAMS = ("time_headway", "max_accel", "inv_2sqrt_ab", "lag")


class ShortGapProbe(EpisodeHook):
    """Watches each episode's lane changes and describes the partner of every short-gap collision."""

    def __init__(self, driver: Any) -> None:
        self.driver = driver
        self.cases: list[dict[str, Any]] = []
        self.changes = 0

    def start(self, core: LaneChangeCore, user_seeds: Sequence[int], driver: Callable[..., np.ndarray]) -> None:
        self.seeds = list(user_seeds)
        e = core.num_envs
        self.began: list[dict[str, Any] | None] = [None] * e
        self.accel: list[list[np.ndarray]] = [[] for _ in range(e)]
        self._changing = np.zeros(e, dtype=bool)
        self.nominal = DriverParams.nominal(core.config.traffic, (1,), core.sim.dt)

    def before_step(self, core: LaneChangeCore, obs: dict[str, np.ndarray], mask: np.ndarray, actions: np.ndarray,
                    running: np.ndarray) -> None:
        sim = core.sim
        self._changing = sim.ego_lc_active.copy()
        alive = getattr(self.driver, "last_alive", None)
        for e in np.nonzero(running & ~sim.ego_lc_active & (actions != KEEP))[0]:
            self.changes += 1
            self.began[e] = {"step": int(sim.step[e]), "lane": sim.lane[e].copy(), "x": sim.x[e].copy(),
                             "lc_active": sim.lc_active[e].copy(), "target": sim.target_lane[e].copy(),
                             "alive": None if alive is None else alive[e].tolist(), "action": int(actions[e])}
            self.accel[e] = []

    def after_step(self, core: LaneChangeCore, result: StepResult, running: np.ndarray) -> None:
        sim = core.sim
        for e in np.nonzero(running)[0]:
            if self.began[e] is not None:
                self.accel[e].append(sim.accel[e].copy())
            if core.outcome[e] != COLLISION:
                if not sim.ego_lc_active[e] and not self._changing[e]:
                    self.began[e] = None
                continue
            if classify_collision(core, e, bool(self._changing[e]), False) != "short_gap" or self.began[e] is None:
                continue
            b, p = self.began[e], int(sim.collision_with[e])
            target = int(sim.target_lane[e, 0])
            if b["lane"][p] == target and not b["lc_active"][p]:
                where = "ahead in the target lane" if b["x"][p] > b["x"][0] else "behind in the target lane"
            elif b["lc_active"][p] and b["target"][p] == target:
                where = "already changing into the target lane"
            elif b["lc_active"][p]:
                where = "changing out of the target lane"
            else:
                where = "changed into the target lane after the ego began"
            acc = np.array([a[p] for a in self.accel[e]]) if self.accel[e] else np.zeros(1)
            params = {n: float(getattr(sim.drivers, n)[e, p] / getattr(self.nominal, n)[0]) for n in _PARAMS}
            self.cases.append({"user_seed": self.seeds[e], "partner": p, "where": where,
                               "gap_at_start_m": float(abs(b["x"][p] - b["x"][0])),
                               "seconds_since_start": float((sim.step[e] - b["step"]) * sim.dt),
                               "action": ("right", "keep", "left")[b["action"]],
                               "partner_mean_accel_mps2": float(acc.mean()),
                               "partner_min_accel_mps2": float(acc.min()),
                               "partner_params_over_median": params, "alive_at_start": b["alive"],
                               "side_by_side_at_start": bool(abs(b["x"][p] - b["x"][0])
                                                             < 0.5 * (sim.length[e, 0] + sim.length[e, p]))})
            self.began[e] = None


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="short_gap", description=__doc__.split("\n\n")[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("policy", type=zoo_spec, help="an lc-eval driver behind the safety layer, e.g. safety-layer:zoo:hybrid-ppo")
    p.add_argument("--follow", type=zoo_spec, default=None, help="the driver the imagined futures follow (lc-eval's --follow)")
    p.add_argument("--samples", type=positive_int, default=3, help="imagined futures per candidate decision (default 3)")
    p.add_argument("--horizon", type=positive_int, default=32, help="decisions imagined after each candidate (default 32)")
    p.add_argument("--episodes", type=positive_int, default=200, help="held-out episodes (default 200)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="evaluation seed (lc-eval's --seed)")
    p.add_argument("--json-out", default=None)
    args = p.parse_args(argv)
    if args.json_out and not os.path.isdir(os.path.dirname(os.path.abspath(args.json_out))):
        p.error(f"--json-out: no folder {os.path.dirname(os.path.abspath(args.json_out))}")
    if args.json_out and os.path.exists(args.json_out):
        p.error(f"--json-out: {args.json_out} exists; choose a new file")
    import torch

    torch.set_num_threads(1)

    try:
        layer = safety_layer_of(args.policy, {"samples": args.samples, "perceived": True,
                                              "horizon_decisions": args.horizon}, args.follow)  # fmt: skip
        driver, config = driver_for(args.policy, safety=layer)
    except (ValueError, OSError) as exc:
        print(f"short_gap: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    probe = ShortGapProbe(driver)
    results = run_episodes(driver, config or paper_scenario(render_image=False),
                           eval_user_seeds(args.episodes, args.seed), hooks=[probe],
                           progress=lambda d, n: print(f"{d}/{n} episodes", file=sys.stderr))
    wins = sum(r.outcome == "success" for r in results)
    side = sum(c["side_by_side_at_start"] for c in probe.cases)
    imagined_safe = sum((c["alive_at_start"] or [0, 0, 0])[("right", "keep", "left").index(c["action"])] == 1.0
                        for c in probe.cases)
    print(f"success {wins}/{len(results)}; lane changes begun {probe.changes}; short-gap collisions {len(probe.cases)}, "
          f"{side} begun with the partner side by side, {imagined_safe} after a change that survived every imagined future")
    for c in probe.cases:
        par = " ".join(f"{k}={v:.2f}" for k, v in c["partner_params_over_median"].items())
        print(f"  {c['user_seed']}: partner {c['where']}, {c['gap_at_start_m']:.1f} m off at start, {c['action']} change, contact "
              f"{c['seconds_since_start']:.2f} s after its start; accel mean {c['partner_mean_accel_mps2']:+.2f} min "
              f"{c['partner_min_accel_mps2']:+.2f} m/s2; params/median {par}; alive at start {c['alive_at_start']}")
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump({"success": wins, "episodes": len(results), "cases": probe.cases}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
