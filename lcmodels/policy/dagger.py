"""DAgger with the oracle as the expert: label the states the policy itself visits, then clone again.

Behaviour cloning of recorded demonstrations learns the expert's decisions on the expert's states; a
policy that errs drifts to states the demonstrations never show (a gap closing in, a lane it should
not be in) and errs more. DAgger (Ross et al., 2011) closes that loop. Each round:

1. the current policy drives ``episodes`` training episodes (deterministic actions);
2. at every decision, :func:`lcsim.planning.search_from` labels the state with the first decision of a
   winning plan from there (or, when none exists, of the branch that survives longest). A plan stays
   valid while the policy follows it, so a new search runs only after the policy deviates. With
   ``labels="winning"``, a deviation after which the episode can still be won keeps the policy's own
   decision as its label, so only losing decisions are corrected;
3. the labelled states join the demonstrations and the policy is trained on all of them (behaviour
   cloning, :func:`lcmodels.policy.warmstart.pretrain`, without the value term: the labels carry no
   return);
4. the policy is saved as ``round<r>/policy.safetensors`` (with the round's labelled states in
   ``round<r>/states.npz``, so that a later call can continue the rounds) and evaluated on the
   held-out episodes.

The expert sees the future; the policy sees only its observation. What a round teaches is which action
the future rewards in states like the ones the policy reaches.
"""

from __future__ import annotations

import functools
import json
import os
import time
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lckit.fileio import check_inside, file_sha256, write_file
from lckit.pool import WorkerPool
from lcmodels.fileio import POLICY_FILE, write_json
from lcmodels.policy.checkpoint import load_policy, save_policy
from lcmodels.policy.driverspec import safety_layer_of
from lcmodels.policy.evaluate import PolicyDriver, evaluate
from lcmodels.policy.obs import mode_keys, scenario_for_mode
from lcmodels.policy.warmstart import Demonstrations, RowChunks, every_tenth, load_demonstrations, pretrain
from lcsim.core import KEEP, SUCCESS, LaneChangeCore, StepResult
from lcsim.episodes import EpisodeHook, run_episodes
from lcsim.planning import LookaheadDriver, SafetyLayerConfig, SearchResult, search_from
from lcsim.suite import VALIDATION_SEED_BASE

LABELS = ("plan", "winning")
"""How :func:`collect` labels a state (see there)."""
ORACLE = "oracle"
"""The default expert of :func:`dagger`: :func:`lcsim.planning.search_from`, which sees the whole future."""


@dataclass
class Collected:
    """States a policy visited, in its observation mode, with the oracle's labels."""

    obs: dict[str, np.ndarray]
    labels: np.ndarray
    agreed: int
    searches: int
    outcomes: list[str]
    actions: np.ndarray
    """The policy's own decision in each state (a label that differs from it is a correction)."""
    harmless: int = 0
    """Decisions off the oracle's plan after which the episode could still be won (those states carry the
    policy's own decision as their label when ``labels="winning"``)."""
    alive: np.ndarray | None = None
    """``(N, 3)`` for an expert behind the safety layer: the share of its imagined futures each decision survived
    in each state (:attr:`lcsim.planning.LookaheadDriver.last_alive`; NaN for a decision not allowed there)."""


class _OracleLabels(EpisodeHook):
    """Labels every state a policy drives into (one environment) with the oracle's plan from it; see
    :func:`collect`."""

    def __init__(self, driver: PolicyDriver, keys: tuple[str, ...], keep_winning: bool) -> None:
        self.driver, self.keys, self.keep_winning = driver, keys, keep_winning
        self.rows: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        self.labels: list[int] = []
        self.own: list[int] = []
        self.agreed = self.searches = self.harmless = 0

    def start(self, core: LaneChangeCore, user_seeds: Sequence[int], driver: Any) -> None:
        self.plan: SearchResult | None = None
        self.j = 0
        self.deviated: tuple[int, int] | None = None  # (state, the policy's decision) off the plan, awaiting a verdict

    def before_step(self, core: LaneChangeCore, obs: dict[str, np.ndarray], mask: np.ndarray, actions: np.ndarray,
                    running: np.ndarray) -> None:
        if self.plan is None or self.j >= len(self.plan.actions):
            self.plan, self.j = search_from(core), 0
            self.searches += 1
            if self.deviated is not None and self.plan.winnable:  # the policy's decision still wins
                self._harmless()
            self.deviated = None
        label = self.plan.actions[self.j] if self.j < len(self.plan.actions) else KEEP
        action = int(actions[0])
        for k in self.keys:
            self.rows[k].append(self.driver.last_observation[k][0])
        self.labels.append(label)
        self.own.append(action)
        if action == label:
            self.agreed += 1
            self.j += 1
        else:
            self.plan, self.deviated = None, (len(self.labels) - 1, action)

    def after_step(self, core: LaneChangeCore, result: StepResult, running: np.ndarray) -> None:
        if core.outcome[0] == SUCCESS and self.deviated is not None:
            self._harmless()
            self.deviated = None

    def _harmless(self) -> None:
        assert self.deviated is not None
        self.harmless += 1
        if self.keep_winning:
            self.labels[self.deviated[0]] = self.deviated[1]


