"""What an ``lc-experiment`` is made of: its presets, the methods of the paper's tables, the paper's own
figures, the layout of an experiment directory, and the record of one stage. Read by the experiment
(:mod:`lcmodels.experiment`) and its report (:mod:`lcmodels.report`)."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lcmodels.fileio import json_default

STAGES_DIR = "stages"
MARKER = "experiment.json"
LOCK_NAME = ".lock"
INVOCATIONS = "invocations.json"
"""Every ``run`` of the directory: start, command, wall time so far (kept up to date by each progress line, so
that a killed invocation keeps the time until its last line) and whether it finished."""
REPORT_NAME = "REPORT.md"
FIG5_NAME = "fig5_safe_forward.png"
FIG6_NAME = "fig6_total_reward.png"


# ------------------------------------------------------------------------------------------------ rows
ROWS: dict[str, str] = {
    "ppo-hybrid": "Hybrid-PPO",
    "ppo-hybrid-warm": "Hybrid-PPO + warm start",
    "a2c-hybrid": "A2C (hybrid)",
    "dqn-hybrid": "DQN (hybrid)",
    "ppo-pure": "PPO pure",
    "ppo-image": "PPO image",
    "ppo-prediction": "PPO prediction",
}
"""The rows of the paper's Tables III and IV a recipe can fill (``Recipe.row``), with their labels."""
RULE_KEY = "rule"
RULE_LABEL = "Rule-based (reference)"
ORACLE_KEY = "oracle"
ORACLE_LABEL = "Oracle (sees the future: the ceiling)"
# The paper's numbers: success / collision / timeout, percent.
PAPER_TABLE3 = {"a2c-hybrid": (47.8, 52.2, 0.0), "dqn-hybrid": (46.5, 53.3, 0.2), "ppo-hybrid": (87.8, 10.5, 2.7)}
PAPER_TABLE4 = {"ppo-pure": (47.6, 50.0, 2.2), "ppo-image": (63.8, 34.0, 0.2), "ppo-prediction": (76.4, 22.7, 0.9),
                "ppo-hybrid": (87.8, 10.5, 2.7)}  # fmt: skip
TABLE3_ROWS = ("a2c-hybrid", "dqn-hybrid", "ppo-hybrid", "ppo-hybrid-warm")
TABLE4_ROWS = ("ppo-pure", "ppo-image", "ppo-prediction", "ppo-hybrid")
PAPER_TABLE2 = {"ade": 0.382, "fde": 0.597}

RECIPES_DIR = Path(__file__).parent / "recipes"
"""The recipes that come with the package (:mod:`lcmodels.experiment.recipe`)."""


@functools.cache
def _listing() -> tuple[tuple[str, bool, int, str], ...]:
    """``(kind, optional, order, name)`` of every packaged recipe, as its file says (read once)."""
    from lckit.config import read_data_file

    rows = []
    for path in sorted(RECIPES_DIR.glob("*.toml")):
        data = read_data_file(path, "recipe")
        rows.append((str(data.get("kind", "best")), bool(data.get("optional", False)), int(data.get("order", 0)),
                     path.stem))  # fmt: skip
    return tuple(rows)


def listed_recipes(kind: str, *, optional: bool = False) -> tuple[str, ...]:
    """The packaged recipes whose files say ``kind = "<kind>"`` and, with ``optional``, ``optional = true`` (else
    not), in their ``order`` (then by name): the presets' lists of recipes are data in the recipe files."""
    return tuple(name for k, opt, _, name in sorted(_listing(), key=lambda r: (r[2], r[3]))
                 if k == kind and opt == optional)  # fmt: skip


PAPER_RECIPES = listed_recipes("paper")
"""The paper-faithful recipes: each method trained from scratch (the warm-start row from rule demonstrations)
with the paper's budgets and observation."""
BEST_RECIPES = listed_recipes("best")
"""The project's best recipe for each method."""
OPTIONAL_RECIPES = listed_recipes("best", optional=True)
"""Recipes the ``paper`` preset runs only when named (``--recipe``): ``hybrid-ppo-dagger`` trains the image network
on every state of its six DAgger rounds, several CPU hours (each round adds tens of thousands of states), for a
route that did not move the pure policy beyond the noise (docs/results/human-traffic); ``attention-ppo``,
``roads-ppo`` and ``drawn-roads-ppo`` are research routes (the ego-attention sensor branch, docs/results/attention;
training on every road of the suite at once, and on roads drawn across its dimensions, docs/results/roads);
``distil-safety-ppo`` labels about 100k decisions with the safety layer, about 25 minutes of one core
(docs/results/distil)."""
ABLATION_INPUTS = ("pure", "image", "prediction", "hybrid", "lane-aware")
"""The inputs of the controlled ablation: the paper's Table IV in its order, then the prediction input fed by the
analytic lane-aware base in place of the learned predictor."""
ABLATION_RECIPES = listed_recipes("ablation")
"""The controlled input ablation: one recipe per input and training block (the paper's road; every road of the
suite), identical but for the input (``[policy].obs`` and the predictor behind it; docs/results/ablation)."""
ABLATION_SEEDS = 3
"""Training seeds of every ablation recipe."""


