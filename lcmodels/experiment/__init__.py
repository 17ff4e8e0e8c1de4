"""``lc-experiment``: the paper's tables and figures end to end, as a graph of resumable stages.

An experiment directory ``DIR`` holds one directory per stage::

    experiment.json              preset, seeds and command of the last invocation (marks DIR as ours)
    stages/                      one record per stage (:mod:`.store`)
    corpus/                      autopilot trajectory corpus (MCAP)                   -> predictor
    predictor/                   predictor.pt, metrics.json (Table II)                -> prediction/hybrid policies
    analytic-predictor/<base>/   predictor.pt of an analytic base (no training)       -> recipes naming predictor = base
    demos/<key>/                 demonstrations (the oracle's by default) with images -> cloning
    rule/, oracle/               the references on the validation and test episodes
    policies/<recipe>/seed<k>/   clone, dagger, train, shielded (lcmodels.policy.train run directories), eval, safety,
                                 suite (a preset with a suite: the final policy on its roads, suite.json + cells/)
    suite/oracle/, suite/rule/   (a preset with a suite) each road's ceiling and floor on the same episodes
    bench/                       (a preset with a suite) BENCH.md, bench.json and figures of every run, by recipe
    zoo/, zoo-safety/, showcase/ (quick) the zoo's policies on the test episodes
    REPORT.md, fig5_safe_forward.png, fig6_total_reward.png

The package, bottom up:

- :mod:`.keys`: :class:`StageKey`, ``(recipe, seed, stage)``, with the stage's name, directory and record name;
- :mod:`.store`: the records of complete and pending stages, the directory's lock and its invocations;
- :mod:`.stages`: what stages share: where they run, what a stage's job is (config, inputs, work), and the jobs
  several kinds are made of (recording, evaluating, measuring on the suite);
- :mod:`.kinds`: every kind of stage, one class and one file each (its recipe table and rules, the stages it adds
  to the graph and what each reads, its job), in one table :data:`KINDS`;
- :mod:`.recipe`: :class:`Recipe`, a recipe file, validated against that table;
- :mod:`.graph`: every stage of the preset and its recipes built before anything runs, each kind adding its own;
  the plan and the report's list of final policies are queries of it;
- :mod:`.runner`: runs the ready stages in dependency order, here, in ``--jobs`` processes or on Ray;
- :mod:`.core`: :class:`Experiment` and :func:`run_experiment`; :mod:`.entries`: a final policy as a zoo entry.

Resumability. A rerun skips a stage whose record matches its current config and inputs and whose outputs still
hash to the recorded values; anything else is redone. A stage interrupted with the same config and inputs
continues from what it left (missing episodes are recorded, a policy resumes from its last checkpoint); a stage
whose config or inputs changed starts from an empty directory. A policy whose only change is a larger
``timesteps`` (or other evaluation settings) continues training instead of starting over. ``DIR/.lock`` keeps a
second invocation out of a directory in use.

The sealed test figures of the report come from the ledger (``lc-bench --final`` measures them); the experiment
evaluates nothing there: the report looks up the policies of the graph's final stages in it.
"""

from lcmodels.experiment.core import Experiment, ExperimentResult, Progress, run_experiment
from lcmodels.experiment.graph import GraphCycle, StageGraph, build_graph, recipe_ranks
from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds import KINDS, Stage, StageKind
from lcmodels.experiment.recipe import Recipe, load_recipe
from lcmodels.experiment.stages import RAY_SHARDS
from lcmodels.presets import (  # re-exported: the experiment's vocabulary
    FIG5_NAME,
    FIG6_NAME,
    INVOCATIONS,
    LOCK_NAME,
    MARKER,
    ORACLE_KEY,
    PAPER_TABLE2,
    PAPER_TABLE3,
    PAPER_TABLE4,
    PRESETS,
    REPORT_NAME,
    ROWS,
    RULE_KEY,
    RULE_LABEL,
    STAGES_DIR,
    TABLE3_ROWS,
    TABLE4_ROWS,
    Preset,
    StageResult,
    demos_key,
    outputs_digest,
    policy_dir,
    previous_policy,
)

__all__ = [
    "FIG5_NAME",
    "FIG6_NAME",
    "INVOCATIONS",
    "KINDS",
    "LOCK_NAME",
    "MARKER",
    "ORACLE_KEY",
    "PAPER_TABLE2",
    "PAPER_TABLE3",
    "PAPER_TABLE4",
    "PRESETS",
    "RAY_SHARDS",
    "REPORT_NAME",
    "ROWS",
    "RULE_KEY",
    "RULE_LABEL",
    "STAGES_DIR",
    "TABLE3_ROWS",
    "TABLE4_ROWS",
    "Experiment",
    "ExperimentResult",
    "GraphCycle",
    "Preset",
    "Progress",
    "Recipe",
    "Stage",
    "StageGraph",
    "StageKey",
    "StageKind",
    "StageResult",
    "build_graph",
    "demos_key",
    "load_recipe",
    "outputs_digest",
    "policy_dir",
    "previous_policy",
    "recipe_ranks",
    "run_experiment",
]
