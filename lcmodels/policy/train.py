"""Online training of the lane-change policy on the batched simulator, resumable (:func:`train_run`), then
evaluation (:func:`evaluate_run`); :func:`train_policy` does both.

A run directory holds::

    run.json                  the PolicyConfig, predictor identity, versions (a rerun must match it)
    checkpoints/latest.json   the last periodic checkpoint: step count, wall time, and the names of its
                              files beside it, step-<t>.safetensors (policy file format, see
                              lcmodels.policy.checkpoint) and step-<t>.optim.pt (the optimiser's tensors,
                              loaded with weights_only=True); written last, so a kill never leaves a
                              half checkpoint behind it
    progress.csv              one row per log interval: timesteps, wall_s and the outcome rates,
                              mean return and safe forward distance over the last 100 episodes
    tb/                       TensorBoard (SB3's scalars plus lc/*)
    train_episode_seeds.npy   simulator seeds of every training episode (for the held-out check)
    warm_start.json           behaviour-cloning losses when warm-started, or the --init-policy started from
    policy.safetensors        the final policy (and policy.card.json, its card for people)
    eval/metrics.json         held-out evaluation (see lcmodels.policy.evaluate); eval/episodes/*.mcap
    metrics.json              training summary + evaluation, what lc-experiment reads

Rerunning with the same ``--out`` resumes from ``checkpoints/latest.json`` (the step count continues),
skips training when the policy is complete, and only evaluates what is missing. Nothing in a run
directory is unpickled. ``overwrite`` replaces a run with another configuration by removing only the
files of this layout (:data:`RUN_OUTPUTS`), after every other check has passed; anything else in the
directory stays.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
import platform
import re
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import VecEnv

from lckit.fileio import check_inside, check_output_folder, loads_json, remove_file, write_file
from lcmodels.fileio import POLICY_FILE, check_dtypes, file_sha256, read_train_seeds, write_json
from lcmodels.policy.checkpoint import (
    MAX_CARD_TIMESTEPS,
    LoadedPolicy,
    card_path,
    load_policy,
    load_weights,
    save_policy,
    scenario_differences,
)
from lcmodels.policy.config import (  # re-exported: the names training's callers know
    FINE_TUNE_LEARNING_RATES,
    PolicyConfig,
    default_learning_rate,
)
from lcmodels.policy.evaluate import EVAL_SEED_BASE, PolicyDriver, evaluate
from lcmodels.policy.extractor import HybridExtractor, ImageEncoder, make_image_net, plain_policy_state
from lcmodels.policy.network import build_model
from lcmodels.policy.obs import EpisodeStats, episode_seeds_of, episode_stats, policy_vec_env, summarize
from lcmodels.policy.plan import RunPlan, resolve
from lcmodels.policy.shield import ShieldedSB3VecEnv
from lcsim.config import ScenarioConfig
from lcsim.sb3 import LaneChangeSB3VecEnv, MixedRoadsSB3VecEnv

log = logging.getLogger(__name__)



PROGRESS_COLUMNS = ("timesteps", "wall_s", "episodes_total", "window", "success_rate", "collision_rate",
                    "off_road_rate", "timeout_rate", "mean_return", "mean_safe_forward_m", "mean_forward_m")  # fmt: skip
# Fields that may change between a run and its continuation.
_RESUMABLE_FIELDS = ("timesteps", "checkpoint_every", "eval_episodes", "eval_seed", "eval_batch", "record_eval")


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
    """What ``metrics.json`` holds: the config, the training summary and (once evaluated) the evaluation."""
    config: PolicyConfig | None = None
    scenario: ScenarioConfig | None = None
    """The scenario the run trained on (what its policy's card stores)."""
    predictor: Path | None = None


class _Logger(BaseCallback):
    """Outcome statistics to TensorBoard and progress.csv; periodic checkpoints."""

    def __init__(self, run: _Run, log_every: int) -> None:
        super().__init__()
        self.run, self.log_every = run, log_every
        self.window: deque[EpisodeStats] = deque(maxlen=100)
        self.episodes_total = run.episodes_total
        self.last_log = run.start_timesteps
        self.last_ckpt = run.start_timesteps

    def _on_step(self) -> bool:
        finished = [e for e in map(episode_stats, self.locals["infos"]) if e is not None]
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
        row.update((k, v) for k, v in summarize(w).items() if k != "episodes")
        for k, v in row.items():
            if k not in ("timesteps", "wall_s"):
                self.logger.record(f"lc/{k}", v)
        self.run.append_progress(row)
        if self.run.progress is not None:
            self.run.progress(row)


class _Run:
    """The run directory while it trains: checkpoints, progress rows, wall time across resumes."""

    def __init__(self, plan: RunPlan, out: Path, progress: Callable[[dict[str, Any]], None] | None, t_start: float,
                 initial: LoadedPolicy | None) -> None:  # fmt: skip
        self.plan, self.cfg, self.out, self.progress = plan, plan.config, out, progress
        self.initial = initial
        """``cfg.init_policy``, loaded and checked, when the run starts from it (not on a resume)."""
        self.ckpt_state = out / "checkpoints" / "latest.json"
        self.start_timesteps = 0
        self.episodes_total = 0
        self.wall_before = 0.0
        self.t_start = t_start
        self.seeds_path = out / "train_episode_seeds.npy"
        self.prior_seeds = np.zeros(0, dtype=np.int64)
        self.env: VecEnv | None = None

    def wall_s(self) -> float:
        return self.wall_before + time.perf_counter() - self.t_start

    def restore(self) -> dict[str, Any]:
        """The last checkpoint's state (empty when there is none), its counters taken over; files of a killed
        attempt that ``latest.json`` does not name (it is written last) are removed."""
        state: dict[str, Any] = {}
        if self.ckpt_state.exists():
            state = read_checkpoint_state(self.ckpt_state)
            self.start_timesteps = int(state["timesteps"])
            self.wall_before = float(state["wall_s"])
            self.episodes_total = int(state["episodes_total"])
            self.prior_seeds = read_train_seeds(self.out) if self.seeds_path.exists() else self.prior_seeds
            self.truncate_progress(self.start_timesteps)
            log.info("resuming %s from step %d", self.out, self.start_timesteps)
        else:  # a previous attempt died before its first checkpoint
            remove_file(self.out / "progress.csv", self.out)
        keep = {state["weights"], state["optimizer"], card_path(state["weights"]).name} if state else set()
        for f in self.ckpt_state.parent.glob("step-*"):
            if f.name not in keep:
                remove_file(f, self.out)
        return state

    def all_seeds(self) -> np.ndarray:
        new = np.asarray(episode_seeds_of(self.env) if self.env is not None else [], dtype=np.int64)
        return np.concatenate([self.prior_seeds, new])

    def checkpoint(self, model: BaseAlgorithm, t: int, episodes_total: int) -> None:
        """Weights, optimiser and counters at step ``t``; ``latest.json`` names them once they are complete,
        then the previous checkpoint's files go."""
        folder = self.ckpt_state.parent
        previous = read_checkpoint_state(self.ckpt_state) if self.ckpt_state.exists() else None
        weights, optim = f"step-{t}.safetensors", f"step-{t}.optim.pt"
        save_policy(model, folder / weights, self.plan.card(t, folder, training_form=self.cfg.freeze_image))
        write_file(folder / optim, lambda tmp: torch.save(model.policy.optimizer.state_dict(), tmp), by_name=True)
        write_file(self.seeds_path, lambda f: np.save(f, self.all_seeds()))
        write_json(self.ckpt_state, {"timesteps": t, "wall_s": self.wall_s(), "episodes_total": episodes_total,
                                     "weights": weights, "optimizer": optim,
                                     "n_updates": int(getattr(model, "_n_updates", 0)),
                                     "n_calls": int(getattr(model, "_n_calls", 0))})  # fmt: skip
        if previous is not None and previous["weights"] != weights:
            for name in (previous["weights"], previous["optimizer"]):
                for f in (folder / name, card_path(folder / name)):
                    remove_file(f, self.out)

    def append_progress(self, row: dict[str, Any]) -> None:
        self.write_progress([*self.progress_rows(), row])

    def truncate_progress(self, t: int) -> None:
        """Drop progress rows logged after the checkpoint we resume from (they will be redone)."""
        if (self.out / "progress.csv").exists():
            self.write_progress([r for r in self.progress_rows() if int(float(r["timesteps"])) <= t])

    def progress_rows(self) -> list[dict[str, Any]]:
        path = self.out / "progress.csv"
        if not path.exists() or path.is_symlink():  # a link is refused when written
            return []
        with path.open(newline="") as f:
            return list(csv.DictReader(f))

    def write_progress(self, rows: list[dict[str, Any]]) -> None:
        """``progress.csv`` rewritten whole (with :func:`~lckit.fileio.write_file`: never through a link)."""
        text = io.StringIO(newline="")
        w = csv.DictWriter(text, fieldnames=PROGRESS_COLUMNS)
        w.writeheader()
        w.writerows(rows)
        write_file(self.out / "progress.csv", text.getvalue())


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


RUN_OUTPUTS: tuple[str, ...] = (
    "run.json", "progress.csv", "metrics.json", "warm_start.json", "train_episode_seeds.npy", "image_encoder.pt",
    "shield.json",
    POLICY_FILE, card_path(POLICY_FILE).name, "checkpoints/latest.json", "checkpoints/step-*.safetensors",
    "checkpoints/step-*.card.json", "checkpoints/step-*.optim.pt", "checkpoints/*.partial*", "*.partial*",
    "eval/metrics.json", "eval/metrics.json.partial", "eval/episodes/*.mcap", "eval/episodes/*.mcap.partial",
    "tb/events.out.tfevents.*", "tb/*/events.out.tfevents.*",
)  # fmt: skip
"""The files a training run writes in its directory (glob patterns relative to it): all that ``overwrite``
removes."""


def remove_run_outputs(out: Path) -> tuple[int, list[Path]]:
    """Remove the files of :data:`RUN_OUTPUTS` in ``out`` (none when one is reached through a link out of ``out``)
    and the folders they leave empty; returns how many files went and the files that stayed (not the tool's)."""
    files = list(dict.fromkeys(f for p in RUN_OUTPUTS for f in out.glob(p) if f.is_file() or f.is_symlink()))
    for f in files:
        check_inside(f.parent, out)
    for f in files:
        remove_file(f, out)
    for d in sorted((d for d in out.rglob("*") if d.is_dir()), key=lambda d: len(d.parts), reverse=True):
        with contextlib.suppress(OSError):
            d.rmdir()  # only when empty
    kept = sorted(f for f in out.rglob("*") if f.is_file()) if out.exists() else []
    return len(files), kept


_CKPT_WEIGHTS = re.compile(r"step-\d{1,15}\.safetensors")
_CKPT_OPTIM = re.compile(r"step-\d{1,15}\.optim\.pt")
"""The names :meth:`checkpoint` gives a checkpoint's files: nothing else is read or deleted from ``latest.json``."""


def read_checkpoint_state(path: Path) -> dict[str, Any]:
    """``checkpoints/latest.json``: the step count, wall time, episodes and file names of the last checkpoint
    (``ValueError`` naming the file when it is corrupt or incomplete)."""
    try:
        if path.stat().st_size > 1 << 20:
            raise OSError(f"{path.stat().st_size} bytes, not a checkpoint record")
        state = loads_json(path.read_text())
        if not isinstance(state, dict):
            raise TypeError(f"a JSON {type(state).__name__}, not an object")
        missing = [k for k in ("timesteps", "wall_s", "episodes_total", "weights", "optimizer") if k not in state]
        if missing:
            raise KeyError(", ".join(missing))
        for key, pattern in (("weights", _CKPT_WEIGHTS), ("optimizer", _CKPT_OPTIM)):
            if not isinstance(state[key], str) or not pattern.fullmatch(state[key]):
                # the names are joined to the folder and the files later deleted: only this tool's own names
                raise TypeError(f"{key} {str(state[key])[:80]!r} is not a checkpoint file name of this folder")
        for key in ("timesteps", "episodes_total", "n_updates", "n_calls"):  # counts the resumed run continues
            v = state.get(key, 0)
            if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= MAX_CARD_TIMESTEPS:
                raise TypeError(f"{key} {str(v)[:40]!r} is not a count in [0, {MAX_CARD_TIMESTEPS}]")
        wall = state["wall_s"]
        if not isinstance(wall, int | float) or isinstance(wall, bool) or not 0 <= wall < 1e10:
            raise TypeError(f"wall_s {str(wall)[:40]!r} is not a number of seconds")
        return state
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} is corrupt ({type(exc).__name__}: {exc}); remove the checkpoints folder to "
                         "restart training from step 0") from None


