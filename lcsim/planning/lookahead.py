"""The lookahead planner: a driver's decision checked against imagined futures (a safety layer, an upper
reference, or, blind and perceived, a planner that needs no privileged state)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lcsim.core import KEEP, RUNNING, SUCCESS, TIMEOUT, LaneChangeCore
from lcsim.drivers import Driver, RuleBasedDriver
from lcsim.planning.estimate import LONGITUDINAL, DriverEstimator
from lcsim.planning.perception import perceive, redraw_future
from lcsim.traffic import driver_fields


@dataclass(frozen=True, slots=True, kw_only=True)
class LookaheadConfig:
    """How far the lookahead planner simulates each candidate decision."""

    horizon_decisions: int = 16
    """Decisions simulated after the candidate one (16 x 0.5 s = 8 s): the ego gains only ~1.7 m/s
    on the traffic, so a trap (a slow leader with both side lanes occupied) closes over seconds."""
    blind: bool = False
    """Imagine futures with the traffic's random draws redrawn (:func:`~lcsim.planning.perception.redraw_future`): the
    planner knows the traffic's rules and present state, not its coming random lane changes."""
    samples: int = 1
    """Blind only: futures imagined per candidate decision, each redrawn with its own salt. A decision's
    survival is the share of them it survives; the driver's own choice stands unless another survives
    more of them."""
    perceived: bool = False
    """Blind only: imagine each future from what the ego's sensors show (:func:`~lcsim.planning.perception.perceive` with
    the scenario's ``sensing_range_m``, the range the observation has): no traffic beyond that range, and
    each vehicle's unseen desired speed estimated. The planner then needs no privileged state, only the
    traffic's rules and the ego's perception."""
    driver_draws: bool = False
    """Perceived only, human-like traffic: each imagined future draws the unseen drivers' own parameters
    (headway, acceleration, reaction, lane-change habits) from the traffic's distribution instead of taking
    the median driver, so with ``samples`` > 1 a decision's survival is its share over drivers the sensors
    cannot tell apart (:func:`~lcsim.planning.perception.perceive`)."""
    estimate_drivers: bool = False
    """Perceived only, human-like traffic: infer each vehicle's own car-following parameters, reaction time and
    desired speed from its motion over the decisions it has been in sight (:class:`~lcsim.planning.estimate.
    DriverEstimator`), and imagine it with a driver drawn from that posterior instead of the median driver."""
    known_drivers: tuple[str, ...] = ()
    """Perceived only, a privileged diagnostic: the imagined copies keep these parameters of every driver (names
    of :class:`~lcsim.traffic.DriverParams` fields: ``time_headway``, ``max_accel``, ``inv_2sqrt_ab``, ``lag``,
    ``lc_inv_duration``, ``eagerness``) at their true values, which no sensor shows: the ceiling of a planner
    that would estimate them from the traffic's motion."""
    margin_m: float = 0.0
    """Blind only: the imagined ego is this much longer at its front and at its back, so a decision survives
    only if it keeps that much more room than contact (a gap the real traffic's noise may close is refused)."""

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
        if isinstance(self.margin_m, bool) or not isinstance(self.margin_m, int | float) or not 0.0 <= self.margin_m <= 10.0:
            raise ValueError(f"margin_m must be a number of metres in [0, 10], got {self.margin_m!r}")
        if self.margin_m and not self.blind:
            raise ValueError("margin_m > 0 needs blind=True (a planner that sees the true future needs no margin)")
        if not isinstance(self.known_drivers, tuple | list):
            raise ValueError(f"known_drivers must be a tuple of driver parameters, got {self.known_drivers!r}")
        object.__setattr__(self, "known_drivers", driver_fields(self.known_drivers, "known_drivers"))  # a list read back from JSON
        if self.known_drivers and not self.perceived:
            raise ValueError("known_drivers needs perceived=True (an unperceived copy knows every driver)")
        if self.estimate_drivers and not self.perceived:
            raise ValueError("estimate_drivers=True needs perceived=True (an unperceived copy knows every driver)")
        if self.driver_draws and not self.perceived:
            raise ValueError("driver_draws=True needs perceived=True (an unperceived copy knows every driver)")


def _driver_name(driver: Driver) -> str:
    return str(getattr(driver, "name", type(driver).__name__))


