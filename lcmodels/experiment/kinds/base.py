"""What a kind of stage is: what a recipe says of it, which stages of it an experiment has and what each reads,
and what each computes. One class per kind (:class:`StageKind`), one file each in this package, collected in the
table :data:`lcmodels.experiment.kinds.KINDS` that a recipe's validation, the graph and the runner iterate.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.stages import StageContext, StageJob
from lcmodels.policy.names import needs_predictor
from lcmodels.presets import Preset, StageResult, canonical
from lcmodels.zoo import ZooEntry

GROUPS = ("data", "recipes", "references", "zoo")
"""The groups of stages, in the order a runner prefers them when several are ready: the corpus, predictor and
demonstrations; the recipes' stages; the rule-based driver and the oracle (after the recipes: the oracle's search
is slower than some training runs); the zoo."""

Needs = tuple[tuple[str, StageKey], ...]
"""``(role, key)`` of each stage a stage reads."""


ANALYTIC_STAGE = "analytic-predictor"
"""The stage (and folder) of an analytic base: ``analytic-predictor/<base>``."""


def predictor_key(source: str) -> StageKey:
    """The stage whose ``predictor.pt`` a recipe with ``predictor = source`` reads."""
    return StageKey.of("predictor") if source == "learned" else StageKey.of(ANALYTIC_STAGE, source)


@dataclass(frozen=True)
class StageKind:
    """One kind of stage. Subclassed once per kind; an instance is what a stage of the kind is made from beyond
    its key and recipe (a kind whose stages differ in more holds that in its fields).

    A recipe is a :class:`~lcmodels.experiment.recipe.Recipe` (which reads this table to validate itself, so the
    kinds name its type in words only)."""

    name: ClassVar[str]
    """The stage's name in its key (``train`` in ``hybrid-ppo/seed0/train``, ``corpus``)."""
    group: ClassVar[str] = "recipes"
    """Its stages' group (:data:`GROUPS`)."""
    trains: ClassVar[bool] = False
    """A training stage: one process of its own when stages run at once."""
    in_recipe: ClassVar[bool] = False
    """A recipe names it in ``stages`` (in the order of the table)."""
    table: ClassVar[type | None] = None
    """The type of its recipe table ``[name]``: ``dict`` (PolicyConfig fields of its stage, over ``[policy]``), a
    spec dataclass (fields of type int, float, str or bool, bounded by its ``LIMITS``), or None (no table)."""

    # -- the recipe --------------------------------------------------------------------------------------
    @classmethod
    def check(cls, recipe: Any) -> None:
        """``ValueError`` for what this kind refuses in ``recipe`` (its table, the stages around its own)."""

    @classmethod
    def settings(cls, recipe: Any) -> dict[str, Any] | None:
        """The PolicyConfig fields ``recipe`` gives a stage of this kind (None: it trains no config of its own)."""
        return None

    @classmethod
    def applies(cls, recipe: Any, preset: Preset) -> bool:
        """Whether each training seed of ``recipe`` has a stage of this kind under ``preset``."""
        return cls.in_recipe and cls.name in recipe.stages

    # -- the graph ---------------------------------------------------------------------------------------
    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        """Add this kind's stages to ``graph``: by default one per training seed of each recipe it applies to,
        reading what :meth:`needs` says."""
        for recipe, seed in graph.runs():
            if cls.applies(recipe, graph.preset):
                graph.add_recipe_stage(cls(), recipe, seed, cls.needs(graph, recipe, seed))

    @classmethod
    def needs(cls, graph: GraphBuilder, recipe: Any, seed: int) -> Needs:
        """What the stage of ``recipe`` with training seed ``seed`` reads, by role."""
        return ()

    # -- the runner --------------------------------------------------------------------------------------
    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        """The job of ``stage`` given the results ``got`` of the stages it needs, by role."""
        raise NotImplementedError(f"no job for stage {stage.key}")


