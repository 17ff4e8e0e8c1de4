"""Online training of the lane-change policy on the batched simulator, resumable, then evaluation.

A run directory holds::

    run.json                  the PolicyConfig, predictor identity, versions (a rerun must match it)
    checkpoints/latest.zip    the last periodic checkpoint (policy checkpoint format) + latest.json
    progress.csv              one row per log interval: timesteps, wall_s and the outcome rates,
                              mean return and safe forward distance over the last 100 episodes
    tb/                       TensorBoard (SB3's scalars plus lc/*)
    train_episode_seeds.npy   simulator seeds of every training episode (for the held-out check)
    warm_start.json           behaviour-cloning losses when warm-started, or the --init-policy started from
    policy.zip                the final policy
    eval/metrics.json         held-out evaluation (see lcmodels.policy.evaluate); eval/episodes/*.mcap
    metrics.json              training summary + evaluation, what lc-experiment reads

Rerunning with the same ``--out`` resumes from ``checkpoints/latest.zip`` (the step count continues),
skips training when ``policy.zip`` is complete, and only evaluates what is missing.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import os
import platform
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure

from lcmodels.fileio import file_sha256, write_json
from lcmodels.policy.checkpoint import ALGOS, LoadedPolicy, save_policy
from lcmodels.policy.evaluate import EVAL_SEED_BASE, PolicyDriver, evaluate
from lcmodels.policy.extractor import (
    IMAGE_FEATURES,
    IMAGE_NETS,
    HybridExtractor,
    ImageEncoder,
    make_image_net,
)
from lcmodels.policy.obs import (
    OBS_MODES,
    EpisodeStats,
    PolicyVecEnv,
    mode_keys,
    needs_predictor,
    scenario_for_mode,
)
from lcmodels.predictor.inference import Predictor
from lcsim import light_scenario
from lcsim.config import (
    NEIGHBOUR_SELECTIONS,
    ScenarioConfig,
    TrafficConfig,
    _check,
    _JsonMixin,
    _non_negative,
    _positive,
    paper_scenario,
)
from lcsim.sb3 import LaneChangeSB3VecEnv

log = logging.getLogger(__name__)



def tiny_scenario() -> ScenarioConfig:
    """8 vehicles on a 150 m route (25 s): for tests and smoke runs, not for results."""
    return ScenarioConfig(traffic=TrafficConfig(num_vehicles=8, spawn_behind_m=40.0, spawn_ahead_m=100.0),
                          route_length_m=150.0, time_limit_s=25.0)


POLICY_SCENARIOS: dict[str, Callable[[], ScenarioConfig]] = {"paper": paper_scenario, "light": light_scenario,
                                                             "tiny": tiny_scenario}
PROGRESS_COLUMNS = ("timesteps", "wall_s", "episodes_total", "window", "success_rate", "collision_rate",
                    "off_road_rate", "timeout_rate", "mean_return", "mean_safe_forward_m", "mean_forward_m")  # fmt: skip
# Fields that may change between a run and its continuation.
_RESUMABLE_FIELDS = ("timesteps", "checkpoint_every", "eval_episodes", "eval_seed", "eval_batch", "record_eval")


_LEARNING_RATES = {"ppo": 3e-4, "a2c": 7e-4, "dqn": 1e-4}
FINE_TUNE_LEARNING_RATES = {"ppo": 3e-5}
"""PPO from a warm start or an initial policy learns at a tenth of its default rate: from the same clone
(69.5% held-out success), 300k steps at 3e-4 fell to 61.0% and at 3e-5 rose to 75.5%
(docs/results/lanes/NOTE.md); PPO from DAgger at 3e-5 gave the project's best policy (docs/results/contact).
A2C and DQN were not measured that way and keep their rates."""


def default_learning_rate(algo: str, fine_tune: bool = False) -> float:
    """The learning rate a run gets when none is given: per algorithm, or :data:`FINE_TUNE_LEARNING_RATES`
    when it continues from a warm start or an initial policy (``fine_tune``)."""
    if algo not in _LEARNING_RATES:
        raise ValueError(f"unknown algorithm {algo!r}; choose one of {', '.join(_LEARNING_RATES)}")
    return FINE_TUNE_LEARNING_RATES.get(algo, _LEARNING_RATES[algo]) if fine_tune else _LEARNING_RATES[algo]


@dataclass(frozen=True, slots=True, kw_only=True)
class PolicyConfig(_JsonMixin):
    """Everything that defines a policy training run (stored in ``run.json``)."""

    LEGACY_DEFAULTS: ClassVar[dict[str, Any]] = {"contact_features": False, "freeze_image": False}

    algo: str = "ppo"
    obs: str = "hybrid"
    scenario: str = "paper"
    timesteps: int = 100_000
    """Online decisions (environment steps summed over environments); 0 with a warm start gives the
    behaviour-cloned policy itself."""
    n_envs: int = 16
    seed: int = 0
    neighbours: str = "lanes"
    """Which vehicles the observation shows (``ScenarioConfig.neighbour_selection``): ``lanes`` or ``nearest``."""
    slots: int = 8
    """How many (``ScenarioConfig.num_neighbours``): the paper's 8, or with ``lanes`` up to 16, the slots
    after the eighth a wider view (:data:`lcsim.config.LANE_SLOTS`). The predictor, which has no slot
    embedding, predicts each shown vehicle with the others as context, however many."""
    image_net: str = "compact"
    image_features: int = 10
    contact_features: bool = True
    """The sensor branch also gets each slot's time to contact, gap and proximity
    (``lcmodels.policy.extractor.ContactFeatures``). Cloning the oracle in ``pure`` mode: 69.5% held-out
    success without, 77.0% with (docs/results/contact). Runs stored before the option existed read as off."""
    window_features: bool = False
    """The sensor branch also gets, per side lane, when over the next 16 s the ego could change into it,
    against when its own leader traps it (``lcmodels.policy.extractor.WindowFeatures``; lane slots only)."""
    accel_features: bool = False
    """The observation also shows each vehicle's acceleration (``ScenarioConfig.observe_acceleration``), and
    with ``window_features`` the sensor branch also looks at the side lanes with those accelerations kept."""
    learning_rate: float = _LEARNING_RATES["ppo"]
    gamma: float = 0.95
    """0.95 (a 10 s horizon at 2 decisions/s): PPO pure reached 24% held-out success in 150k steps with
    0.95 and no entropy bonus, 7% with 0.99 and 0.01 in 100k (measured, 200 episodes)."""
    n_steps: int = 128
    """PPO / A2C rollout length per environment (A2C default 8)."""
    batch_size: int = 256
    n_epochs: int = 10
    ent_coef: float = 0.0
    reward_scale: float = 0.01
    """Rewards handed to the learner are scaled by this (returns in the logs are unscaled)."""
    collision_weight: float = 1.0
    """The learner's collision reward is this many times the scenario's (training shaping: the logged and
    evaluated returns keep the paper's reward)."""
    buffer_size: int = 50_000
    """DQN replay buffer (transitions)."""
    learning_starts: int = 2_000
    exploration_fraction: float = 0.3
    target_update_interval: int = 2_000
    checkpoint_every: int = 20_000
    eval_episodes: int = 200
    eval_seed: int = 0
    eval_batch: int = 20
    record_eval: bool = True
    warm_start: str = ""
    """Directory of recorded MCAP episodes to pretrain on ('' = none)."""
    warm_start_epochs: int = 10
    init_policy: str = ""
    """A ``policy.zip`` (a behaviour-cloned run's, a DAgger round's) whose weights start the online
    training ('' = none): same algorithm, observation mode, predictor, scenario and network as this run."""
    freeze_image: bool = False
    """With ``init_policy`` in the ``image`` and ``hybrid`` modes: the image branch keeps the initial
    policy's weights and runs once per step in the observation wrapper, so the rollout buffer holds its
    features instead of the image and the update epochs never run the network (several times the online
    steps per minute in ``hybrid`` mode). ``policy.zip`` is a plain policy of the mode, image branch
    included; ``checkpoints/latest.zip`` is in the training form, for resuming only."""

    def __post_init__(self) -> None:
        _check(self.algo in ALGOS, self, "algo", f"must be one of {', '.join(ALGOS)}", self.algo)
        _check(self.obs in OBS_MODES, self, "obs", f"must be one of {', '.join(OBS_MODES)}", self.obs)
        _check(self.scenario in POLICY_SCENARIOS, self, "scenario", f"must be one of {', '.join(POLICY_SCENARIOS)}",
               self.scenario)  # fmt: skip
        _check(self.neighbours in NEIGHBOUR_SELECTIONS, self, "neighbours",
               f"must be one of {', '.join(NEIGHBOUR_SELECTIONS)}", self.neighbours)
        _check(not self.window_features or self.neighbours == "lanes", self, "window_features",
               "needs neighbours='lanes' (which vehicle is in which lane)", self.window_features)
        _check(self.image_net in IMAGE_NETS, self, "image_net", f"must be one of {', '.join(IMAGE_NETS)}",
               self.image_net)  # fmt: skip
        _positive(self, "n_envs", "image_features", "learning_rate", "n_steps", "batch_size",
                  "n_epochs", "reward_scale", "collision_weight", "buffer_size", "target_update_interval",
                  "checkpoint_every", "eval_batch", "warm_start_epochs")
        _non_negative(self, "timesteps", "ent_coef", "learning_starts", "eval_episodes", "seed", "eval_seed")
        _check(not (self.warm_start and self.init_policy), self, "init_policy",
               "cannot be combined with warm_start (clone first, then start from that run's policy.zip)",
               self.init_policy)  # fmt: skip
        _check(not self.freeze_image or bool(self.init_policy), self, "freeze_image",
               "needs init_policy (a policy whose image branch is trained already)", self.freeze_image)
        _check(not self.freeze_image or "image" in mode_keys(self.obs), self, "freeze_image",
               f"needs an observation mode with the image (image, hybrid), not {self.obs!r}", self.freeze_image)
        _check(self.timesteps > 0 or bool(self.warm_start), self, "timesteps",
               "must be > 0 without a warm start (0 with one: behaviour cloning only)", self.timesteps)  # fmt: skip
        _check(0 < self.gamma <= 1, self, "gamma", "must be in (0, 1]", self.gamma)
        _check(0 < self.exploration_fraction <= 1, self, "exploration_fraction", "must be in (0, 1]",
               self.exploration_fraction)  # fmt: skip
        _check(self.seed < 1_000_000, self, "seed", "must be < 1000000 (keeps training seeds off evaluation's)",
               self.seed)  # fmt: skip
        try:  # slots (and neighbours) as the scenario itself validates them
            self.scenario_config()
        except ValueError as exc:
            raise ValueError(f"PolicyConfig.slots {self.slots} does not fit the scenario: {exc}") from None

    def scenario_config(self) -> ScenarioConfig:
        base = dataclasses.replace(POLICY_SCENARIOS[self.scenario](), neighbour_selection=self.neighbours,
                                   num_neighbours=self.slots, observe_acceleration=self.accel_features)
        return scenario_for_mode(base, self.obs)


def build_model(cfg: PolicyConfig, env: PolicyVecEnv, tensorboard: str | None = None,
                device: str = "cpu") -> BaseAlgorithm:
    """A fresh SB3 model of ``cfg.algo`` with the hybrid extractor."""
    policy_kwargs: dict[str, Any] = {
        "features_extractor_class": HybridExtractor,
        "features_extractor_kwargs": {"image_net": cfg.image_net, "image_features": cfg.image_features,
                                      "contact_features": cfg.contact_features,
                                      "window_features": cfg.window_features},
        "net_arch": [128, 64] if cfg.algo == "dqn" else {"pi": [64, 64], "vf": [64, 64]},
    }
    common: dict[str, Any] = {"policy_kwargs": policy_kwargs, "seed": cfg.seed, "device": device,
                              "gamma": cfg.gamma, "tensorboard_log": tensorboard, "verbose": 0}  # fmt: skip
    if cfg.algo == "ppo":
        return ALGOS["ppo"]("MultiInputPolicy", env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps,
                            batch_size=cfg.batch_size, n_epochs=cfg.n_epochs, ent_coef=cfg.ent_coef, **common)
    if cfg.algo == "a2c":
        return ALGOS["a2c"]("MultiInputPolicy", env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps,
                            ent_coef=cfg.ent_coef, **common)
    return ALGOS["dqn"]("MultiInputPolicy", env, learning_rate=cfg.learning_rate, buffer_size=cfg.buffer_size,
                        learning_starts=cfg.learning_starts, batch_size=cfg.batch_size,
                        train_freq=1, gradient_steps=1,  # one minibatch per vector step (n_envs transitions)
                        target_update_interval=cfg.target_update_interval,
                        exploration_fraction=cfg.exploration_fraction, exploration_final_eps=0.02, **common)


def train_seed_base(seed: int, start_timesteps: int) -> int:
    """User seed of environment 0 at a (re)start: ``1000 * seed`` fresh, a hash of (seed, step) on resume."""
    if start_timesteps == 0:
        return 1000 * seed
    state = np.random.SeedSequence([seed, start_timesteps]).generate_state(1, dtype=np.uint32)[0]
    return int(state) % (EVAL_SEED_BASE - 10_000)


@dataclass
class TrainResult:
    out: Path
    timesteps: int
    wall_s: float
    metrics: dict[str, Any] = field(default_factory=dict)


class _Logger(BaseCallback):
    """Outcome statistics to TensorBoard and progress.csv; periodic checkpoints."""

    def __init__(self, run: _Run, env: PolicyVecEnv, log_every: int) -> None:
        super().__init__()
        self.run, self.env, self.log_every = run, env, log_every
        self.window: deque[EpisodeStats] = deque(maxlen=100)
        self.episodes_total = run.episodes_total
        self.last_log = run.start_timesteps
        self.last_ckpt = run.start_timesteps

    def _on_step(self) -> bool:
        finished = self.env.pop_finished()
        self.window.extend(finished)
        self.episodes_total += len(finished)
        t = self.num_timesteps
        if t - self.last_log >= self.log_every:
            self.last_log = t
            self._log(t)
        if t - self.last_ckpt >= self.run.cfg.checkpoint_every:
            self.last_ckpt = t
            self.run.checkpoint(self.model, t, self.episodes_total)
        return True

    def _log(self, t: int) -> None:
        w = list(self.window)
        n = len(w)
        row: dict[str, float] = {"timesteps": t, "wall_s": round(self.run.wall_s(), 3),
                                 "episodes_total": self.episodes_total, "window": n}  # fmt: skip
        for o in ("success", "collision", "off_road", "timeout"):
            row[f"{o}_rate"] = sum(e.outcome == o for e in w) / n if n else float("nan")
        row["mean_return"] = float(np.mean([e.ret for e in w])) if n else float("nan")
        row["mean_safe_forward_m"] = float(np.mean([e.safe_forward_m for e in w])) if n else float("nan")
        row["mean_forward_m"] = float(np.mean([e.forward_m for e in w])) if n else float("nan")
        for k, v in row.items():
            if k not in ("timesteps", "wall_s"):
                self.logger.record(f"lc/{k}", v)
        self.run.append_progress(row)
        if self.run.progress is not None:
            self.run.progress(row)


class _Run:
    """The run directory: config check, checkpoints, progress rows, wall time across resumes."""

    def __init__(self, cfg: PolicyConfig, out: Path, predictor_path: Path | None, predictor_sha256: str | None,
                 progress: Callable[[dict[str, Any]], None] | None) -> None:
        self.cfg, self.out, self.progress = cfg, out, progress
        self.predictor: dict[str, str] | None = None
        if predictor_path is not None:
            self.predictor = {"path": str(predictor_path.resolve()), "file": predictor_path.name,
                              "sha256": str(predictor_sha256)}  # fmt: skip
        self.ckpt = out / "checkpoints" / "latest.zip"
        self.ckpt_state = out / "checkpoints" / "latest.json"
        self.start_timesteps = 0
        self.episodes_total = 0
        self.wall_before = 0.0
        self.t_start = time.perf_counter()
        self.seeds_path = out / "train_episode_seeds.npy"
        self.prior_seeds = np.zeros(0, dtype=np.int64)
        self.env: PolicyVecEnv | None = None

    def wall_s(self) -> float:
        return self.wall_before + time.perf_counter() - self.t_start

    def meta(self, timesteps: int, training_form: bool = False) -> dict[str, Any]:
        """The checkpoint metadata; ``training_form``: a frozen-image run's checkpoint, which sees the image
        branch's features in place of the image (resumable, not loadable as a policy)."""
        meta = {"algo": self.cfg.algo, "obs_mode": self.cfg.obs, "image_net": self.cfg.image_net,
                "scenario_name": self.cfg.scenario, "scenario": self.cfg.scenario_config().to_dict(),
                "predictor": self.predictor, "train_config": self.cfg.to_dict(), "timesteps": timesteps}  # fmt: skip
        if training_form:
            meta["training_form"] = IMAGE_FEATURES
        return meta

    def all_seeds(self) -> np.ndarray:
        new = np.asarray(self.env.episode_seeds if self.env is not None else [], dtype=np.int64)
        return np.concatenate([self.prior_seeds, new])

    def checkpoint(self, model: BaseAlgorithm, t: int, episodes_total: int) -> None:
        save_policy(model, self.ckpt, self.meta(t, training_form=self.cfg.freeze_image))
        np.save(self.seeds_path, self.all_seeds())
        write_json(self.ckpt_state, {"timesteps": t, "wall_s": self.wall_s(), "episodes_total": episodes_total})

    def append_progress(self, row: dict[str, Any]) -> None:
        path = self.out / "progress.csv"
        new = not path.exists()
        with path.open("a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=PROGRESS_COLUMNS)
            if new:
                w.writeheader()
            w.writerow(row)

    def truncate_progress(self, t: int) -> None:
        """Drop progress rows logged after the checkpoint we resume from (they will be redone)."""
        path = self.out / "progress.csv"
        if not path.exists():
            return
        with path.open(newline="") as f:
            rows = [r for r in csv.DictReader(f) if int(float(r["timesteps"])) <= t]
        with path.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=PROGRESS_COLUMNS)
            w.writeheader()
            w.writerows(rows)


def versions() -> dict[str, str]:
    import gymnasium
    import stable_baselines3

    import lcsim

    return {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "stable_baselines3": stable_baselines3.__version__, "gymnasium": gymnasium.__version__,
            "lc_toolkit": lcsim.__version__, "platform": platform.platform()}  # fmt: skip


def stored_config(data: dict[str, Any]) -> dict[str, Any]:
    """A :class:`PolicyConfig` dict as stored (``run.json``, an experiment's stage record) in today's form: a
    field added since reads as loading it would (its ``LEGACY_DEFAULTS`` value, else its default, which
    for a field like ``slots`` is the behaviour before it existed). A dict that is no config stays as it is."""
    try:
        return PolicyConfig.from_dict(data).to_dict()
    except (ValueError, TypeError):
        return data


def check_run_dir(cfg: PolicyConfig, out: Path, predictor_sha256: str | None) -> None:
    """``ValueError`` when ``out`` holds a run with another config or predictor (says what differs)."""
    run_json = out / "run.json"
    if not run_json.exists():
        if out.exists() and any(out.iterdir()):
            raise ValueError(f"{out} exists and is not a policy run directory; choose another --out")
        return
    try:
        prev = json.loads(run_json.read_text())
        prev_cfg = stored_config(prev["config"])
    except (json.JSONDecodeError, KeyError, AttributeError) as exc:
        raise ValueError(f"{run_json} is corrupt: {exc}") from exc
    now = cfg.to_dict()
    diffs = [f"{k}: {prev_cfg.get(k)!r} -> {now[k]!r}" for k in now
             if k not in _RESUMABLE_FIELDS and prev_cfg.get(k) != now[k]]  # fmt: skip
    if (prev.get("predictor") or {}).get("sha256") != predictor_sha256:
        diffs.append("predictor file content differs")
    if diffs:
        raise ValueError(f"{out} holds a run with another configuration ({'; '.join(diffs)}); "
                         "use another --out or --overwrite")  # fmt: skip


def train_policy(
    cfg: PolicyConfig,
    out: str | os.PathLike[str],
    *,
    predictor: str | os.PathLike[str] | None = None,
    device: str = "cpu",
    progress: Callable[[dict[str, Any]], None] | None = None,
    eval_progress: Callable[[int, int], None] | None = None,
    log_every: int | None = None,
) -> TrainResult:
    """Train (or resume, or just finish evaluating) the run in ``out``; see the module docstring.

    Args:
        cfg: the run's configuration.
        predictor: predictor checkpoint, required by the ``prediction`` and ``hybrid`` modes.
        progress: called with each progress row (a dict of :data:`PROGRESS_COLUMNS`).
        log_every: timesteps between progress rows (default: one PPO/A2C rollout, 2048 for DQN).

    Raises:
        ValueError: bad input (missing predictor, a different run in ``out``).
    """
    out = Path(out)
    pred_path = Path(predictor) if predictor is not None and needs_predictor(cfg.obs) else None
    if needs_predictor(cfg.obs) and pred_path is None:
        raise ValueError(f"observation mode {cfg.obs!r} needs a trained predictor (--predictor)")
    pred = Predictor.load(pred_path) if pred_path is not None else None
    pred_sha = file_sha256(pred_path) if pred_path is not None else None
    check_run_dir(cfg, out, pred_sha)
    out.mkdir(parents=True, exist_ok=True)
    run = _Run(cfg, out, pred_path, pred_sha, progress)
    write_json(out / "run.json", {"config": cfg.to_dict(), "predictor": run.predictor,
                                   "scenario": cfg.scenario_config().to_dict(), "versions": versions()})  # fmt: skip
    final = out / "policy.zip"
    train_info: dict[str, Any] = {}
    if (out / "metrics.json").exists():
        train_info = json.loads((out / "metrics.json").read_text()).get("train", {})
    done_steps = int(train_info.get("timesteps", 0)) if final.exists() else 0
    torch.manual_seed(cfg.seed)
    if not final.exists() or done_steps < cfg.timesteps:
        train_info = _train(cfg, run, pred, device, log_every, final)
    config = cfg.scenario_config()
    metrics: dict[str, Any] = {"config": cfg.to_dict(), "train": train_info}
    eval_json = out / "eval" / "metrics.json"
    if cfg.eval_episodes > 0:
        summary = json.loads(eval_json.read_text()) if eval_json.exists() else {}
        policy_sha = file_sha256(final)  # a run continued to more timesteps has a new policy to evaluate
        if (summary.get("episodes"), summary.get("eval_seed"), summary.get("policy_sha256")) != (
                cfg.eval_episodes, cfg.eval_seed, policy_sha):
            from lcmodels.policy.checkpoint import load_policy

            loaded: LoadedPolicy = load_policy(final, predictor=pred_path, device=device)
            train_seeds = np.load(run.seeds_path) if run.seeds_path.exists() else None
            t0 = time.perf_counter()
            summary, _ = evaluate(PolicyDriver(loaded), config, episodes=cfg.eval_episodes, seed=cfg.eval_seed,
                                  out_dir=out / "eval" / "episodes" if cfg.record_eval else None,
                                  batch=cfg.eval_batch, overwrite=True, train_seeds=train_seeds,
                                  progress=eval_progress)  # fmt: skip
            summary["wall_s"] = time.perf_counter() - t0
            summary["policy_sha256"] = policy_sha
            write_json(eval_json, summary)
        metrics["eval"] = summary
    write_json(out / "metrics.json", metrics)
    return TrainResult(out, int(train_info.get("timesteps", 0)), float(train_info.get("wall_s", 0.0)), metrics)


def _train(cfg: PolicyConfig, run: _Run, pred: Predictor | None, device: str, log_every: int | None,
           final: Path) -> dict[str, Any]:
    out = run.out
    resume = run.ckpt.exists() and run.ckpt_state.exists()
    if resume:
        state = json.loads(run.ckpt_state.read_text())
        run.start_timesteps = int(state["timesteps"])
        run.wall_before = float(state["wall_s"])
        run.episodes_total = int(state["episodes_total"])
        if run.seeds_path.exists():
            run.prior_seeds = np.load(run.seeds_path)
        run.truncate_progress(run.start_timesteps)
        log.info("resuming %s from step %d", out, run.start_timesteps)
    elif (out / "progress.csv").exists():
        (out / "progress.csv").unlink()  # a previous attempt died before its first checkpoint
    config = cfg.scenario_config()
    base = LaneChangeSB3VecEnv(cfg.n_envs, config)
    # The initial policy, loaded once: its weights start the model, its image branch (when frozen) the wrapper.
    initial = _load_init_policy(cfg, run, config, device) if cfg.init_policy and not resume else None
    encoder = _frozen_image_encoder(cfg, run, config, initial) if cfg.freeze_image else None
    env = PolicyVecEnv(base, cfg.obs, pred, reward_scale=cfg.reward_scale, image_encoder=encoder,
                       collision_weight=cfg.collision_weight)
    run.env = env
    tb = str(out / "tb")
    warm: dict[str, Any] | None = None
    if resume:
        model = ALGOS[cfg.algo].load(run.ckpt, env=env, device=device, tensorboard_log=tb)
    else:
        model = build_model(cfg, env, tb, device)
        if cfg.warm_start:
            warm = _warm_start(cfg, model, pred, config)
            write_json(out / "warm_start.json", warm)
        elif cfg.init_policy:
            assert initial is not None
            warm = _init_policy(cfg, model, initial)
            write_json(out / "warm_start.json", warm)
    env.seed(train_seed_base(cfg.seed, run.start_timesteps))
    model.set_logger(configure(tb, ["tensorboard"]))
    every = log_every or (cfg.n_envs * cfg.n_steps if cfg.algo != "dqn" else 2048)
    callback = _Logger(run, env, every)
    remaining = cfg.timesteps - run.start_timesteps
    if remaining > 0:
        model.learn(total_timesteps=remaining, callback=callback, reset_num_timesteps=False,
                    tb_log_name=f"{cfg.algo}_{cfg.obs}")  # fmt: skip
    t = int(model.num_timesteps)
    if callback.last_log != t:
        callback._log(t)
    run.checkpoint(model, t, callback.episodes_total)
    if encoder is not None:
        model = _with_image_branch(cfg, model, encoder, PolicyVecEnv(base, cfg.obs, pred), device)
    save_policy(model, final, run.meta(t))
    info = {"timesteps": t, "wall_s": run.wall_s(), "episodes": callback.episodes_total,
            "resumed_from": run.start_timesteps, "warm_start": warm}  # fmt: skip
    env.close()
    return info


def _load_init_policy(cfg: PolicyConfig, run: _Run, config: ScenarioConfig, device: str) -> LoadedPolicy:
    """``cfg.init_policy``, after checking that it fits this run (mode, predictor, scenario, algorithm)."""
    from lcmodels.policy.checkpoint import load_policy

    path = Path(cfg.init_policy)
    if not path.is_file():
        raise ValueError(f"init_policy {path} does not exist")
    loaded = load_policy(path, obs_mode=cfg.obs, scenario=config, device=device,
                         predictor=run.predictor["path"] if run.predictor else None)  # fmt: skip
    if loaded.meta.get("algo") != cfg.algo:
        raise ValueError(f"init_policy {path} is a {loaded.meta.get('algo')} policy, this run trains {cfg.algo}")
    return loaded


def _init_policy(cfg: PolicyConfig, model: BaseAlgorithm, loaded: LoadedPolicy) -> dict[str, Any]:
    """Copy the weights of the initial policy ``loaded`` (``cfg.init_policy``) into ``model``."""
    path = Path(cfg.init_policy)
    state = loaded.model.policy.state_dict()
    if cfg.freeze_image:  # the image branch runs in the observation wrapper (_frozen_image_encoder)
        state = {k: v for k, v in state.items() if _IMAGE_BRANCH not in k}
    try:
        model.policy.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f"init_policy {path} has another network: {str(exc).splitlines()[0]}") from exc
    log.info("starting from the weights of %s", path)
    return {"init_policy": str(path.resolve()), "sha256": file_sha256(path)}