class LookaheadDriver:
    """A privileged planner: a driver (the rule-based one by default), checked against the simulator's future.

    Before each decision it copies every environment that has a choice (with its random state) once per
    decision it may take (and per sample), side by side in one batch (:meth:`LaneChangeCore.replicate`),
    applies right / keep / left in the copies, follows the driver ``rule`` for ``horizon_decisions`` more
    decisions and keeps that driver's own choice if its future is collision-free; otherwise it takes a
    surviving alternative (keep first). Unless ``blind``, it sees
    exactly what will happen, which no policy can, so it is an *upper reference* for what the scenario
    allows, not a baseline to beat. Blind, it is one step of policy improvement over its rollout driver
    that a policy could in principle learn (a teacher for DAgger).

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
        self._prediction: np.ndarray | None = None
        self._estimator: DriverEstimator | None = None

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
        """The predictions the driver that made the decision saw (recorded by lc-eval), if it has any: taken when it
        decided, before the imagined futures (where the same driver may run on their batch) replace its own."""
        return self._prediction

    def survives(self, core: LaneChangeCore, actions: np.ndarray, salt: int | np.ndarray = 1) -> np.ndarray:
        """``(E,)`` bool: no collision or off-road within the horizon after ``actions``, then the driver
        ``rule`` (in a future redrawn with ``salt``, one or one per environment, when blind)."""
        rows = np.arange(core.num_envs)
        return self._survives(core.replicate(rows), actions, salt, rows)

    def _survives(self, future: LaneChangeCore, actions: np.ndarray, salt: int | np.ndarray,
                  rows: np.ndarray) -> np.ndarray:  # fmt: skip
        """:meth:`survives` in ``future``, a copy the call may change of the environments ``rows``."""
        if self.config.blind:
            redraw_future(future.sim, salt)
        if self.config.perceived:
            perceive(future.sim, future.config.sensing_range_m, draw_drivers=self.config.driver_draws,
                     known_drivers=self.config.known_drivers)
            if self._estimator is not None:
                self._imagine_estimated(future, np.broadcast_to(np.asarray(salt), rows.shape), rows)
        if self.config.margin_m:
            future.sim.length[:, 0] += 2.0 * self.config.margin_m
        future.step(actions)
        for _ in range(self.config.horizon_decisions):
            if (future.outcome != RUNNING).all():  # ended environments stay frozen; nothing left to see
                break
            obs = future.observe() if self._observe else {}
            future.step(self.rule(obs, future.action_mask(), future))
        return np.isin(future.outcome, (RUNNING, SUCCESS, TIMEOUT))

    def _imagine_estimated(self, future: LaneChangeCore, salt: np.ndarray, rows: np.ndarray) -> None:
        """The drivers of the vehicles the estimator has evidence on, drawn from their posteriors."""
        assert self._estimator is not None
        sim = future.sim
        drawn, v0, known = self._estimator.draw(rows, salt, np.asarray(sim.step))  # traffic in sight, never the ego
        for name in LONGITUDINAL:
            getattr(sim.drivers, name)[...] = np.where(known, getattr(drawn, name), getattr(sim.drivers, name))
        sim.v0 = np.where(known, v0, sim.v0)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        mask = np.asarray(action_mask, dtype=bool).reshape(-1, 3)
        decider = self.proposer or self.rule
        planned = decider(obs, mask, core)
        self._prediction = getattr(decider, "last_prediction", None)
        return self.check(planned, mask, core)

    def check(self, planned: np.ndarray, action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        """The decisions executed for the proposals ``planned`` in ``core``'s environments: each kept if no
        surviving alternative does better in the imagined futures (what :meth:`__call__` does with the
        proposer's or the rule's decisions; a shield in training passes the policy's)."""
        if self.config.estimate_drivers and core.sim.human:
            if self._estimator is None:
                cfg = core.config
                self._estimator = DriverEstimator(cfg.traffic, cfg.dt_s, cfg.steps_per_decision, cfg.sensing_range_m)
            self._estimator.observe(core)
        mask = np.asarray(action_mask, dtype=bool).reshape(-1, 3)
        planned = np.asarray(planned, dtype=np.int64).reshape(len(mask))
        # a proposal the mask refuses becomes a keep, which the planner then checks: it never passes on a
        # refused decision (rewarded off_road under "refuse", leaving the road under "leave_road")
        planned = np.where(mask[np.arange(len(mask)), planned], planned, KEEP)
        # during a lane change only keep is allowed, and an ended episode is frozen: nothing to look at
        choice = (mask.sum(axis=1) > 1) & (core.outcome == RUNNING)
        self.last_alive = np.full(mask.shape, np.nan)
        if not choice.any():
            return planned
        # Every (environment with a choice, decision it may take, sample) is one environment of a single imagined
        # batch: all the futures run side by side in the compiled core.
        env, action = np.nonzero(mask & choice[:, None])
        samples = self.config.samples
        env, action = np.repeat(env, samples), np.repeat(action, samples)
        salt = np.tile(np.arange(1, samples + 1), len(env) // samples)
        survived = self._survives(core.replicate(env), action, salt, env)
        alive = np.zeros(mask.shape)  # share of the imagined futures each decision survives
        np.add.at(alive, (env, action), survived)
        alive /= samples
        self.last_alive = np.where(mask & choice[:, None], alive, np.nan)
        best = alive.max(axis=1)
        fallback = np.where(alive[:, KEEP] >= best, KEEP, alive.argmax(axis=1))  # keep, else the first best change
        override = choice & (alive[np.arange(len(planned)), planned] < best)
        self.choices += int(choice.sum())
        self.overrides += int(override.sum())
        return np.where(override, fallback, planned).astype(np.int64)
