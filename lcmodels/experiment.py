"""``lc-experiment``: the paper's tables and figures end to end, resumable stage by stage.

An experiment directory ``DIR`` holds one directory per stage::

    experiment.json              preset, seeds and command of the last invocation (marks DIR as ours)
    stages/                      one record per stage (see below)
    corpus/                      autopilot trajectory corpus (MCAP)                   -> predictor
    predictor/                   predictor.pt, metrics.json (Table II)                -> prediction/hybrid policies
    demos/                       demonstrations (the oracle's by default) with images -> warm start
    rule/metrics.json            rule-based reference on the held-out evaluation seeds
    policies/<method>/seed<k>/   lcmodels.policy.train run directories (metrics.json, progress.csv, policy.safetensors)
    REPORT.md, fig5_safe_forward.png, fig6_total_reward.png

Resumability. Each stage gets a record ``stages/<stage>.json`` when it completes: the stage's config,
the content hashes of its inputs (the outputs of the stages it reads) and the SHA-256 of each of its own
outputs. A rerun skips a stage whose record matches the current config and inputs and whose outputs
still hash to the recorded values; anything else is redone. ``stages/<stage>.pending.json`` is written when a
stage starts: a stage interrupted with the same config and inputs continues from what it left (missing
episodes are recorded, a policy resumes from its last checkpoint); a stage whose config or inputs
changed starts from an empty directory. A policy whose only change is a larger ``timesteps`` (or other
evaluation settings) continues training instead of starting over.

Parallel policies. With ``jobs > 1`` the policy stages (each an independent training run with its own
seed) run in that many worker processes, ``threads`` torch threads each; a stage's result does not
depend on which process ran it. ``DIR/.lock`` keeps a second invocation out of a directory in use.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcmodels.fileio import POLICY_FILE, file_sha256, read_json, write_json
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
    canonical,
    demos_key,
    outputs_digest,
    policy_dir,
    previous_policy,
)
from lcmodels.recipe import DemoSpec, Recipe, load_recipe

log = logging.getLogger(__name__)

def _hash_outputs(base: Path, names: Sequence[str]) -> dict[str, str] | None:
    out = {}
    for name in names:
        p = base / name
        if not p.is_file():
            return None
        out[name] = file_sha256(p)
    return out


@dataclass
class ExperimentResult:
    out: Path
    preset: Preset
    seeds: int
    stages: list[StageResult]
    wall_s: float
    report: Path


Progress = Callable[[str], None]


def _resumable_policy_change(prior: dict[str, Any], now: dict[str, Any]) -> bool:
    """A policy run can continue under ``now``: only evaluation settings or a larger budget differ."""
    free = ("timesteps", "checkpoint_every", "eval_episodes", "eval_seed", "eval_batch", "record_eval")
    if any(prior.get(k) != now.get(k) for k in now if k not in free):
        return False
    return int(prior.get("timesteps", 0)) <= int(now["timesteps"])


def _no_wall() -> None:
    pass


def _stored_stage_config(data: dict[str, Any]) -> dict[str, Any]:
    """A policy stage's recorded config in today's form (:func:`lcmodels.policy.train.stored_config`), the
    shielded stage's ``shield`` table kept as it is."""
    from lcmodels.policy.train import stored_config

    if "shield" not in data:
        return stored_config(data)
    return stored_config({k: v for k, v in data.items() if k != "shield"}) | {"shield": data["shield"]}


def lookahead_settings(s: Any) -> dict[str, Any]:
    """The settings of a recipe's safety layer (a :class:`lcsim.planning.SafetyLayerConfig`, blind) as its stages
    record them, so that stages measured before stay complete."""
    return {"horizon_decisions": s.horizon_decisions, "samples": s.samples, "perceived": s.perceived}


def _evaluated(done: Sequence[StageResult]) -> bool:
    """A recipe's stages reached its evaluation (a ``shielded`` stage waits for the policy its layer follows)."""
    return bool(done) and done[-1].name.endswith("/eval")