# ------------------------------------------------------------------------------------------------ presets
@dataclass(frozen=True, slots=True, kw_only=True)
class Preset:
    """What an experiment runs: the corpus and predictor budgets, the recipes, how they are evaluated, and
    caps on every budget (``tiny`` is for tests, ``quick`` for ``make demo``, ``paper`` for results)."""

    name: str
    scenario: str = "paper"
    """Policy scenario (:data:`lcsim.registry.TASK_SCENARIOS`): paper, light or tiny."""
    corpus_episodes: int = 24
    corpus_seed: int = 100
    corpus_steps: int | None = None
    """Episode length of the corpus in simulation steps (None: the paper's 2000)."""
    record_workers: int = 2
    predictor_d_model: int = 64
    predictor_heads: int = 4
    predictor_layers: int = 2
    predictor_ff_dim: int = 256
    predictor_epochs: int = 20
    predictor_time_limit_s: float | None = 600.0
    predictor_max_train_windows: int = 200_000
    predictor_stride: int = 1
    predictor_tensorboard: bool = True
    recipes: tuple[str, ...] = (*PAPER_RECIPES, *BEST_RECIPES)
    """Recipe names or files (:mod:`lcmodels.experiment.recipe`), each trained with every training seed."""
    recipe_seeds: tuple[tuple[str, int], ...] = ()
    """Recipes trained with more seeds than ``--seeds`` asks, ``(name, seeds)``; a recipe whose policy a
    safety layer follows gets as many seeds as the recipe it serves."""
    caps: tuple[tuple[str, int], ...] = ()
    """Upper bounds on the recipes' integer settings, ``(name, cap)`` (``timesteps``, ``episodes``, ``epochs``,
    ``warm_start_epochs``, ``rounds``, ``n_envs``, ``horizon_decisions``...): the small presets' budgets."""
    val_episodes: int = 200
    val_seeds: tuple[int, ...] = (0, 1)
    """Validation: the evaluation seeds every recipe was chosen on (``lc-eval --seed``)."""
    test_episodes: int = 1000
    test_seed: int = 9
    """Test: held-out episodes of an evaluation seed never used for any choice; the report's figures."""
    oracle: bool = True
    """Evaluate the oracle (the ceiling of any policy) on the same episodes."""
    suite: str = ""
    """A benchmark suite (:data:`lcsim.suite.SUITES`) every recipe's final policy is also measured on, on
    validation episodes, next to each road's ceiling and floor: lc-bench's table, paired tests and figures in
    ``DIR/bench`` ("": none)."""
    suite_episodes: int = 100
    suite_seed: int = 0
    """Validation episodes per road of :attr:`suite`, and their evaluation seed (``lc-bench --episodes --seed``)."""
    zoo: bool = False
    """Also evaluate every policy of the zoo on the test episodes (``make demo``)."""
    record_eval: bool = False
    """Keep the test episodes' recordings (MCAP)."""
    showcase_episodes: int = 0
    """Episodes of the best zoo policy recorded for viewing (and one exported as a Rerun ``.rrd``)."""

    def __post_init__(self) -> None:
        from lcsim.registry import TASK_SCENARIOS

        if self.scenario not in TASK_SCENARIOS:
            raise ValueError(f"Preset.scenario must be one of {', '.join(TASK_SCENARIOS)}, got {self.scenario!r}")
        if self.corpus_episodes < 3:
            raise ValueError(f"Preset.corpus_episodes must be >= 3 (train/val/test split), got {self.corpus_episodes}")
        for name in ("val_episodes", "test_episodes", "record_workers", "predictor_epochs"):
            if getattr(self, name) < 1:
                raise ValueError(f"Preset.{name} must be >= 1, got {getattr(self, name)}")
        for name, n in self.recipe_seeds:
            if not isinstance(n, int) or isinstance(n, bool) or n < 1:
                raise ValueError(f"Preset.recipe_seeds: {name!r} needs an integer >= 1, got {n!r}")
        if self.suite:
            from lcsim.suite import SUITES

            if self.suite not in SUITES:
                raise ValueError(f"Preset.suite must be one of {', '.join(SUITES)} or empty, got {self.suite!r}")
        if self.suite_episodes < 1 or self.suite_seed < 0:
            raise ValueError(f"Preset.suite_episodes must be >= 1 and suite_seed >= 0, got {self.suite_episodes}, "
                             f"{self.suite_seed}")
        if self.test_seed in self.val_seeds:
            raise ValueError(f"Preset.test_seed {self.test_seed} must not be a validation seed {self.val_seeds}")

    @property
    def cap_dict(self) -> dict[str, int]:
        return dict(self.caps)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


