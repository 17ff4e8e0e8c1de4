"""What the stages of an experiment share: where they run (:class:`StageContext`), what a stage's job is
(:class:`StageJob`: its config, its inputs, the hashes of what it reads, and its work), and the jobs several kinds
of stage are made of (recording episodes, evaluating a driver, measuring one on the suite).

A kind of stage (:mod:`lcmodels.experiment.kinds`) turns a stage and the results of the stages it needs into
its :class:`StageJob`, which the store checks against the stage's record and a runner runs. A job is a pure
function of those arguments, so a worker process rebuilds the job of a training stage from the same arguments.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lckit.fileio import make_folder, remove_file
from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.store import Resumable, Upgrade
from lcmodels.fileio import read_json, write_json
from lcmodels.presets import Preset, StageResult

if TYPE_CHECKING:
    from lcmodels.policy.driverspec import DriverSpec

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


# ------------------------------------------------------------------------------------------------ recordings
def record_job(ctx: StageContext, key: StageKey, config: Any, seeds: list[int], driver: str, scenario: str,
               images: bool) -> StageJob:  # fmt: skip
    """The episodes of ``driver`` on ``config`` (scenario ``scenario``) with the user seeds ``seeds``, one MCAP each
    (``images``: with the bird's-eye images), recorded in the stage's directory; a rerun records the missing."""
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



# ----------------------------------------------------------------------------------------------- evaluations
def evaluation_job(ctx: StageContext, key: StageKey, driver: DriverSpec, inputs: dict[str, str], *,
                    predictor: Path | None = None, lookahead: dict[str, Any] | None = None,
                    scenario: Any = None, label: str | None = None, test_only: bool = False) -> StageJob:  # fmt: skip
    """``metrics.json`` of ``driver`` on the validation seeds and the test episodes (see
    :class:`~lcmodels.presets.Preset`; ``test_only``: the test episodes alone). ``label``: the driver as the
    stage's config names it (not the policy's path, an input by its hash); ``lookahead``: its safety layer's
    settings as the config names them (they are in ``driver``)."""
    p = ctx.preset
    path = key.path(ctx.out)
    splits = [] if test_only else [("val", s, p.val_episodes) for s in p.val_seeds]
    splits.append(("test", p.test_seed, p.test_episodes))
    cfg = {"driver": label or driver.text, "splits": splits, "follow": driver.follow is not None,
           "lookahead": lookahead or {},
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

        t0 = time.perf_counter()
        rec = p.record_eval and split == "test"
        if rec:
            make_folder(path / "episodes", ctx.out)  # never recorded through a link out of the experiment
        pool = ctx.pool()
        summary, _ = evaluate_sharded(
            driver, scenario, episodes=episodes, seed=seed, pool=pool, shards=ctx.shards(pool), executor=ctx.executor,
            predictor=str(predictor) if predictor else None,
            out_dir=path / "episodes" if rec else None, scenario=p.scenario, overwrite=True)  # fmt: skip
        summary["wall_s"] = time.perf_counter() - t0
        write_json(done, summary)  # kept before anything else can interrupt the stage
        save_wall()
        ctx.emit(f"[{key}] {split} (seed {seed}, {episodes} episodes): success "
                 f"{100 * summary['success_rate']:.1f}% collision {100 * summary['collision_rate']:.1f}%")
        return summary

    return StageJob(cfg, inputs, lambda: ["metrics.json"], work)


def suite_job(ctx: StageContext, key: StageKey, spec: DriverSpec, inputs: dict[str, str], *, group: str,
               predictor: Path | None = None) -> StageJob:
    """``suite.json``: the driver ``spec`` on every road of the preset's suite, ``suite_episodes`` validation episodes
    of ``suite_seed`` each, as lc-bench measures a cell (each road's cell kept as it ends: a rerun resumes)."""
    p = ctx.preset
    path = key.path(ctx.out)
    label = f"{key.recipe}/seed{key.seed}" if key.recipe is not None else spec.text
    cfg = {"driver": label, "suite": p.suite, "episodes": p.suite_episodes, "seed": p.suite_seed}

    def work(keep: bool, save_wall: Callable[[], None]) -> float:
        from lcmodels.bench.run import Runner, bench_cell, resolve_driver
        from lcsim.suite import suite

        driver = dataclasses.replace(resolve_driver(spec, predictor=str(predictor) if predictor else None),
                                     label=label)  # fmt: skip
        cells = {}
        for sc in suite(p.suite):
            cell = bench_cell(driver, sc, Runner(threads=ctx.threads), episodes=p.suite_episodes, seed=p.suite_seed,
                              final=False, cache_dir=path / "cells")  # fmt: skip
            cells[sc.name] = cell.record
            save_wall()
            ctx.emit(f"[{key}] {sc.name}: success {100 * cell.record['success_rate']:.1f}% "
                     f"({cell.record['episodes']} episodes{', cached' if cell.source == 'cache' else ''})")
        write_json(path / "suite.json", {"config": cfg, "label": label, "group": group, "cells": cells})
        return float(sum(c["wall_s"] for c in cells.values()))

    return StageJob(cfg, inputs, lambda: ["suite.json"], work)


def predictor_file(recipe: Any, got: Mapping[str, StageResult]) -> Path | None:
    """The predictor file the policy of ``recipe`` (a :class:`~lcmodels.experiment.recipe.Recipe`) reads, from
    the results ``got`` of the stages its stage needs (None: it reads no predictions)."""
    from lcmodels.policy.obs import needs_predictor

    pred = got.get("predictor")
    return pred.path / "predictor.pt" if pred is not None and needs_predictor(recipe.obs) else None