class Experiment:
    """The stages of one experiment directory; :meth:`run` does what is missing or stale."""

    def __init__(self, preset: Preset, out: str | Path, *, seeds: int = 1, command: str = "", threads: int = 1,
                 progress: Progress | None = None, executor: str = "local",
                 ray_address: str | None = None) -> None:  # fmt: skip
        from lcdata.executors import EXECUTORS

        if executor not in EXECUTORS:
            raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
        self.executor, self.ray_address = executor, ray_address
        if seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {seeds}")
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.preset, self.out, self.seeds, self.command = preset, Path(out), seeds, command
        self.threads = threads
        self.dry_run = False
        self._progress = progress
        self._save_wall: Callable[[], None] = _no_wall
        """Put the time spent so far on the running stage into its pending record (``_stage`` sets it)."""
        self.invocations: list[dict[str, Any]] = []
        """What :data:`INVOCATIONS` holds (this invocation last while :meth:`run` runs)."""
        self._invocation_t0: float | None = None
        self._invocation_lock = threading.Lock()
        self.stages: list[StageResult] = []
        self._recipes: list[Recipe] | None = None
        self.jobs = 1
        """Processes at once (:meth:`run`'s ``jobs``): policy tasks, and the shards of an evaluation run here."""
        self._eval_pool: Any = None

    # -- helpers -------------------------------------------------------------------------------------
    def eval_pool(self) -> Any:
        """The ``jobs`` processes an evaluation of this process cuts its episodes over (local executor,
        ``jobs`` > 1; None otherwise), started at the first evaluation and kept until :meth:`run` ends."""
        if self.executor != "local" or self.jobs < 2:
            return None
        if self._eval_pool is None:
            from lcmodels.policy.evaluate import shard_pool

            self._eval_pool = shard_pool(self.jobs, self.threads)
        return self._eval_pool

    def _close_eval_pool(self, *, kill: bool = False) -> None:
        """Stop :meth:`eval_pool`'s processes (``kill``: now, a shard under way too; its stage resumes)."""
        if self._eval_pool is not None:
            from lcdata.procs import stop_pool

            stop_pool(self._eval_pool, kill=kill)
            self._eval_pool = None

    def emit(self, msg: str) -> None:
        log.info(msg)
        if self._invocation_t0 is not None:
            self._save_invocation(finished=False)
        if self._progress is not None:
            self._progress(msg)

    def _save_invocation(self, *, finished: bool) -> None:
        assert self._invocation_t0 is not None
        with self._invocation_lock:  # progress lines of parallel policies come from another thread
            self.invocations[-1].update(wall_s=time.perf_counter() - self._invocation_t0, finished=finished)
            write_json(self.out / INVOCATIONS, self.invocations)

    def record_paths(self, name: str) -> tuple[Path, Path]:
        """``(complete record, pending record)`` of stage ``name`` (kept outside the stage's directory)."""
        base = self.out / STAGES_DIR / name.replace("/", "__")
        return base.with_suffix(".json"), base.with_suffix(".pending.json")

    def check_out(self) -> None:
        """``ValueError`` when ``out`` is a file, a non-empty directory that is not an experiment, the filesystem
        root or the home directory, or a folder nothing can be written in."""
        from lcdata.fileio import check_output_folder

        check_output_folder(self.out)
        if self.out.is_dir() and any(q.name != LOCK_NAME for q in self.out.iterdir()) and not (
                self.out / MARKER).exists():
            raise ValueError(f"--out {self.out} is a non-empty directory without {MARKER}; "
                             "choose a new or an experiment directory")  # fmt: skip

    def _stage(self, name: str, path: Path, config: dict[str, Any], inputs: dict[str, str],
               outputs: Callable[[], list[str]], work: Callable[[bool], float | None],
               resumable: Callable[[dict[str, Any], dict[str, Any]], bool] | None = None,
               upgrade: Callable[[dict[str, Any]], dict[str, Any]] | None = None) -> StageResult:
        """Skip the stage when complete, else run ``work(keep)`` (``keep``: the directory holds a prefix of it).

        The record's ``wall_s`` is what ``work`` returns (the compute time behind the outputs, every resumed
        part counted, when the stage knows it) or else the time of this call plus that of the interrupted
        calls before it, as far as :meth:`_save_wall` put them into the pending record.
        """
        t0 = time.perf_counter()
        config, inputs = canonical(config), canonical(inputs)
        rec_path, pend_path = self.record_paths(name)

        def stored(rec: dict[str, Any] | None) -> dict[str, Any] | None:
            # a config stored before a field was added compares as the config it stands for today
            if rec is None or upgrade is None or not isinstance(rec.get("config"), dict):
                return rec
            return rec | {"config": canonical(upgrade(rec["config"]))}

        record = stored(read_json(rec_path))
        if record is not None and record.get("config") == config and record.get("inputs") == inputs:
            current = _hash_outputs(path, list(record.get("outputs", {})))
            if current is not None and current == record["outputs"]:
                self.emit(f"[{name}] complete, skipped")
                res = StageResult(name, "skipped", path, float(record.get("wall_s", 0.0)),
                                  time.perf_counter() - t0, current)  # fmt: skip
                self.stages.append(res)
                return res
            why = "outputs missing or changed"
        elif record is not None:
            why = "stale: " + ("config changed" if record.get("config") != config else "inputs changed")
        elif (pending := stored(read_json(pend_path))) is None:
            why = "new"
        elif pending.get("config") == config and pending.get("inputs") == inputs:
            why = "resuming an interrupted run"
        else:
            why = "stale: config or inputs changed since an interrupted run"
        if self.dry_run:
            self.emit(f"[{name}] would run ({why})")
            res = StageResult(name, f"would run ({why})", path, 0.0, time.perf_counter() - t0, {"pending": name})
            self.stages.append(res)
            return res
        prior = None if record is not None and why == "outputs missing or changed" else (
            record or stored(read_json(pend_path)))
        keep = prior is not None and prior.get("inputs") == inputs and (
            prior.get("config") == config or (resumable is not None and resumable(prior.get("config", {}), config)))
        if not keep and path.exists():
            shutil.rmtree(path)
        path.mkdir(parents=True, exist_ok=True)
        rec_path.unlink(missing_ok=True)
        pending = {"stage": name, "config": config, "inputs": inputs}
        before = float(prior.get("wall_s_parts", 0.0)) if keep and prior is not None else 0.0
        write_json(pend_path, pending | {"wall_s_parts": before})
        self.emit(f"[{name}] running ({why})")
        w0 = time.perf_counter()
        self._save_wall = lambda: write_json(pend_path, pending | {"wall_s_parts": before + time.perf_counter() - w0})
        try:
            wall = work(keep)
        finally:
            self._save_wall = _no_wall
        if wall is None:
            wall = before + time.perf_counter() - w0
        hashes = _hash_outputs(path, outputs())
        if hashes is None:
            raise RuntimeError(f"stage {name} finished without all of its outputs in {path}")
        write_json(rec_path, {"stage": name, "config": config, "inputs": inputs, "outputs": hashes, "wall_s": wall,
                              "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")})  # fmt: skip
        pend_path.unlink(missing_ok=True)
        self.emit(f"[{name}] done in {wall:.1f} s")
        res = StageResult(name, "done", path, wall, time.perf_counter() - t0, hashes)
        self.stages.append(res)
        return res

    # -- stages --------------------------------------------------------------------------------------
    def _record_stage(self, name: str, path: Path, config: Any, seeds: list[int], driver: str, scenario: str,
                      images: bool) -> StageResult:  # fmt: skip
        from lcdata.record import episode_filename, iter_record_episodes

        names = [episode_filename(scenario, driver, s) for s in seeds]

        def work(keep: bool) -> None:
            for p in path.glob("*.partial"):
                p.unlink()
            todo = [s for s, n in zip(seeds, names, strict=True) if not (path / n).exists()]
            workers = max(1, min(self.preset.record_workers, len(todo)))
            for k, r in enumerate(iter_record_episodes(config, todo, driver, path, scenario=scenario,
                                                       workers=workers, images=images,
                                                       executor=self.executor), 1):  # fmt: skip
                self._save_wall()  # an interrupted stage keeps the time of the episodes it has written
                self.emit(f"[{name}] {k}/{len(todo)} episodes: {r.path.name} {r.outcome}")

        stage_cfg = {"scenario": config.to_dict(), "seeds": seeds, "driver": driver, "images": images,
                     "scenario_name": scenario}  # fmt: skip
        return self._stage(name, path, stage_cfg, {}, lambda: names, work)

    def corpus(self) -> StageResult:
        from lcsim.config import corpus_scenario

        config = corpus_scenario()
        if self.preset.corpus_steps is not None:
            config = dataclasses.replace(config, time_limit_s=self.preset.corpus_steps * config.dt_s)
        p = self.preset
        seeds = list(range(p.corpus_seed, p.corpus_seed + p.corpus_episodes))
        return self._record_stage("corpus", self.out / "corpus", config, seeds, "autopilot", "corpus", False)

    def predictor_config(self) -> Any:
        from lcmodels.predictor import PredictorConfig, TrainConfig

        p = self.preset
        return TrainConfig(
            model=PredictorConfig(d_model=p.predictor_d_model, num_heads=p.predictor_heads,
                                  num_layers=p.predictor_layers, ff_dim=p.predictor_ff_dim),
            stride=p.predictor_stride, max_epochs=p.predictor_epochs, time_limit_s=p.predictor_time_limit_s,
            max_train_windows=p.predictor_max_train_windows, num_threads=self.threads, progress=False,
            tensorboard=p.predictor_tensorboard,
        )  # fmt: skip

    def predictor(self, corpus: StageResult) -> StageResult:
        tc = self.predictor_config()
        path = self.out / "predictor"

        def work(keep: bool) -> None:
            from lcdata.corpus import load_tracks
            from lcmodels.predictor import train_predictor

            m = train_predictor(load_tracks(corpus.path), tc, path)
            self.emit(f"[predictor] test ADE {m['model']['ade']:.4f} m FDE {m['model']['fde']:.4f} m "
                      f"(constant velocity {m['constant_velocity']['ade']:.4f} / "
                      f"{m['constant_velocity']['fde']:.4f})")  # fmt: skip

        cfg = {k: v for k, v in dataclasses.asdict(tc).items() if k not in ("progress", "num_threads")}
        return self._stage("predictor", path, cfg, {"corpus": corpus.digest},
                           lambda: ["predictor.pt", "metrics.json"], work)  # fmt: skip

    def demos(self, spec: DemoSpec) -> StageResult:
        """The demonstrations ``spec`` (with images), recorded once however many recipes clone them."""
        from lcmodels.policy.config import PolicyConfig

        config = PolicyConfig(scenario=self.preset.scenario, obs="hybrid").scenario_config()
        seeds = list(range(spec.seed, spec.seed + spec.episodes))
        key = demos_key(spec)
        return self._record_stage(f"demos/{key}", self.out / "demos" / key, config, seeds, spec.driver,
                                  self.preset.scenario, True)  # fmt: skip

    def evaluation(self, name: str, path: Path, spec: str, inputs: dict[str, str], *,
                   predictor: Path | None = None, follow: str | None = None,
                   lookahead: dict[str, Any] | None = None, scenario: Any = None,
                   label: str | None = None, test_only: bool = False) -> StageResult:  # fmt: skip
        """``metrics.json`` of driver ``spec`` on the validation seeds and the test episodes (see :class:`Preset`;
        ``test_only``: the test episodes alone). ``label``: the driver as the stage's config names it (not the
        policy's path, an input by its hash)."""
        p = self.preset
        splits = [] if test_only else [("val", s, p.val_episodes) for s in p.val_seeds]
        splits.append(("test", p.test_seed, p.test_episodes))

        def work(keep: bool) -> float:
            result: dict[str, Any] = {"config": cfg, "val": {}}
            total = 0.0
            for split, seed, episodes in splits:
                done = path / f"{split}-seed{seed}.json"  # a split finished before an interruption is kept
                summary = read_json(done) if keep else None
                if summary is None or summary.get("episodes") != episodes:
                    summary = run_split(split, seed, episodes, done)
                total += float(summary["wall_s"])
                if split == "val":
                    result["val"][str(seed)] = summary
                else:
                    result["test"] = summary
            write_json(path / "metrics.json", result)
            return total

        def run_split(split: str, seed: int, episodes: int, done: Path) -> dict[str, Any]:
            from lcmodels.policy.evaluate import evaluate_sharded
            from lcsim.planning import safety_layer_of

            t0 = time.perf_counter()
            rec = p.record_eval and split == "test"
            pool = self.eval_pool()
            summary, _ = evaluate_sharded(
                spec, scenario, episodes=episodes, seed=seed, pool=pool,
                shards=RAY_SHARDS if self.executor == "ray" else self.jobs if pool is not None else 1,
                executor=self.executor,
                predictor=str(predictor) if predictor else None, safety=safety_layer_of(spec, lookahead, follow),
                out_dir=path / "episodes" if rec else None, scenario=p.scenario, overwrite=True)  # fmt: skip
            summary["wall_s"] = time.perf_counter() - t0
            write_json(done, summary)  # kept before anything else can interrupt the stage
            self._save_wall()
            self.emit(f"[{name}] {split} (seed {seed}, {episodes} episodes): success "
                      f"{100 * summary['success_rate']:.1f}% collision {100 * summary['collision_rate']:.1f}%")
            return summary

        cfg = {"driver": label or spec, "splits": splits, "follow": bool(follow), "lookahead": lookahead or {},
               "record": p.record_eval, "scenario": p.scenario}  # fmt: skip
        return self._stage(name, path, cfg, inputs, lambda: ["metrics.json"], work)

    def reference(self, key: str) -> StageResult:
        """The rule-based driver or the oracle on the validation and test episodes."""
        from lcmodels.policy.config import PolicyConfig

        config = PolicyConfig(scenario=self.preset.scenario, obs="pure").scenario_config()
        return self.evaluation(key, self.out / key, key, {}, scenario=config)

    # -- recipes -------------------------------------------------------------------------------------
    def _policy_stage(self, recipe: Recipe, stage: str, seed: int, predictor: StageResult | None,
                      demos: StageResult | None, previous: StageResult | None,
                      follow: StageResult | None = None) -> StageResult:  # fmt: skip
        """One ``clone``, ``train`` or ``shielded`` stage of ``recipe``: an ``lcmodels.policy.train`` run
        directory. ``follow``: for ``shielded``, the final stage of the recipe the safety layer follows."""
        from lcmodels.policy.obs import needs_predictor
        from lcmodels.policy.train import train_policy

        path = policy_dir(self.out, recipe.name, seed) / stage
        init = str(previous_policy(previous)) if previous is not None and stage != "clone" else ""
        cfg = recipe.policy_config(stage, scenario=self.preset.scenario, seed=seed,
                                   warm_start=str(demos.path.resolve()) if demos is not None else "",
                                   init_policy=init, eval_episodes=0, caps=self.preset.cap_dict)  # fmt: skip
        inputs: dict[str, str] = {}
        pred_path = None
        if needs_predictor(cfg.obs):
            assert predictor is not None
            inputs["predictor"] = predictor.digest
            pred_path = predictor.path / "predictor.pt"
        if cfg.warm_start:
            assert demos is not None
            inputs["demos"] = demos.digest
        if cfg.init_policy:
            assert previous is not None
            inputs["init_policy"] = previous.digest
        shield_cfg: dict[str, Any] = {}
        if stage == "shielded":
            assert follow is not None and recipe.safety is not None
            inputs["follow"] = follow.digest
            shield_cfg = {"lookahead": lookahead_settings(recipe.safety), "penalty": float(recipe.shielded.penalty)}
        name = f"{recipe.name}/seed{seed}/{stage}"
        shown = [0]

        def show(row: dict[str, Any]) -> None:
            t = int(row["timesteps"])  # about 8 lines per run, whatever the algorithm's log interval
            if t < cfg.timesteps and t - shown[0] < cfg.timesteps / 8:
                return
            shown[0] = t
            self.emit(f"[{name}] step {t}/{cfg.timesteps} success {row['success_rate']:.2f} "
                      f"collision {row['collision_rate']:.2f} return {row['mean_return']:.1f}")

        def work(keep: bool) -> float:
            shield = None
            if shield_cfg:
                from lcmodels.policy.shield import shield_for

                assert follow is not None
                assert recipe.safety is not None
                shield = shield_for(dataclasses.replace(recipe.safety, follow=str(previous_policy(follow))),
                                    shield_cfg["penalty"], cfg.scenario_config(),
                                    str(pred_path) if pred_path else None)  # fmt: skip
            try:
                res = train_policy(cfg, path, predictor=pred_path, progress=show, shield=shield)
            except ValueError as exc:  # the directory holds another run (e.g. moved --out): start over
                if "another configuration" not in str(exc):
                    raise
                shutil.rmtree(path)
                path.mkdir(parents=True)
                res = train_policy(cfg, path, predictor=pred_path, progress=show, shield=shield)
            return res.wall_s

        stage_cfg = cfg.to_dict() | {"warm_start": "demos" if cfg.warm_start else "",
                                     "init_policy": "previous" if cfg.init_policy else ""}  # fmt: skip
        if shield_cfg:
            stage_cfg["shield"] = shield_cfg
        outputs = [POLICY_FILE, "metrics.json"] + (["progress.csv"] if cfg.timesteps > 0 else [])
        return self._stage(name, path, stage_cfg, inputs, lambda: outputs, work,
                           resumable=_resumable_policy_change, upgrade=_stored_stage_config)  # fmt: skip

    def _dagger_stage(self, recipe: Recipe, seed: int, clone: StageResult, demos: StageResult | None) -> StageResult:
        from lcmodels.policy.dagger import dagger

        spec = recipe.dagger
        path = policy_dir(self.out, recipe.name, seed) / "dagger"
        name = f"{recipe.name}/seed{seed}/dagger"

        def work(keep: bool) -> None:
            dagger(clone.path, path, rounds=spec.rounds, episodes=spec.episodes, epochs=spec.epochs,
                   seed=spec.seed + 10_000 * seed, workers=1, eval_episodes=0, labels=spec.labels,
                   expert=spec.expert, resume=keep and (path / "dagger.json").exists(),
                   demonstrations=demos.path if demos is not None else None,
                   progress=lambda m: self.emit(f"[{name}] {m}"))  # fmt: skip

        cfg = dataclasses.asdict(spec) | {"training_seed": seed}
        return self._stage(name, path, cfg, {"clone": clone.digest},
                           lambda: [f"round{spec.rounds}/{POLICY_FILE}", "dagger.json"], work)

    def recipe_stages(self, recipe: Recipe, seed: int, predictor: StageResult | None, demos: StageResult | None,
                      follow: StageResult | None = None,
                      done: Sequence[StageResult] = ()) -> list[StageResult]:  # fmt: skip
        """Every stage of ``recipe`` with training seed ``seed``, then its evaluation. A ``shielded`` stage needs
        ``follow``, the final stage of the recipe its safety layer follows: without it the stages stop before it
        (and :func:`_evaluated` is false); ``done``: the stages such a call returned, to go on from."""
        from lcmodels.policy.obs import needs_predictor

        done = list(done)
        previous: StageResult | None = done[-1] if done else None
        for stage in recipe.stages[len(done):]:
            if stage == "dagger":
                assert previous is not None
                previous = self._dagger_stage(recipe, seed, previous, demos)
            elif stage == "shielded" and follow is None:
                return done
            else:
                previous = self._policy_stage(recipe, stage, seed, predictor, demos if stage == "clone" else None,
                                              previous, follow if stage == "shielded" else None)  # fmt: skip
            done.append(previous)
        assert previous is not None
        uses_predictor = needs_predictor(recipe.obs)
        if self.dry_run and "pending" in previous.outputs:
            return done
        done.append(self.evaluation(
            f"{recipe.name}/seed{seed}/eval", policy_dir(self.out, recipe.name, seed) / "eval",
            str(previous_policy(previous)), {"policy": previous.digest}, label="policy",
            predictor=predictor.path / "predictor.pt" if uses_predictor and predictor else None))  # fmt: skip
        return done

    def safety(self, recipe: Recipe, seed: int, final: StageResult, follow: StageResult | None,
               predictor: StageResult | None) -> StageResult:  # fmt: skip
        """``recipe``'s final policy behind the lookahead planner (its ``[safety]`` table), evaluated."""
        from lcmodels.policy.obs import needs_predictor

        assert recipe.safety is not None  # capped with the recipe (Experiment.recipes)
        look = lookahead_settings(recipe.safety)
        inputs = {"policy": final.digest} | ({"follow": follow.digest} if follow is not None else {})
        return self.evaluation(
            f"{recipe.name}/seed{seed}/safety", policy_dir(self.out, recipe.name, seed) / "safety",
            f"lookahead-blind:{previous_policy(final)}", inputs,
            predictor=predictor.path / "predictor.pt" if predictor and needs_predictor(recipe.obs) else None,
            follow=str(previous_policy(follow)) if follow is not None else None, lookahead=look,
            label="lookahead-blind:policy")  # fmt: skip

    def follower_ready(self, recipe: Recipe, seed: int, predictor: StageResult | None,
                       follow: tuple[Recipe, StageResult | None] | None) -> StageResult | None:  # fmt: skip
        """The final stage of the recipe ``recipe``'s safety layer follows (``follow``: that recipe and its
        demonstrations) with training seed ``seed``, when it is trained and evaluated already; else None."""
        from lcmodels.policy.obs import needs_predictor

        if recipe.safety is None or not recipe.safety.follow or follow is None:
            return None
        f_recipe, f_demos = follow
        dry, progress, n = self.dry_run, self._progress, len(self.stages)
        self.dry_run, self._progress = True, None  # a look at the follower's stages, not progress
        try:
            f_done = self.recipe_stages(f_recipe, seed, predictor if needs_predictor(f_recipe.obs) else None, f_demos)
        finally:
            self.dry_run, self._progress, self.stages[n:] = dry, progress, []
        if not _evaluated(f_done) or any(st.status != "skipped" for st in f_done):
            return None
        return f_done[-2]

    def safety_when_ready(self, recipe: Recipe, seed: int, done: list[StageResult], predictor: StageResult | None,
                          follow: tuple[Recipe, StageResult | None] | None) -> StageResult | None:  # fmt: skip
        """``recipe``'s safety stage right after its training (``done``: its stages), when the policy the
        planner follows is trained already; else None, and the run does it after every recipe. ``follow``:
        the followed recipe and its demonstrations. Parallel workers call it, so that the one-core safety
        evaluation overlaps the remaining training."""
        if recipe.safety is None or not _evaluated(done) or done[-1].status not in ("skipped", "done"):
            return None
        follow_final = None
        if recipe.safety.follow:
            follow_final = self.follower_ready(recipe, seed, predictor, follow)
            if follow_final is None:
                return None
        return self.safety(recipe, seed, done[-2], follow_final, predictor)

    def _follow_of(self, recipe: Recipe, demos: dict[str, StageResult]) -> tuple[Recipe, StageResult | None] | None:
        """The recipe ``recipe``'s safety layer follows and its demonstrations (``demos`` by key), if any."""
        if recipe.safety is None or not recipe.safety.follow:
            return None
        f = next((r for r in self.recipes() if r.name == recipe.safety.follow), None)
        if f is None:
            return None
        return f, demos[demos_key(f.demos)] if "clone" in f.stages else None

    def _shielded_after(self, tasks: list[tuple[Any, ...]], results: list[list[StageResult]]) -> None:
        """The ``shielded`` stages (and evaluations) left waiting for the policy their layer follows, now that
        every recipe's other stages ran; ``results`` updated in place."""
        index = {(t[0].name, t[1]): i for i, t in enumerate(tasks)}
        for i, task in enumerate(tasks):
            r, seed = task[0], task[1]
            if _evaluated(results[i]) or "shielded" not in r.stages or r.safety is None:
                continue
            j = index.get((r.safety.follow, seed))
            if j is None or not results[j]:
                continue
            if _evaluated(results[j]) and "pending" not in results[j][-2].outputs:
                follow = results[j][-2]
            elif self.dry_run:  # the plan: the stage would run once the follower's stages have
                follow = results[j][-1]
            else:
                continue
            results[i] = self.recipe_stages(*task, follow=follow, done=results[i])

    # -- the whole run -------------------------------------------------------------------------------
    def plan(self) -> list[StageResult]:
        """What :meth:`run` would do, without doing it: each stage ``skipped`` or ``would run (why)``.

        A stage downstream of one that would run shows as stale (its inputs are not known yet).
        """
        self.check_out()
        self.dry_run = True
        try:
            self._stages(skip_train=False)
        finally:
            self.dry_run = False
        return list(self.stages)

    def run(self, *, skip_train: bool = False, jobs: int = 1) -> ExperimentResult:
        """Every stage in order (skipping what is complete), then REPORT.md and the figures.

        ``jobs``: policy stages trained at once, each in its own process (1: all in this process).
        """
        import torch

        from lcmodels.policy.train import versions
        from lcmodels.report import ReportInput, write_report

        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        t0 = time.perf_counter()
        self.check_out()
        self.out.mkdir(parents=True, exist_ok=True)
        with self.lock():
            if skip_train:  # a report-only rebuild keeps the command that made the results
                self.command = (read_json(self.out / MARKER) or {}).get("command") or self.command
            write_json(self.out / MARKER, {"preset": self.preset.to_dict(), "seeds": self.seeds,
                                           "command": self.command, "versions": versions()})  # fmt: skip
            previous = read_json(self.out / INVOCATIONS)
            self.invocations = [*(previous if isinstance(previous, list) else []),
                                {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "command": self.command}]
            self._invocation_t0 = t0
            try:
                self._save_invocation(finished=False)
                torch.set_num_threads(self.threads)
                if self.executor == "ray":
                    from lcdata.executors import ray_session

                    with ray_session(self.ray_address):
                        self._stages(skip_train=skip_train, jobs=jobs)
                else:
                    self._stages(skip_train=skip_train, jobs=jobs)
                self._save_invocation(finished=True)
            except BaseException:
                self._close_eval_pool(kill=True)
                raise
            finally:
                self._invocation_t0 = None
                self._close_eval_pool()
                self.jobs = 1
            wall = time.perf_counter() - t0
            report = write_report(ReportInput(self.out, self.preset, self.max_seeds, list(self.stages), self.invocations,
                                              self.command, self.recipes(),
                                              {r.name: self.seeds_of(r.name) for r in self.recipes()}), wall_s=wall)
        self.emit(f"[report] wrote {report}")
        return ExperimentResult(self.out, self.preset, self.seeds, list(self.stages), wall, report)

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold ``DIR/.lock`` (an advisory ``flock``, released when the process ends however it ends).

        ``ValueError`` when another process holds it: two runs in one directory would overwrite each other.
        """
        from lcdata.fileio import folder_lock

        with folder_lock(self.out, "lc-experiment", LOCK_NAME, doing="is running in"):
            yield

    def recipes(self) -> list[Recipe]:
        """The preset's recipes (capped), and any recipe a safety layer follows that the preset leaves out."""
        if self._recipes is not None:  # read once per experiment (the stages and the report use them)
            return self._recipes
        out = [load_recipe(n) for n in self.preset.recipes]
        for r in out:  # grows as it goes: a follower's own follower joins too
            if r.safety is not None and r.safety.follow and r.safety.follow not in {x.name for x in out}:
                out.append(load_recipe(r.safety.follow))
        follows = _follows(out)
        for name in follows:  # a layer following itself is allowed; a longer loop would wait on itself
            chain, loops = _follow_chain(follows, name)
            if loops:
                raise ValueError(f"the safety layers' followers form a loop: {' -> '.join([*chain, name])} "
                                 "(safety.follow)")
        self._recipes = [r.capped(self.preset.cap_dict) for r in out]
        return self._recipes

    def seeds_of(self, name: str) -> int:
        """Training seeds of recipe ``name``: ``--seeds``, or more where the preset asks (``recipe_seeds``), and
        a followed recipe as many as the recipe whose safety layer follows it (same seed, same follower)."""
        asked = dict(self.preset.recipe_seeds)
        n = max(self.seeds, asked.get(name, 1))
        for r in self.recipes():
            if r.safety is not None and r.safety.follow == name and r.name != name:
                n = max(n, self.seeds_of(r.name))
        return n

    @property
    def max_seeds(self) -> int:
        return max([self.seeds, *(self.seeds_of(r.name) for r in self.recipes())])

    def _stages(self, *, skip_train: bool, jobs: int = 1) -> None:
        from lcmodels.policy.obs import needs_predictor

        self.stages = []
        recipes = self.recipes()
        corpus = self.corpus()
        predictor = self.predictor(corpus)
        demos: dict[str, StageResult] = {}
        for r in recipes:
            if "clone" in r.stages and demos_key(r.demos) not in demos:
                demos[demos_key(r.demos)] = self.demos(r.demos)
        tasks = []
        for seed in range(self.max_seeds):
            for r in recipes:
                if seed >= self.seeds_of(r.name):
                    continue
                task = (r, seed, predictor if needs_predictor(r.obs) else None,
                        demos[demos_key(r.demos)] if "clone" in r.stages else None)  # fmt: skip
                if skip_train:  # a complete stage is reported as such (with its recorded time); the rest not run
                    dry, self.dry_run = self.dry_run, True
                    n = len(self.stages)
                    try:
                        done = self.recipe_stages(*task)
                        follow = self._follow_of(r, demos)
                        if not _evaluated(done) and (ready := self.follower_ready(r, seed, predictor, follow)):
                            self.recipe_stages(*task, follow=ready, done=done)
                        elif not _evaluated(done):  # waiting for the policy its layer follows: listed, not run
                            base = policy_dir(self.out, r.name, seed)
                            self.stages.extend(StageResult(f"{r.name}/seed{seed}/{st}", "not run", base / st, 0.0)
                                               for st in (*r.stages[len(done):], "eval"))  # fmt: skip
                    finally:
                        self.dry_run = dry
                    self.stages[n:] = [s if s.status == "skipped" else StageResult(s.name, "not run", s.path, 0.0)
                                       for s in self.stages[n:]]  # fmt: skip
                    continue
                tasks.append(task)
        rank = _task_ranks(recipes)
        tasks.sort(key=lambda t: rank[t[0].name])
        if self.executor == "ray" and not self.dry_run and tasks:
            results = self._ray_policies(tasks, demos)
        elif jobs == 1 or self.dry_run or len(tasks) < 2:
            results = [self.recipe_stages(*task) for task in tasks]  # their stages are in self.stages already
        else:
            results = self._parallel_policies(tasks, jobs, demos)
        if not self.dry_run and (self.executor == "ray" or (jobs > 1 and len(tasks) >= 2)):
            for res in results:
                self.stages.extend(res)
        self._shielded_after(tasks, results)
        self.reference(RULE_KEY)  # after the recipes: the oracle's search is slower than some training runs
        if self.preset.oracle:
            self.reference(ORACLE_KEY)
        if skip_train or self.dry_run:
            return
        finals = {(t[0].name, t[1]): res[-2] for t, res in zip(tasks, results, strict=True) if _evaluated(res)}
        for r, seed, _pred, _ in tasks:
            if r.safety is None or (r.name, seed) not in finals or (r.safety.follow and (
                    r.safety.follow, seed) not in finals):  # fmt: skip
                continue
            follow = finals.get((r.safety.follow, seed)) if r.safety.follow else None
            self.safety(r, seed, finals[(r.name, seed)], follow, predictor)
        if self.preset.zoo:
            self.zoo_stages(predictor)

    def zoo_stages(self, predictor: StageResult) -> None:
        """Every zoo policy on the test episodes (with the zoo's predictor), and behind its safety layer where
        its card has one; then a few recorded episodes of the best one and a Rerun ``.rrd`` of the first
        (``make demo``)."""
        from lcmodels.zoo import zoo_entries

        results = []
        entries = zoo_entries()
        for entry in entries:
            res = self.evaluation(f"zoo/{entry.name}", self.out / "zoo" / entry.name, str(entry.policy),
                                  {"policy": entry.sha256}, predictor=entry.predictor, label=f"zoo:{entry.name}")
            results.append((entry, res))
        for entry in entries:
            self.zoo_safety(entry, {e.name: e for e in entries})
        if not results or self.preset.showcase_episodes < 1 or self.dry_run:
            return
        best_success = -1.0
        for entry, res in results:
            success = float((read_json(res.path / "metrics.json") or {}).get("test", {}).get("success_rate", -1.0))
            if success > best_success:
                best, best_success = (entry, res), success
        self.showcase(*best)

    def zoo_safety(self, entry: Any, zoo: dict[str, Any]) -> StageResult | None:
        """Zoo policy ``entry`` behind the safety layer its card was measured with (the lookahead settings of
        the card, the imagined futures following the zoo's entry of the recipe's ``safety.follow``), on the
        test episodes alone; None when the card has no safety layer or the zoo lacks the followed policy."""
        look = ((entry.card.get("safety_layer") or {}).get("config") or {}).get("lookahead")
        if not look:
            return None
        try:
            recipe = load_recipe(str(entry.card.get("recipe", "")))
        except ValueError:
            return None
        follow = zoo.get(recipe.safety.follow) if recipe.safety is not None and recipe.safety.follow else None
        if recipe.safety is None or (recipe.safety.follow and follow is None):
            return None
        inputs = {"policy": entry.sha256} | ({"follow": follow.sha256} if follow is not None else {})
        return self.evaluation(f"zoo-safety/{entry.name}", self.out / "zoo-safety" / entry.name,
                               f"lookahead-blind:{entry.policy}", inputs, predictor=entry.predictor,
                               follow=str(follow.policy) if follow is not None else None, lookahead=dict(look),
                               label=f"lookahead-blind:zoo:{entry.name}", test_only=True)  # fmt: skip

    def showcase(self, entry: Any, evaluated: StageResult) -> StageResult:
        """``showcase_episodes`` test episodes of zoo policy ``entry`` recorded (MCAP) in ``DIR/showcase``, and
        the first as a Rerun file ``DIR/showcase/<episode>.rrd`` (``lc-view`` opens either)."""
        path = self.out / "showcase"
        p = self.preset

        def work(keep: bool) -> None:
            from lcdata.viewer.app import convert
            from lcmodels.policy.evaluate import driver_for, evaluate

            for old in path.glob("*"):
                old.unlink()
            driver, config = driver_for(str(entry.policy), predictor=str(entry.predictor) if entry.predictor else None)
            evaluate(driver, config, episodes=p.showcase_episodes, seed=p.test_seed, out_dir=path,
                     scenario=f"zoo-{entry.name}", overwrite=True)  # fmt: skip
            first = sorted(path.glob("*.mcap"))[0]
            convert([first], first.with_suffix(".rrd"))
            self.emit(f"[showcase] {p.showcase_episodes} episodes of zoo:{entry.name} in {path}; open one with "
                      f"lc-view {first.with_suffix('.rrd')}")  # fmt: skip

        def outputs() -> list[str]:
            return sorted(q.name for q in path.glob("*") if q.suffix in (".mcap", ".rrd"))

        cfg = {"zoo": entry.name, "episodes": p.showcase_episodes, "seed": p.test_seed}
        return self._stage("showcase", path, cfg, {"policy": entry.sha256, "eval": evaluated.digest}, outputs, work)

    def _ray_policies(self, tasks: list[tuple[Any, ...]],
                      demos: dict[str, StageResult]) -> list[list[StageResult]]:  # fmt: skip
        """The policy stages ``tasks`` as Ray tasks of ``threads`` CPUs each; results in task order. A stage
        records, resumes and skips as it does locally: each task runs :meth:`policy` in this directory, and goes
        on to its shielded and safety stages when the policy its layer follows is trained (``demos``: the
        demonstrations by key, for those followed recipes)."""
        from lcdata.executors import ray_map

        calls = [(i, self.preset, self.out, self.seeds, self.threads, *task, self._follow_of(task[0], demos))
                 for i, task in enumerate(tasks)]  # fmt: skip
        done: dict[int, list[StageResult]] = {}
        for i, result in ray_map(_ray_policy_task, calls, num_cpus=self.threads):
            done[i] = result
            self.emit(f"[{tasks[i][0].name}/seed{tasks[i][1]}] on Ray ({len(done)}/{len(tasks)} recipes)")
        return [done[i] for i in range(len(tasks))]

    def _parallel_policies(self, tasks: list[tuple[Any, ...]], jobs: int,
                           demos: dict[str, StageResult]) -> list[list[StageResult]]:  # fmt: skip
        """The policy stages ``tasks`` in ``jobs`` spawned processes (``demos``: the demonstrations by key, for
        the recipes their safety layers follow); results in task order.

        Progress lines come back through a queue. The first failure stops every worker and is raised; a worker
        that dies (killed, or out of memory) ends the run with :class:`ChildProcessError` naming the recipes
        left, instead of a wait for a result that never comes. The stages interrupted keep their pending records
        and resume on the next run.
        """
        import multiprocessing as mp
        from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool

        from lcdata.procs import stop_pool

        ctx = mp.get_context("spawn")  # no fork of a process that may hold torch threads
        queue = ctx.Queue()

        def pump() -> None:
            while (msg := queue.get()) is not None:
                self.emit(msg)

        printer = threading.Thread(target=pump, daemon=True)
        printer.start()
        pool = ProcessPoolExecutor(min(jobs, len(tasks)), mp_context=ctx, initializer=_policy_worker_init,
                                   initargs=(queue, self.threads, os.getpid()))  # fmt: skip
        futures = []
        try:
            for task in tasks:
                futures.append(pool.submit(_policy_worker, self.preset, self.out, self.seeds, *task,
                                           self._follow_of(task[0], demos)))  # fmt: skip
            wait(futures, return_when=FIRST_EXCEPTION)
            for fut in futures:
                exc = fut.exception() if fut.done() else None
                if isinstance(exc, BrokenProcessPool):
                    left = [f"{t[0].name}/seed{t[1]}" for t, g in zip(tasks, futures, strict=True)
                            if not g.done() or g.exception() is not None]  # fmt: skip
                    raise ChildProcessError(f"a worker process died (killed, or out of memory?) with {', '.join(left)} "
                                            "unfinished; what finished is kept and a rerun resumes the rest") from None
                if exc is not None:
                    raise exc
            results = [fut.result() for fut in futures]
        except BaseException:
            stop_pool(pool, kill=True)  # a running stage stops now; its pending record resumes it
            raise
        else:
            pool.shutdown(wait=True)
        finally:
            queue.put(None)
            printer.join()
        return results


