"""``safety``: a recipe's final policy behind its safety layer (its ``[safety]`` table), evaluated; the layer's
imagined futures follow the final policy of the recipe ``safety.follow`` names (same training seed), or the
policy itself."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from lcmodels.experiment.kinds.base import GraphBuilder, Needs, Stage, StageKind
from lcmodels.experiment.layer import lookahead_settings
from lcmodels.experiment.stages import StageContext, StageJob, evaluation_job, predictor_file
from lcmodels.policy.driverspec import policy_spec
from lcmodels.presets import Preset, StageResult, previous_policy


@dataclasses.dataclass(frozen=True)
class Safety(StageKind):
    name = "safety"

    @classmethod
    def applies(cls, recipe: Any, preset: Preset) -> bool:
        return recipe.safety is not None

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        return (*graph.predictor(recipe), *graph.final(recipe, seed), *graph.follow(recipe, seed))

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        final, follow = got["policy"], got.get("follow")
        inputs = {"policy": final.digest} | ({"follow": follow.digest} if follow is not None else {})
        settings = lookahead_settings(stage.recipe.safety)
        driver = policy_spec(previous_policy(final), behind=settings,
                             follow=previous_policy(follow) if follow is not None else None)
        return evaluation_job(ctx, stage.key, driver, inputs, predictor=predictor_file(stage.recipe, got),
                              lookahead=settings,
                              label="lookahead-blind:policy")  # fmt: skip
