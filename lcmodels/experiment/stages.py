"""What each stage of the graph computes: its config, its inputs (the hashes of what it reads) and its work.

:func:`stage_job` turns a :class:`~lcmodels.experiment.graph.Stage` and the results of the stages it needs into a
:class:`StageJob`, which the store checks against the stage's record and a runner runs. It is a pure function of
its arguments, so a worker process rebuilds the job of a training stage from the same arguments.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lckit.fileio import make_folder, remove_file, remove_tree
from lcmodels.experiment.graph import Stage
from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.layer import card_lookahead, recipe_lookahead
from lcmodels.experiment.store import Resumable, Upgrade
from lcmodels.fileio import POLICY_FILE, read_json, write_json
from lcmodels.presets import ORACLE_KEY, RULE_KEY, Preset, StageResult, canonical, previous_policy
from lcmodels.recipe import Recipe

log = logging.getLogger("lcmodels.experiment")

RAY_SHARDS = 4
"""Ray tasks an evaluation stage is cut into."""

Work = Callable[[bool, Callable[[], None]], "float | None"]
"""``work(keep, save_wall)``: compute the stage's outputs (``keep``: its directory holds a prefix of them;
``save_wall()`` puts the time so far into the pending record); returns the compute time behind the outputs when
the stage knows it (every resumed part counted), else None."""


@dataclass
class StageContext:
    """Where the stages of one experiment run: its preset and directory, torch threads, the executor, and the
    processes an evaluation cuts its episodes over."""

    preset: Preset
    out: Path
    threads: int = 1
    executor: str = "local"
    emit: Callable[[str], None] = log.info
    pool: Callable[[], Any] = field(default=lambda: None)
    """The ``concurrent.futures`` executor an evaluation of this process cuts its episodes over (None: none)."""
    jobs: int = 1
    """Shards of an evaluation over ``pool``."""

    def shards(self, pool: Any) -> int:
        return RAY_SHARDS if self.executor == "ray" else self.jobs if pool is not None else 1


@dataclass
class StageJob:
    config: dict[str, Any]
    inputs: dict[str, str]
    outputs: Callable[[], list[str]]
    work: Work
    resumable: Resumable | None = None
    upgrade: Upgrade | None = None


def stage_job(ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
    """The job of ``stage`` given the results ``got`` of the stages it needs, by role."""
    k = stage.key
    if k.recipe is not None:
        assert stage.recipe is not None
        if k.stage in ("clone", "train", "shielded"):
            job = _policy_job(ctx, k, stage.recipe, got)
        elif k.stage == "dagger":
            job = _dagger_job(ctx, k, stage.recipe, got)
        elif k.stage == "eval":
            job = _recipe_eval_job(ctx, k, stage.recipe, got)
        elif k.stage == "safety":
            job = _safety_job(ctx, k, stage.recipe, got)
        else:
            raise ValueError(f"no such recipe stage: {k}")
    elif k.stage == "corpus":
        job = _corpus_job(ctx, k)
    elif k.stage == "predictor":
        job = _predictor_job(ctx, k, got["corpus"])
    elif k.stage == "demos":
        job = _demos_job(ctx, k, stage.demos)
    elif k.stage in (RULE_KEY, ORACLE_KEY):
        job = _reference_job(ctx, k)
    elif k.stage == "zoo":
        job = _evaluation_job(ctx, k, str(stage.zoo.policy), {"policy": stage.zoo.sha256},
                              predictor=stage.zoo.predictor, label=f"zoo:{stage.zoo.name}")  # fmt: skip
    elif k.stage == "zoo-safety":
        job = _zoo_safety_job(ctx, k, stage.zoo, stage.follow_zoo)
    elif k.stage == "showcase":
        job = _showcase_job(ctx, k, stage.zoo, got)
    else:
        raise ValueError(f"no such stage: {k}")
    job.config, job.inputs = canonical(job.config), canonical(job.inputs)
    return job


# ------------------------------------------------------------------------------------------------ recordings
def _record_job(ctx: StageContext, key: StageKey, config: Any, seeds: list[int], driver: str, scenario: str,
                images: bool) -> StageJob:  # fmt: skip
    from lcdata.record import episode_filename

    path = key.path(ctx.out)
    names = [episode_filename(scenario, driver, s) for s in seeds]

    def work(keep: bool, save_wall: Callable[[], None]) -> None:
        from lcdata.record import iter_record_episodes

        for p in path.glob("*.partial"):
            remove_file(p, ctx.out)
        todo = [s for s, n in zip(seeds, names, strict=True) if not (path / n).exists()]
        workers = max(1, min(ctx.preset.record_workers, len(todo)))
        for i, r in enumerate(iter_record_episodes(config, todo, driver, path, scenario=scenario, workers=workers,
                                                   images=images, executor=ctx.executor), 1):  # fmt: skip
            save_wall()  # an interrupted stage keeps the time of the episodes it has written
            ctx.emit(f"[{key}] {i}/{len(todo)} episodes: {r.path.name} {r.outcome}")

    cfg = {"scenario": config.to_dict(), "seeds": seeds, "driver": driver, "images": images, "scenario_name": scenario}
    return StageJob(cfg, {}, lambda: names, work)


def _corpus_job(ctx: StageContext, key: StageKey) -> StageJob:
    from lcsim.config import corpus_scenario

    p = ctx.preset
    config = corpus_scenario()
    if p.corpus_steps is not None:
        config = dataclasses.replace(config, time_limit_s=p.corpus_steps * config.dt_s)
    seeds = list(range(p.corpus_seed, p.corpus_seed + p.corpus_episodes))
    return _record_job(ctx, key, config, seeds, "autopilot", "corpus", False)


def _demos_job(ctx: StageContext, key: StageKey, spec: Any) -> StageJob:
    """The demonstrations ``spec`` (with images), recorded once however many recipes clone them."""
    from lcmodels.policy.config import PolicyConfig

    config = PolicyConfig(scenario=ctx.preset.scenario, obs="hybrid").scenario_config()
    seeds = list(range(spec.seed, spec.seed + spec.episodes))
    return _record_job(ctx, key, config, seeds, spec.driver, ctx.preset.scenario, True)


def predictor_config(preset: Preset, threads: int) -> Any:
    """The :class:`lcmodels.predictor.TrainConfig` of ``preset``'s predictor stage."""
    from lcmodels.predictor import PredictorConfig, TrainConfig

    p = preset
    return TrainConfig(
        model=PredictorConfig(d_model=p.predictor_d_model, num_heads=p.predictor_heads,
                              num_layers=p.predictor_layers, ff_dim=p.predictor_ff_dim),
        stride=p.predictor_stride, max_epochs=p.predictor_epochs, time_limit_s=p.predictor_time_limit_s,
        max_train_windows=p.predictor_max_train_windows, num_threads=threads, progress=False,
        tensorboard=p.predictor_tensorboard,
    )  # fmt: skip