def collect(policy_path: str | os.PathLike[str], user_seeds: Sequence[int], *,
            predictor: str | os.PathLike[str] | None = None, threads: int = 1, labels: str = "plan") -> Collected:
    """Drive one episode per user seed with the policy and label every state with the oracle.

    ``labels``: ``"plan"`` labels each state with the first decision of the oracle's plan from it;
    ``"winning"`` keeps the policy's own decision where the episode can still be won after it (known
    from the search that follows it anyway), so only the decisions that lose are corrected.
    """
    if labels not in LABELS:
        raise ValueError(f"labels must be one of {', '.join(LABELS)}, got {labels!r}")
    torch.set_num_threads(threads)
    loaded = load_policy(policy_path, predictor=predictor)
    driver = PolicyDriver(loaded)
    hook = _OracleLabels(driver, mode_keys(loaded.obs_mode), labels == "winning")
    done = run_episodes(driver, scenario_for_mode(loaded.scenario, loaded.obs_mode), user_seeds, batch=1,
                        hooks=[hook])
    obs = {k: np.stack(v) if v else np.zeros((0,)) for k, v in hook.rows.items()}
    return Collected(obs, np.asarray(hook.labels, dtype=np.int64), hook.agreed, hook.searches,
                     [r.outcome for r in done], np.asarray(hook.own, dtype=np.int64), hook.harmless)


class _ExpertLabels(EpisodeHook):
    """Labels every state with a choice that a policy drives into with an expert driver's decision."""

    def __init__(self, driver: PolicyDriver, teacher: Any, keys: tuple[str, ...]) -> None:
        self.driver, self.teacher, self.keys = driver, teacher, keys
        self.rows: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        self.labels: list[np.ndarray] = []
        self.own: list[np.ndarray] = []
        # the safety layer's survival of each decision, kept alongside its labels
        self.alive: list[np.ndarray] | None = [np.zeros((0, 3))] if isinstance(teacher, LookaheadDriver) else None
        self.agreed = 0

    def before_step(self, core: LaneChangeCore, obs: dict[str, np.ndarray], mask: np.ndarray, actions: np.ndarray,
                    running: np.ndarray) -> None:
        live = np.flatnonzero(running & (mask.sum(axis=1) > 1))
        label = np.asarray(self.teacher(obs, mask, core), dtype=np.int64).reshape(-1)[live]
        if self.alive is not None:
            self.alive.append(self.teacher.last_alive[live])
        for k in self.keys:
            self.rows[k].append(self.driver.last_observation[k][live])
        self.labels.append(label)
        self.own.append(actions[live])
        self.agreed += int((label == actions[live]).sum())