_WORKER: dict[str, Any] = {}


RAY_SHARDS = 4
"""Ray tasks an evaluation stage is cut into."""


def _follows(recipes: Sequence[Recipe]) -> dict[str, str]:
    """Recipe name -> the recipe its safety layer follows, for the recipes whose layer follows one."""
    return {r.name: r.safety.follow for r in recipes if r.safety is not None and r.safety.follow}


def _follow_chain(follows: dict[str, str], name: str) -> tuple[list[str], bool]:
    """``name`` and the recipes its layer follows in turn, until one follows nothing or itself; and whether
    the chain comes back to ``name`` (a loop)."""
    chain = [name]
    while (nxt := follows.get(chain[-1])) and nxt != chain[-1] and nxt not in chain:
        chain.append(nxt)
    return chain, bool(nxt) and nxt != chain[-1] and nxt == name


def _task_ranks(recipes: Sequence[Recipe]) -> dict[str, int]:
    """The order in which the recipes' policy tasks start (sorted stably, so recipe order within a rank): the
    policies a safety layer follows first, then the recipes whose layer follows them (a chain by its depth),
    then the rest. A follower is then trained by the time the recipe that follows it ends its training, so
    that recipe's worker goes on to its shielded and safety stages itself instead of leaving them to run one
    after another at the end."""
    follows = _follows(recipes)
    depth = {r.name: len(_follow_chain(follows, r.name)[0]) - 1 for r in recipes}
    involved = set(follows) | set(follows.values())
    last = 1 + max((depth[n] for n in involved if n in depth), default=0)
    return {r.name: depth[r.name] if r.name in involved or r.safety is not None else last for r in recipes}