def _predictor_job(ctx: StageContext, key: StageKey, corpus: StageResult) -> StageJob:
    tc = predictor_config(ctx.preset, ctx.threads)
    path = key.path(ctx.out)

    def work(keep: bool, save_wall: Callable[[], None]) -> None:
        from lcdata.corpus import load_tracks
        from lcmodels.predictor import train_predictor

        m = train_predictor(load_tracks(corpus.path), tc, path)
        ctx.emit(f"[{key}] test ADE {m['model']['ade']:.4f} m FDE {m['model']['fde']:.4f} m "
                 f"(constant velocity {m['constant_velocity']['ade']:.4f} / "
                 f"{m['constant_velocity']['fde']:.4f})")  # fmt: skip

    cfg = {k: v for k, v in dataclasses.asdict(tc).items() if k not in ("progress", "num_threads")}
    return StageJob(cfg, {"corpus": corpus.digest}, lambda: ["predictor.pt", "metrics.json"], work,
                    upgrade=stored_predictor_config)


def stored_predictor_config(data: dict[str, Any]) -> dict[str, Any]:
    """A predictor stage's recorded config in today's form: a model field added since reads as a checkpoint
    without it does (:meth:`lcmodels.predictor.PredictorConfig.from_dict`), so the model it trained is the same."""
    from lcmodels.predictor import PredictorConfig

    model = data.get("model")
    if not isinstance(model, dict):
        return data
    try:
        return data | {"model": dataclasses.asdict(PredictorConfig.from_dict(model))}
    except (TypeError, ValueError):
        return data


