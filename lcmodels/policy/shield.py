"""Training behind the safety layer: PPO steps in which the safety layer executes the policy's decisions.

Post-posed shielding with a penalty (Alshiekh et al., "Safe reinforcement learning via shielding", 2018): the
policy proposes, the safety layer (:meth:`lcsim.planning.LookaheadDriver.check`) executes its proposal
or overrides it, and each proposal not executed as proposed costs the policy ``penalty`` raw
reward (a collision costs 500): one the layer overrode, and a lane change the action mask refuses, which the
layer turns into a keep (towards a lane the road does not have, or while a change is under way, when the
simulator ignores the decision). The policy trains unmasked, so it learns to propose what the layer executes.
The training returns in ``progress.csv`` include the penalties. The policy learns what the layer lets through instead of relying on it; behind the same
layer at evaluation it proposes fewer decisions that lead into states with none left that survives.

``lc-experiment`` runs it as a recipe's ``shielded`` stage (:mod:`lcmodels.experiment.recipe`); :func:`shield_for` builds
the layer of a recipe's ``[safety]`` table (a :class:`~lcsim.planning.SafetyLayerConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from lcmodels.policy.driverspec import parse_driver_spec
from lcsim.config import ScenarioConfig
from lcsim.planning import LookaheadDriver, SafetyLayerConfig
from lcsim.sb3 import LaneChangeSB3VecEnv


@dataclass
class Shield:
    """The safety layer between a training policy and the road, and what it did."""

    layer: LookaheadDriver
    """It checks the policy's proposals (:meth:`~lcsim.planning.LookaheadDriver.check`) and counts its choices
    and overrides."""
    penalty: float
    """Raw reward taken per proposal not executed as proposed (before the run's reward scale)."""
    replaced: int = 0
    """Proposals not executed as proposed, the penalised ones: the overrides and the lane changes the mask
    refuses."""

    def __post_init__(self) -> None:
        if isinstance(self.penalty, bool) or not isinstance(self.penalty, int | float) or not (
                0 <= self.penalty < float("inf")):  # fmt: skip
            raise ValueError(f"the penalty of training behind the safety layer must be a number >= 0, got "
                             f"{self.penalty!r}")  # fmt: skip
        if not self.layer.config.blind:
            raise ValueError("training behind the safety layer needs a blind layer (safety.blind = true: one that "
                             "sees the future is privileged)")  # fmt: skip

    @property
    def choices(self) -> int:
        """Decisions the layer saw with a choice to make."""
        return self.layer.choices

    @property
    def overrides(self) -> int:
        """Of those, the proposals it overrode."""
        return self.layer.overrides

    def execute(self, proposed: np.ndarray, core: Any) -> tuple[np.ndarray, np.ndarray]:
        """The decisions the layer executes for ``proposed`` in ``core``'s environments, and where they differ
        from the proposals (the penalised environments)."""
        proposed = np.asarray(proposed, dtype=np.int64).reshape(-1)
        executed = self.layer.check(proposed, core.action_mask(), core)
        replaced = executed != proposed
        self.replaced += int(replaced.sum())
        return executed, replaced

    def counts(self) -> dict[str, int]:
        return {"choices": self.choices, "overrides": self.overrides, "replaced": self.replaced}


class ShieldedSB3VecEnv(LaneChangeSB3VecEnv):
    """:class:`~lcsim.sb3.LaneChangeSB3VecEnv` with ``shield`` between the policy and the road: the layer's
    decision is executed, and the reward of an environment whose proposal was not executed is lowered by the
    shield's penalty."""

    def __init__(self, num_envs: int, config: ScenarioConfig | None, shield: Shield) -> None:
        super().__init__(num_envs, config)
        self.shield = shield

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async() first"
        self._actions, replaced = self.shield.execute(self._actions, self.venv.core)
        obs, reward, dones, infos = super().step_wait()
        return obs, (reward - self.shield.penalty * replaced).astype(np.float32), dones, infos


def shield_for(safety: SafetyLayerConfig, penalty: float, scenario: ScenarioConfig,
               predictor: str | None = None) -> Shield:  # fmt: skip
    """The shield of a recipe's safety layer ``safety`` (blind), whose imagined futures follow ``safety.follow``:
    a policy file that does not read the image, or a built-in driver (a recipe's name resolved to its policy by
    the caller)."""
    from lcmodels.policy.evaluate import _follower

    if not safety.follow:
        raise ValueError("training behind the safety layer needs the driver its imagined futures follow "
                         "(safety.follow)")  # fmt: skip
    follow = parse_driver_spec(safety.follow)  # a training config stores the follower as its words
    return Shield(LookaheadDriver(safety, rule=_follower(follow, scenario, predictor, "cpu")), float(penalty))


__all__ = ["Shield", "ShieldedSB3VecEnv", "shield_for"]