_IMAGE_BRANCH = ".branches.image."  # in the policy's state-dict keys


def _frozen_image_encoder(cfg: PolicyConfig, run: _Run, config: ScenarioConfig,
                          initial: LoadedPolicy | None) -> ImageEncoder:
    """The frozen image branch of a ``freeze_image`` run: the initial policy's, kept in the run directory
    (``image_encoder.pt``) on the first start so that a resume (``initial`` None) does not need that file."""
    path = run.out / "image_encoder.pt"
    if path.exists():
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises several types for a damaged file
            raise ValueError(f"{path} is not readable (corrupt or truncated?): {str(exc).splitlines()[0]}") from exc
    else:
        assert initial is not None, "a first start has the initial policy"
        extractor = initial.model.policy.features_extractor
        if not isinstance(extractor, HybridExtractor) or "image" not in extractor.branches:
            raise ValueError(f"init_policy {cfg.init_policy} has no image branch to freeze")
        state = {k: v.detach().cpu() for k, v in extractor.branches["image"].state_dict().items()}
        tmp = path.with_suffix(".partial")
        torch.save(state, tmp)
        tmp.replace(path)
    net = make_image_net(cfg.image_net, 3, config.render.image_size_px, cfg.image_features)
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f"the image branch of {cfg.init_policy} is not a {cfg.image_net} network with "
                         f"{cfg.image_features} features: {str(exc).splitlines()[0]}") from exc
    return ImageEncoder(net, cfg.image_features)