# ----------------------------------------------------------------------------------------------- evaluations
def _evaluation_job(ctx: StageContext, key: StageKey, spec: str, inputs: dict[str, str], *,
                    predictor: Path | None = None, follow: str | None = None, lookahead: dict[str, Any] | None = None,
                    scenario: Any = None, label: str | None = None, test_only: bool = False) -> StageJob:  # fmt: skip
    """``metrics.json`` of driver ``spec`` on the validation seeds and the test episodes (see
    :class:`~lcmodels.presets.Preset`; ``test_only``: the test episodes alone). ``label``: the driver as the
    stage's config names it (not the policy's path, an input by its hash)."""
    p = ctx.preset
    path = key.path(ctx.out)
    splits = [] if test_only else [("val", s, p.val_episodes) for s in p.val_seeds]
    splits.append(("test", p.test_seed, p.test_episodes))
    cfg = {"driver": label or spec, "splits": splits, "follow": bool(follow), "lookahead": lookahead or {},
           "record": p.record_eval, "scenario": p.scenario}  # fmt: skip

    def work(keep: bool, save_wall: Callable[[], None]) -> float:
        result: dict[str, Any] = {"config": cfg, "val": {}}
        total = 0.0
        for split, seed, episodes in splits:
            done = path / f"{split}-seed{seed}.json"  # a split finished before an interruption is kept
            summary = read_json(done) if keep else None
            if not isinstance(summary, dict) or summary.get("episodes") != episodes or not isinstance(
                    summary.get("wall_s"), int | float):  # a split cut short or edited is run again
                summary = run_split(split, seed, episodes, done, save_wall)
            total += float(summary["wall_s"])
            if split == "val":
                result["val"][str(seed)] = summary
            else:
                result["test"] = summary
        write_json(path / "metrics.json", result)
        return total

    def run_split(split: str, seed: int, episodes: int, done: Path, save_wall: Callable[[], None]) -> dict[str, Any]:
        from lcmodels.policy.evaluate import evaluate_sharded
        from lcsim.planning import safety_layer_of

        t0 = time.perf_counter()
        rec = p.record_eval and split == "test"
        if rec:
            make_folder(path / "episodes", ctx.out)  # never recorded through a link out of the experiment
        pool = ctx.pool()
        summary, _ = evaluate_sharded(
            spec, scenario, episodes=episodes, seed=seed, pool=pool, shards=ctx.shards(pool), executor=ctx.executor,
            predictor=str(predictor) if predictor else None, safety=safety_layer_of(spec, lookahead, follow),
            out_dir=path / "episodes" if rec else None, scenario=p.scenario, overwrite=True)  # fmt: skip
        summary["wall_s"] = time.perf_counter() - t0
        write_json(done, summary)  # kept before anything else can interrupt the stage
        save_wall()
        ctx.emit(f"[{key}] {split} (seed {seed}, {episodes} episodes): success "
                 f"{100 * summary['success_rate']:.1f}% collision {100 * summary['collision_rate']:.1f}%")
        return summary

    return StageJob(cfg, inputs, lambda: ["metrics.json"], work)


def _reference_job(ctx: StageContext, key: StageKey) -> StageJob:
    """The rule-based driver or the oracle on the validation and test episodes."""
    from lcmodels.policy.config import PolicyConfig

    config = PolicyConfig(scenario=ctx.preset.scenario, obs="pure").scenario_config()
    return _evaluation_job(ctx, key, key.stage, {}, scenario=config)


def _predictor_file(recipe: Recipe, got: Mapping[str, StageResult]) -> Path | None:
    from lcmodels.policy.obs import needs_predictor

    pred = got.get("predictor")
    return pred.path / "predictor.pt" if pred is not None and needs_predictor(recipe.obs) else None


def _recipe_eval_job(ctx: StageContext, key: StageKey, recipe: Recipe, got: Mapping[str, StageResult]) -> StageJob:
    """``recipe``'s final policy on the validation and test episodes."""
    final = got["policy"]
    return _evaluation_job(ctx, key, str(previous_policy(final)), {"policy": final.digest}, label="policy",
                           predictor=_predictor_file(recipe, got))  # fmt: skip


def _safety_job(ctx: StageContext, key: StageKey, recipe: Recipe, got: Mapping[str, StageResult]) -> StageJob:
    """``recipe``'s final policy behind the lookahead planner (its ``[safety]`` table), evaluated."""
    final, follow = got["policy"], got.get("follow")
    inputs = {"policy": final.digest} | ({"follow": follow.digest} if follow is not None else {})
    return _evaluation_job(ctx, key, f"lookahead-blind:{previous_policy(final)}", inputs,
                           predictor=_predictor_file(recipe, got),
                           follow=str(previous_policy(follow)) if follow is not None else None,
                           lookahead=recipe_lookahead(recipe), label="lookahead-blind:policy")  # fmt: skip