def _ray_policy_task(index: int, preset: Preset, out: Path, seeds: int, threads: int, recipe: Recipe, seed: int,
                     predictor: StageResult | None, demos: StageResult | None,
                     follow: tuple[Recipe, StageResult | None] | None = None) -> tuple[int, list[StageResult]]:
    """One policy stage as a Ray task of :meth:`Experiment._ray_policies` (its progress lines go to the task's
    log, which Ray forwards to the driver)."""
    import torch

    logging.basicConfig(level=logging.INFO, format="%(message)s")  # a fresh worker: its log goes to the driver
    torch.set_num_threads(threads)
    exp = Experiment(preset, out, seeds=seeds, threads=threads, progress=log.info)
    # the safety stage is left to the driver, which cuts its episodes into Ray tasks
    return index, _recipe_then_layer(exp, recipe, seed, predictor, demos, follow, safety=False)


def _policy_worker_init(queue: Any, threads: int, parent: int | None = None) -> None:
    import torch

    from lcdata.procs import die_with_parent

    die_with_parent(parent)

    torch.set_num_threads(threads)
    _WORKER["queue"], _WORKER["threads"] = queue, threads


def _policy_worker(preset: Preset, out: Path, seeds: int, recipe: Recipe, seed: int, predictor: StageResult | None,
                   demos: StageResult | None,
                   follow: tuple[Recipe, StageResult | None] | None = None) -> list[StageResult]:  # fmt: skip
    """One recipe's stages in a worker process of :meth:`Experiment._parallel_policies`; its shielded stage and
    safety stage too if the policy its layer follows is trained (:meth:`Experiment.follower_ready`)."""
    exp = Experiment(preset, out, seeds=seeds, threads=_WORKER["threads"], progress=_WORKER["queue"].put)
    return _recipe_then_layer(exp, recipe, seed, predictor, demos, follow)


