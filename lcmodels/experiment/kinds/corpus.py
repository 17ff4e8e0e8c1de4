"""``corpus``: the autopilot trajectory corpus the predictor learns from (MCAP, no images)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Stage, StageKind
from lcmodels.experiment.stages import StageContext, StageJob, record_job
from lcmodels.presets import StageResult


@dataclasses.dataclass(frozen=True)
class Corpus(StageKind):
    name = "corpus"
    group = "data"

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        graph.add(Stage(StageKey.of(cls.name), priority=graph.priority("data", 0), kind=cls(), group="data"))

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        """The preset's corpus episodes (``corpus_episodes`` from ``corpus_seed``, ``corpus_steps`` long)."""
        from lcsim.config import corpus_scenario

        p = ctx.preset
        config = corpus_scenario()
        if p.corpus_steps is not None:
            config = dataclasses.replace(config, time_limit_s=p.corpus_steps * config.dt_s)
        seeds = list(range(p.corpus_seed, p.corpus_seed + p.corpus_episodes))
        return record_job(ctx, stage.key, config, seeds, "autopilot", "corpus", False)
