"""``zoo-safety/<entry>``: a zoo policy behind the safety layer its card was measured with (the imagined futures
following the zoo's entry of the recipe's ``safety.follow``), on the test episodes alone: for each entry whose card
has a layer and whose followed policy the zoo holds."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Stage, StageKind
from lcmodels.experiment.layer import card_lookahead
from lcmodels.experiment.stages import StageContext, StageJob, evaluation_job
from lcmodels.policy.driverspec import policy_spec
from lcmodels.presets import StageResult
from lcmodels.zoo import ZooEntry


@dataclasses.dataclass(frozen=True)
class ZooSafety(StageKind):
    name = "zoo-safety"
    group = "zoo"

    entry: ZooEntry | None = None
    """The zoo's entry evaluated behind its layer."""
    follow: ZooEntry | None = None
    """The zoo's entry the layer follows (None: the policy itself)."""

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        if not graph.preset.zoo:
            return
        assert graph.load is not None, "the zoo's cards name their recipes"
        by_name = {e.name: e for e in graph.zoo}
        for i, entry in enumerate(graph.zoo):
            if card_lookahead(entry.card) is None:
                continue
            try:
                recipe = graph.load(str(entry.card.get("recipe", "")))
            except ValueError:
                continue
            f = recipe.follows
            if recipe.safety is None or (f and f not in by_name):
                continue
            graph.add(Stage(StageKey.of(cls.name, entry.name), priority=graph.priority("zoo", 1, i),
                            kind=cls(entry, by_name[f] if f else None), group="zoo"))  # fmt: skip

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        entry, follow = self.entry, self.follow
        assert entry is not None
        inputs = {"policy": entry.sha256} | ({"follow": follow.sha256} if follow is not None else {})
        settings = card_lookahead(entry.card)
        driver = policy_spec(entry.policy, behind=settings or {}, follow=follow.policy if follow is not None else None)
        return evaluation_job(ctx, stage.key, driver, inputs, predictor=entry.predictor,
                              lookahead=settings, label=f"lookahead-blind:zoo:{entry.name}",
                              test_only=True)  # fmt: skip
