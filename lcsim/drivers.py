"""Non-learning drivers: a rule-based gap-acceptance lane changer, a lookahead planner, keep-lane, random.

``make_driver("oracle")`` gives the omniscient whole-episode search of :mod:`lcsim.oracle`.

A driver is called once per decision as ``driver(obs, action_mask, core) -> actions (E,)`` with the
batched observation, the ``(E, 3)`` action mask and the :class:`~lcsim.core.LaneChangeCore` (for
drivers that use privileged state), so one driver serves the single env, the vector env and the
recorder, and is evaluated exactly like a learned policy.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lcsim.config import _non_negative, _positive
from lcsim.core import KEEP, RUNNING, SUCCESS, TIMEOUT, LaneChangeCore


def imagined_copy(core: LaneChangeCore) -> LaneChangeCore:
    """A copy of ``core`` to imagine a future in: it shares no state with ``core`` and has no hooks (a
    recorder must not see the imagined future) and no renderer."""
    return copy.deepcopy(core, {id(core.sim.hooks): [], id(core.renderer): None})


class Driver(Protocol):
    name: str

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray,
                 core: LaneChangeCore) -> np.ndarray: ...


@dataclass(frozen=True, slots=True, kw_only=True)
class RuleDriverConfig:
    """Gap acceptance as a cost-function baseline would do it (all distances bumper to bumper)."""

    horizon_s: float = 60.0
    """Times to reach a leader beyond this count as this (no preference among free lanes)."""
    trigger_time_s: float = 15.0
    """Look for another lane once we would reach the leader within this time ..."""
    trigger_gap_m: float = 30.0
    """... or once it is closer than this."""
    min_front_gap_m: float = 12.0
    min_front_time_s: float = 5.0
    """Time to reach the new leader at the current closing speed must be at least this."""
    min_rear_gap_m: float = 5.0
    rear_time_s: float = 2.5
    """Required rear gap grows with the closing speed of the follower in the target lane."""
    gain_s: float = 4.0
    """A lane must give this many more seconds before reaching its leader to be worth a change."""
    urgent_time_s: float = 2.5
    urgent_rear_gap_m: float = 1.0

    def __post_init__(self) -> None:
        _positive(self, "horizon_s", "trigger_time_s", "trigger_gap_m", "min_front_gap_m", "min_front_time_s",
                  "rear_time_s")
        _non_negative(self, "min_rear_gap_m", "gain_s", "urgent_time_s", "urgent_rear_gap_m")


class RuleBasedDriver:
    """Changes lane when the leader gets close and a side lane offers a safe, larger gap.

    Works on the exact lane gaps around the ego (:meth:`LaneChangeCore.lane_gaps`): the perception a
    cost-function planner is usually given. It never brakes (the ego does not, by default).
    """

    name = "rule"

    def __init__(self, config: RuleDriverConfig | None = None) -> None:
        self.config = config or RuleDriverConfig()

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        c = self.config
        g = core.lane_gaps()
        v = core.sim.speed[:, 0][:, None]
        front, rear = g["front_gap"], g["rear_gap"]
        closing = np.maximum(v - g["front_speed"], 0.05)
        reach = np.minimum(front / closing, c.horizon_s)  # seconds until we reach each lane's leader
        own_front, own_reach = front[:, 1], reach[:, 1]
        pressed = (own_front < c.trigger_gap_m) | (own_reach < c.trigger_time_s)
        rear_need = np.maximum(c.min_rear_gap_m, c.rear_time_s * np.maximum(g["rear_speed"] - v, 0.0))
        safe = (front >= c.min_front_gap_m) & (reach >= c.min_front_time_s) & (rear >= rear_need)
        # About to hit the leader: a tighter rear gap is acceptable (the follower brakes for us).
        urgent = (own_reach < c.urgent_time_s)[:, None]
        safe |= urgent & (front >= own_front[:, None] + 2.0) & (rear >= c.urgent_rear_gap_m)
        better = reach >= own_reach[:, None] + c.gain_s
        ok = safe & better & np.asarray(action_mask, dtype=bool)
        ok[:, KEEP] = False
        # Prefer the lane whose leader we reach last; overtake on the left on a tie.
        score = np.where(ok, reach + np.array([0.0, 0.0, 0.01]), -np.inf)
        go = pressed & np.isfinite(score.max(axis=1))
        actions = np.full(len(front), KEEP, dtype=np.int64)
        actions[go] = score.argmax(axis=1)[go]
        return actions


@dataclass(frozen=True, slots=True, kw_only=True)
class LookaheadConfig:
    """How far the lookahead planner simulates each candidate decision."""

    horizon_decisions: int = 16
    """Decisions simulated after the candidate one (16 x 0.5 s = 8 s): the ego gains only ~1.7 m/s
    on the traffic, so a trap (a slow leader with both side lanes occupied) closes over seconds."""
    blind: bool = False
    """Imagine futures with the traffic's random draws redrawn (:meth:`HighwaySim.redraw_future`): the
    planner knows the traffic's rules and present state, not its coming random lane changes."""
    samples: int = 1
    """Blind only: futures imagined per candidate decision, each redrawn with its own salt. A decision's
    survival is the share of them it survives; the driver's own choice stands unless another survives
    more of them."""
    perceived: bool = False
    """Blind only: imagine each future from what the ego's sensors show (:meth:`HighwaySim.perceive` with
    the scenario's ``sensing_range_m``, the range the observation has): no traffic beyond that range, and
    each vehicle's unseen desired speed estimated. The planner then needs no privileged state, only the
    traffic's rules and the ego's perception."""

    def __post_init__(self) -> None:
        if not isinstance(self.horizon_decisions, int) or self.horizon_decisions < 1:
            raise ValueError(f"horizon_decisions must be an int >= 1, got {self.horizon_decisions!r}")
        if not isinstance(self.samples, int) or self.samples < 1:
            raise ValueError(f"samples must be an int >= 1, got {self.samples!r}")
        if self.samples > 1 and not self.blind:
            raise ValueError("samples > 1 needs blind=True (unredrawn copies all see the same future)")
        if self.perceived and not self.blind:
            raise ValueError("perceived=True needs blind=True (a planner that sees the coming random draws is "
                             "privileged whatever it perceives)")