def collect_from_driver(policy_path: str | os.PathLike[str], user_seeds: Sequence[int], expert: str, *,
                        predictor: str | os.PathLike[str] | None = None, threads: int = 1,
                        batch: int = 20, safety: SafetyLayerConfig | None = None,
                        progress: Callable[[int, int], None] | None = None) -> Collected:
    """Drive one episode per user seed with the policy, ``batch`` at a time, and label every state with the
    decision of ``expert``, a driver spec of :func:`lcmodels.policy.evaluate.driver_for` (for example
    ``safety-layer:runs/pure/policy.safetensors``: a policy behind the safety layer, which sees no more of the
    future than the policy could). Only states with a choice are kept: in the middle of a lane change the
    simulator ignores the decision, and a label there ("keep") would teach the network something that matters
    nowhere. ``safety``: the settings of an expert's safety layer (as ``driver_for``'s); the share of imagined
    futures each decision survived is kept too (``Collected.alive``). ``progress`` is called with (episodes
    done, episodes) after each batch."""
    from lcmodels.policy.evaluate import driver_for

    torch.set_num_threads(threads)
    loaded = load_policy(policy_path, predictor=predictor)
    config = scenario_for_mode(loaded.scenario, loaded.obs_mode)
    teacher, teacher_config = driver_for(expert, safety=safety)
    if teacher_config is not None and replace(teacher_config, render_image=False) != replace(config, render_image=False):
        raise ValueError(f"the expert {expert} was trained on another scenario than {policy_path}")
    driver = PolicyDriver(loaded)
    hook = _ExpertLabels(driver, teacher, mode_keys(loaded.obs_mode))
    done = run_episodes(driver, config, user_seeds, batch=batch, hooks=[hook], progress=progress)
    obs_ = {k: np.concatenate(v) if v else np.zeros((0,)) for k, v in hook.rows.items()}
    labels = np.concatenate(hook.labels) if hook.labels else np.zeros(0, dtype=np.int64)
    actions_ = np.concatenate(hook.own) if hook.own else np.zeros(0, dtype=np.int64)
    return Collected(obs_, labels, hook.agreed, 0, [r.outcome for r in done], actions_,
                     alive=None if hook.alive is None else np.concatenate(hook.alive))


_STATES = "states.npz"


