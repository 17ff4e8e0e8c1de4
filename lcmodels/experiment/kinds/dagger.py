"""``dagger``: DAgger rounds from the recipe's clone (its ``[dagger]`` table); with the safety layer as the expert
(``expert = "safety-layer"``), the final policy of the recipe ``safety.follow`` names (same training seed) behind
the layer labels the states, and a dagger stage that comes first starts from that policy."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

from lcmodels.experiment.kinds.base import GraphBuilder, Needs, Stage, StageKind
from lcmodels.experiment.kinds.demos import demos_of
from lcmodels.experiment.layer import lookahead_settings
from lcmodels.experiment.stages import StageContext, StageJob
from lcmodels.fileio import POLICY_FILE
from lcmodels.presets import StageResult, previous_policy

DAGGER_EXPERTS: tuple[str, ...] = ("oracle", "safety-layer")
"""Who labels a recipe's DAgger states: the oracle (sees the future), or the final policy of the recipe the
``[safety]`` layer follows, behind that layer."""


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class DaggerSpec:
    LIMITS: ClassVar[dict[str, float]] = {"rounds": 1_000, "episodes": 100_000, "epochs": 10_000, "seed": 100_000_000,
                                          "correction_weight": 1_000.0}  # fmt: skip

    rounds: int = 2
    episodes: int = 100
    """Episodes the policy drives per round."""
    epochs: int = 10
    seed: int = 100_000
    expert: str = "oracle"
    """One of :data:`DAGGER_EXPERTS`."""
    labels: str = "plan"
    correction_weight: float = 1.0
    """Training weight of a labelled state whose label differs from the student's own decision there, against 1
    (:func:`lcmodels.policy.dagger.dagger`)."""
    balance_actions: bool = True
    """Weight each state by the inverse square root of its label's frequency, as cloning does; False: alike."""


def stored_dagger_config(data: dict[str, Any]) -> dict[str, Any]:
    """A dagger stage's recorded config in today's form: one recorded before the correction weight and the action
    balance were settings trained at weight 1, balanced."""
    return {"correction_weight": 1.0, "balance_actions": True} | data


@dataclasses.dataclass(frozen=True)
class Dagger(StageKind):
    name = "dagger"
    trains = True
    in_recipe = True
    table = DaggerSpec

    @classmethod
    def check(cls, recipe: Any) -> None:
        spec, stages, safety = recipe.table(cls.name), recipe.stages, recipe.safety
        if spec.expert not in DAGGER_EXPERTS:
            raise ValueError(f"dagger.expert must be one of {', '.join(DAGGER_EXPERTS)}, got {spec.expert!r}")
        distils = spec.expert == "safety-layer"
        if cls.name in stages and distils and (safety is None or not safety.follow or safety.follow == recipe.name):
            raise ValueError("dagger.expert = \"safety-layer\" needs a [safety] table naming the recipe whose policy "
                             "is the expert behind it (safety.follow, another recipe)")  # fmt: skip
        if cls.name in stages and "clone" not in stages and not distils:
            raise ValueError("a dagger stage needs a clone stage before it (or the safety layer as its expert, "
                             "starting from the policy it follows)")  # fmt: skip
        if not (math.isfinite(spec.correction_weight) and spec.correction_weight > 0):
            raise ValueError(f"dagger.correction_weight must be > 0, got {spec.correction_weight!r}")
        if spec.labels not in ("plan", "winning"):
            raise ValueError(f"dagger.labels must be plan or winning, got {spec.labels!r}")

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        """Its clone and the clone's demonstrations; the followed recipe's final policy when the layer labels."""
        demos = (("demos", demos_of(recipe)),) if "clone" in recipe.stages else ()
        follow = graph.follow(recipe, seed) if recipe.table(cls.name).expert == "safety-layer" else ()
        return (*graph.predictor(recipe), *demos, *graph.previous(recipe, seed, cls.name), *follow)

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        """DAgger rounds. ``got``: ``previous`` (its clone), ``demos`` (the clone's demonstrations), and for the
        safety layer as the expert ``follow``: the followed recipe's final policy, which behind the layer labels the
        states and, when the stage comes first, is the student it starts from."""
        key, recipe = stage.key, stage.recipe
        spec = recipe.table(self.name)
        follow, demos = got.get("follow"), got.get("demos")
        start = got.get("previous") or follow
        assert start is not None
        path = key.path(ctx.out)
        seed = key.seed
        assert seed is not None
        layer, expert = None, spec.expert
        if spec.expert == "safety-layer":
            assert follow is not None and recipe.safety is not None
            layer = dataclasses.replace(recipe.safety, follow="")  # the imagined futures follow the expert's own
            expert = f"safety-layer:{previous_policy(follow)}"

        def work(keep: bool, save_wall: Callable[[], None]) -> None:
            from lcmodels.policy.dagger import dagger

            dagger(start.path, path, rounds=spec.rounds, episodes=spec.episodes, epochs=spec.epochs,
                   seed=spec.seed + 10_000 * seed, workers=1, eval_episodes=0, labels=spec.labels,
                   expert=expert, correction_weight=spec.correction_weight, balance_actions=spec.balance_actions,
                   expert_safety=layer,
                   resume=keep and (path / "dagger.json").exists(),
                   demonstrations=demos.path if demos is not None else None,
                   progress=lambda m: ctx.emit(f"[{key}] {m}"))  # fmt: skip

        cfg = dataclasses.asdict(spec) | {"training_seed": seed}
        inputs = {"clone": start.digest}
        if layer is not None:
            assert follow is not None
            cfg["safety"] = lookahead_settings(recipe.safety)
            inputs["expert"] = follow.digest
        return StageJob(cfg, inputs, lambda: [f"round{spec.rounds}/{POLICY_FILE}", "dagger.json"], work,
                        upgrade=stored_dagger_config)