def _driver_name(driver: Driver) -> str:
    return str(getattr(driver, "name", type(driver).__name__))


class LookaheadDriver:
    """A privileged planner: a driver (the rule-based one by default), checked against the simulator's future.

    Before each decision it copies the whole simulator (every environment, with its random state)
    three times, applies right / keep / left in the copies, follows the driver ``rule`` for
    ``horizon_decisions`` more decisions and keeps that driver's own choice if its future is
    collision-free; otherwise it takes a surviving alternative (keep first). Unless ``blind``, it sees
    exactly what will happen, which no policy can, so it is an *upper reference* for what the scenario
    allows, not a baseline to beat. Blind, it is one step of policy improvement over its rollout driver
    that a policy could in principle learn (a teacher for DAgger). About 50x the cost of a decision.

    A rollout driver that reads the observation sets ``needs_observation = True``; it gets the imagined
    copy's observation, which has no image (the copies do not render).

    ``proposer``, when given, makes the decision the planner checks instead of ``rule``: a safety layer in
    front of a driver that reads what the imagined futures cannot show (a policy that reads the image),
    with ``rule`` as the model of how the ego drives on after the decision.
    """

    def __init__(self, config: LookaheadConfig | None = None, rule: Driver | None = None,
                 proposer: Driver | None = None) -> None:
        self.config = config or LookaheadConfig()
        self.rule = rule or RuleBasedDriver()
        self.proposer = proposer
        self.choices = self.overrides = 0  # decisions with a choice seen, and those where the planner overrode
        self.last_alive: np.ndarray | None = None
        """``(E, 3)`` after each call: the share of imagined futures each decision survived, NaN where it was
        not imagined (not allowed, or no choice to make): the labels a learned safety critic is fitted to."""
        self._observe = bool(getattr(self.rule, "needs_observation", False))

    @property
    def name(self) -> str:  # type: ignore[override]
        """``lookahead``, ``lookahead-blind`` or ``lookahead-perceived``, then the driver followed (unless the
        rule) and, first, the proposer."""
        name = "lookahead-perceived" if self.config.perceived else "lookahead-blind" if self.config.blind else "lookahead"
        if not isinstance(self.rule, RuleBasedDriver) or self.proposer is not None:
            name += f"-{_driver_name(self.rule)}"
        return name if self.proposer is None else f"{_driver_name(self.proposer)}+{name}"

    @property
    def last_prediction(self) -> np.ndarray | None:
        """The predictions the driver that made the decision saw (recorded by lc-eval), if it has any."""
        return getattr(self.proposer or self.rule, "last_prediction", None)

    def survives(self, core: LaneChangeCore, actions: np.ndarray, salt: int = 1) -> np.ndarray:
        """``(E,)`` bool: no collision or off-road within the horizon after ``actions``, then the driver
        ``rule`` (in a future redrawn with ``salt`` when blind)."""
        future = imagined_copy(core)
        if self.config.blind:
            future.sim.redraw_future(salt)
        if self.config.perceived:
            future.sim.perceive(future.config.sensing_range_m)
        future.step(actions)
        for _ in range(self.config.horizon_decisions):
            if (future.outcome != RUNNING).all():  # ended environments stay frozen; nothing left to see
                break
            obs = future.observe() if self._observe else {}
            future.step(self.rule(obs, future.action_mask(), future))
        return np.isin(future.outcome, (RUNNING, SUCCESS, TIMEOUT))

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        mask = np.asarray(action_mask, dtype=bool).reshape(-1, 3)
        planned = np.asarray((self.proposer or self.rule)(obs, mask, core), dtype=np.int64).reshape(len(mask))
        # a proposal the mask refuses becomes a keep, which the planner then checks: it never passes on a
        # refused decision (rewarded off_road under "refuse", leaving the road under "leave_road")
        planned = np.where(mask[np.arange(len(mask)), planned], planned, KEEP)
        # during a lane change only keep is allowed, and an ended episode is frozen: nothing to look at
        choice = (mask.sum(axis=1) > 1) & (core.outcome == RUNNING)
        self.last_alive = np.full(mask.shape, np.nan)
        if not choice.any():
            return planned
        alive = np.zeros(mask.shape)  # share of the imagined futures each decision survives
        for action in range(3):
            if (mask[:, action] & choice).any():  # imagined futures per action someone can take
                actions = np.where(mask[:, action], action, KEEP)
                for salt in range(1, self.config.samples + 1):
                    alive[:, action] += self.survives(core, actions, salt) & mask[:, action]
        alive /= self.config.samples
        self.last_alive = np.where(mask & choice[:, None], alive, np.nan)
        best = alive.max(axis=1)
        fallback = np.where(alive[:, KEEP] >= best, KEEP, alive.argmax(axis=1))  # keep, else the first best change
        override = choice & (alive[np.arange(len(planned)), planned] < best)
        self.choices += int(choice.sum())
        self.overrides += int(override.sum())
        return np.where(override, fallback, planned).astype(np.int64)