def check_run_dir(cfg: PolicyConfig, out: Path, predictor_sha256: str | None, *, overwrite: bool = False,
                  scenario: ScenarioConfig | None = None) -> bool:
    """Whether ``out`` can hold this run. ``ValueError`` when it holds a run with another config or predictor
    (says what differs) unless ``overwrite``, or files that are no run of this tool's. Returns True when the
    run there is to be replaced (``overwrite`` and a different run), False to start or resume. ``scenario``:
    the run's scenario when the caller has read it (else read from ``cfg``)."""
    run_json = out / "run.json"
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a directory")
    if not run_json.exists():
        if out.exists() and any(out.iterdir()):
            raise ValueError(f"{out} exists and is not a policy run directory (no run.json); choose another --out "
                             "(--overwrite only replaces a run this tool wrote)")
        return False
    try:
        prev = loads_json(run_json.read_text())
        prev_cfg = stored_config(prev["config"])
        if not isinstance(prev.get("predictor") or {}, dict):
            raise TypeError("its predictor is not an object")
    except (OSError, ValueError, KeyError, AttributeError, TypeError) as exc:
        if overwrite:
            return True
        raise ValueError(f"{run_json} is corrupt ({type(exc).__name__}: {exc}); pass --overwrite to replace "
                         "the run") from None
    now = cfg.to_dict()
    diffs = [f"{k}: {prev_cfg.get(k)!r} -> {now[k]!r}" for k in now
             if k not in _RESUMABLE_FIELDS and prev_cfg.get(k) != now[k]]  # fmt: skip
    if (prev.get("predictor") or {}).get("sha256") != predictor_sha256:
        diffs.append("predictor file content differs")
    if "scenario" in prev and not diffs:  # a scenario file whose content changed since the run began
        changed = scenario_differences(prev["scenario"] or {}, scenario)
        if changed:
            diffs.append(f"the scenario's content differs ({'; '.join(changed[:3])})")
    if diffs and not overwrite:
        raise ValueError(f"{out} holds a run with another configuration ({'; '.join(diffs)}); "
                         "use another --out or --overwrite")  # fmt: skip
    legacy = [f for f in (out / "policy.zip", out / "checkpoints" / "latest.zip") if f.exists()]
    if legacy and not overwrite:
        raise ValueError(f"{out} is a run of an older version ({legacy[0].relative_to(out)} is a pickle, which this "
                         "version never loads to resume); use another --out, or --overwrite to restart it")
    if legacy:
        return True
    if not diffs and (out / "checkpoints" / "latest.json").exists():
        read_checkpoint_state(out / "checkpoints" / "latest.json")
    return bool(diffs)