@dataclass(frozen=True)
class Stage:
    """One stage: its key, the stages it reads by role, when the runner prefers it, and what it is made from."""

    key: StageKey
    needs: Needs = ()
    """``(role, key)`` of each stage it reads: ``corpus``, ``predictor``, ``demos``, ``previous`` (the recipe's
    stage before), ``follow`` (the final stage of the recipe the safety layer follows), ``policy`` (the stage whose
    policy is evaluated), ``zoo:<entry>`` (the showcase's candidates)..."""
    priority: tuple[int, ...] = ()
    """Among ready stages the runner starts the smallest first."""
    kind: StageKind | None = None
    recipe: Any = None
    """The :class:`~lcmodels.experiment.recipe.Recipe` of a recipe's stage."""
    group: str = "recipes"
    """:data:`GROUPS`: ``--skip-train`` only looks at the recipes' and the zoo's stages."""

    @property
    def trains(self) -> bool:
        """A training stage (clone, dagger, train, shielded): one process of its own when stages run at once."""
        return self.kind is not None and self.kind.trains

    def job(self, ctx: StageContext, got: Mapping[str, StageResult]) -> StageJob:
        """Its kind's job, config and inputs in their canonical form (as the store records them)."""
        if self.kind is None:
            raise ValueError(f"stage {self.key} has no kind")
        job = self.kind.job(ctx, self, got)
        job.config, job.inputs = canonical(job.config), canonical(job.inputs)
        return job


@dataclass
class GraphBuilder:
    """The stages of one experiment while its kinds add them (:func:`lcmodels.experiment.graph.build_graph`)."""

    preset: Preset
    recipes: Sequence[Any]
    """The experiment's recipes (capped; every recipe a safety layer follows among them)."""
    seeds: Mapping[str, int]
    """Training seeds of each recipe."""
    rank: Mapping[str, int]
    """The order in which the runner prefers the recipes' stages (:func:`lcmodels.experiment.graph.recipe_ranks`)."""
    kinds: Sequence[type[StageKind]]
    """The table of kinds, in order (a recipe's stages are in this order)."""
    zoo: Sequence[ZooEntry] = ()
    """The zoo's policies to evaluate."""
    load: Callable[[str], Any] | None = None
    """Reads a packaged recipe by name (what a zoo card names)."""
    stages: dict[StageKey, Stage] = field(default_factory=dict)

    def add(self, stage: Stage) -> StageKey:
        self.stages[stage.key] = stage
        return stage.key

    @staticmethod
    def priority(group: str, *rest: int) -> tuple[int, ...]:
        return (GROUPS.index(group), *rest)

    def runs(self) -> list[tuple[Any, int]]:
        """``(recipe, training seed)`` of every run of the experiment, seed by seed."""
        return [(r, seed) for seed in range(max(self.seeds.values(), default=0)) for r in self.recipes
                if seed < self.seeds[r.name]]  # fmt: skip

    def add_recipe_stage(self, kind: StageKind, recipe: Any, seed: int, needs: Needs) -> StageKey:
        """The stage of ``kind`` of ``recipe`` and training seed ``seed``, after the recipe's stages before it."""
        mine = [k.name for k in self.kinds if k.applies(recipe, self.preset)]
        at = self.priority("recipes", self.rank[recipe.name], seed, self._index(recipe), mine.index(kind.name))
        return self.add(Stage(StageKey(recipe.name, seed, kind.name), needs, at, kind, recipe, "recipes"))

    def _index(self, recipe: Any) -> int:
        return [r.name for r in self.recipes].index(recipe.name)

    # -- what a recipe's stage reads -----------------------------------------------------------------------
    @staticmethod
    def predictor(recipe: Any) -> Needs:
        """The predictor stage a recipe's prediction input reads (the trained one, or an analytic base's), when
        its policy reads predictions."""
        if not needs_predictor(recipe.obs):
            return ()
        return (("predictor", predictor_key(recipe.predictor)),)

    @staticmethod
    def previous(recipe: Any, seed: int, stage: str) -> Needs:
        """The recipe's training stage before ``stage`` (none for its first)."""
        at = recipe.stages.index(stage)
        return (("previous", StageKey(recipe.name, seed, recipe.stages[at - 1])),) if at > 0 else ()

    @staticmethod
    def final(recipe: Any, seed: int) -> Needs:
        """The recipe's final training stage, whose policy is evaluated."""
        return (("policy", StageKey(recipe.name, seed, recipe.final_stage)),)

    def follow(self, recipe: Any, seed: int) -> Needs:
        """The final stage of the recipe the safety layer follows (same training seed), when it follows one."""
        name = recipe.follows
        if not name:
            return ()
        followed = next(r for r in self.recipes if r.name == name)
        return (("follow", StageKey(name, seed, followed.final_stage)),)
