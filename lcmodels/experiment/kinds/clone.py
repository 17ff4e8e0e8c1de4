"""``clone``: behaviour cloning of the recipe's demonstrations (its ``[clone]`` table: PolicyConfig fields over
``[policy]``); the first stage of a recipe that has one."""

from __future__ import annotations

import dataclasses
from typing import Any

from lcmodels.experiment.kinds.base import GraphBuilder, Needs
from lcmodels.experiment.kinds.demos import demos_of
from lcmodels.experiment.kinds.policy import PolicyStage


@dataclasses.dataclass(frozen=True)
class Clone(PolicyStage):
    name = "clone"
    table = dict
    online = False
    warm_starts = True

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        return (*graph.predictor(recipe), ("demos", demos_of(recipe)), *graph.previous(recipe, seed, cls.name))