def train_policy(
    cfg: PolicyConfig,
    out: str | os.PathLike[str],
    *,
    predictor: str | os.PathLike[str] | None = None,
    device: str = "cpu",
    progress: Callable[[dict[str, Any]], None] | None = None,
    eval_progress: Callable[[int, int], None] | None = None,
    log_every: int | None = None,
    overwrite: bool = False,
) -> TrainResult:
    """Resolve ``cfg`` (:func:`lcmodels.policy.plan.resolve`), train (or resume) the run in ``out``
    (:func:`train_run`), then evaluate it on ``cfg.eval_episodes`` held-out episodes (:func:`evaluate_run`); see
    the module docstring.

    Args:
        cfg: the run's configuration.
        predictor: predictor checkpoint, required by the ``prediction`` and ``hybrid`` modes.
        progress: called with each progress row (a dict of :data:`PROGRESS_COLUMNS`).
        eval_progress: called with (episodes done, episodes) while evaluating.
        log_every: timesteps between progress rows (default: one PPO/A2C rollout, 2048 for DQN).
        overwrite: replace a run of another configuration in ``out`` (only its own files go, and only
            after every other check has passed).

    Raises:
        ValueError: bad input (missing predictor, an unreadable scenario, a different run in ``out``, an ``out``
            that cannot be written or is the filesystem root or the home directory, an unusable initial policy
            or warm-start directory); nothing has been written then.
    """
    result = train_run(resolve(cfg, predictor=predictor), out, device=device, progress=progress,
                       log_every=log_every, overwrite=overwrite)  # fmt: skip
    if cfg.eval_episodes > 0:
        evaluate_run(result, device=device, progress=eval_progress)
    return result