def _with_image_branch(cfg: PolicyConfig, model: BaseAlgorithm, encoder: ImageEncoder, env: PolicyVecEnv,
                       device: str) -> BaseAlgorithm:
    """A plain policy of the mode (``env``: the wrapper without the encoder) with ``model``'s weights and
    the frozen image branch: the same function of the observation, in a file any loader reads."""
    plain = build_model(cfg, env, None, device)
    trained = model.policy.state_dict()
    image = encoder.state_dict()
    state = {k: image[k.split(_IMAGE_BRANCH, 1)[1]] if _IMAGE_BRANCH in k else trained[k]
             for k in plain.policy.state_dict()}
    plain.policy.load_state_dict(state)
    plain.num_timesteps = model.num_timesteps
    return plain


def _warm_start(cfg: PolicyConfig, model: BaseAlgorithm, pred: Predictor | None,
                config: ScenarioConfig) -> dict[str, Any]:
    from lcmodels.policy.warmstart import bc_loss, every_tenth, load_demonstrations, pretrain

    t0 = time.perf_counter()
    demos = load_demonstrations(cfg.warm_start, cfg.obs, pred, gamma=cfg.gamma, reward_scale=cfg.reward_scale,
                                collision_weight=cfg.collision_weight, scenario=config,
                                progress=every_tenth(log.info, "warm start: read {}/{} episodes"))
    before = bc_loss(model, demos)
    epochs = cfg.warm_start_epochs
    losses = pretrain(model, demos, epochs=epochs, seed=cfg.seed,
                      progress=lambda e, loss: log.info("warm start: epoch %d/%d, loss %.4f", e, epochs, loss))
    after = bc_loss(model, demos)
    log.info("warm start on %d decisions of %d episodes: NLL %.3f -> %.3f", len(demos), demos.episodes, before, after)
    return {"data": cfg.warm_start, "episodes": demos.episodes, "decisions": len(demos), "nll_before": before,
            "nll_after": after, "epoch_losses": losses, "wall_s": time.perf_counter() - t0}  # fmt: skip
