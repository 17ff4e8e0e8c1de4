"""The experiment of one directory: its preset and recipes, its stage graph, and a run of it with its report."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcmodels.experiment.graph import StageGraph, build_graph, follow_closure, recipe_seeds
from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.recipe import Recipe, load_recipe
from lcmodels.experiment.runner import Runner
from lcmodels.experiment.stages import StageContext
from lcmodels.experiment.store import Invocations, StageStore
from lcmodels.presets import PRESETS, Preset, StageResult

log = logging.getLogger("lcmodels.experiment")

Progress = Callable[[str], None]


@dataclass
class ExperimentResult:
    out: Path
    preset: Preset
    seeds: int
    stages: list[StageResult]
    wall_s: float
    report: Path


class Experiment:
    """The stages of one experiment directory; :meth:`run` does what is missing or stale."""

    def __init__(self, preset: Preset, out: str | Path, *, seeds: int = 1, command: str = "", threads: int = 1,
                 progress: Progress | None = None, executor: str = "local",
                 ray_address: str | None = None) -> None:  # fmt: skip
        from lcdata.executors import EXECUTORS

        if executor not in EXECUTORS:
            raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
        if seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {seeds}")
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.preset, self.out, self.seeds, self.command = preset, Path(out), seeds, command
        self.threads, self.executor, self.ray_address = threads, executor, ray_address
        self.store = StageStore(self.out)
        self.invocations = Invocations(self.out)
        self._progress = progress
        self._recipes: list[Recipe] | None = None
        self._graph: StageGraph | None = None

    def emit(self, msg: str) -> None:
        log.info(msg)
        self.invocations.save(finished=False)
        if self._progress is not None:
            self._progress(msg)

    # -- what the experiment is ------------------------------------------------------------------
    def recipes(self) -> list[Recipe]:
        """The preset's recipes (capped), and any recipe a safety layer follows that the preset leaves out."""
        if self._recipes is None:  # read once per experiment (the graph and the report use them)
            out = follow_closure([load_recipe(n) for n in self.preset.recipes], load_recipe)
            self._recipes = [r.capped(self.preset.cap_dict) for r in out]
        return self._recipes

    def seeds_of(self, name: str) -> int:
        """Training seeds of recipe ``name``: ``--seeds``, or more where the preset asks (``recipe_seeds``), and
        a followed recipe as many as the recipe whose safety layer follows it (same seed, same follower)."""
        return self._seeds()[name]

    def _seeds(self) -> dict[str, int]:
        return recipe_seeds(self.recipes(), self.seeds, dict(self.preset.recipe_seeds))

    @property
    def max_seeds(self) -> int:
        return max([self.seeds, *self._seeds().values()])

    def graph(self) -> StageGraph:
        """Every stage of the experiment and what each needs (:class:`~lcmodels.experiment.graph.GraphCycle`, a
        ``ValueError``, when stages wait on each other)."""
        if self._graph is None:
            zoo: list[Any] = []
            if self.preset.zoo:
                from lcmodels.zoo import zoo_entries

                zoo = zoo_entries()
            self._graph = build_graph(self.preset, self.recipes(), self._seeds(), zoo)
        return self._graph

    def context(self) -> StageContext:
        return StageContext(self.preset, self.out, self.threads, self.executor, self.emit)

    def check_out(self) -> None:
        """``ValueError`` when ``out`` cannot be an experiment directory (:meth:`StageStore.check_out`)."""
        self.store.check_out()

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold ``DIR/.lock``; ``ValueError`` when another process holds it."""
        with self.store.lock():
            yield

    # -- queries and runs ------------------------------------------------------------------------
    def plan(self) -> list[StageResult]:
        """What :meth:`run` would do, without doing it: each stage ``skipped`` (complete), ``would run (why)``, or
        ``would run (after S)`` when a stage S it reads would run (its inputs are not known yet)."""
        self.check_out()
        return Runner(self.graph(), self.store, self.context(), dry_run=True).run()

    def run_stage(self, key: StageKey) -> StageResult:
        """Stage ``key`` alone, here, when it is not complete; ``ValueError`` when a stage it reads is not."""
        graph = self.graph()
        if key not in graph:
            raise ValueError(f"the experiment has no stage {key}")
        quiet = StageContext(self.preset, self.out, self.threads, self.executor, lambda msg: None)
        up = Runner(graph, self.store, quiet, dry_run=True).run(graph.upstream(key))
        given = {StageKey.parse(r.name): r for r in up}
        for k in graph.needed(key):
            if given[k].status != "skipped":
                raise ValueError(f"stage {key} needs {k}, which is not complete ({given[k].status})")
        return Runner(graph, self.store, self.context()).run([key], given)[0]

    def run(self, *, skip_train: bool = False, jobs: int = 1) -> ExperimentResult:
        """Every stage in dependency order (skipping what is complete), then REPORT.md and the figures.

        ``jobs``: training stages at once, each in its own process (1: all in this process). ``skip_train``: the
        recipes' and the zoo's stages are only reported as they are (complete or not run).
        """
        import torch

        from lcmodels.policy.train import versions
        from lcmodels.report import ReportInput, write_report

        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        t0 = time.perf_counter()
        self.check_out()
        graph = self.graph()
        self.out.mkdir(parents=True, exist_ok=True)
        with self.lock():
            if skip_train:  # a report-only rebuild keeps the command that made the results
                self.command = self.store.marker().get("command") or self.command
            self.store.write_marker({"preset": self.preset.to_dict(), "seeds": self.seeds, "command": self.command,
                                     "versions": versions()})  # fmt: skip
            self.invocations.start(self.command, t0)
            try:
                torch.set_num_threads(self.threads)
                runner = Runner(graph, self.store, self.context(), jobs=jobs,
                                look_only=(lambda st: st.group in ("recipes", "zoo")) if skip_train else None)
                with self._executor_session():
                    stages = runner.run()
                self.invocations.save(finished=True)
            finally:
                self.invocations.stop()
            wall = time.perf_counter() - t0
            report = write_report(ReportInput(self.out, self.preset, self.max_seeds, stages, self.invocations.entries,
                                              self.command, self.recipes(), self._seeds(), graph.finals()),
                                  wall_s=wall)  # fmt: skip
        self.emit(f"[report] wrote {report}")
        return ExperimentResult(self.out, self.preset, self.seeds, stages, wall, report)

    @contextlib.contextmanager
    def _executor_session(self) -> Iterator[None]:
        if self.executor != "ray":
            yield
            return
        from lcdata.executors import ray_session

        with ray_session(self.ray_address):
            yield


def run_experiment(preset: Preset | str, out: str | Path, *, seeds: int = 1, command: str = "", threads: int = 1,
                   progress: Progress | None = None, skip_train: bool = False, jobs: int = 1, executor: str = "local",
                   ray_address: str | None = None) -> ExperimentResult:  # fmt: skip
    """Run (or resume) the experiment of ``preset`` in ``out``; see :mod:`lcmodels.experiment`."""
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
        preset = PRESETS[preset]
    exp = Experiment(preset, out, seeds=seeds, command=command, threads=threads, progress=progress,
                     executor=executor, ray_address=ray_address)
    return exp.run(skip_train=skip_train, jobs=jobs)