def _zoo_safety_job(ctx: StageContext, key: StageKey, entry: Any, follow: Any) -> StageJob:
    """Zoo policy ``entry`` behind the safety layer its card was measured with (the imagined futures following
    the zoo's entry ``follow`` of the recipe's ``safety.follow``), on the test episodes alone."""
    inputs = {"policy": entry.sha256} | ({"follow": follow.sha256} if follow is not None else {})
    return _evaluation_job(ctx, key, f"lookahead-blind:{entry.policy}", inputs, predictor=entry.predictor,
                           follow=str(follow.policy) if follow is not None else None,
                           lookahead=card_lookahead(entry.card), label=f"lookahead-blind:zoo:{entry.name}",
                           test_only=True)  # fmt: skip


def _showcase_job(ctx: StageContext, key: StageKey, entries: Any, got: Mapping[str, StageResult]) -> StageJob:
    """``showcase_episodes`` test episodes of the zoo policy with the best test success recorded (MCAP) in
    ``DIR/showcase``, and the first as a Rerun file ``DIR/showcase/<episode>.rrd`` (``lc-view`` opens either)."""
    path = key.path(ctx.out)
    p = ctx.preset
    best_success, best = -1.0, None
    for entry in entries:
        res = got[f"zoo:{entry.name}"]
        success = float((read_json(res.path / "metrics.json") or {}).get("test", {}).get("success_rate", -1.0))
        if success > best_success:
            best, best_success = (entry, res), success
    assert best is not None
    entry, evaluated = best

    def work(keep: bool, save_wall: Callable[[], None]) -> None:
        from lcdata.viewer.app import convert
        from lcmodels.policy.evaluate import driver_for, evaluate

        for old in path.glob("*"):
            remove_file(old, ctx.out)
        driver, config = driver_for(str(entry.policy), predictor=str(entry.predictor) if entry.predictor else None)
        evaluate(driver, config, episodes=p.showcase_episodes, seed=p.test_seed, out_dir=path,
                 scenario=f"zoo-{entry.name}", overwrite=True)  # fmt: skip
        first = sorted(path.glob("*.mcap"))[0]
        convert([first], first.with_suffix(".rrd"))
        ctx.emit(f"[{key}] {p.showcase_episodes} episodes of zoo:{entry.name} in {path}; open one with "
                 f"lc-view {first.with_suffix('.rrd')}")  # fmt: skip

    def outputs() -> list[str]:
        return sorted(q.name for q in path.glob("*") if q.suffix in (".mcap", ".rrd"))

    cfg = {"zoo": entry.name, "episodes": p.showcase_episodes, "seed": p.test_seed}
    return StageJob(cfg, {"policy": entry.sha256, "eval": evaluated.digest}, outputs, work)


# --------------------------------------------------------------------------------------------------- policies
def resumable_policy_change(prior: dict[str, Any], now: dict[str, Any]) -> bool:
    """A policy run can continue under ``now``: only evaluation settings or a larger budget differ."""
    free = ("timesteps", "checkpoint_every", "eval_episodes", "eval_seed", "eval_batch", "record_eval")
    if any(prior.get(k) != now.get(k) for k in now if k not in free):
        return False
    timesteps = prior.get("timesteps", 0)
    return isinstance(timesteps, int) and timesteps <= int(now["timesteps"])


def stored_stage_config(data: dict[str, Any]) -> dict[str, Any]:
    """A policy stage's recorded config in today's form (:func:`lcmodels.policy.train.stored_config`), the
    shielded stage's ``shield`` table kept as it is."""
    from lcmodels.policy.train import stored_config

    if "shield" not in data:
        return stored_config(data)
    return stored_config({k: v for k, v in data.items() if k != "shield"}) | {"shield": data["shield"]}


