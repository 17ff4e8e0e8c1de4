"""The kinds of stage an experiment is made of, one class per kind and one file each, in one table.

:data:`KINDS` is the table, in the order of the experiment: the data (corpus, predictor and its analytic bases,
demonstrations), a recipe's training stages (the order its ``stages`` list keeps), the evaluations of its final
policy, the references and the benchmark, the zoo. A recipe validates itself against it
(:mod:`lcmodels.experiment.recipe`: the stages it may name, the table of each and its rules), the graph asks each
kind for its stages and what each reads (:func:`lcmodels.experiment.graph.build_graph`), and the runner asks a
stage's kind for its job. A new kind of stage is a file here and a line in the table.
"""

from __future__ import annotations

from lcmodels.experiment.kinds.base import GROUPS, GraphBuilder, Needs, Stage, StageKind
from lcmodels.experiment.kinds.bench import Bench
from lcmodels.experiment.kinds.clone import Clone
from lcmodels.experiment.kinds.corpus import Corpus
from lcmodels.experiment.kinds.dagger import DAGGER_EXPERTS, Dagger, DaggerSpec
from lcmodels.experiment.kinds.demos import Demos, DemoSpec
from lcmodels.experiment.kinds.evaluation import Eval
from lcmodels.experiment.kinds.policy import PolicyStage
from lcmodels.experiment.kinds.predictor import AnalyticPredictor, Predictor
from lcmodels.experiment.kinds.reference import Oracle, Rule
from lcmodels.experiment.kinds.safety import Safety
from lcmodels.experiment.kinds.shielded import Shielded, ShieldedSpec
from lcmodels.experiment.kinds.showcase import Showcase
from lcmodels.experiment.kinds.suite import Suite
from lcmodels.experiment.kinds.train import Train
from lcmodels.experiment.kinds.zoo import Zoo
from lcmodels.experiment.kinds.zoo_safety import ZooSafety

KINDS: tuple[type[StageKind], ...] = (Corpus, Predictor, AnalyticPredictor, Demos, Clone, Dagger, Train, Shielded, Eval, Safety, Suite,
                                      Bench, Rule, Oracle, Zoo, ZooSafety, Showcase)  # fmt: skip
"""Every kind of stage, in the experiment's order."""
KIND: dict[str, type[StageKind]] = {k.name: k for k in KINDS}
"""The kinds by the stage name in their keys."""
TRAINING_STAGES: tuple[str, ...] = tuple(k.name for k in KINDS if k.in_recipe)
"""The stages a recipe may name in ``stages``, in the order it names them."""

__all__ = [
                                      "DAGGER_EXPERTS",
                                      "GROUPS",
                                      "KIND",
                                      "KINDS",
                                      "TRAINING_STAGES",
                                      "AnalyticPredictor",
                                      "Bench",
                                      "Clone",
                                      "Corpus",
                                      "Dagger",
                                      "DaggerSpec",
                                      "DemoSpec",
                                      "Demos",
                                      "Eval",
                                      "GraphBuilder",
                                      "Needs",
                                      "Oracle",
                                      "PolicyStage",
                                      "Predictor",
                                      "Rule",
                                      "Safety",
                                      "Shielded",
                                      "ShieldedSpec",
                                      "Showcase",
                                      "Stage",
                                      "StageKind",
                                      "Suite",
                                      "Train",
                                      "Zoo",
                                      "ZooSafety",
]
