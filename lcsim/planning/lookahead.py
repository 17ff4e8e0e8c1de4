"""The safety layer: a driver's decision checked against futures imagined in copies of the simulator (blind and
perceived, a layer that needs no privileged state; not blind, a privileged layer, an upper reference)."""

from __future__ import annotations

import numpy as np

from lcsim.core import KEEP, RUNNING, SUCCESS, TIMEOUT, LaneChangeCore
from lcsim.drivers import Driver, RuleBasedDriver
from lcsim.planning.perception import perceive, redraw_future
from lcsim.planning.report import DecisionReport, ImaginedPaths, check_imagined_paths
from lcsim.planning.safety import SafetyLayerConfig


def _driver_name(driver: Driver) -> str:
    return str(getattr(driver, "name", type(driver).__name__))


class LookaheadDriver:
    """The safety layer in front of a driver: each decision checked against futures imagined in copies of the
    simulator (:class:`~lcsim.planning.SafetyLayerConfig` says how).

    Before each decision it copies every environment that has a choice (with its random state) once per
    decision it may take (and per sample), side by side in one batch (:meth:`LaneChangeCore.replicate`),
    turns each copy into the future it imagines (:meth:`imagine`), applies right / keep / left in the copies,
    follows the driver ``rule`` for ``horizon_decisions`` more decisions and keeps the proposed decision unless
    another survives more of the imagined futures; then it takes the best surviving one (keep first). Blind and
    perceived, it needs no privileged state: one step of policy improvement over its rollout driver that a
    policy could in principle learn (a teacher for DAgger). Not blind, it sees exactly what will happen, which
    no policy can: an *upper reference* for what the scenario allows, not a baseline to beat.

    A rollout driver that reads the observation sets ``needs_observation = True``; it gets the imagined
    copy's observation, which has no image (the copies do not render).

    ``proposer``, when given, makes the decision the layer checks instead of ``rule``: the layer in front of a
    driver that reads what the imagined futures cannot show (a policy that reads the image), with ``rule`` as
    the model of how the ego drives on after the decision.

    After each decision :attr:`last_report` says what the layer scored for each candidate (a
    :class:`~lcsim.planning.DecisionReport`); with ``imagined_paths = K`` (default 0) it also keeps the ego's path in
    the first ``K`` imagined futures of each candidate, which changes no decision.
    """

    def __init__(self, config: SafetyLayerConfig | None = None, rule: Driver | None = None,
                 proposer: Driver | None = None, *, imagined_paths: int = 0) -> None:
        self.config = config or SafetyLayerConfig()
        self.rule = rule or RuleBasedDriver()
        self.proposer = proposer
        self.imagined_paths = imagined_paths
        self.choices = self.overrides = 0  # decisions with a choice seen, and those where the layer overrode
        self.last_alive: np.ndarray | None = None
        """``(E, 3)`` after each call: the share of imagined futures each decision survived, NaN where it was
        not imagined (not allowed, or no choice to make): the labels a learned safety critic is fitted to."""
        self.last_report: DecisionReport | None = None
        """After each call: the scores (:attr:`last_alive`), the proposal, the decision executed, whether the layer
        overrode the proposal, and the imagined paths kept (:attr:`imagined_paths`)."""
        self._observe = bool(getattr(self.rule, "needs_observation", False))
        self._prediction: np.ndarray | None = None

    @property
    def name(self) -> str:  # type: ignore[override]
        """``lookahead``, ``lookahead-blind`` or ``lookahead-perceived``, then the driver followed (unless the
        rule) and, first, the proposer."""
        name = "lookahead-perceived" if self.config.perceived else "lookahead-blind" if self.config.blind else "lookahead"
        if not isinstance(self.rule, RuleBasedDriver) or self.proposer is not None:
            name += f"-{_driver_name(self.rule)}"
        return name if self.proposer is None else f"{_driver_name(self.proposer)}+{name}"

    @property
    def imagined_paths(self) -> int:
        """Imagined futures per candidate whose ego path :attr:`last_report` keeps (0: none; at most
        :data:`~lcsim.planning.report.MAX_IMAGINED_FUTURES`, and there are ``config.samples``); ``ValueError`` for
        another value."""
        return self._imagined_paths

    @imagined_paths.setter
    def imagined_paths(self, futures: int) -> None:
        self._imagined_paths = check_imagined_paths(futures)

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
        return self._imagine_futures(future, actions, salt, rows)[0]

    def _imagine_futures(self, future: LaneChangeCore, actions: np.ndarray, salt: int | np.ndarray, rows: np.ndarray,
                         track: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """:meth:`_survives`, and the ego's (x, y) in the copies ``track`` ((B,) bool; None: none): ``(survived (B,),
        points (T, Bt, 2), counts (Bt,))``, the points before the decision and after each decision imagined
        (``T <= horizon_decisions + 2``), of which the first ``counts`` of each copy count (up to the end of its
        imagined episode). Reading the copies changes nothing in them."""
        self.imagine(future, salt, rows)
        tracked = np.flatnonzero(track) if track is not None else np.zeros(0, dtype=np.int64)
        points = [np.stack([future.sim.x[tracked, 0], future.sim.y[tracked, 0]], axis=-1)]
        counts = np.zeros(len(tracked), dtype=np.int64)  # 0: still running
        future.step(actions)
        for k in range(self.config.horizon_decisions + 1):
            if len(tracked):
                points.append(np.stack([future.sim.x[tracked, 0], future.sim.y[tracked, 0]], axis=-1))
                counts[(counts == 0) & (future.outcome[tracked] != RUNNING)] = len(points)
            if k == self.config.horizon_decisions or (future.outcome != RUNNING).all():
                break  # ended environments stay frozen; nothing left to see
            obs = future.observe() if self._observe else {}
            future.step(self.rule(obs, future.action_mask(), future))
        counts[counts == 0] = len(points)
        return np.isin(future.outcome, (RUNNING, SUCCESS, TIMEOUT)), np.stack(points), counts

    def imagine(self, future: LaneChangeCore, salt: int | np.ndarray, rows: np.ndarray) -> None:
        """Turn ``future``, a fresh copy of the environments ``rows`` of the real core, into the future the layer
        imagines, before the candidate decisions are applied in it: blind, the traffic's random draws redrawn with
        ``salt`` (one, or one per copy); perceived, reduced to what the ego's sensors show. A layer that imagines
        otherwise overrides this (the research variants in ``experiments/imagined_drivers``)."""
        if self.config.blind:
            redraw_future(future.sim, salt)
        if self.config.perceived:
            perceive(future.sim, future.config.sensing_range_m)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        mask = np.asarray(action_mask, dtype=bool).reshape(-1, 3)
        decider = self.proposer or self.rule
        planned = decider(obs, mask, core)
        self._prediction = getattr(decider, "last_prediction", None)
        return self.check(planned, mask, core)

    def check(self, planned: np.ndarray, action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        """The decisions executed for the proposals ``planned`` in ``core``'s environments: each kept if no
        surviving alternative does better in the imagined futures (what :meth:`__call__` does with the
        proposer's or the rule's decisions; training behind the layer passes the policy's)."""
        mask = np.asarray(action_mask, dtype=bool).reshape(-1, 3)
        proposed = np.asarray(planned, dtype=np.int64).reshape(len(mask)).copy()
        # a proposal the mask refuses becomes a keep, which the layer then checks: it never passes on a
        # refused decision (rewarded off_road under "refuse", leaving the road under "leave_road")
        planned = np.where(mask[np.arange(len(mask)), proposed], proposed, KEEP)
        # during a lane change only keep is allowed, and an ended episode is frozen: nothing to look at
        choice = (mask.sum(axis=1) > 1) & (core.outcome == RUNNING)
        self.last_alive = np.full(mask.shape, np.nan)
        if not choice.any():
            self._report(proposed, planned, np.zeros(len(mask), dtype=bool))
            return planned
        # Every (environment with a choice, decision it may take, sample) is one environment of a single imagined
        # batch: all the futures run side by side in the compiled core.
        env, action = np.nonzero(mask & choice[:, None])
        samples = self.config.samples
        env, action = np.repeat(env, samples), np.repeat(action, samples)
        salt = np.tile(np.arange(1, samples + 1), len(env) // samples)
        track = salt <= self.imagined_paths if self.imagined_paths else None
        if track is None:  # through _survives, the hook a research variant overrides (experiments/)
            survived, points, counts = self._survives(core.replicate(env), action, salt, env), None, None
        else:
            survived, points, counts = self._imagine_futures(core.replicate(env), action, salt, env, track)
        alive = np.zeros(mask.shape)  # share of the imagined futures each decision survives
        np.add.at(alive, (env, action), survived)
        alive /= samples
        self.last_alive = np.where(mask & choice[:, None], alive, np.nan)
        best = alive.max(axis=1)
        fallback = np.where(alive[:, KEEP] >= best, KEEP, alive.argmax(axis=1))  # keep, else the first best change
        override = choice & (alive[np.arange(len(planned)), planned] < best)
        self.choices += int(choice.sum())
        self.overrides += int(override.sum())
        executed = np.where(override, fallback, planned).astype(np.int64)
        paths = None
        if track is not None and points is not None and counts is not None:
            xy = np.concatenate([np.zeros((0, 2)), *(points[:c, i] for i, c in enumerate(counts))])
            paths = ImaginedPaths(env=env[track], action=action[track], future=salt[track] - 1,
                                  survived=survived[track].astype(bool), xy=xy,
                                  offsets=np.concatenate([[0], np.cumsum(counts)]))  # fmt: skip
        self._report(proposed, executed, override, paths)
        return executed

    def _report(self, proposed: np.ndarray, executed: np.ndarray, overridden: np.ndarray,
                paths: ImaginedPaths | None = None) -> None:  # fmt: skip
        assert self.last_alive is not None
        self.last_report = DecisionReport(scores=self.last_alive, proposed=proposed, executed=executed,
                                          overridden=overridden, paths=paths)  # fmt: skip


def rule_behind_layer(layer: SafetyLayerConfig, spec: str = "safety-layer:rule") -> LookaheadDriver:
    """The rule-based driver behind the safety layer ``layer`` (the driver spec ``spec``, named in errors): its
    imagined futures follow the rule too; ``ValueError`` when ``layer`` names another driver to follow."""
    if layer.follow not in ("", "rule"):
        raise ValueError(f"a driver to follow applies to a policy behind the safety layer, not to {spec}")
    return LookaheadDriver(layer, rule=RuleBasedDriver())