def train_run(
    plan: RunPlan,
    out: str | os.PathLike[str],
    *,
    device: str = "cpu",
    progress: Callable[[dict[str, Any]], None] | None = None,
    log_every: int | None = None,
    overwrite: bool = False,
) -> TrainResult:
    """Train the run of ``plan`` in ``out``, resume it, or find it complete: :func:`train_policy` without the
    evaluation (the other arguments are its own). Writes ``metrics.json`` with the config and the training
    summary; behind ``plan.layer``, what the layer did in ``shield.json``."""
    out, cfg, shield = Path(out), plan.config, plan.layer
    replace, initial = _check(plan, out, device, overwrite)
    run = _Run(plan, out, progress, time.perf_counter(), initial)
    # Every check has passed: from here on the directory is written.
    if replace:
        removed, kept = remove_run_outputs(out)
        log.info("--overwrite: removed the %d files of the previous run in %s%s", removed, out,
                 f"; kept {len(kept)} files it did not write" if kept else "")
    out.mkdir(parents=True, exist_ok=True)
    run_predictor = None if plan.predictor_path is None else {
        "file": plan.predictor_path.name, "sha256": str(plan.predictor_sha256), "path": plan.predictor_file}
    write_json(out / "run.json", {"config": cfg.to_dict(), "predictor": run_predictor,
                                   "scenario": plan.scenario.to_dict(), "versions": versions()})  # fmt: skip
    final = out / POLICY_FILE
    train_info: dict[str, Any] = {}
    if (out / "metrics.json").exists():
        train_info = json.loads((out / "metrics.json").read_text()).get("train", {})
    done_steps = int(train_info.get("timesteps", 0)) if final.exists() else 0
    torch.manual_seed(cfg.seed)
    if not final.exists() or done_steps < cfg.timesteps:
        train_info = _train(run, device, log_every, final)
        if shield is not None:  # the decisions of the steps this call trained (a resumed run: since its checkpoint)
            write_json(out / "shield.json", shield.counts() | {"penalty": shield.penalty,
                                                               "from_step": run.start_timesteps,
                                                               "to_step": int(train_info.get("timesteps", 0))})
    metrics: dict[str, Any] = {"config": cfg.to_dict(), "train": train_info}
    write_json(out / "metrics.json", metrics)
    return TrainResult(out, int(train_info.get("timesteps", 0)), float(train_info.get("wall_s", 0.0)), metrics,
                       cfg, plan.scenario, plan.predictor_path)  # fmt: skip


