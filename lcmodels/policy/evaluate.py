"""Evaluation on fixed held-out seeds, with 95% intervals, recording every episode to MCAP.

Evaluation episode ``i`` of evaluation seed ``S`` is the episode ``LaneChangeEnv.reset(seed=u)`` gives
for the user seed ``u = EVAL_SEED_BASE + S * 100_000 + i``. Training resets use user seeds below
``EVAL_SEED_BASE`` and then draw episode seeds from those streams; the simulator seeds of every
training episode are stored with the run (``train_episode_seeds.npy``) and :func:`evaluate` reports
how many evaluation episodes coincide with one (``overlap_with_training``, expected 0).

Episodes run batched (``batch`` at a time in one :class:`~lcsim.core.LaneChangeCore`), each recorded
by its own :class:`~lcdata.record.EpisodeRecorder` with actions, reward components and, for policies
that use them, the predictions the policy saw (``/prediction``, world frame).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lcdata.record import RecordingHook, episode_filename, episode_metadata
from lckit.pool import WorkerPool
from lcmodels.policy.checkpoint import LoadedPolicy
from lcmodels.policy.driverspec import DriverSpec, as_driver_spec, policy_spec, split_policy_spec
from lcmodels.policy.obs import EpisodeStats, ObsMode, build_observation, scenario_for_mode, summarize
from lcmodels.stats import normal_interval as mean_interval
from lcmodels.stats import wilson_interval
from lcsim.config import ScenarioConfig
from lcsim.core import OUTCOMES, LaneChangeCore
from lcsim.drivers import Driver
from lcsim.episodes import EpisodeHook, run_episodes
from lcsim.suite import MAX_VALIDATION_SEED, SEED_STRIDE, VALIDATION_SEED_BASE, check_unsealed, observed_by

if TYPE_CHECKING:
    from lcsim.planning import SafetyLayerConfig

EVAL_SEED_BASE = VALIDATION_SEED_BASE
EVAL_SEED_STRIDE = SEED_STRIDE


def eval_user_seeds(episodes: int, seed: int = 0) -> list[int]:
    """User seeds of the held-out validation episodes of evaluation seed ``seed`` (disjoint from training's and
from the sealed test episodes', see :mod:`lcsim.suite`)."""
    if episodes > EVAL_SEED_STRIDE:
        raise ValueError(f"at most {EVAL_SEED_STRIDE} evaluation episodes per seed, got {episodes}")
    if not 0 <= seed < MAX_VALIDATION_SEED:
        raise ValueError(f"evaluation seed must be in 0..{MAX_VALIDATION_SEED - 1}, got {seed} (the seeds above are "
                         "the benchmark's sealed test episodes: lc-bench --final)")
    return [EVAL_SEED_BASE + seed * EVAL_SEED_STRIDE + i for i in range(episodes)]


class PolicyDriver:
    """A trained policy as a driver (``driver(obs, action_mask, core) -> actions``), deterministic actions.

    After each call, :attr:`last_prediction` holds the ``(E, K, F, 2)`` ego-frame predictions the policy
    saw (``None`` when its mode has none).
    """

    needs_observation = True
    """It reads the observation (a :class:`lcsim.planning.LookaheadDriver` builds one in its imagined futures)."""

    def __init__(self, policy: LoadedPolicy, *, deterministic: bool = True) -> None:
        self.policy = policy
        self.name = f"{policy.algo}-{policy.obs_mode}"
        self.deterministic = deterministic
        self.last_prediction: np.ndarray | None = None
        self.last_observation: dict[str, np.ndarray] = {}
        """The policy observation of the last call (what the network saw)."""

    @property
    def config(self) -> ScenarioConfig:
        """The scenario the policy expects (rendering on only when it uses the image)."""
        return scenario_for_mode(self.policy.scenario, self.policy.obs_mode)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        pobs = build_observation(obs, self.policy.obs_mode, self.policy.predictor)
        self.last_observation = pobs
        self.last_prediction = pobs.get("prediction")
        actions, _ = self.policy.model.predict(pobs, deterministic=self.deterministic)
        return np.asarray(actions, dtype=np.int64).reshape(-1)


def summarize_with_intervals(episodes: Sequence[EpisodeStats]) -> dict[str, Any]:
    """:func:`lcmodels.policy.obs.summarize` with a 95% interval for each figure (``*_ci95``: Wilson for the
    rates, normal for the means)."""
    out = summarize(episodes)
    for o in OUTCOMES:
        out[f"{o}_rate_ci95"] = list(wilson_interval(sum(e.outcome == o for e in episodes), len(episodes)))
    for key, attr in (("mean_return", "ret"), ("mean_safe_forward_m", "safe_forward_m"),
                      ("mean_forward_m", "forward_m")):  # fmt: skip
        out[f"{key}_ci95"] = list(mean_interval([getattr(e, attr) for e in episodes]))
    return out


def evaluate(
    driver: Driver | Callable[..., np.ndarray],
    config: ScenarioConfig,
    *,
    episodes: int = 200,
    seed: int = 0,
    out_dir: str | os.PathLike[str] | None = None,
    scenario: str = "paper",
    batch: int = 16,
    overwrite: bool = False,
    images: bool = True,
    train_seeds: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    hooks: Sequence[EpisodeHook] = (),
    user_seeds: Sequence[int] | None = None,
    sealed: bool = False,
) -> tuple[dict[str, Any], list[EpisodeStats]]:
    """Run ``episodes`` held-out episodes with ``driver`` and summarise them.

    Args:
        driver: ``driver(obs, action_mask, core) -> actions`` (a lcsim driver or :class:`PolicyDriver`).
        config: the scenario (for a policy, ``PolicyDriver.config``).
        out_dir: when given, every episode is recorded there as MCAP (existing files are refused unless
            ``overwrite``).
        batch: episodes simulated together.
        train_seeds: simulator seeds seen in training, for the overlap check.
        progress: called with (done, total) after each batch.
        hooks: more watchers of the episodes (:class:`lcsim.episodes.EpisodeHook`, e.g. an analysis).
        user_seeds: run these episodes instead of the ``episodes`` of evaluation seed ``seed`` (a shard).
        sealed: the benchmark's final path's leave to run sealed test episodes (:func:`lcsim.suite.check_unsealed`:
            without it they are refused with a ``ValueError``); nothing else passes it.

    Returns:
        ``(summary, per-episode statistics)``; the summary has the keys of
        :func:`summarize_with_intervals` plus ``seeds``, ``overlap_with_training`` and ``driver``.
    """
    user_seeds = eval_user_seeds(episodes, seed) if user_seeds is None else [int(u) for u in user_seeds]
    check_unsealed(user_seeds, sealed=sealed)
    name = str(getattr(driver, "name", type(driver).__name__))
    out_path = Path(out_dir) if out_dir is not None else None
    if out_path is not None:
        out_path.mkdir(parents=True, exist_ok=True)
        if not overwrite:
            existing = [p for u in user_seeds if (p := out_path / episode_filename(scenario, name, u)).exists()]
            if existing:
                raise FileExistsError(f"{existing[0]} exists ({len(existing)} evaluation files); use --overwrite "
                                      "or another output directory")  # fmt: skip
    hooks = list(hooks)
    if out_path is not None:
        hooks.append(RecordingHook(
            lambda u: out_path / episode_filename(scenario, name, u),
            lambda u: episode_metadata(config, u, driver=name, scenario=scenario,
                                       driver_description=f"{name}: evaluation episode of user seed {u}"),
            overwrite=overwrite, images=images, writer="thread",
        ))  # fmt: skip
    done = run_episodes(driver, config, user_seeds, batch=batch, hooks=hooks, progress=progress, sealed=sealed)
    results = [EpisodeStats.of(r.outcome, r.total_reward, r.decisions, r.forward_reward, config.reward.forward_per_m,
                               r.episode_seed) for r in done]  # fmt: skip
    summary = summarize_with_intervals(results)
    summary["driver"] = name
    summary["eval_seed"] = seed
    summary["user_seeds"] = [user_seeds[0], user_seeds[-1]] if user_seeds else []
    if train_seeds is not None:
        summary["overlap_with_training"] = int(np.isin([r.seed for r in results], train_seeds).sum())
    return summary, results


def policy_path_of(spec: str) -> Path:
    """The checkpoint a driver spec that is not a built-in driver names (its words: a stored record's)."""
    return Path((split_policy_spec(spec) or ("", spec))[1])


CHECK_EPISODES = 8
"""Held-out episodes whose outcomes a zoo card lists, so that anyone can check the entry reproduces them."""


def check_episodes(policy: str | os.PathLike[str], *, seed: int, episodes: int = CHECK_EPISODES) -> list[dict[str, Any]]:
    """The first ``episodes`` held-out episodes of evaluation seed ``seed`` driven by ``policy``: user seed,
    outcome and return of each (what a zoo card lists and a test re-derives)."""
    driver, config = driver_for(policy_spec(policy))
    _, stats = evaluate(driver, config, episodes=episodes, seed=seed, images=True)
    return [{"seed": int(e.seed), "outcome": e.outcome, "return": round(float(e.ret), 6)} for e in stats]


def transfer_problems(policy: LoadedPolicy, target: ScenarioConfig) -> list[str]:
    """Why ``policy`` cannot drive in ``target`` (empty: it can): the observation it would see there differs in
    a key or a shape from the one it was trained on."""
    from lcmodels.policy.obs import policy_observation_space

    future = policy.predictor.future_steps if policy.predictor is not None else 10
    have = policy_observation_space(policy.scenario, policy.obs_mode, future)
    there = policy_observation_space(target, policy.obs_mode, future)
    problems = [f"{k} {have[k].shape} there is {there[k].shape}" for k in have.spaces
                if k in there.spaces and have[k].shape != there[k].shape]
    problems += [f"{k} is missing there" for k in have.spaces if k not in there.spaces]
    return problems


def driver_for(spec: DriverSpec | str, *, predictor: str | None = None, device: str = "cpu",
               safety: SafetyLayerConfig | None = None,
               scenario: ScenarioConfig | None = None) -> tuple[Any, ScenarioConfig | None]:
    """The driver a :class:`~lcmodels.policy.driverspec.DriverSpec` names: a built-in driver, a policy file, or
    either behind the safety layer (its settings and what its imagined futures follow in the spec). The layer's
    imagined futures follow the spec's ``follow`` (a built-in driver, or a checkpoint of the same scenario that
    does not read the image; then the policy proposes and the layer checks), else the driver itself, which must
    then not read the image (the imagined futures are not rendered). The words of a spec are taken too (parsed
    once here, ``safety`` in place of the layer they mean: the scripts' and stored records' form).
    ``scenario``: run a policy on that road instead of the one it was trained on, observed with the policy's
    own sensor settings (:func:`lcsim.suite.observed_by`; ``ValueError`` naming what differs when its
    observation would not have the shapes the policy was trained on).

    Returns the driver and, for a policy, the scenario it drives in (``None`` for lcsim drivers).
    """
    from lcmodels.policy.checkpoint import load_policy
    from lcsim.planning import LookaheadDriver, rule_behind_layer
    from lcsim.registry import make_driver

    spec = as_driver_spec(spec, safety)
    layer = spec.layer
    if spec.kind == "callable":
        raise ValueError(f"{spec.text}: a user's callable drives in lc-bench, not here")
    if spec.kind == "driver":
        return (make_driver(spec.name) if layer is None else rule_behind_layer(layer, spec.text)), None
    path = spec.path
    policy = load_policy(path, predictor=predictor, device=device)
    driver: Any = PolicyDriver(policy)
    config = driver.config
    trained = policy.scenario
    if scenario is not None:
        there = observed_by(scenario, trained)
        problems = transfer_problems(policy, there)
        if problems:
            raise ValueError(f"{path} cannot drive in that scenario: its observation {problems[0]} "
                             f"({len(problems)} difference(s) from the scenario it was trained on)")
        config = scenario_for_mode(there, policy.obs_mode)
    if layer is not None:
        if spec.follow is not None:
            driver = LookaheadDriver(layer, rule=_follower(spec.follow, trained, predictor, device),
                                     proposer=driver)  # fmt: skip
        elif ObsMode.of(policy.obs_mode).reads_image:
            raise ValueError(f"{path}: the safety layer's imagined futures cannot follow a policy that reads the "
                             f"image (mode {policy.obs_mode}): they are not rendered; name a driver for them to "
                             "follow (--follow)")  # fmt: skip
        else:
            driver = LookaheadDriver(layer, rule=driver)
    return driver, config


def _follower(spec: DriverSpec, scenario: ScenarioConfig, predictor: str | None, device: str) -> Any:
    """The driver the safety layer's imagined futures follow: a built-in driver, or a policy trained on
    ``scenario`` (the proposer's) that does not read the image."""
    from lcmodels.policy.checkpoint import load_policy
    from lcsim.registry import make_driver

    if spec.kind == "driver":
        return make_driver(spec.name)
    path = spec.path
    try:
        policy = load_policy(path, predictor=predictor, scenario=scenario, device=device)
    except ValueError as exc:
        raise ValueError(f"driver to follow: {exc}") from exc
    if ObsMode.of(policy.obs_mode).reads_image:
        raise ValueError(f"driver to follow: {path} reads the image (mode {policy.obs_mode}), which the "
                         "imagined futures do not render")
    return PolicyDriver(policy)


__all__ = [
    "CHECK_EPISODES",
    "EVAL_SEED_BASE",
    "PolicyDriver",
    "check_episodes",
    "driver_for",
    "eval_user_seeds",
    "evaluate",
    "evaluate_sharded",
    "mean_interval",
    "policy_path_of",
    "summarize_with_intervals",
    "transfer_problems",
    "wilson_interval",
]


def _evaluate_shard(index: int, spec: DriverSpec, scenario_json: str | None, user_seeds: list[int],
                    options: dict[str, Any]) -> tuple[int, str, list[dict[str, Any]], int, int]:
    """One shard of :func:`evaluate_sharded`, in a worker: the driver rebuilt from its spec (nothing loaded
    is shipped), its episodes run and recorded. Returns the shard's index, the driver's name, the episodes'
    statistics and the safety layer's choices and overrides (0 for other drivers)."""
    from lcsim.planning import LookaheadDriver

    target = None if scenario_json is None else ScenarioConfig.from_json(scenario_json)
    driver, config = driver_for(spec, predictor=options["predictor"], scenario=target)
    if config is None:
        config = target
    out_dir = options["out_dir"]
    _, results = evaluate(driver, config, out_dir=out_dir, scenario=options["scenario"], batch=options["batch"],
                          overwrite=options["overwrite"], user_seeds=user_seeds, sealed=options["sealed"])
    planner = driver if isinstance(driver, LookaheadDriver) else None
    return (index, str(getattr(driver, "name", type(driver).__name__)), [dataclasses.asdict(r) for r in results],
            planner.choices if planner else 0, planner.overrides if planner else 0)


def _evaluate_shard_task(*args: Any) -> tuple[int, str, list[dict[str, Any]], int, int]:
    """:func:`_evaluate_shard` as a Ray task of one CPU (one torch thread)."""
    import torch

    torch.set_num_threads(1)
    return _evaluate_shard(*args)


def shard_pool(workers: int, threads: int = 1) -> WorkerPool:
    """``workers`` processes for :func:`evaluate_sharded`'s ``pool``, ``threads`` torch threads each (a
    :class:`lckit.pool.WorkerPool`: hold it in a ``with`` block)."""
    return WorkerPool(workers, threads=threads)


def evaluate_sharded(spec: DriverSpec | str, config: ScenarioConfig | None, *, episodes: int = 200, seed: int = 0,
                     shards: int = 4, executor: str = "local", predictor: str | None = None,
                     safety: SafetyLayerConfig | None = None,
                     out_dir: str | os.PathLike[str] | None = None, scenario: str = "paper", batch: int = 16,
                     overwrite: bool = False, train_seeds: np.ndarray | None = None,
                     progress: Callable[[int, int], None] | None = None,
                     driver_name: str | None = None, pool: WorkerPool | None = None,
                     user_seeds: Sequence[int] | None = None,
                     sealed: bool = False) -> tuple[dict[str, Any], list[EpisodeStats]]:
    """:func:`evaluate` of the driver ``spec`` (as :func:`driver_for` takes it, ``safety`` too) with the episodes cut into
    ``shards`` parts, each run where ``executor`` says (``local``: one after the other here, or at once in the
    processes of ``pool``; ``ray``: as Ray tasks in the open :func:`lcdata.executors.ray_session`), each shard
    whole batches of ``batch`` episodes.
    Every episode depends only on its seed and runs where :func:`evaluate` runs it, so the summary and the
    recorded files are the ones :func:`evaluate` gives, episode for episode (the ``random`` driver aside,
    whose draws follow the batch's calls). ``config``: the scenario of a built-in driver, or the scenario a
    policy drives in instead of its own (``None``: its own). The summary
    also has ``planner_choices`` / ``planner_overrides`` behind the safety layer. ``driver_name``: the driver's name,
    when the caller has built it already (else it is built here once, to check for existing files).
    ``user_seeds``: run these episodes instead of the ``episodes`` of evaluation seed ``seed``; ``sealed``: as
    :func:`evaluate` takes it."""
    from lcdata.executors import EXECUTORS, ray_map
    from lcdata.executors import shards as cut

    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
    spec = as_driver_spec(spec, safety)
    if spec.kind == "driver" and spec.name == "random" and (shards > 1 or executor == "ray"):
        raise ValueError("the random driver's draws follow its calls: it is evaluated in one process (no shards)")
    user_seeds = eval_user_seeds(episodes, seed) if user_seeds is None else [int(u) for u in user_seeds]
    check_unsealed(user_seeds, sealed=sealed)
    if out_dir is not None and not overwrite:  # refuse before any shard writes, as evaluate() does
        name = driver_name
        if name is None:  # (the name the files carry: build the driver once here to learn it)
            driver, _ = driver_for(spec, predictor=predictor, scenario=config)
            name = str(getattr(driver, "name", type(driver).__name__))
        existing = [p for u in user_seeds if (p := Path(out_dir) / episode_filename(scenario, name, u)).exists()]
        if existing:
            raise FileExistsError(f"{existing[0]} exists ({len(existing)} evaluation files); use --overwrite "
                                  "or another output directory")
    options = {"predictor": predictor, "out_dir": None if out_dir is None else str(out_dir), "scenario": scenario, "batch": batch,
               "overwrite": overwrite, "sealed": sealed}  # fmt: skip
    scenario_json = None if config is None else config.to_json()
    # whole batches per shard: an episode then runs at the same place of the same batch as in evaluate(),
    # so even what a recording says of its batch (the environment's index) is the same
    batches = [user_seeds[i : i + batch] for i in range(0, len(user_seeds), batch)]
    parts = [[u for b in group for u in b] for group in cut(batches, shards)]
    calls = [(i, spec, scenario_json, part, options) for i, part in enumerate(parts)]
    done: dict[int, tuple[str, list[dict[str, Any]], int, int]] = {}
    if executor == "ray":
        runner: Iterable[tuple[Any, ...]] = ray_map(_evaluate_shard_task, calls)
    elif pool is not None and len(calls) > 1:
        runner = pool.map(_evaluate_shard, calls, star=True, ordered=False)
    else:
        runner = (_evaluate_shard(*c) for c in calls)
    for index, *out in runner:
        done[index] = tuple(out)  # type: ignore[assignment]
        if progress is not None:
            progress(sum(len(d[1]) for d in done.values()), len(user_seeds))
    ordered = [done[i] for i in range(len(parts))]
    results = [EpisodeStats(**r) for _, rows, _, _ in ordered for r in rows]
    summary = summarize_with_intervals(results)
    summary["driver"] = ordered[0][0] if ordered else spec.text
    summary["eval_seed"] = seed
    summary["user_seeds"] = [user_seeds[0], user_seeds[-1]] if user_seeds else []
    if train_seeds is not None:
        summary["overlap_with_training"] = int(np.isin([r.seed for r in results], train_seeds).sum())
    if any(d[2] for d in ordered):
        summary["planner_choices"] = sum(d[2] for d in ordered)
        summary["planner_overrides"] = sum(d[3] for d in ordered)
    return summary, results
