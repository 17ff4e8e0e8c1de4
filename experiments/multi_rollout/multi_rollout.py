"""The safety layer scoring each candidate decision by rollouts of several base policies (Bertsekas' rollout with
multiple base policies): a small policy tree judged across all the imagined futures.

The perceived safety layer (:class:`lcsim.planning.LookaheadDriver`) applies each candidate decision (right, keep,
left) in ``safety.samples`` imagined futures, follows ONE driver for ``safety.horizon_decisions`` more decisions and
scores the candidate by the share of the futures it survives. This variant continues every (candidate, future)
with each of K closed-loop base policies and scores the candidate by the best base policy's share::

    score(decision) = max over base policies k of  mean over futures s of  survived(decision, s, k)

Each base policy is judged across all the futures together: never re-chosen per future, which would be clairvoyant
(inside one imagined future almost every decision has some continuation that survives). Then the layer's own rule:
the proposed decision stands unless another scores better. The (candidate, future) copies run as one batch of the
compiled core with the first base policy, then every (candidate, future, other base policy) copy of the candidates
the first does not carry through every future as a second batch (a share of 1 cannot be beaten).

Base policies (``--bases``, comma-separated): ``follow`` (the layer's own follower: the driver behind it, or
``--follow``), ``rule`` (the rule-based driver), ``forced`` (the rule-based driver changing lane only when its
leader is close: :data:`FORCED`), ``keep`` (never changes lane; the ego does not brake, so it survives only a free
lane), or a policy file or ``zoo:NAME`` that does not read the image. With ``--bases follow`` it decides exactly as
the layer does. ``--baseline`` runs the layer itself on the same path (what ``lc-bench`` runs for a cell).

Run from the repository root (one road of the ``highway`` suite, its validation episodes; the driver, ``--follow``
and ``--set safety.KEY=VALUE`` as ``lc-bench`` takes them)::

    python -m experiments.multi_rollout.multi_rollout safety-layer:zoo:roads-ppo --scenario paper \\
        --set safety.horizon_decisions=32 --set safety.samples=3 --episodes 200 --seed 0 --baseline \\
        --json-out docs/results/multi-rollout/layer-paper.json
    python -m experiments.multi_rollout.multi_rollout safety-layer:zoo:roads-ppo --scenario paper \\
        --set safety.horizon_decisions=32 --set safety.samples=3 --episodes 200 --seed 0 --bases follow,rule,forced \\
        --against docs/results/multi-rollout/layer-paper.json --json-out docs/results/multi-rollout/multi-paper.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lccli.common import add_safety_layer_arguments, safety_layer_from_args, zoo_spec
from lcmodels.bench.ledger import counts, outcome_string
from lcmodels.stats import mcnemar
from lcsim.core import KEEP, RUNNING, SUCCESS, TIMEOUT, LaneChangeCore
from lcsim.drivers import Driver, KeepLaneDriver, RuleBasedDriver, RuleDriverConfig
from lcsim.planning import LookaheadDriver, SafetyLayerConfig

FORCED = RuleDriverConfig(trigger_time_s=4.0, trigger_gap_m=8.0, gain_s=0.5)
"""``forced``: the rule-based driver that keeps its lane until it would reach its leader within 4 s (or is within
8 m of it), then takes a side lane that is safe and at least 0.5 s better: keep lane unless forced."""

BUILT_IN_BASES = ("follow", "rule", "forced", "keep")


class TimedLayer(LookaheadDriver):
    """:class:`~lcsim.planning.LookaheadDriver` that counts the CPU time of its decisions (the process's, all its
    threads: the time of one core when torch and the simulator run on one thread) and the decisions it made."""

    def __init__(self, config: SafetyLayerConfig | None = None, rule: Driver | None = None,
                 proposer: Driver | None = None) -> None:  # fmt: skip
        super().__init__(config, rule, proposer)
        self.cpu_s = 0.0
        self.decisions = 0  # environments still running at a call (each made one decision)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        start = time.process_time()
        out = super().__call__(obs, action_mask, core)
        self.cpu_s += time.process_time() - start
        self.decisions += int((core.outcome == RUNNING).sum())
        return out

    def cost(self) -> dict[str, float]:
        """CPU milliseconds per decision and per decision with a choice (the proposer's time included)."""
        ms = 1000.0 * self.cpu_s
        return {"cpu_s": round(self.cpu_s, 2), "ms_per_decision": ms / max(self.decisions, 1),
                "ms_per_choice": ms / max(self.choices, 1), "decisions": self.decisions}


class MultiRolloutLayer(TimedLayer):
    """The safety layer whose candidate decisions are scored by the best of several base policies, each judged
    across all the imagined futures (see the module's docstring). ``bases``: the drivers the futures are continued
    with (``None`` in the list: the layer's follower ``rule``); a driver that reads the observation sets
    ``needs_observation`` and is called on the observation of the copies it drives (its ``core`` argument is the
    whole batch), any other is called on the whole batch and its decisions for its copies are taken."""

    def __init__(self, config: SafetyLayerConfig | None = None, rule: Driver | None = None,
                 proposer: Driver | None = None, *, bases: Sequence[Driver | None] = (None,),
                 progress_gain_m: float | None = None) -> None:  # fmt: skip
        super().__init__(config, rule, proposer)
        if not bases:
            raise ValueError("name at least one base policy")
        if progress_gain_m is not None and not 0.0 <= progress_gain_m <= 1_000.0:
            raise ValueError(f"the progress gain must be in [0, 1000] m, got {progress_gain_m!r}")
        self.progress_gain_m = progress_gain_m
        self._progress = np.zeros((0, 3))  # (E, 3) per candidate: the ego's mean progress under its best base
        self.bases: list[Driver] = [self.rule if b is None else b for b in bases]
        self.best_base = np.zeros(len(self.bases), dtype=np.int64)
        """How often each base policy gave a candidate its score (the first best on a tie)."""

    @property
    def name(self) -> str:  # type: ignore[override]
        return f"{super().name}-multi{len(self.bases)}"

    def check(self, planned: np.ndarray, action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        """The layer's decisions; with ``progress_gain_m``, then, among the decisions of the best score, the one
        whose ego goes furthest over the horizon (the mean over the futures, under the base policy that gave the
        score) where it goes at least ``progress_gain_m`` further than the decision the layer took."""
        self._progress = np.full((core.num_envs, 3), np.nan)
        out = super().check(planned, action_mask, core)
        if self.progress_gain_m is None or not np.isfinite(self.last_alive).any():
            return out
        alive, rows = np.nan_to_num(self.last_alive, nan=-1.0), np.arange(len(out))
        tied = (alive == alive.max(axis=1, keepdims=True)) & np.isfinite(self.last_alive)
        progress = np.where(tied, self._progress, -np.inf)
        further = progress.argmax(axis=1)
        switch = tied[rows, out] & (progress[rows, further] >= self._progress[rows, out] + self.progress_gain_m)
        kept = out == np.asarray(planned, dtype=np.int64).reshape(len(out))  # (an override already counted)
        self.overrides += int((switch & kept).sum())
        return np.where(switch, further, out).astype(np.int64)

    def _survives(self, future: LaneChangeCore, actions: np.ndarray, salt: int | np.ndarray,
                  rows: np.ndarray) -> np.ndarray:  # fmt: skip
        """Per copy of ``future``, whether it survives under the base policy that survives the most of its group's
        futures. :meth:`LookaheadDriver.check` lays the copies out in groups of ``samples`` (one per imagined future
        of an (environment, decision) pair, salts 1..samples) and scores a decision by the mean over its group:
        that mean is then the best base policy's share. Copies not so laid out are each their own group.

        The first base runs first; the others only for the groups it does not carry through every future (a share
        of 1 cannot be beaten, and the first best wins a tie): the same scores as every base on every copy."""
        n, k = future.num_envs, len(self.bases)
        salts = np.broadcast_to(np.asarray(salt, dtype=np.int64), (n,))
        actions, rows = np.asarray(actions, dtype=np.int64).reshape(n), np.asarray(rows).reshape(n)
        s = self.config.samples
        group = s if n % s == 0 and np.array_equal(salts, np.tile(np.arange(1, s + 1), n // s)) else 1
        alive, progress = np.zeros((n, k), dtype=bool), np.zeros((n, k))
        every = np.arange(n)
        alive[:, 0], progress[:, 0] = self._rollout(future, every, np.zeros(n, dtype=np.int64), actions, salts, rows)
        open_groups = np.flatnonzero(~alive[:, 0].reshape(-1, group).all(axis=1))
        if k > 1 and len(open_groups):
            ids = (open_groups[:, None] * group + np.arange(group)).ravel()
            rest, went = self._rollout(future, np.repeat(ids, k - 1), np.tile(np.arange(1, k), len(ids)), actions,
                                       salts, rows)  # fmt: skip
            alive[ids, 1:], progress[ids, 1:] = rest.reshape(len(ids), k - 1), went.reshape(len(ids), k - 1)
        alive, progress = alive.reshape(n // group, group, k), progress.reshape(n // group, group, k)
        best = alive.mean(axis=1).argmax(axis=1)  # per (environment, decision): the base surviving most futures
        np.add.at(self.best_base, best, 1)
        first = np.arange(0, n, group)  # (a group is one (environment, decision) pair)
        if group == s and len(rows) and rows.max() < len(self._progress):
            self._progress[rows[first], actions[first]] = progress[np.arange(len(best)), :, best].mean(axis=1)
        return alive[np.arange(len(best)), :, best].reshape(n)

    def _rollout(self, future: LaneChangeCore, of: np.ndarray, base: np.ndarray, actions: np.ndarray,
                 salts: np.ndarray, rows: np.ndarray) -> np.ndarray:  # fmt: skip
        """``(len(of),)`` bool, whether copies ``of`` of ``future`` (which stays as it is), each imagined with its salt,
        given its candidate decision, then driven by its base policy ``base`` for the horizon, survive; and
        ``(len(of),)`` the metres the ego goes in each (to its contact, where it has one)."""
        copies = future.replicate(of)
        start = copies.sim.x[:, 0].copy()
        self.imagine(copies, salts[of], rows[of])
        copies.step(actions[of])
        for _ in range(self.config.horizon_decisions):
            running = copies.outcome == RUNNING
            if not running.any():
                break
            mask = copies.action_mask()
            decided = np.full(copies.num_envs, KEEP, dtype=np.int64)
            for j, driver in enumerate(self.bases):
                ids = np.flatnonzero(running & (base == j))
                if not len(ids):
                    continue
                if getattr(driver, "needs_observation", False):
                    decided[ids] = driver(copies.observe(ids), mask[ids], copies)
                else:
                    decided[ids] = np.asarray(driver({}, mask, copies))[ids]
            copies.step(decided)
        return np.isin(copies.outcome, (RUNNING, SUCCESS, TIMEOUT)), copies.sim.x[:, 0] - start


def base_drivers(names: Sequence[str]) -> list[Driver | None]:
    """The base policies ``names`` (``follow`` is ``None``: the layer's follower); ``ValueError`` for a policy that
    cannot be loaded or reads the image."""
    from lcmodels.policy.evaluate import driver_for

    out: list[Driver | None] = []
    for name in names:
        if name == "follow":
            out.append(None)
        elif name == "rule":
            out.append(RuleBasedDriver())
        elif name == "forced":
            forced = RuleBasedDriver(FORCED)
            forced.name = "forced"  # type: ignore[misc]
            out.append(forced)
        elif name == "keep":
            out.append(KeepLaneDriver())
        else:
            driver, _ = driver_for(name)
            if not getattr(driver, "needs_observation", False) or getattr(getattr(driver, "policy", None),
                                                                            "obs_mode", "pure") != "pure":
                raise ValueError(f"base policy {name}: expected a policy that reads no image (mode pure) or one of "
                                 f"{', '.join(BUILT_IN_BASES)}")
            out.append(driver)
    return out


def _bases(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError("expected base policies separated by commas (follow,rule,forced)")
    return tuple(n if n in BUILT_IN_BASES else zoo_spec(n) for n in names)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="multi_rollout", description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("policy", help="a driver behind the safety layer, as lc-bench names it: safety-layer:zoo:NAME, "
                   "safety-layer:POLICY.safetensors or safety-layer:rule")
    add_safety_layer_arguments(p)
    p.add_argument("--bases", type=_bases, default=("follow", "rule", "forced"), metavar="NAMES",
                   help="base policies, comma-separated: follow, rule, forced, keep, a policy file or zoo:NAME "
                   "(default follow,rule,forced)")
    p.add_argument("--progress-gain-m", type=float, default=None, metavar="M",
                   help="among the decisions of the best score, take the one whose ego goes furthest over the horizon "
                   "when it goes at least M metres further than the layer's (default: no tie-break)")
    p.add_argument("--baseline", action="store_true", help="run the safety layer itself (no --bases)")
    p.add_argument("--scenario", default="paper", help="a road of the highway suite (default paper)")
    p.add_argument("--episodes", type=int, default=200, help="validation episodes (default 200)")
    p.add_argument("--seed", type=int, default=0, help="validation evaluation seed, as lc-bench --seed (default 0)")
    p.add_argument("--batch", type=int, default=20, help="episodes simulated together (default 20, as lc-bench)")
    p.add_argument("--against", type=Path, default=None, metavar="JSON",
                   help="a summary this script wrote for the same episodes: McNemar's paired test against it")
    p.add_argument("--json-out", type=Path, default=None, help="write the summary as JSON here (not over a file)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)

    def error(msg: str) -> int:
        print(f"multi_rollout: error: {' '.join(str(msg).split())}", file=sys.stderr)
        return 2

    import torch

    from lcmodels.bench.run import resolve_driver
    from lcmodels.policy.evaluate import driver_for, eval_user_seeds, evaluate
    from lcsim.suite import SUITE_SCENARIOS

    torch.set_num_threads(1)
    if args.scenario not in SUITE_SCENARIOS:
        return error(f"unknown suite scenario {args.scenario!r}; choose {', '.join(SUITE_SCENARIOS)}")
    if args.json_out is not None and args.json_out.exists():
        return error(f"--json-out {args.json_out} exists: name another file")
    against = None
    try:
        if args.against is not None:
            against = json.loads(args.against.read_text())
        seeds = eval_user_seeds(args.episodes, args.seed)
        bench = resolve_driver(args.policy, safety=safety_layer_from_args(args.policy, args))
        if bench.spec.layer is None:
            return error(f"{args.policy} drives behind no safety layer: name it safety-layer:{args.policy}")
        sc = SUITE_SCENARIOS[args.scenario]
        config = sc.make()
        plain, own = driver_for(bench.spec, predictor=bench.predictor, scenario=config)
        if args.baseline:
            driver: TimedLayer = TimedLayer(plain.config, plain.rule, plain.proposer)
        else:
            driver = MultiRolloutLayer(plain.config, plain.rule, plain.proposer, bases=base_drivers(args.bases),
                                       progress_gain_m=args.progress_gain_m)  # fmt: skip
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    if against is not None and against.get("user_seeds") != [seeds[0], seeds[-1]]:
        return error(f"--against {args.against} holds other episodes than these")
    show = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", file=sys.stderr, flush=True))
    start = time.perf_counter()
    _, results = evaluate(driver, own or config, user_seeds=seeds, batch=args.batch, progress=show,
                          scenario=sc.name)  # fmt: skip
    outcomes = outcome_string(r.outcome for r in results)
    summary: dict[str, Any] = {
        "driver": args.policy, "scenario": sc.name, "split": f"validation seed {args.seed}",
        "user_seeds": [seeds[0], seeds[-1]], "batch": args.batch, "safety_layer": bench.spec.layer.to_dict(),
        "bases": [] if args.baseline else list(args.bases),
        "progress_gain_m": None if args.baseline else args.progress_gain_m, "outcomes": outcomes, **counts(outcomes),
        "mean_return": float(np.mean([r.ret for r in results])),
        "planner_choices": driver.choices, "planner_overrides": driver.overrides, **driver.cost(),
        "wall_s": round(time.perf_counter() - start, 1),
        "command": "python -m experiments.multi_rollout.multi_rollout " + " ".join(argv or sys.argv[1:])}  # fmt: skip
    if isinstance(driver, MultiRolloutLayer):
        summary["best_base_counts"] = dict(zip(args.bases, driver.best_base.tolist(), strict=True))
    lo, hi = summary["success_wilson95"]
    print(f"{args.policy} on {sc.name}, {len(seeds)} episodes: success {100 * summary['success_rate']:.1f}% "
          f"[{100 * lo:.1f}, {100 * hi:.1f}], overrides {driver.overrides} of {driver.choices} decisions with a "
          f"choice; {summary['ms_per_decision']:.1f} ms of CPU per decision ({summary['ms_per_choice']:.1f} per "
          f"decision with a choice), {summary['wall_s']} s")  # fmt: skip
    if against is not None:
        won = [c == "s" for c in outcomes]
        test = mcnemar([c == "s" for c in against["outcomes"]], won)
        summary["mcnemar_vs"] = {"against": str(args.against), "n": test.n, "only_against": test.only_a,
                                 "only_this": test.only_b, "p_value": test.p_value}  # fmt: skip
        print(f"McNemar against {args.against}: it alone won {test.only_a}, this alone {test.only_b}, "
              f"p = {test.p_value:.3g}")
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
