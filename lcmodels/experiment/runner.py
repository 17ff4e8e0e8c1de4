"""Run the stages of a graph in dependency order: each stage whose needs are complete is checked against the
store and skipped, or run; a plan is the same walk without running anything.

Where the stages run. With one job everything runs in this process, one stage after another. With ``jobs`` > 1
the training stages (clone, dagger, train, shielded; each an independent run with its own seed) run in ``jobs``
worker processes of one pool, ``threads`` torch threads each, and the evaluations of this process cut their
episodes over the same processes. On Ray each training stage is a Ray task and each evaluation is cut into Ray
tasks. A stage's result does not depend on where it ran. Among ready stages the runner starts the one of smallest
:attr:`~lcmodels.experiment.graph.Stage.priority` first: the data, then the recipes (the policies a safety layer
follows first), then the references and the zoo.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Collection
from concurrent.futures import FIRST_COMPLETED, Future, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from lckit.pool import WorkerPool
from lcmodels.experiment.graph import StageGraph
from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds import Stage
from lcmodels.experiment.stages import StageContext, StageJob
from lcmodels.experiment.store import Attempt, StageStore, Verdict
from lcmodels.presets import Preset, StageResult

log = logging.getLogger("lcmodels.experiment")

COMPLETE = ("skipped", "done")
"""Statuses of a stage whose outputs are there."""
MAX_LINE = 900
"""Characters of a worker's progress line sent back (a pipe write under PIPE_BUF bytes is atomic)."""


def worker_pool(jobs: int, threads: int) -> WorkerPool:
    """``jobs`` spawned processes with ``threads`` torch threads each (a :class:`lckit.pool.WorkerPool`: they die
    with this process and leave Ctrl-C to it): the training stages of a run and the evaluation shards of this
    process run in them."""
    from lcmodels.policy.evaluate import shard_pool

    return shard_pool(jobs, threads)


@dataclass(frozen=True)
class WorkRequest:
    """A training stage's work as a worker process or a Ray task gets it: it rebuilds the job from these."""

    preset: Preset
    out: Path
    threads: int
    stage: Stage
    got: dict[str, StageResult]
    keep: bool


def _no_wall() -> None:
    pass


def _work(req: WorkRequest, emit: Callable[[str], None]) -> float | None:
    ctx = StageContext(req.preset, req.out, req.threads, emit=emit)
    return req.stage.job(ctx, req.got).work(req.keep, _no_wall)


def _work_in_process(req: WorkRequest, lines: Any) -> float | None:
    """:func:`_work` in a process of :func:`worker_pool`, its progress lines sent back through ``lines``."""
    return _work(req, lambda msg: lines.send(msg[:MAX_LINE]))


def _work_on_ray(req: WorkRequest) -> float | None:
    """:func:`_work` as a Ray task (its progress lines go to the task's log, which Ray forwards to the driver)."""
    import torch

    logging.basicConfig(level=logging.INFO, format="%(message)s")  # a fresh worker: its log goes to the driver
    torch.set_num_threads(req.threads)
    return _work(req, log.info)


class _Here:
    """Every stage in this process (the base of the backends that hand training stages elsewhere)."""

    concurrent = False
    error: BaseException | None = None
    """An exception raised while relaying a worker's progress line (by the progress callback)."""

    def room(self, busy: int) -> bool:
        """Whether a training stage can be handed over while ``busy`` ones run."""
        return False

    def pool(self) -> WorkerPool | None:
        """The processes an evaluation of this process cuts its episodes over."""
        return None

    def submit(self, req: WorkRequest) -> Any:
        raise NotImplementedError

    def wait(self, handles: list[Any]) -> list[Any]:
        """The handles among ``handles`` that have finished (at least one)."""
        raise NotImplementedError

    def result(self, handle: Any) -> float | None:
        """The finished work's return value (its exception raised)."""
        raise NotImplementedError

    def close(self, pending: Collection[Any], *, kill: bool = False) -> None:
        pass


