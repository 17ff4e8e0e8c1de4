"""Non-learning drivers: a rule-based gap-acceptance lane changer, keep-lane, random.

The planners (the lookahead and the oracle) live in :mod:`lcsim.planning`; :mod:`lcsim.registry` names
them all (``make_driver("oracle")``).

A driver is called once per decision as ``driver(obs, action_mask, core) -> actions (E,)`` with the
batched observation, the ``(E, 3)`` action mask and the :class:`~lcsim.core.LaneChangeCore` (for
drivers that use privileged state), so one driver serves the single env, the vector env and the
recorder, and is evaluated exactly like a learned policy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lckit.config import require_non_negative, require_positive
from lcsim import kernel
from lcsim.core import KEEP, LaneChangeCore


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
        require_positive(self, "horizon_s", "trigger_time_s", "trigger_gap_m", "min_front_gap_m", "min_front_time_s",
                  "rear_time_s")
        require_non_negative(self, "min_rear_gap_m", "gain_s", "urgent_time_s", "urgent_rear_gap_m")


class RuleBasedDriver:
    """Changes lane when the leader gets close and a side lane offers a safe, larger gap.

    Works on the exact lane gaps around the ego (:meth:`LaneChangeCore.lane_gaps`): the perception a
    cost-function planner is usually given. It never brakes (the ego does not, by default). Compiled
    (:func:`lcsim.kernel.rule_actions`): the planners run it in every imagined future.
    """

    name = "rule"

    def __init__(self, config: RuleDriverConfig | None = None) -> None:
        self.config = config or RuleDriverConfig()
        self._params = np.array([getattr(self.config, name) for name in kernel.RULE_NAMES], dtype=np.float64)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        sim = core.sim
        mask = np.ascontiguousarray(np.asarray(action_mask, dtype=bool).reshape(-1, 3))
        actions = np.empty(core.num_envs, dtype=np.int64)
        kernel.rule_actions(self._params, mask, sim.vf, sim.vi, sim.road.num_lanes, actions)
        return actions


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
