"""``eval``: a recipe's final policy on the validation seeds and the test episodes."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from lcmodels.experiment.kinds.base import GraphBuilder, Needs, Stage, StageKind
from lcmodels.experiment.stages import StageContext, StageJob, evaluation_job, predictor_file
from lcmodels.policy.driverspec import policy_spec
from lcmodels.presets import Preset, StageResult, previous_policy


@dataclasses.dataclass(frozen=True)
class Eval(StageKind):
    name = "eval"

    @classmethod
    def applies(cls, recipe: Any, preset: Preset) -> bool:
        return True

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        return (*graph.predictor(recipe), *graph.final(recipe, seed))

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        final = got["policy"]
        return evaluation_job(ctx, stage.key, policy_spec(previous_policy(final)), {"policy": final.digest}, label="policy",
                              predictor=predictor_file(stage.recipe, got))  # fmt: skip
