"""``train``: online RL (its ``[train]`` table: PolicyConfig fields over ``[policy]``), from the previous stage's
policy when there is one."""

from __future__ import annotations

import dataclasses
from typing import Any

from lcmodels.experiment.kinds.base import GraphBuilder, Needs
from lcmodels.experiment.kinds.policy import PolicyStage


@dataclasses.dataclass(frozen=True)
class Train(PolicyStage):
    name = "train"
    table = dict

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        return (*graph.predictor(recipe), *graph.previous(recipe, seed, cls.name))