class KeepLaneDriver:
    """Never changes lane (with ``adaptive_cruise`` on, the lane-keeping reference)."""

    name = "keep"

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        return np.full(np.asarray(action_mask).reshape(-1, 3).shape[0], KEEP, dtype=np.int64)


class RandomDriver:
    """Uniformly random among the valid actions, from its own seeded generator."""

    name = "random"

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        mask = np.asarray(action_mask, dtype=bool).reshape(-1, 3)
        u = self.rng.random(mask.shape) * mask
        return u.argmax(axis=1).astype(np.int64)


def _oracle(seed: int) -> Driver:
    from lcsim.oracle import OracleDriver  # it plans with the rule-based driver defined here

    return OracleDriver()


_FACTORIES: dict[str, Callable[[int], Driver]] = {
    "rule": lambda seed: RuleBasedDriver(),
    "lookahead": lambda seed: LookaheadDriver(),
    "lookahead-blind": lambda seed: LookaheadDriver(LookaheadConfig(blind=True)),
    "oracle": _oracle,
    "keep": lambda seed: KeepLaneDriver(),
    "random": RandomDriver,
}
DRIVER_NAMES = tuple(_FACTORIES)
"""Names :func:`make_driver` accepts."""
POLICY_PREFIXES = ("policy:", "lookahead:", "lookahead-blind:")
"""Prefixes of a driver spec that name a policy checkpoint: the policy itself, or the lookahead (blind or not)
following it (built in lcmodels, which loads policies)."""


def split_policy_spec(spec: str) -> tuple[str, str] | None:
    """``(prefix, checkpoint path)`` of a spec with one of :data:`POLICY_PREFIXES` and a non-empty path, else None."""
    prefix = next((p for p in POLICY_PREFIXES if spec.startswith(p) and len(spec) > len(p)), None)
    return None if prefix is None else (prefix, spec.removeprefix(prefix))


def make_driver(name: str, seed: int = 0) -> Driver:
    """A driver by name (``autopilot`` is a simulator mode, not a policy); ``seed`` seeds ``random``."""
    factory = _FACTORIES.get(name)
    if factory is None:
        raise ValueError(f"unknown driver {name!r}; choose {', '.join(DRIVER_NAMES)}")
    return factory(seed)
