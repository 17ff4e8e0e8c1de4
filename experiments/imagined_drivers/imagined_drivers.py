"""The safety layer imagining the traffic's drivers otherwise than as the median driver: four research variants.

The perceived safety layer (:class:`lcsim.planning.LookaheadDriver`, ``perceived = true``) imagines every vehicle in
sight as the median driver of the traffic, its desired speed read from its motion. These variants change what it
imagines, on human-like traffic (``docs/results/safety-samples`` measured them; none changed the figure beyond the
noise of 400 validation episodes, so none is a setting of the product's safety layer):

- ``--draw-drivers``: each imagined future draws the unseen drivers from the traffic's distribution (with
  ``safety.samples`` > 1 a decision's survival is its share over drivers the sensors cannot tell apart);
- ``--estimate-drivers``: each vehicle's car-following parameters, reaction time and desired speed inferred from its
  motion while in sight (:class:`~experiments.imagined_drivers.estimate.DriverEstimator`), its imagined driver drawn
  from that estimate;
- ``--known-drivers FIELDS``: a privileged diagnostic: the imagined futures keep these driver parameters at their
  true values, the ceiling of a layer that would estimate them;
- ``--margin-m M``: the imagined ego M metres longer at its front and back, so a decision survives only with that
  much more room than contact (blind layers, perceived or not).

Run from the repository root (the driver, ``--follow`` and ``--set safety.KEY=VALUE`` as ``lc-eval`` takes them)::

    python -m experiments.imagined_drivers.imagined_drivers safety-layer:zoo:hybrid-ppo --follow zoo:pure-ppo \\
        --set safety.horizon_decisions=32 --set safety.samples=3 --known-drivers lag,time_headway \\
        --episodes 200 --seed 0 --breakdown
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from lccli.common import add_safety_layer_arguments, safety_layer_from_args, zoo_spec
from lccli.evaluate import format_eval
from lcmodels.analysis import CollisionBreakdown
from lcmodels.policy.evaluate import driver_for, evaluate
from lcsim.config import paper_scenario
from lcsim.core import LaneChangeCore
from lcsim.drivers import Driver
from lcsim.planning import LookaheadDriver, SafetyLayerConfig
from lcsim.sim import HighwaySim
from lcsim.traffic import DriverParams

from .estimate import LONGITUDINAL, DriverEstimator


def driver_fields(names: Sequence[str], what: str = "") -> tuple[str, ...]:
    """``names`` as a tuple, each a :class:`~lcsim.traffic.DriverParams` field; ``ValueError`` naming the first that
    is not (and ``what`` holds them)."""
    bad = [n for n in names if n not in DriverParams.__slots__]
    if bad:
        raise ValueError(f"{what + ': ' if what else ''}{bad[0]!r} is not a driver parameter "
                         f"(one of {', '.join(DriverParams.__slots__)})")
    return tuple(names)


def draw_drivers(sim: HighwaySim, mask: np.ndarray) -> None:
    """Draw the drivers where ``mask`` is set from the traffic's distribution, from a generator seeded by the copy's
    random keys and its time (so each redrawn future imagines other plausible drivers, and the same state gives
    the same draws)."""
    keys = np.concatenate([np.asarray(sim.key, dtype=np.uint64), np.asarray(sim.step, dtype=np.uint64)])
    gen = np.random.default_rng(keys.view(np.uint32))
    drawn = DriverParams.nominal(sim.config.traffic, mask.shape, sim.dt)
    for e in range(mask.shape[0]):
        drawn.draw(e, gen, sim.config.traffic, sim.dt, mask.shape[1])
    sim.drivers.set_where(mask, drawn)


class ImaginedDriversLayer(LookaheadDriver):
    """The safety layer with the research variants of what it imagines (see the module's docstring); with none
    of them it decides as :class:`~lcsim.planning.LookaheadDriver` does."""

    def __init__(self, config: SafetyLayerConfig | None = None, rule: Driver | None = None,
                 proposer: Driver | None = None, *, draw: bool = False, known: Sequence[str] = (),
                 estimate: bool = False, margin_m: float = 0.0) -> None:  # fmt: skip
        super().__init__(config, rule, proposer)
        self.draw, self.known, self.estimate = bool(draw), driver_fields(list(known), "known drivers"), bool(estimate)
        if isinstance(margin_m, bool) or not isinstance(margin_m, int | float) or not 0.0 <= margin_m <= 10.0:
            raise ValueError(f"the margin must be a number of metres in [0, 10], got {margin_m!r}")
        self.margin_m = float(margin_m)
        if (self.draw or self.known or self.estimate) and not self.config.perceived:
            raise ValueError("drawn, known and estimated drivers need a perceived safety layer (an unperceived copy "
                             "knows every driver)")
        if self.margin_m and not self.config.blind:
            raise ValueError("a margin needs a blind safety layer (one that sees the true future needs none)")
        self._estimator: DriverEstimator | None = None

    def check(self, planned: np.ndarray, action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        if self.estimate and core.sim.human:  # what the sensors show now, before the futures are imagined
            if self._estimator is None:
                cfg = core.config
                self._estimator = DriverEstimator(cfg.traffic, cfg.dt_s, cfg.steps_per_decision, cfg.sensing_range_m)
            self._estimator.observe(core)
        return super().check(planned, action_mask, core)

    def imagine(self, future: LaneChangeCore, salt: int | np.ndarray, rows: np.ndarray) -> None:
        sim = future.sim
        durations = sim.drivers.lc_inv_duration.copy()  # the true ones, before perception makes them the median's
        true = {name: getattr(sim.drivers, name).copy() for name in self.known}
        super().imagine(future, salt, rows)
        if self.config.perceived and sim.human:
            if self.draw:
                traffic = sim.is_traffic.copy()
                traffic[:, 0] = False
                draw_drivers(sim, traffic)  # a lane change under way keeps its pace (its progress shows)
                sim.drivers.lc_inv_duration[...] = np.where(sim.lc_active, durations, sim.drivers.lc_inv_duration)
            for name, values in true.items():
                getattr(sim.drivers, name)[...] = values
            if self._estimator is not None:
                self._imagine_estimated(future, np.broadcast_to(np.asarray(salt), rows.shape), rows)
        if self.margin_m:
            sim.length[:, 0] += 2.0 * self.margin_m

    def _imagine_estimated(self, future: LaneChangeCore, salt: np.ndarray, rows: np.ndarray) -> None:
        """The drivers of the vehicles the estimator has evidence on, drawn from their posteriors."""
        assert self._estimator is not None
        sim = future.sim
        drawn, v0, known = self._estimator.draw(rows, salt, np.asarray(sim.step))  # traffic in sight, never the ego
        for name in LONGITUDINAL:
            getattr(sim.drivers, name)[...] = np.where(known, getattr(drawn, name), getattr(sim.drivers, name))
        sim.v0 = np.where(known, v0, sim.v0)


def _fields(text: str) -> tuple[str, ...]:
    try:
        return driver_fields([n.strip() for n in text.split(",") if n.strip()] or [text])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="imagined_drivers", description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("policy", type=zoo_spec, help="a driver behind the safety layer: safety-layer:POLICY, "
                   "safety-layer:rule, or an older spelling (lookahead-blind:POLICY)")
    add_safety_layer_arguments(p)
    p.add_argument("--draw-drivers", action="store_true", help="each imagined future draws the unseen drivers")
    p.add_argument("--estimate-drivers", action="store_true", help="imagine each driver as its motion tells")
    p.add_argument("--known-drivers", type=_fields, default=(), metavar="FIELDS",
                   help="keep these driver parameters true in the imagined futures (comma-separated: time_headway, "
                   "max_accel, inv_2sqrt_ab, lag, lc_inv_duration, eagerness)")
    p.add_argument("--margin-m", type=float, default=0.0, metavar="M", help="the imagined ego M metres longer")
    p.add_argument("--episodes", type=int, default=200, help="held-out episodes, as lc-eval's (default 200)")
    p.add_argument("--seed", type=int, default=0, help="evaluation seed, as lc-eval --seed (default 0)")
    p.add_argument("--batch", type=int, default=20, help="episodes simulated together (default 20)")
    p.add_argument("--breakdown", action="store_true", help="also sort every collision at contact")
    p.add_argument("--json-out", default=None, help="write the summary as JSON here")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    import torch

    torch.set_num_threads(1)

    def error(msg: str) -> int:
        print(f"imagined_drivers: error: {' '.join(msg.split())}", file=sys.stderr)
        return 2

    try:
        layer = safety_layer_from_args(args.policy, args)
        if layer is None:
            return error(f"{args.policy} drives behind no safety layer: name it safety-layer:{args.policy}")
        plain, config = driver_for(args.policy, safety=layer)
        driver = ImaginedDriversLayer(plain.config, plain.rule, plain.proposer, draw=args.draw_drivers,
                                      known=args.known_drivers, estimate=args.estimate_drivers, margin_m=args.margin_m)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    hooks: list[Any] = [CollisionBreakdown()] if args.breakdown else []
    show = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", file=sys.stderr, flush=True))
    summary, _ = evaluate(driver, config or paper_scenario(render_image=False), episodes=args.episodes,
                          seed=args.seed, batch=args.batch, hooks=hooks, progress=show)
    summary["planner_choices"], summary["planner_overrides"] = driver.choices, driver.overrides
    summary["safety_layer"] = layer.to_dict()
    summary["imagined_drivers"] = {"draw": driver.draw, "known": list(driver.known), "estimate": driver.estimate,
                                   "margin_m": driver.margin_m}
    if hooks:
        summary["collision_kinds"] = hooks[0].counts
    print(format_eval(summary))
    print(f"the safety layer overrode {driver.overrides} of {driver.choices} decisions with a choice")
    if hooks:
        print("collisions by kind: " + ", ".join(f"{k} {v}" for k, v in hooks[0].counts.items()))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(summary, f, indent=1, sort_keys=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