def _policy_job(ctx: StageContext, key: StageKey, recipe: Recipe, got: Mapping[str, StageResult]) -> StageJob:
    """One ``clone``, ``train`` or ``shielded`` stage of ``recipe``: an ``lcmodels.policy.train`` run directory.
    ``got``: ``predictor`` (when the policy reads predictions), ``demos`` (a clone), ``previous`` (the recipe's
    stage before), ``follow`` (a shielded stage: the final stage of the recipe the safety layer follows)."""
    from lcmodels.policy.obs import needs_predictor

    stage, seed = key.stage, key.seed
    assert seed is not None
    predictor, previous, follow = got.get("predictor"), got.get("previous"), got.get("follow")
    demos = got.get("demos") if stage == "clone" else None
    path = key.path(ctx.out)
    init = str(previous_policy(previous)) if previous is not None and stage != "clone" else ""
    cfg = recipe.policy_config(stage, scenario=ctx.preset.scenario, seed=seed,
                               warm_start=str(demos.path.resolve()) if demos is not None else "",
                               init_policy=init, eval_episodes=0, caps=ctx.preset.cap_dict)  # fmt: skip
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
        assert follow is not None
        inputs["follow"] = follow.digest
        shield_cfg = {"lookahead": recipe_lookahead(recipe), "penalty": float(recipe.shielded.penalty)}
    shown = [0]

    def show(row: dict[str, Any]) -> None:
        t = int(row["timesteps"])  # about 8 lines per run, whatever the algorithm's log interval
        if t < cfg.timesteps and t - shown[0] < cfg.timesteps / 8:
            return
        shown[0] = t
        ctx.emit(f"[{key}] step {t}/{cfg.timesteps} success {row['success_rate']:.2f} "
                 f"collision {row['collision_rate']:.2f} return {row['mean_return']:.1f}")

    def work(keep: bool, save_wall: Callable[[], None]) -> float:
        from lcmodels.policy.train import train_run

        shield = None
        if shield_cfg:
            from lcmodels.policy.shield import shield_for

            assert follow is not None
            assert recipe.safety is not None
            shield = shield_for(dataclasses.replace(recipe.safety, follow=str(previous_policy(follow))),
                                shield_cfg["penalty"], cfg.scenario_config(),
                                str(pred_path) if pred_path else None)  # fmt: skip
        try:
            res = train_run(cfg, path, predictor=pred_path, progress=show, shield=shield)
        except ValueError as exc:  # the directory holds another run (e.g. moved --out): start over
            if "another configuration" not in str(exc):
                raise
            remove_tree(path, ctx.out)
            make_folder(path, ctx.out)
            res = train_run(cfg, path, predictor=pred_path, progress=show, shield=shield)
        return res.wall_s

    stage_cfg = cfg.to_dict() | {"warm_start": "demos" if cfg.warm_start else "",
                                 "init_policy": "previous" if cfg.init_policy else ""}  # fmt: skip
    if shield_cfg:
        stage_cfg["shield"] = shield_cfg
    outputs = [POLICY_FILE, "metrics.json"] + (["progress.csv"] if cfg.timesteps > 0 else [])
    return StageJob(stage_cfg, inputs, lambda: outputs, work, resumable=resumable_policy_change,
                    upgrade=stored_stage_config)  # fmt: skip


def _dagger_job(ctx: StageContext, key: StageKey, recipe: Recipe, got: Mapping[str, StageResult]) -> StageJob:
    """DAgger rounds of ``recipe``. ``got``: ``previous`` (its clone), ``demos`` (the clone's demonstrations), and
    for the safety layer as the expert ``follow``: the followed recipe's final policy, which behind the layer labels
    the states and, when the stage comes first, is the student it starts from."""
    spec = recipe.dagger
    follow, demos = got.get("follow"), got.get("demos")
    start = got.get("previous") or follow
    assert start is not None
    path = key.path(ctx.out)
    seed = key.seed
    assert seed is not None
    layer, expert = None, spec.expert
    if spec.expert == "safety-layer":
        assert follow is not None and recipe.safety is not None
        layer = dataclasses.replace(recipe.safety, follow="")  # the imagined futures follow the expert's own policy
        expert = f"safety-layer:{previous_policy(follow)}"

    def work(keep: bool, save_wall: Callable[[], None]) -> None:
        from lcmodels.policy.dagger import dagger

        dagger(start.path, path, rounds=spec.rounds, episodes=spec.episodes, epochs=spec.epochs,
               seed=spec.seed + 10_000 * seed, workers=1, eval_episodes=0, labels=spec.labels,
               expert=expert, correction_weight=spec.correction_weight, balance_actions=spec.balance_actions,
               expert_safety=layer,
               resume=keep and (path / "dagger.json").exists(),
               demonstrations=demos.path if demos is not None else None,
               progress=lambda m: ctx.emit(f"[{key}] {m}"))  # fmt: skip

    cfg = dataclasses.asdict(spec) | {"training_seed": seed}
    inputs = {"clone": start.digest}
    if layer is not None:
        assert follow is not None
        cfg["safety"] = recipe_lookahead(recipe)
        inputs["expert"] = follow.digest
    return StageJob(cfg, inputs, lambda: [f"round{spec.rounds}/{POLICY_FILE}", "dagger.json"], work,
                    upgrade=stored_dagger_config)


def stored_dagger_config(data: dict[str, Any]) -> dict[str, Any]:
    """A dagger stage's recorded config in today's form: one recorded before the correction weight and the action
    balance were settings trained at weight 1, balanced."""
    return {"correction_weight": 1.0, "balance_actions": True} | data
