"""``<recipe>/seed<k>/suite``: a recipe's final policy on every road of the preset's benchmark suite; and
``suite/oracle``, ``suite/rule``: each road's ceiling and floor (lc-bench's cells, on validation episodes)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Needs, Stage, StageKind
from lcmodels.experiment.stages import StageContext, StageJob, predictor_file, suite_job
from lcmodels.policy.driverspec import parse_driver_spec, policy_spec
from lcmodels.presets import ORACLE_KEY, RULE_KEY, Preset, StageResult, previous_policy

REFERENCES = (ORACLE_KEY, RULE_KEY)
"""The drivers measured on the suite besides the recipes' policies: each road's ceiling, then its floor."""


@dataclasses.dataclass(frozen=True)
class Suite(StageKind):
    name = "suite"

    @classmethod
    def applies(cls, recipe: Any, preset: Preset) -> bool:
        return bool(preset.suite)

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        """When the preset names a suite: every recipe's runs, and the references."""
        if not graph.preset.suite:
            return
        super().add(graph)
        for j, who in enumerate(REFERENCES):
            graph.add(Stage(StageKey.of(cls.name, who), priority=graph.priority("references", 2, j), kind=cls(),
                            group="references"))  # fmt: skip

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        return (*graph.predictor(recipe), *graph.final(recipe, seed))

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        key = stage.key
        if key.recipe is None:
            assert key.part is not None
            return suite_job(ctx, key, parse_driver_spec(key.part), {}, group=key.part)
        final = got["policy"]
        return suite_job(ctx, key, policy_spec(previous_policy(final)), {"policy": final.digest}, group=key.recipe,
                         predictor=predictor_file(stage.recipe, got))  # fmt: skip