def _finished_rounds(out: Path, run_dir: Path, *, episodes: int, seed: int, labels: str, expert: str,
                    correction_weight: float, balance_actions: bool,
                    expert_layer: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The records of the rounds in ``out`` that can be resumed, checked against the arguments."""
    try:
        book = json.loads((out / "dagger.json").read_text())
    except (OSError, ValueError) as exc:
        raise FileExistsError(f"{out} is not empty and holds no readable dagger.json ({exc})") from exc
    if not isinstance(book, dict) or not isinstance(book.get("run_dir", ""), str):
        raise ValueError(f"{out}/dagger.json is not a record of DAgger rounds; choose a new --out")
    records = book.get("rounds") or []
    if not records:
        raise FileNotFoundError(f"{out}/dagger.json lists no finished round")
    _check_rounds(out, records)
    same_place = Path(book.get("run_dir", "")).resolve() == run_dir.resolve()
    moved = (not same_place and bool(book.get("run_policy_sha256"))
             and book["run_policy_sha256"] == file_sha256(run_dir / POLICY_FILE))  # fmt: skip
    if not (same_place or moved):  # the run's policy, wherever it is now (a published experiment resumed elsewhere)
        raise ValueError(f"{out} continues the run {book.get('run_dir')}, not {run_dir}")
    first = records[0]
    differs = [f"{name}: {have} there, {want} asked" for name, have, want in (
        ("episodes", first.get("episodes"), episodes), ("seed", first.get("user_seeds", [None])[0], seed),
        ("labels", first.get("labels"), labels), ("expert", first.get("expert", ORACLE), expert),
        ("correction weight", first.get("correction_weight", 1.0), correction_weight),
        ("action balance", first.get("balance_actions", True), balance_actions),
        ("expert's safety layer", _recorded_layer(first), expert_layer)) if have != want]
    if differs:
        raise ValueError(f"cannot resume {out}: " + "; ".join(differs))
    for record in records:
        if record.get("states_labelled") and not (out / f"round{record['round']}" / _STATES).is_file():
            raise FileNotFoundError(f"{out}/round{record['round']}/{_STATES} is missing (rounds made before DAgger "
                                    "kept its states cannot be resumed)")
    return records


def _check_rounds(out: Path, records: Any) -> None:
    """``ValueError`` in one line unless ``records`` (``dagger.json``'s ``rounds``) are the rounds 1, 2, ... in
    order, each a table with its counts and seeds as numbers, whose folders ``round<r>/`` are in ``out``."""
    if not isinstance(records, list):
        raise ValueError(f"{out}/dagger.json: rounds is not a list; choose a new --out")
    for r, record in enumerate(records, 1):
        seeds = record.get("user_seeds") if isinstance(record, dict) else None
        fields = [record.get(k) for k in ("round", "states_labelled", "episodes")] if isinstance(record, dict) else []
        if (not fields or fields[0] != r or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0
                                                   for v in fields)
                or not (isinstance(seeds, list) and len(seeds) == 2 and all(isinstance(s, int) for s in seeds))):
            shown = " ".join(json.dumps(record, default=str).split())[:80]
            raise ValueError(f"{out}/dagger.json: round {r} is not a record of round {r} ({shown}); choose a new "
                             "--out")
        check_inside(out / f"round{r}", out)


def _recorded_layer(record: dict[str, Any]) -> dict[str, Any] | None:
    """The safety layer of a round's expert as its record holds it (rounds recorded before the layer had one
    config: the expert's spec with the settings given then)."""
    if "expert_safety_layer" in record:
        return record["expert_safety_layer"]
    try:
        layer = safety_layer_of(str(record.get("expert", ORACLE)), record.get("expert_lookahead") or None)
    except ValueError:
        return record.get("expert_lookahead")  # settings no layer takes now: differs from any asked
    return None if layer is None else layer.to_dict()


def _collect_job(args: tuple[str, list[int], str | None, str, str, dict[str, Any] | None]) -> Collected:
    path, seeds, predictor, labels, expert, layer = args
    if expert == ORACLE:
        return collect(path, seeds, predictor=predictor, labels=labels)
    safety = None if layer is None else SafetyLayerConfig.from_dict(layer)
    return collect_from_driver(path, seeds, expert, predictor=predictor, safety=safety)


def dagger(
    run_dir: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    rounds: int = 2,
    episodes: int = 100,
    epochs: int = 10,
    seed: int = 100_000,
    workers: int = 2,
    eval_episodes: int = 200,
    eval_seed: int = 0,
    labels: str = "plan",
    expert: str = ORACLE,
    correction_weight: float = 1.0,
    balance_actions: bool = True,
    expert_safety: SafetyLayerConfig | None = None,
    resume: bool = False,
    demonstrations: str | os.PathLike[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Run DAgger rounds from a warm-started ``lc-train-policy`` run; returns every round's record.

    Args:
        run_dir: a run directory with ``policy.safetensors`` and ``run.json`` whose config names the demonstrations
            it was warm-started on (``--warm-start``); they stay in the training set.
        out: new directory for ``round<r>/policy.safetensors``, ``round<r>/metrics.json`` and ``dagger.json``.
        episodes: training episodes the policy drives per round (user seeds ``seed + r * episodes + i``:
            keep them apart from the demonstrations' and from evaluation's, which start at 10^9).
        epochs: behaviour-cloning epochs over all labelled states per round.
        labels: ``"plan"`` or ``"winning"``, as in :func:`collect` (the oracle's labels only).
        expert: ``"oracle"`` (:func:`collect`) or a driver spec that labels the states instead
            (:func:`collect_from_driver`), for example ``safety-layer:runs/pure/policy.safetensors``.
        correction_weight: how much more a labelled state counts in training when its label differs from
            the decision the policy took there (a correction), than one where they agree. An expert
            that corrects one decision in a hundred needs this above 1 to be heard.
        balance_actions: weight each state by the inverse square root of its label's frequency in training, as
            cloning demonstrations does (:func:`lcmodels.policy.warmstart.pretrain`); False: every state alike
            (times its correction weight), for a student whose lane changes are already about as frequent as the
            expert's (a trained policy taught by its own safety layer).
        expert_safety: the settings of the expert's safety layer (:class:`lcsim.planning.SafetyLayerConfig`, for
            example ``horizon_decisions=32``, 16 s; default: what the expert's spec means); ``ValueError`` for an
            expert behind no safety layer.
        resume: continue the rounds already in ``out`` (made with the same run, episodes, seed and labels)
            up to ``rounds`` in all: their labelled states rejoin the training set and the last round's
            policy is trained on. The result is the one an uninterrupted call gives (each round trains
            with a fresh optimiser and a seed of its own).
        demonstrations: where the run's demonstrations are now, when they have moved with it (an experiment
            directory published and resumed elsewhere); default: the path its ``run.json`` names.
    """
    run_dir, out = Path(run_dir), Path(out)
    say = progress or (lambda _msg: None)
    if labels not in LABELS:
        raise ValueError(f"labels must be one of {', '.join(LABELS)}, got {labels!r}")
    if min(rounds, episodes, epochs, workers) < 1:
        raise ValueError("rounds, episodes, epochs and workers must be >= 1")
    if not correction_weight > 0:
        raise ValueError(f"correction_weight must be > 0, got {correction_weight}")
    if not 0 <= seed <= VALIDATION_SEED_BASE - rounds * episodes:
        raise ValueError(f"seed {seed} + {rounds} rounds x {episodes} episodes reaches the validation episodes' seeds "
                         f"(evaluation's seeds start there, at {VALIDATION_SEED_BASE}); training seeds stay below")
    layer = safety_layer_of(expert, where="expert") if expert != ORACLE else None
    if expert_safety is not None:
        if layer is None:
            raise ValueError(f"settings of the safety layer apply to an expert behind it, not to {expert}")
        layer = expert_safety
    expert_layer = None if layer is None else layer.to_dict()
    done: list[dict[str, Any]] = []
    if out.exists() and any(out.iterdir()):
        if not resume:
            raise FileExistsError(f"{out} exists and is not empty; choose a new directory, or resume its rounds")
        done = _finished_rounds(out, run_dir, episodes=episodes, seed=seed, labels=labels, expert=expert,
                                correction_weight=correction_weight, balance_actions=balance_actions,
                                expert_layer=expert_layer)
    elif resume:
        raise FileNotFoundError(f"{out} holds no DAgger rounds to resume")
    policy_path = run_dir / POLICY_FILE
    if not policy_path.is_file() or not (run_dir / "run.json").is_file():
        raise FileNotFoundError(f"{run_dir} is not a finished lc-train-policy run (policy.safetensors, run.json)")
    run = json.loads((run_dir / "run.json").read_text())
    run_sha256 = file_sha256(policy_path)
    demos_dir = run["config"].get("warm_start") or ""
    if demos_dir and demonstrations is not None:
        demos_dir = str(demonstrations)
    if demos_dir and not Path(demos_dir).is_dir():
        raise FileNotFoundError(f"the demonstrations {run_dir} was warm-started on are not at {demos_dir} any more; "
                                "name where they are now")
    loaded = load_policy(policy_path)  # the predictor its card names (found by SHA-256 if the run has moved)
    predictor = str(loaded.predictor_path) if loaded.predictor_path is not None else None
    mode, model = loaded.obs_mode, loaded.model
    config = scenario_for_mode(loaded.scenario, mode)
    data: dict[str, list[np.ndarray]] = {k: [] for k in mode_keys(mode)}
    targets: list[np.ndarray] = []
    weights: list[np.ndarray] = []

    def weigh(labels_: np.ndarray, own: np.ndarray | None) -> np.ndarray:
        if own is None:  # demonstrations, or states kept before DAgger kept the policy's own decisions
            return np.ones(len(labels_), dtype=np.float32)
        return np.where(labels_ != own, correction_weight, 1.0).astype(np.float32)

    if demos_dir:
        demos = load_demonstrations(demos_dir, mode, loaded.predictor, scenario=config,
                                    progress=every_tenth(say, "demonstrations: read {}/{} episodes"))
        for k in data:
            data[k].append(demos.obs[k])
        targets.append(demos.actions)
        weights.append(weigh(demos.actions, None))
        say(f"demonstrations: {len(demos)} decisions of {demos.episodes} episodes from {demos_dir}")
    out.mkdir(parents=True, exist_ok=True)
    records: list[dict[str, Any]] = list(done)
    current = policy_path
    for record in done:
        if record["states_labelled"]:
            path = out / f"round{record['round']}" / _STATES
            try:
                with np.load(path) as states:
                    for k in data:
                        data[k].append(states[k])
                    targets.append(states["labels"])
                    weights.append(weigh(states["labels"], states["actions"] if "actions" in states else None))
            except (KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # cut short, or not these states
                raise ValueError(f"{path} is not the labelled states of its round ({type(exc).__name__}: "
                                 f"{' '.join(str(exc).split())[:100]}); choose a new --out") from None
        current = out / f"round{record['round']}" / POLICY_FILE
    if len(done) >= rounds:
        say(f"{out} already holds {len(done)} rounds; nothing to do for --rounds {rounds}")
    elif done:
        model = load_policy(current, predictor=predictor).model
        say(f"resuming after round {len(done)}: {sum(len(t) for t in targets)} states, policy {current}")
    for r in range(len(done) + 1, rounds + 1):
        t0 = time.perf_counter()
        seeds = [seed + (r - 1) * episodes + i for i in range(episodes)]
        parts = [seeds[i::workers] for i in range(workers) if seeds[i::workers]]
        jobs = [(str(current), p, predictor, labels, expert, expert_layer) for p in parts]
        if len(jobs) == 1:  # in this process: it may itself be a worker of a pool (lc-experiment --jobs 2)
            got = [_collect_job(jobs[0])]
        else:
            with WorkerPool(len(parts)) as pool:
                got = list(pool.map(_collect_job, jobs))
        kept = [g for g in got if len(g.labels)]
        states = sum(len(g.labels) for g in kept)
        if kept:
            round_obs = {k: np.concatenate([g.obs[k] for g in kept]) for k in data}
            round_labels = np.concatenate([g.labels for g in kept])
            round_own = np.concatenate([g.actions for g in kept])
            for k in data:
                data[k].append(round_obs[k])
            targets.append(round_labels)
            weights.append(weigh(round_labels, round_own))
            write_file(out / f"round{r}" / _STATES, functools.partial(  # whole or not at all, never via a link
                np.savez_compressed, labels=round_labels, actions=round_own, **round_obs), root=out)  # fmt: skip
        outcomes = [o for g in got for o in g.outcomes]
        collect_s = time.perf_counter() - t0
        say(f"round {r}: the policy drove {episodes} episodes ({outcomes.count('success')} successes), "
            f"{states} states labelled with {sum(g.searches for g in got)} searches in {collect_s:.0f} s")
        all_labels = np.concatenate(targets)
        train = Demonstrations({k: RowChunks(v) for k, v in data.items()}, all_labels,
                               np.zeros(len(all_labels), dtype=np.float32), 0, np.concatenate(weights))  # fmt: skip
        t1 = time.perf_counter()
        losses = pretrain(model, train, epochs=epochs, value_coef=0.0, seed=r, balance_actions=balance_actions)
        train_s = time.perf_counter() - t1
        current = out / f"round{r}" / POLICY_FILE
        meta = {k: v for k, v in loaded.meta.items() if k not in ("format", "version")}
        meta["dagger"] = {"from": str(policy_path), "round": r, "states": len(all_labels)}
        save_policy(model, current, meta)
        say(f"round {r}: trained on {len(all_labels)} states, {epochs} epochs in {train_s:.0f} s -> {current}")
        record: dict[str, Any] = {
            "round": r, "episodes": episodes, "user_seeds": [seeds[0], seeds[-1]], "states_labelled": states,
            "agreement": sum(g.agreed for g in got) / max(states, 1), "searches": sum(g.searches for g in got),
            "labels": labels, "expert": expert, "expert_safety_layer": expert_layer,
            "correction_weight": correction_weight, "balance_actions": balance_actions,
            "harmless_deviations": sum(g.harmless for g in got),
            "policy_success_in_collection": outcomes.count("success") / len(outcomes),
            "training_states": len(all_labels), "epoch_losses": losses, "collect_s": collect_s,
            "train_s": train_s,
        }  # fmt: skip
        if eval_episodes > 0:
            summary, _ = evaluate(PolicyDriver(load_policy(current, predictor=predictor)), config,
                                  episodes=eval_episodes, seed=eval_seed, batch=20)  # fmt: skip
            record["eval"] = summary
            say(f"round {r}: held-out {eval_episodes}: success {100 * summary['success_rate']:.1f}%, "
                f"collision {100 * summary['collision_rate']:.1f}%")
        write_json(out / f"round{r}" / "metrics.json", record)
        records.append(record)
        write_json(out / "dagger.json", {"run_dir": str(run_dir), "run_policy_sha256": run_sha256,
                                         "demonstrations": demos_dir, "rounds": records})  # fmt: skip
    return records


__all__ = ["LABELS", "ORACLE", "Collected", "collect", "collect_from_driver", "dagger"]
