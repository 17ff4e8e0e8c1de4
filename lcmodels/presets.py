"""What an ``lc-experiment`` is made of: its presets, the methods of the paper's tables, the paper's own
figures, the layout of an experiment directory, and the record of one stage. Read by the experiment
(:mod:`lcmodels.experiment`) and its report (:mod:`lcmodels.report`)."""

from __future__ import annotations

import dataclasses
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


# ------------------------------------------------------------------------------------------------ presets
@dataclass(frozen=True, slots=True, kw_only=True)
class Preset:
    """Budgets of every stage. ``tiny`` is for tests, ``quick`` for ``make demo``, ``paper`` for results."""

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
    demo_episodes: int = 200
    demo_seed: int = 5000
    demo_driver: str = "oracle"
    """Who drives the warm start's demonstrations (an lcsim.drivers name). The oracle (privileged: it
    searches each episode's future) wins 97% of them; the rule-based driver, the earlier default, 54%, and
    98% of its decisions are 'keep', so cloning it taught little (docs/results/lanes/NOTE.md)."""
    ppo_timesteps: int = 150_000
    a2c_timesteps: int = 150_000
    dqn_timesteps: int = 150_000
    n_envs: int = 16
    ppo_n_steps: int = 128
    ppo_batch_size: int = 256
    ppo_n_epochs: int = 10
    a2c_n_steps: int = 8
    dqn_batch_size: int = 256
    """DQN minibatch (one gradient step per vector step of n_envs transitions)."""
    dqn_learning_starts: int = 2_000
    dqn_buffer_size: int = 50_000
    dqn_target_update_interval: int = 2_000
    warm_start_epochs: int = 10
    checkpoint_every: int = 20_000
    eval_episodes: int = 200
    eval_seed: int = 0
    record_eval: bool = True

    def __post_init__(self) -> None:
        from lcsim.registry import TASK_SCENARIOS

        if self.scenario not in TASK_SCENARIOS:
            raise ValueError(f"Preset.scenario must be one of {', '.join(TASK_SCENARIOS)}, got {self.scenario!r}")
        if self.corpus_episodes < 3:
            raise ValueError(f"Preset.corpus_episodes must be >= 3 (train/val/test split), got {self.corpus_episodes}")
        from lcsim.registry import DRIVER_NAMES

        if self.demo_driver not in DRIVER_NAMES:
            raise ValueError(f"Preset.demo_driver must be one of {', '.join(DRIVER_NAMES)}, got {self.demo_driver!r}")
        for name in ("demo_episodes", "ppo_timesteps", "a2c_timesteps", "dqn_timesteps", "n_envs", "eval_episodes",
                     "record_workers", "predictor_epochs", "checkpoint_every"):  # fmt: skip
            if getattr(self, name) < 1:
                raise ValueError(f"Preset.{name} must be >= 1, got {getattr(self, name)}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


PRESETS: dict[str, Preset] = {
    # Seconds: exercises every stage for the tests; the numbers mean nothing.
    "tiny": Preset(
        name="tiny", scenario="tiny", corpus_episodes=3, corpus_steps=200, record_workers=1,
        predictor_d_model=16, predictor_heads=2, predictor_layers=1, predictor_ff_dim=32, predictor_epochs=1,
        predictor_time_limit_s=None, predictor_max_train_windows=2_000, predictor_stride=5,
        predictor_tensorboard=False, demo_episodes=2, ppo_timesteps=128, a2c_timesteps=128, dqn_timesteps=128,
        n_envs=4, ppo_n_steps=32, ppo_batch_size=64, ppo_n_epochs=2, dqn_batch_size=32, dqn_learning_starts=32,
        dqn_buffer_size=1_000, dqn_target_update_interval=64, warm_start_epochs=1, checkpoint_every=10_000,
        eval_episodes=4, record_eval=False,
    ),
    # About 15 minutes on 2 CPU cores: the pipeline end to end with budgets far below convergence.
    "quick": Preset(
        name="quick", scenario="light", corpus_episodes=6, corpus_steps=1000, predictor_epochs=20,
        predictor_time_limit_s=60.0, predictor_max_train_windows=50_000, predictor_stride=2,
        demo_episodes=8, ppo_timesteps=4_096, a2c_timesteps=4_096, dqn_timesteps=4_096, n_envs=16,
        ppo_n_steps=64, ppo_n_epochs=4, dqn_batch_size=32, dqn_learning_starts=1_000, dqn_target_update_interval=1_000,
        warm_start_epochs=5, checkpoint_every=2_048, eval_episodes=50, record_eval=False,
    ),
    # The paper's setting: budgets each method needs to converge (hours on a CPU; use --seeds and resume).
    "paper": Preset(name="paper"),
}


# ------------------------------------------------------------------------------------------------ methods
@dataclass(frozen=True, slots=True)
class Method:
    key: str
    label: str
    algo: str
    obs: str
    warm_start: bool = False


RULE_KEY = "rule"
RULE_LABEL = "Rule-based (reference)"
METHODS: tuple[Method, ...] = (
    Method("ppo-hybrid", "Hybrid-PPO", "ppo", "hybrid"),
    Method("ppo-hybrid-warm", "Hybrid-PPO + warm start", "ppo", "hybrid", warm_start=True),
    Method("a2c-hybrid", "A2C (hybrid)", "a2c", "hybrid"),
    Method("dqn-hybrid", "DQN (hybrid)", "dqn", "hybrid"),
    Method("ppo-pure", "PPO pure", "ppo", "pure"),
    Method("ppo-image", "PPO image", "ppo", "image"),
    Method("ppo-prediction", "PPO prediction", "ppo", "prediction"),
)
METHOD_BY_KEY = {m.key: m for m in METHODS}
# The paper's numbers: success / collision / timeout, percent.
PAPER_TABLE3 = {"a2c-hybrid": (47.8, 52.2, 0.0), "dqn-hybrid": (46.5, 53.3, 0.2), "ppo-hybrid": (87.8, 10.5, 2.7)}
PAPER_TABLE4 = {"ppo-pure": (47.6, 50.0, 2.2), "ppo-image": (63.8, 34.0, 0.2), "ppo-prediction": (76.4, 22.7, 0.9),
                "ppo-hybrid": (87.8, 10.5, 2.7)}  # fmt: skip
TABLE3_ROWS = (RULE_KEY, "a2c-hybrid", "dqn-hybrid", "ppo-hybrid", "ppo-hybrid-warm")
TABLE4_ROWS = ("ppo-pure", "ppo-image", "ppo-prediction", "ppo-hybrid")
PAPER_TABLE2 = {"ade": 0.382, "fde": 0.597}


def policy_dir(out: Path, key: str, seed: int) -> Path:
    return Path(out) / "policies" / key / f"seed{seed}"


def method_timesteps(preset: Preset, method: Method) -> int:
    return {"ppo": preset.ppo_timesteps, "a2c": preset.a2c_timesteps, "dqn": preset.dqn_timesteps}[method.algo]


def policy_config(preset: Preset, method: Method, seed: int, demos: Path | None) -> Any:
    """The :class:`~lcmodels.policy.train.PolicyConfig` of one (method, seed) run."""
    from lcmodels.policy.train import PolicyConfig, default_learning_rate

    # The warm-started row keeps the algorithm's rate (not the fine-tuning one of lc-train-policy), so
    # that it differs from the row trained from scratch by the warm start alone, as the stored results did.
    lr = default_learning_rate(method.algo)
    n_steps = preset.a2c_n_steps if method.algo == "a2c" else preset.ppo_n_steps
    batch = preset.dqn_batch_size if method.algo == "dqn" else preset.ppo_batch_size
    return PolicyConfig(
        algo=method.algo, obs=method.obs, scenario=preset.scenario, timesteps=method_timesteps(preset, method),
        n_envs=preset.n_envs, seed=seed, learning_rate=lr, n_steps=n_steps, batch_size=batch,
        n_epochs=preset.ppo_n_epochs, buffer_size=preset.dqn_buffer_size,
        learning_starts=preset.dqn_learning_starts, target_update_interval=preset.dqn_target_update_interval,
        checkpoint_every=preset.checkpoint_every, eval_episodes=preset.eval_episodes, eval_seed=preset.eval_seed,
        record_eval=preset.record_eval, warm_start=str(demos.resolve()) if method.warm_start and demos else "",
        warm_start_epochs=preset.warm_start_epochs,
    )  # fmt: skip


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