_TINY_CAPS = (("timesteps", 128), ("episodes", 2), ("warm_start_epochs", 1), ("epochs", 1), ("rounds", 1),
              ("n_envs", 4), ("n_steps", 32), ("batch_size", 64), ("n_epochs", 2), ("learning_starts", 32),
              ("buffer_size", 1_000), ("target_update_interval", 64), ("checkpoint_every", 10_000), ("horizon_decisions", 2))
PRESETS: dict[str, Preset] = {
    # Seconds: exercises every recipe and stage for the tests; the numbers mean nothing.
    "tiny": Preset(
        name="tiny", scenario="tiny", corpus_episodes=3, corpus_steps=200, record_workers=1,
        predictor_d_model=16, predictor_heads=2, predictor_layers=1, predictor_ff_dim=32, predictor_epochs=1,
        predictor_time_limit_s=None, predictor_max_train_windows=2_000, predictor_stride=5,
        predictor_tensorboard=False, recipes=(*PAPER_RECIPES, *BEST_RECIPES, *OPTIONAL_RECIPES, "quick-pure", "ablation-lane-aware"),
        caps=_TINY_CAPS,
        val_episodes=4, val_seeds=(0,), test_episodes=4, oracle=True,
    ),
    # make demo (minutes; the README says how long): the corpus and predictor at small budgets, the zoo's policies on
    # fresh held-out episodes, one quick recipe trained from scratch, a few episodes of the best zoo policy.
    "quick": Preset(
        name="quick", scenario="paper", corpus_episodes=6, corpus_steps=1000, predictor_epochs=20,
        predictor_time_limit_s=60.0, predictor_max_train_windows=50_000, predictor_stride=2,
        recipes=("quick-pure",), val_episodes=200, val_seeds=(0,), test_episodes=200, oracle=False, zoo=True,
        showcase_episodes=3,
    ),
    # The paper's setting: every recipe at its own budget, Hybrid-PPO with two training seeds (hours on a CPU;
    # it resumes).
    "paper": Preset(name="paper", recipe_seeds=(("hybrid-ppo", 2),)),
    # The controlled input ablation: every input with the same trunk, algorithm, budget and stages, three training
    # seeds each, on the paper's road and across the suite (a night on 2 cores; it resumes); every policy measured
    # on every road of the suite, the tables, paired tests and figures in DIR/bench (docs/results/ablation).
    "ablation": Preset(
        name="ablation", recipes=ABLATION_RECIPES,
        recipe_seeds=tuple((r, ABLATION_SEEDS) for r in ABLATION_RECIPES), val_episodes=200, val_seeds=(0,),
        test_episodes=200, oracle=False, suite="highway", suite_episodes=100,
    ),
}


def policy_dir(out: Path, recipe: str, seed: int) -> Path:
    """Where the stages of ``recipe`` with training seed ``seed`` live."""
    return Path(out) / "policies" / recipe / f"seed{seed}"


def demos_key(spec: Any) -> str:
    """The directory name of the demonstrations ``spec`` (a :class:`lcmodels.experiment.kinds.DemoSpec`, recorded in
    ``demos/<key>``): recipes with the same demonstrations share them."""
    return f"{spec.driver}-s{spec.seed}-n{spec.episodes}"


def previous_policy(stage: StageResult) -> Path:
    """The policy file a ``clone``, ``dagger`` or ``train`` stage ends with (a stand-in in a dry run)."""
    from lcmodels.fileio import POLICY_FILE

    name = next((k for k in stage.outputs if k.endswith(POLICY_FILE)), None)
    return (stage.path / (name or "pending")).resolve()


# ---------------------------------------------------------------------------------------------- hashing
def canonical(x: Any) -> Any:
    """JSON round trip: tuples become lists, keys sorted, so records compare equal to fresh configs."""
    return json.loads(json.dumps(x, sort_keys=True, default=json_default))


def outputs_digest(outputs: dict[str, str]) -> str:
    """One hash for a stage's outputs: what the stages that read them record as their input."""
    return hashlib.sha256(json.dumps(outputs, sort_keys=True).encode()).hexdigest()


@dataclass
class StageResult:
    name: str
    status: str
    """``skipped`` (complete), ``done`` (computed in this run), ``not run`` (--skip-train) or, in a dry run,
    ``would run (why)``."""
    path: Path
    wall_s: float
    """Wall time of the computation that produced the outputs (recorded; 0 for not run)."""
    run_s: float = 0.0
    """Time spent on the stage in this invocation (hashing included)."""
    outputs: dict[str, str] = field(default_factory=dict)

    @property
    def digest(self) -> str:
        return outputs_digest(self.outputs)


