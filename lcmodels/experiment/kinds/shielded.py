"""``shielded``: fine-tuning behind the recipe's safety layer (:mod:`lcmodels.policy.shield`): more PPO steps with
the ``[train]`` settings from the previous stage's policy, the layer executing each decision and each proposal
not executed as proposed costing ``[shielded].penalty``; the layer's imagined futures follow the final policy of
the recipe ``safety.follow`` names (same training seed)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar

from lcmodels.experiment.kinds.base import GraphBuilder, Needs
from lcmodels.experiment.kinds.policy import PolicyStage
from lcmodels.experiment.layer import lookahead_settings
from lcmodels.presets import StageResult, previous_policy


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class ShieldedSpec:
    LIMITS: ClassVar[dict[str, float]] = {"timesteps": 1_000_000_000, "penalty": 1_000_000.0}

    timesteps: int = 150_000
    """PPO steps behind the safety layer, from the previous stage's policy with the ``[train]`` settings."""
    penalty: float = 100.0
    """Raw reward taken per proposal not executed as proposed (:mod:`lcmodels.policy.shield`; a collision costs
    500)."""


@dataclasses.dataclass(frozen=True)
class Shielded(PolicyStage):
    name = "shielded"
    table = ShieldedSpec

    @classmethod
    def check(cls, recipe: Any) -> None:
        spec, stages, safety = recipe.table(cls.name), recipe.stages, recipe.safety
        if cls.name in stages and (stages[0] == cls.name or safety is None or not safety.follow):
            raise ValueError("a shielded stage needs a stage before it and a [safety] table naming the recipe its "
                             "imagined futures follow (safety.follow)")  # fmt: skip
        if not math.isfinite(spec.penalty) or spec.penalty < 0:
            raise ValueError(f"shielded.penalty must be >= 0, got {spec.penalty!r}")
        if cls.name in stages and safety is not None and safety.follow == recipe.name:
            raise ValueError("a shielded stage's safety layer cannot follow the recipe itself (safety.follow)")

    @classmethod
    def settings(cls, recipe: Any) -> dict[str, Any]:
        return {**recipe.policy, **recipe.table("train"), "timesteps": recipe.table(cls.name).timesteps}

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        return (*graph.predictor(recipe), *graph.previous(recipe, seed, cls.name), *graph.follow(recipe, seed))

    def layer(self, recipe: Any, got: Mapping[str, StageResult]) -> tuple[Any, dict[str, Any]]:
        """The recipe's layer, its imagined futures following the followed recipe's final policy (``follow``)."""
        layer = dataclasses.replace(recipe.safety, follow=str(previous_policy(got["follow"])))
        return layer, {"lookahead": lookahead_settings(recipe.safety), "penalty": float(recipe.table(self.name).penalty)}