class _Pool(_Here):
    """Training stages in the processes of :func:`worker_pool` (started when first needed), their progress lines
    pumped to ``emit`` by a thread of this process."""

    concurrent = True

    def __init__(self, jobs: int, threads: int, emit: Callable[[str], None]) -> None:
        self.jobs, self.threads, self.emit = jobs, threads, emit
        self._pool: WorkerPool | None = None
        self._lines: Any = None
        self._pump: threading.Thread | None = None

    def room(self, busy: int) -> bool:
        return busy < self.jobs

    def pool(self) -> WorkerPool:
        if self._pool is None:
            import multiprocessing as mp

            recv, self._lines = mp.get_context("spawn").Pipe(duplex=False)

            def pump() -> None:
                while (msg := recv.recv()) is not None:
                    if self.error is None:  # after an error, the lines are drained so that no worker blocks
                        try:
                            self.emit(msg)
                        except BaseException as exc:  # raised in the runner's thread
                            self.error = exc
                recv.close()

            self._pump = threading.Thread(target=pump, name="worker-progress", daemon=True)
            self._pump.start()
            self._pool = worker_pool(self.jobs, self.threads)
        return self._pool

    def submit(self, req: WorkRequest) -> Future[float | None]:
        try:
            return self.pool().submit(_work_in_process, req, self._lines)
        except OSError as exc:  # a worker died while another was being started: the pool is broken
            raise BrokenProcessPool(str(exc)) from exc

    def wait(self, handles: list[Any]) -> list[Any]:
        return list(wait(handles, return_when=FIRST_COMPLETED).done)

    def result(self, handle: Any) -> float | None:
        return handle.result()

    def close(self, pending: Collection[Any], *, kill: bool = False) -> None:
        """Stop the processes (``kill``: now, a stage under way too; its pending record resumes it)."""
        if self._pool is not None:
            self._pool.close(kill=kill)
            self._pool = None
        if self._pump is not None:
            self._lines.send(None)
            self._pump.join()
            self._lines.close()
            self._pump = None


class _Ray(_Here):
    """Training stages as Ray tasks of ``threads`` CPUs each (in the open Ray session); evaluations cut into Ray
    tasks by themselves."""

    concurrent = True

    def __init__(self, threads: int) -> None:
        from lcdata.executors import ray_module

        self.ray = ray_module()
        self.remote = self.ray.remote(num_cpus=threads, max_retries=0)(_work_on_ray)

    def room(self, busy: int) -> bool:
        return True

    def submit(self, req: WorkRequest) -> Any:
        return self.remote.remote(req)

    def wait(self, handles: list[Any]) -> list[Any]:
        return list(self.ray.wait(handles, num_returns=1)[0])

    def result(self, handle: Any) -> float | None:
        return self.ray.get(handle)

    def close(self, pending: Collection[Any], *, kill: bool = False) -> None:
        for ref in pending:
            with contextlib.suppress(Exception):  # a task that ended meanwhile
                self.ray.cancel(ref, force=True)


@dataclass
class _Running:
    key: StageKey
    attempt: Attempt
    job: StageJob
    t0: float


