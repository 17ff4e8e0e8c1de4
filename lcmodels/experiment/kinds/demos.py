"""``demos/<key>``: the demonstrations a recipe's clone learns from (with images), recorded once however many
recipes clone the same ones; the recipe's ``[demos]`` table says whose and how many."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Stage, StageKind
from lcmodels.experiment.stages import StageContext, StageJob, record_job
from lcmodels.presets import StageResult, demos_key


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class DemoSpec:
    LIMITS: ClassVar[dict[str, int]] = {"episodes": 100_000, "seed": 100_000_000}

    driver: str = "oracle"
    """Who drives the demonstrations (an lcsim driver name)."""
    episodes: int = 400
    seed: int = 5000
    """First user seed (the demonstrations' seeds are kept apart from training's and evaluation's)."""


def demos_of(recipe: Any) -> StageKey:
    """The demonstrations stage whose episodes ``recipe``'s clone learns from."""
    return StageKey.of("demos", demos_key(recipe.table("demos")))


@dataclasses.dataclass(frozen=True)
class Demos(StageKind):
    name = "demos"
    group = "data"
    table = DemoSpec

    spec: DemoSpec = DemoSpec()

    @classmethod
    def check(cls, recipe: Any) -> None:
        from lcsim.registry import DRIVER_NAMES

        spec = recipe.table("demos")
        if "clone" in recipe.stages and spec.driver not in DRIVER_NAMES:
            raise ValueError(f"demos.driver must be one of {', '.join(DRIVER_NAMES)}, got {spec.driver!r}")

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        """One stage per distinct ``[demos]`` of the recipes that clone, in recipe order."""
        for r in graph.recipes:
            key = demos_of(r)
            if "clone" in r.stages and key not in graph.stages:
                n = sum(k.stage == cls.name for k in graph.stages)
                graph.add(Stage(key, priority=graph.priority("data", 2, n), kind=cls(r.table("demos")), group="data"))

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        """The demonstrations (with images) on the preset's scenario, as a hybrid policy sees it."""
        from lcmodels.policy.config import PolicyConfig
        from lcmodels.policy.plan import policy_scenario

        spec = self.spec
        config = policy_scenario(PolicyConfig(scenario=ctx.preset.scenario, obs="hybrid"))
        seeds = list(range(spec.seed, spec.seed + spec.episodes))
        return record_job(ctx, stage.key, config, seeds, spec.driver, ctx.preset.scenario, True)