def _recipe_then_layer(exp: Experiment, recipe: Recipe, seed: int, predictor: StageResult | None,
                       demos: StageResult | None, follow: tuple[Recipe, StageResult | None] | None, *,
                       safety: bool = True) -> list[StageResult]:  # fmt: skip
    """A worker's share of one recipe and seed: its stages, then its shielded stage and (``safety``) its safety
    stage if the policy its layer follows is trained already (:meth:`Experiment.follower_ready`); else the run
    does them after every recipe."""
    done = exp.recipe_stages(recipe, seed, predictor, demos)
    if not _evaluated(done) and (follow_final := exp.follower_ready(recipe, seed, predictor, follow)) is not None:
        done = exp.recipe_stages(recipe, seed, predictor, demos, follow_final, done)  # its shielded stage, then on
    if safety:
        exp.safety_when_ready(recipe, seed, done, predictor, follow)
    return done


def run_experiment(preset: Preset | str, out: str | Path, *, seeds: int = 1, command: str = "", threads: int = 1,
                   progress: Progress | None = None, skip_train: bool = False, jobs: int = 1, executor: str = "local",
                   ray_address: str | None = None) -> ExperimentResult:  # fmt: skip
    """Run (or resume) the experiment of ``preset`` in ``out``; see the module docstring."""
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
        preset = PRESETS[preset]
    exp = Experiment(preset, out, seeds=seeds, command=command, threads=threads, progress=progress,
                     executor=executor, ray_address=ray_address)
    return exp.run(skip_train=skip_train, jobs=jobs)


__all__ = [
    "FIG5_NAME",
    "FIG6_NAME",
    "INVOCATIONS",
    "LOCK_NAME",
    "MARKER",
    "ORACLE_KEY",
    "PAPER_TABLE2",
    "PAPER_TABLE3",
    "PAPER_TABLE4",
    "PRESETS",
    "REPORT_NAME",
    "ROWS",
    "RULE_KEY",
    "RULE_LABEL",
    "STAGES_DIR",
    "TABLE3_ROWS",
    "TABLE4_ROWS",
    "Experiment",
    "ExperimentResult",
    "Preset",
    "StageResult",
    "demos_key",
    "outputs_digest",
    "policy_dir",
    "previous_policy",
    "run_experiment",
]
