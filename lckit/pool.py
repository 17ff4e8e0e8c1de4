"""One process pool for every command that fans out: :class:`WorkerPool`.

    from lckit.pool import WorkerPool

    with WorkerPool(4, threads=1) as pool:                      # 4 spawned processes, 1 thread each
        for result in pool.map(work, jobs, progress=show):      # work(job) in the workers, in job order
            ...
        for result in pool.map(work, arg_tuples, star=True, ordered=False):  # work(*args), as each ends
            ...
        future = pool.submit(work, job)                         # a concurrent.futures.Future

What every worker gets, whoever made the pool:

- it dies with the process that made the pool, even one killed with SIGKILL (which runs no clean-up):
  Linux's ``prctl(PR_SET_PDEATHSIG)`` and, on every system, a thread that watches the parent's pid
  (:func:`die_with_parent`). A killed run leaves no orphan writing files nobody asked for any more, nor
  holding the parent's pipes open (``lc-record ... | cat`` returns);
- it ignores Ctrl-C (SIGINT): the terminal sends it to the whole process group, and the parent, which
  handles it, stops the pool (leaving the ``with`` block on the ``KeyboardInterrupt`` kills the workers);
- it runs ``threads`` threads in torch, numba and BLAS: ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``,
  ``MKL_NUM_THREADS`` and ``NUMBA_NUM_THREADS`` are in its environment from its start, and torch or numba
  imported before the initializer runs are set too. More threads per worker than cores in all collapse;
- it is started with ``start_method`` (``spawn`` by default: no fork of a process that may hold threads,
  torch's or a writer's); ``initializer(*initargs)`` then runs in it, as in ``concurrent.futures``;
- :func:`report` in a job sends a line to the pool's ``messages`` callable, which runs in the parent (a
  thread of the pool): progress from deep inside a job.

Results: :meth:`WorkerPool.map` yields them in job order (``ordered=False``: as each job ends) and calls
``progress(done, total)`` as each job ends. The first job that raises ends the iteration with its exception
at once, whatever the order, and the jobs not started are cancelled. A worker that dies (killed, out of
memory) is :class:`WorkerDied`, a ``ChildProcessError`` (an ``OSError``: the commands end on it in one line)
naming the jobs left unfinished. Leaving the ``with`` block normally waits for the workers to end; on an
exception it terminates them first, so that work under way stops now.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Any

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1
WATCH_INTERVAL_S = 0.2
"""How often a worker's watchdog thread looks at its parent's pid."""
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
"""The environment variables that set torch's, BLAS's and numba's threads in a worker."""

_ENVIRON_LOCK = threading.Lock()
_WORKER: dict[str, Any] = {}


def die_with_parent(parent_pid: int | None = None) -> None:
    """Kill this process when its parent exits. ``parent_pid``: the pid the parent had when it started
    this process (default: the current parent); if it is gone already, exit at once."""
    expected = os.getppid() if parent_pid is None else parent_pid
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # no prctl: the watchdog below still works
            pass
    if os.getppid() != expected:  # the parent died before the signal was armed
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(WATCH_INTERVAL_S)
            if os.getppid() != expected:
                os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def limit_threads(threads: int) -> None:
    """``threads`` threads for torch, numba and BLAS in this process from now on: the environment variables
    (:data:`THREAD_VARIABLES`) for libraries not loaded yet, and torch and numba if they are loaded."""
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    torch = sys.modules.get("torch")
    if torch is not None and hasattr(torch, "set_num_threads"):
        torch.set_num_threads(threads)
    numba = sys.modules.get("numba")  # (its count is fixed at import; lowering it starts its thread pool)
    if numba is not None and getattr(getattr(numba, "config", None), "NUMBA_NUM_THREADS", 0) > threads:
        numba.set_num_threads(threads)


def report(text: str) -> None:
    """Send a line to the ``messages`` callable of the pool this job runs in; outside such a pool (a job run
    in the parent, a pool without ``messages``), log it at INFO instead."""
    queue = _WORKER.get("queue")
    if queue is None:
        log.info("%s", text)
    else:
        queue.put(text)


def in_worker() -> bool:
    """Whether this process is a worker of a :class:`WorkerPool`."""
    return "parent" in _WORKER


def _start_worker(parent: int, threads: int, queue: Any, initializer: Callable[..., Any] | None,
                  initargs: tuple[Any, ...]) -> None:  # fmt: skip
    die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_threads(threads)
    _WORKER.update(parent=parent, queue=queue)
    if initializer is not None:
        initializer(*initargs)


@contextlib.contextmanager
def _thread_environment(threads: int) -> Iterator[None]:
    """The thread variables set to ``threads`` while a worker is started (it inherits this environment)."""
    with _ENVIRON_LOCK:
        saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
        os.environ.update({name: str(threads) for name in THREAD_VARIABLES})
        try:
            yield
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


class WorkerDied(ChildProcessError):
    """A worker process of a :class:`WorkerPool` died (killed, out of memory) before its jobs were done.
    ``unfinished``: the indices (in the order given to :meth:`WorkerPool.map`) of the jobs not finished."""

    def __init__(self, unfinished: list[int], total: int) -> None:
        super().__init__(f"a worker process died (killed, or out of memory?) with {len(unfinished)} of {total} "
                         "jobs unfinished")
        self.unfinished = unfinished


def _finished(future: Future[Any]) -> bool:
    return future.done() and not future.cancelled() and future.exception() is None