def evaluate_run(result: TrainResult, *, device: str = "cpu",
                 progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Evaluate the policy of a trained run on its config's held-out episodes (``eval/``; reused while the
    episodes, seed and policy are the same), and add the summary to ``metrics.json`` and ``result.metrics``."""
    cfg, out = result.config, result.out
    assert cfg is not None and result.scenario is not None, "a result of train_run"
    final, eval_json = out / POLICY_FILE, out / "eval" / "metrics.json"
    summary = json.loads(eval_json.read_text()) if eval_json.exists() else {}
    policy_sha = file_sha256(final)  # a run continued to more timesteps has a new policy to evaluate
    recorded = (out / "eval" / "episodes").is_dir() or not cfg.record_eval
    if not recorded or (summary.get("episodes"), summary.get("eval_seed"), summary.get("policy_sha256")) != (
            cfg.eval_episodes, cfg.eval_seed, policy_sha):
        loaded: LoadedPolicy = load_policy(final, predictor=result.predictor, device=device)
        train_seeds = read_train_seeds(out)
        t0 = time.perf_counter()
        summary, _ = evaluate(PolicyDriver(loaded), result.scenario, episodes=cfg.eval_episodes,
                              seed=cfg.eval_seed, out_dir=out / "eval" / "episodes" if cfg.record_eval else None,
                              batch=cfg.eval_batch, overwrite=True, train_seeds=train_seeds,
                              progress=progress)  # fmt: skip
        summary["wall_s"] = time.perf_counter() - t0
        summary["policy_sha256"] = policy_sha
        write_json(eval_json, summary)
    result.metrics["eval"] = summary
    write_json(out / "metrics.json", result.metrics)
    return summary


def _check(plan: RunPlan, out: Path, device: str, overwrite: bool) -> tuple[bool, LoadedPolicy | None]:
    """Every check of the run directory ``out`` and of what the run starts from (``ValueError``, nothing
    written): whether the run there is to be replaced, and the initial policy, loaded, when it starts from one."""
    cfg = plan.config
    check_output_folder(out)
    for folder in ("checkpoints", "eval", "eval/episodes", "tb"):  # what the run writes in: never through a link
        check_inside(out / folder, out)
    replace = check_run_dir(cfg, out, plan.predictor_sha256, overwrite=overwrite, scenario=plan.scenario)
    if cfg.warm_start:
        path = Path(cfg.warm_start)
        if not path.is_dir():
            raise ValueError(f"warm_start {path} is not a directory of recorded episodes")
        if not any(path.glob("*.mcap")):
            raise ValueError(f"warm_start {path} holds no .mcap episodes (record some with lc-record)")
    if replace:  # what the run starts from must not be among what --overwrite removes
        for what, given in (("init_policy", cfg.init_policy), ("warm_start", cfg.warm_start)):
            if given and Path(given).resolve().is_relative_to(out.resolve()):
                raise ValueError(f"{what} {given} is inside {out}, whose run --overwrite would remove; copy it "
                                 "elsewhere first, or use another --out")
    initial = None
    if cfg.init_policy and (replace or not (out / "checkpoints" / "latest.json").exists()):
        path = Path(cfg.init_policy)  # checked to fit this run: mode, predictor, scenario, algorithm
        if not path.is_file():
            raise ValueError(f"init_policy {path} does not exist")
        initial = load_policy(path, obs_mode=cfg.obs, scenario=plan.scenario, device=device,
                              predictor=plan.predictor_file)
        if initial.meta.get("algo") != cfg.algo:
            raise ValueError(f"init_policy {path} is a {initial.meta.get('algo')} policy, this run trains {cfg.algo}")
    return replace, initial


def _train(run: _Run, device: str, log_every: int | None, final: Path) -> dict[str, Any]:
    plan, cfg = run.plan, run.cfg
    state = run.restore()
    env, encoder, model, warm = _build(run, state, device)
    run.env = env
    env.seed(train_seed_base(cfg.seed, run.start_timesteps))
    model.set_logger(configure(str(run.out / "tb"), ["tensorboard"]))
    every = log_every or (cfg.n_envs * cfg.n_steps if cfg.algo != "dqn" else 2048)
    callback = _Logger(run, every)
    remaining = cfg.timesteps - run.start_timesteps
    if remaining > 0:
        model.learn(total_timesteps=remaining, callback=callback, reset_num_timesteps=False,
                    tb_log_name=f"{cfg.algo}_{cfg.obs}")  # fmt: skip
    t = int(model.num_timesteps)
    if callback.last_log != t:
        callback._log(t)
    run.checkpoint(model, t, callback.episodes_total)
    # the policy file of a frozen-image run holds the image branch again: any loader reads it as a plain policy
    save_policy(model, final, plan.card(t, final.parent),
                state=None if encoder is None else plain_policy_state(model.policy, encoder))  # fmt: skip
    info = {"timesteps": t, "wall_s": run.wall_s(), "episodes": callback.episodes_total,
            "resumed_from": run.start_timesteps, "warm_start": warm}  # fmt: skip
    env.close()
    return info


_IMAGE_BRANCH = ".branches.image."  # in the policy's state-dict keys


def _build(run: _Run, state: dict[str, Any], device: str
           ) -> tuple[VecEnv, ImageEncoder | None, BaseAlgorithm, dict[str, Any] | None]:
    """The environments (the simulator's, behind the plan's safety layer when it has one, in the observation
    wrapper), the frozen image branch of a ``freeze_image`` run, and the model: a checkpoint's when ``state`` names
    one, else a fresh network, warm-started or started from the initial policy (its weights; its image branch when
    frozen)."""
    plan, cfg, initial, out = run.plan, run.cfg, run.initial, run.out
    if plan.layer is not None:
        base: VecEnv = ShieldedSB3VecEnv(cfg.n_envs, plan.scenario, plan.layer)
    elif len(plan.roads) > 1:
        base = MixedRoadsSB3VecEnv(cfg.n_envs, plan.roads)
    else:
        base = LaneChangeSB3VecEnv(cfg.n_envs, plan.scenario)
    encoder = None
    if cfg.freeze_image:  # kept in the run directory on the first start: a resume does not need init_policy
        encoder = _frozen_image_encoder(run, out / "image_encoder.pt")
    env = policy_vec_env(base, cfg.obs, plan.predictor, reward_scale=cfg.reward_scale, image_encoder=encoder,
                         collision_weight=cfg.collision_weight)
    model = build_model(cfg, env, str(out / "tb"), device)
    warm: dict[str, Any] | None = None
    if state:  # a checkpoint's tensors, optimiser state and counters; nothing unpickled
        folder = out / "checkpoints"
        weights, optim = folder / state["weights"], folder / state["optimizer"]
        for f in (weights, optim):
            if not f.is_file():
                raise ValueError(f"checkpoint file {f} named by {folder / 'latest.json'} is missing")
        load_weights(model, weights, device)
        try:
            model.policy.optimizer.load_state_dict(torch.load(optim, map_location=device, weights_only=True))
        except Exception as exc:  # torch raises several types for a damaged file
            raise ValueError(f"{optim} is not a readable optimiser state (truncated, corrupt or foreign: "
                             f"{type(exc).__name__})") from None
        model.num_timesteps = int(state["timesteps"])
        model._n_updates = int(state.get("n_updates", 0))
        if cfg.algo == "dqn":
            model._n_calls = int(state.get("n_calls", 0))
    elif cfg.warm_start:
        from lcmodels.policy.warmstart import warm_start

        warm = warm_start(cfg, model, plan.predictor, plan.scenario, say=log.info)
        write_json(out / "warm_start.json", warm)
    elif cfg.init_policy:
        assert initial is not None
        path, weights = Path(cfg.init_policy), initial.model.policy.state_dict()
        if cfg.freeze_image:  # the image branch runs in the observation wrapper
            weights = {k: v for k, v in weights.items() if _IMAGE_BRANCH not in k}
        try:
            model.policy.load_state_dict(weights)
        except RuntimeError as exc:
            raise ValueError(f"init_policy {path} has another network: {str(exc).splitlines()[0]}") from exc
        log.info("starting from the weights of %s", path)
        warm = {"init_policy": str(path.resolve()), "sha256": file_sha256(path)}
        write_json(out / "warm_start.json", warm)
    return env, encoder, model, warm


def _frozen_image_encoder(run: _Run, path: Path) -> ImageEncoder:
    """The image branch of a ``freeze_image`` run with the initial policy's weights, which the first start
    keeps in the run directory (``path``) so that a resume (no ``initial``) does not need them."""
    cfg, plan = run.cfg, run.plan
    if path.exists():
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises several types for a damaged file
            raise ValueError(f"{path} is not readable (truncated, corrupt or not a state dict: "
                             f"{type(exc).__name__})") from None
    else:
        assert run.initial is not None, "a first start has the initial policy"
        policy = run.initial.model.policy
        extractor = policy.q_net.features_extractor if hasattr(policy, "q_net") else policy.features_extractor
        if not isinstance(extractor, HybridExtractor) or "image" not in extractor.branches:
            raise ValueError(f"init_policy {cfg.init_policy} has no image branch to freeze")
        state = {k: v.detach().cpu() for k, v in extractor.branches["image"].state_dict().items()}
        write_file(path, lambda tmp: torch.save(state, tmp), by_name=True)
    net = make_image_net(cfg.image_net, 3, plan.scenario.render.image_size_px, cfg.image_features)
    check_dtypes(state, net.state_dict(), str(path))
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f"the image branch of {cfg.init_policy} is not a {cfg.image_net} network with "
                         f"{cfg.image_features} features: {str(exc).splitlines()[0]}") from exc
    return ImageEncoder(net, cfg.image_features)


__all__ = [
    "FINE_TUNE_LEARNING_RATES",
    "RUN_OUTPUTS",
    "PolicyConfig",
    "TrainResult",
    "build_model",
    "check_run_dir",
    "default_learning_rate",
    "evaluate_run",
    "remove_run_outputs",
    "stored_config",
    "train_policy",
    "train_run",
    "versions",
]
