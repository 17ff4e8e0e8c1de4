"""``rule`` and ``oracle``: the rule-based driver (the floor) and the oracle (it sees the future: the ceiling of
any policy) on the validation and test episodes."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Stage, StageKind
from lcmodels.experiment.stages import StageContext, StageJob, evaluation_job
from lcmodels.policy.driverspec import parse_driver_spec
from lcmodels.presets import ORACLE_KEY, RULE_KEY, Preset, StageResult


@dataclasses.dataclass(frozen=True)
class Rule(StageKind):
    name = RULE_KEY
    group = "references"
    order = 0
    """Its place among the references."""

    @classmethod
    def wanted(cls, preset: Preset) -> bool:
        return True

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        if cls.wanted(graph.preset):
            graph.add(Stage(StageKey.of(cls.name), priority=graph.priority("references", cls.order), kind=cls(),
                            group="references"))  # fmt: skip

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        """The driver on the preset's scenario, as a pure policy sees it."""
        from lcmodels.policy.config import PolicyConfig
        from lcmodels.policy.plan import policy_scenario

        config = policy_scenario(PolicyConfig(scenario=ctx.preset.scenario, obs="pure"))
        return evaluation_job(ctx, stage.key, parse_driver_spec(stage.key.stage), {}, scenario=config)


@dataclasses.dataclass(frozen=True)
class Oracle(Rule):
    name = ORACLE_KEY
    order = 1

    @classmethod
    def wanted(cls, preset: Preset) -> bool:
        return preset.oracle