class WorkerPool:
    """``workers`` processes for jobs; see the module docstring for what each worker gets.

    Args:
        workers: processes at most (started as jobs come, kept until :meth:`close`).
        threads: torch, numba and BLAS threads in each.
        start_method: ``spawn`` (default), ``forkserver`` or ``fork``.
        initializer, initargs: called in each worker once it is set up, as ``initializer(*initargs)``.
        messages: called in the parent with each line a job sends with :func:`report`.
    """

    def __init__(self, workers: int, *, threads: int = 1, start_method: str = "spawn",
                 initializer: Callable[..., Any] | None = None, initargs: tuple[Any, ...] = (),
                 messages: Callable[[str], Any] | None = None) -> None:  # fmt: skip
        if workers < 1 or threads < 1:
            raise ValueError(f"workers and threads must be >= 1, got {workers} and {threads}")
        self.workers, self.threads = workers, threads
        context = multiprocessing.get_context(start_method)
        self._queue = context.Queue() if messages is not None else None
        self._pump: threading.Thread | None = None
        if messages is not None:
            self._pump = threading.Thread(target=self._forward, args=(messages,), name="pool-messages", daemon=True)
            self._pump.start()
        self._executor = ProcessPoolExecutor(workers, mp_context=context, initializer=_start_worker,
                                             initargs=(os.getpid(), threads, self._queue, initializer, initargs))
        self._closed = False

    def _forward(self, messages: Callable[[str], Any]) -> None:
        assert self._queue is not None
        while (text := self._queue.get()) is not None:
            try:
                messages(text)
            except Exception:  # a broken callback must not stop the lines after it
                log.exception("the pool's messages callback failed")

    @property
    def pids(self) -> list[int]:
        """The process ids of the workers started so far (and not ended)."""
        return sorted(getattr(self._executor, "_processes", None) or {})

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        """``fn(*args, **kwargs)`` in a worker (``fn`` a module-level function: it is pickled by name)."""
        with _thread_environment(self.threads):  # a worker it starts inherits its thread count
            try:
                return self._executor.submit(fn, *args, **kwargs)
            except (OSError, ValueError) as exc:
                # A worker started while another is being killed can fail on the dead one's pipes (OSError, or
                # ValueError "bad value(s) in fds_to_keep" from the spawn): that is the pool breaking, not a bug.
                if self._a_worker_died():
                    raise BrokenProcessPool(f"a worker process died while another was started ({exc})") from exc
                raise

    def _a_worker_died(self, processes: dict[int, Any] | None = None) -> bool:
        if getattr(self._executor, "_broken", False):
            return True
        if processes is None:
            processes = getattr(self._executor, "_processes", None) or {}
        return any(p.exitcode not in (None, 0) for p in list(processes.values()))

    def map(self, fn: Callable[..., Any], jobs: Iterable[Any], *, star: bool = False, ordered: bool = True,
            progress: Callable[[int, int], Any] | None = None) -> Iterator[Any]:  # fmt: skip
        """``fn(job)`` (``star``: ``fn(*job)``) for every job, in the workers; results in job order (``ordered``)
        or as each ends. All jobs are submitted now; ``progress(done, total)`` is called as each ends. The first
        exception of a job is raised at once; :class:`WorkerDied` when a worker dies. Closing the iterator early
        cancels the jobs not started."""
        futures = [self.submit(fn, *job) if star else self.submit(fn, job) for job in jobs]
        return self._results(futures, ordered, progress)

    @staticmethod
    def _results(futures: list[Future[Any]], ordered: bool,
                 progress: Callable[[int, int], Any] | None) -> Iterator[Any]:  # fmt: skip
        index = {f: i for i, f in enumerate(futures)}
        waiting: dict[int, Any] = {}
        next_index = done = 0
        try:
            for future in as_completed(futures):
                try:
                    result = future.result()
                except BrokenProcessPool:
                    left = [i for i, f in enumerate(futures) if not _finished(f)]
                    raise WorkerDied(left, len(futures)) from None
                done += 1
                if progress is not None:
                    progress(done, len(futures))
                if not ordered:
                    yield result
                    continue
                waiting[index[future]] = result
                while next_index in waiting:
                    yield waiting.pop(next_index)
                    next_index += 1
        finally:
            for future in futures:
                future.cancel()

    def close(self, *, kill: bool = False) -> None:
        """Stop the pool: jobs not started are cancelled, then the workers end (``kill``: terminated first, so
        that work under way stops now). Lines sent with :func:`report` before are delivered first."""
        if self._closed:
            return
        self._closed = True
        # The executor's own threads and processes, kept before shutdown drops its references to them: a worker
        # started by a submit racing a dead worker's cleanup is added to this dict, and the cleanup would wait
        # for it forever; it is terminated here instead.
        manager = getattr(self._executor, "_executor_manager_thread", None)
        processes = getattr(self._executor, "_processes", None) or {}
        if kill:
            for proc in list(processes.values()):
                proc.terminate()
        self._executor.shutdown(wait=False, cancel_futures=True)
        while manager is not None and manager.is_alive():
            manager.join(0.2)
            if kill or self._a_worker_died(processes):
                for proc in list(processes.values()):
                    if proc.exitcode is None:
                        proc.terminate()
        if self._queue is not None and self._pump is not None:
            self._queue.put(None)
            self._pump.join()
            self._queue.close()

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        self.close(kill=kind is not None)
