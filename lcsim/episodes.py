"""The one episode loop: a driver drives whole episodes of a scenario, batched, and hooks see every step.

Evaluation, recording, DAgger's data collection and the analyses all run episodes the same way, so they
run them here::

    results = run_episodes(driver, config, user_seeds, batch=20, hooks=[recorder, counter])

Episode ``i`` is ``LaneChangeEnv.reset(seed=user_seeds[i])``: its episode seed is derived from the user seed
as the gymnasium environment derives it, so the same seed gives the same episode everywhere. Episodes run
``batch`` at a time in one :class:`~lcsim.core.LaneChangeCore`; an ended environment is frozen until
the batch ends. A hook (:class:`EpisodeHook`) is told when a batch starts (after the reset), before and
after every decision, and when the batch ends (also when it ends by an exception).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from lcsim.config import ScenarioConfig
from lcsim.core import RUNNING, LaneChangeCore, StepResult
from lcsim.envs import episode_seed
from lcsim.suite import check_unsealed


class EpisodeHook:
    """Something that watches the episodes of :func:`run_episodes`; every method does nothing by default."""

    def start(self, core: LaneChangeCore, user_seeds: Sequence[int], driver: Callable[..., np.ndarray]) -> None:
        """A batch begins: ``core`` was just reset, environment ``i`` runs ``user_seeds[i]``."""

    def before_step(self, core: LaneChangeCore, obs: dict[str, np.ndarray], mask: np.ndarray, actions: np.ndarray,
                    running: np.ndarray) -> None:
        """The driver decided ``actions (E,)`` from ``obs`` and ``mask (E, 3)``; ``running (E,)`` marks the
        environments whose episode goes on (the others are frozen)."""

    def after_step(self, core: LaneChangeCore, result: StepResult, running: np.ndarray) -> None:
        """The decision was simulated; ``running`` is as it was before the step."""

    def end(self, core: LaneChangeCore, failed: bool) -> None:
        """The batch is over (``failed``: it ended by an exception, the episodes are incomplete)."""


@dataclass(frozen=True, slots=True)
class EpisodeResult:
    """One finished episode."""

    user_seed: int
    episode_seed: int
    outcome: str
    """``success``, ``collision``, ``off_road`` or ``timeout``."""
    total_reward: float
    """The paper's reward summed over the episode."""
    forward_reward: float
    """The reward's go-forward component summed (``forward_per_m`` per metre travelled)."""
    decisions: int


def run_episodes(driver: Callable[..., np.ndarray], config: ScenarioConfig, user_seeds: Sequence[int], *,
                 batch: int = 16, hooks: Sequence[EpisodeHook] = (), autopilot_ego: bool = False,
                 progress: Callable[[int, int], None] | None = None, sealed: bool = False) -> list[EpisodeResult]:
    """Drive one episode per user seed with ``driver(obs, action_mask, core) -> actions (E,)``.

    Args:
        batch: episodes simulated together (the results do not depend on it).
        hooks: told of every batch and decision (see :class:`EpisodeHook`), in this order.
        autopilot_ego: the traffic's autopilot drives the ego (the driver's actions are ignored).
        progress: called with (episodes done, episodes in all) after each batch.
        sealed: the benchmark's final path's leave to run its sealed test episodes
            (:func:`lcsim.suite.check_unsealed`); without it a sealed user seed is refused (``ValueError``).

    Returns:
        One :class:`EpisodeResult` per user seed, in their order.
    """
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    check_unsealed(user_seeds, sealed=sealed)
    results: list[EpisodeResult] = []
    for start in range(0, len(user_seeds), batch):
        chunk = [int(u) for u in user_seeds[start : start + batch]]
        e = len(chunk)
        core = LaneChangeCore(config, e, autopilot_ego=autopilot_ego)
        seeds = [episode_seed(u) for u in chunk]
        core.reset(np.arange(e), seeds)
        ret, fwd, decisions = [0.0] * e, [0.0] * e, [0] * e  # (Python floats add as float64 does, with less fuss)
        started: list[EpisodeHook] = []
        failed = True
        try:
            for hook in hooks:
                hook.start(core, chunk, driver)
                started.append(hook)
            running = core.outcome == RUNNING
            live = running.tolist()
            while any(live):
                obs = core.observe()
                mask = core.action_mask()
                actions = np.asarray(driver(obs, mask, core), dtype=np.int64).reshape(e)
                for hook in hooks:
                    hook.before_step(core, obs, mask, actions, running)
                res = core.step(actions)
                rewards, forward = res.reward.tolist(), res.components["forward"].tolist()
                for i in range(e):  # (ended episodes add nothing)
                    if live[i]:
                        ret[i] += rewards[i]
                        fwd[i] += forward[i]
                        decisions[i] += 1
                for hook in hooks:
                    hook.after_step(core, res, running)
                running = core.outcome == RUNNING
                live = running.tolist()
            failed = False
        finally:
            for hook in started:
                hook.end(core, failed)
        results += [EpisodeResult(chunk[i], int(seeds[i]), str(core.outcome[i]), ret[i], fwd[i], decisions[i])
                    for i in range(e)]
        if progress is not None:
            progress(len(results), len(user_seeds))
    return results
