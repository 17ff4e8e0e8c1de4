"""``zoo/<entry>``: a policy of the zoo (:mod:`lcmodels.zoo`) on the validation and test episodes, when the preset
evaluates the zoo."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Stage, StageKind
from lcmodels.experiment.stages import StageContext, StageJob, evaluation_job
from lcmodels.policy.driverspec import policy_spec
from lcmodels.presets import StageResult
from lcmodels.zoo import ZooEntry


@dataclasses.dataclass(frozen=True)
class Zoo(StageKind):
    name = "zoo"
    group = "zoo"

    entry: ZooEntry | None = None
    """The zoo's entry evaluated."""

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        if graph.preset.zoo:
            for i, entry in enumerate(graph.zoo):
                graph.add(Stage(StageKey.of(cls.name, entry.name), priority=graph.priority("zoo", 0, i),
                                kind=cls(entry), group="zoo"))  # fmt: skip

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        e = self.entry
        assert e is not None
        return evaluation_job(ctx, stage.key, policy_spec(e.policy), {"policy": e.sha256}, predictor=e.predictor,
                              label=f"zoo:{e.name}")  # fmt: skip