class Runner:
    """Runs (or, ``dry_run``, plans) the stages of ``graph`` against ``store``.

    ``look_only``: stages that are reported as they are (complete: ``skipped``; else ``not run``) and never run
    (``--skip-train``). ``jobs``, ``executor``: where the stages run (module docstring).
    """

    def __init__(self, graph: StageGraph, store: StageStore, ctx: StageContext, *, jobs: int = 1,
                 dry_run: bool = False, look_only: Callable[[Stage], bool] | None = None) -> None:  # fmt: skip
        self.graph, self.store, self.dry_run = graph, store, dry_run
        self.look_only = look_only or (lambda st: False)
        if dry_run:
            self.backend: _Here = _Here()
        elif ctx.executor == "ray":
            self.backend = _Ray(ctx.threads)
        elif jobs > 1:
            self.backend = _Pool(jobs, ctx.threads, ctx.emit)
        else:
            self.backend = _Here()
        self.ctx = replace(ctx, pool=self.backend.pool, jobs=jobs)
        self._waiting: dict[StageKey, tuple[StageJob, Verdict]] = {}
        self._here: StageKey | None = None
        """The stage running in this process."""
        self._position = {k: i for i, k in enumerate(graph.keys())}

    def run(self, keys: Collection[StageKey] | None = None,
            given: dict[StageKey, StageResult] | None = None) -> list[StageResult]:  # fmt: skip
        """Every stage of ``keys`` (default: all), in the order they were settled. ``given``: results of stages
        outside ``keys`` that those read (every stage ``keys`` reads must be among them or in ``keys``)."""
        want = set(self.graph.keys() if keys is None else keys)
        results: dict[StageKey, StageResult] = dict(given or {})
        running: dict[Any, _Running] = {}
        try:
            while not want <= results.keys():
                ready = [k for k in self.graph.ready(results, {r.key for r in running.values()}) if k in want]
                for key in ready:
                    res = self._settle(key, results, running)
                    if res is not None:
                        results[key] = res
                        break  # the stages that waited on it may come before the rest
                else:
                    if not running:
                        missing = sorted(k.name for k in want - results.keys())
                        raise ValueError(f"stages {', '.join(missing)} wait for stages not given")
                    for handle in self.backend.wait(list(running)):
                        r = running.pop(handle)
                        results[r.key] = self._finish(r.attempt, r.job, self.backend.result(handle), r.t0)
                if self.backend.error is not None:
                    raise self.backend.error
        except BaseException as exc:
            self.backend.close(list(running), kill=True)
            if isinstance(exc, BrokenProcessPool | ChildProcessError):
                left = [r.key.name for r in running.values()] + ([self._here.name] if self._here else [])
                raise ChildProcessError(f"a worker process died (killed, or out of memory?) with {', '.join(left)} "
                                        "unfinished; what finished is kept and a rerun resumes the rest") from None
            raise
        self.backend.close([])
        if self.backend.error is not None:  # a line relayed after the last stage ended
            raise self.backend.error
        return [res for k, res in results.items() if k in want]

    def _settle(self, key: StageKey, results: dict[StageKey, StageResult],
                running: dict[Any, _Running]) -> StageResult | None:  # fmt: skip
        """Stage ``key``'s result, when it can be had now: complete (skipped), waiting for a stage it reads,
        planned, looked at only, or run here. None when it is handed to the backend (``running``) or waits for
        room there."""
        t0 = time.perf_counter()
        stage = self.graph[key]
        path = key.path(self.store.out)
        got = {role: results[k] for role, k in stage.needs}
        waits = [k for _, k in stage.needs if results[k].status not in COMPLETE]
        if waits:  # a stage it reads would run or is not run: its inputs are not known
            blocked = results[max(waits, key=self._position.__getitem__)]  # the last of them to come
            status = f"would run (after {blocked.name})" if blocked.status.startswith("would run") else "not run"
            return self._say(StageResult(key.name, status, path, 0.0), status)
        if key in self._waiting:  # checked before, and waiting for room since
            job, verdict = self._waiting.pop(key)
        else:
            job = stage.job(self.ctx, got)
            verdict = self.store.check(key, job.config, job.inputs, upgrade=job.upgrade, resumable=job.resumable)
        if verdict.complete:
            return self._say(self.store.skipped(key, verdict, t0), "complete, skipped")
        if self.dry_run:
            status = f"would run ({verdict.why})"
            return self._say(StageResult(key.name, status, path, 0.0, time.perf_counter() - t0), status)
        if self.look_only(stage):
            return self._say(StageResult(key.name, "not run", path, 0.0), "not run")
        if stage.trains and self.backend.concurrent:
            if not self.backend.room(len(running)):
                self._waiting[key] = (job, verdict)
                return None
            attempt = self.store.begin(key, verdict, job.config, job.inputs)
            req = WorkRequest(self.ctx.preset, self.ctx.out, self.ctx.threads, stage, got, attempt.keep)
            running[self.backend.submit(req)] = _Running(key, attempt, job, t0)
            self.ctx.emit(f"[{key}] running ({verdict.why})")  # once a process has it
            return None
        attempt = self.store.begin(key, verdict, job.config, job.inputs)
        self.ctx.emit(f"[{key}] running ({verdict.why})")
        self._here = key
        wall = job.work(attempt.keep, attempt.save_wall)
        self._here = None
        return self._finish(attempt, job, wall, t0)

    def _finish(self, attempt: Attempt, job: StageJob, wall: float | None, t0: float) -> StageResult:
        res = self.store.finish(attempt, job.outputs(), wall, t0)
        self.ctx.emit(f"[{attempt.key}] done in {res.wall_s:.1f} s")
        return res

    def _say(self, res: StageResult, what: str) -> StageResult:
        self.ctx.emit(f"[{res.name}] {what}")
        return res
