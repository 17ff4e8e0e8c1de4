"""How many threads step a batch of environments, and the shards they step.

The compiled calls that do a batch's heavy work (the simulation steps, the observation, the image) release
Python's lock and compute each environment from its own state only, so a batch cut into contiguous shards of
environments, computed by several threads at once, gives the same bytes as the whole batch in one call.
:func:`run_shards` does the cutting: the calling thread and a small pool of threads take the shards as they come.

The number of threads:

- a ``threads`` argument of :class:`~lcsim.sim.HighwaySim`, :class:`~lcsim.core.LaneChangeCore` and the batched
  environments: exactly that many (1: one thread, the serial path);
- else the process's setting, :func:`set_threads`, else the ``LC_THREADS`` environment variable, else
  ``OMP_NUM_THREADS`` (Ray sets it for its workers), else 1 in a worker process of :mod:`multiprocessing` (a
  pool of worker processes already fills the cores), else every core this process may run on; taken only for
  batches of at least :data:`MIN_ENVS_PER_THREAD` environments per thread, so a small batch stays on one thread.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

ENV_VAR = "LC_THREADS"
"""The environment variable that sets the process's default thread count (``LC_THREADS=1``: serial)."""
MIN_ENVS_PER_THREAD = 8
"""Under the default thread count, each thread gets at least this many environments of a batch."""
CHUNKS_PER_THREAD = 2
""":func:`run_shards` hands out a share ``1 / (CHUNKS_PER_THREAD x threads)`` of what is left of a batch at a time,
rounded up to a multiple of :data:`CHUNK_ALIGN` environments."""
MAX_CHUNK = 16
"""... and at most this many: a thread that a busy machine leaves waiting holds up the others by one chunk at most,
so a chunk is kept short (16 environments: about a millisecond of a decision's simulation)."""
CHUNK_ALIGN = 8
"""Chunks start at multiples of this many environments: 64 bytes of a per-environment float64 or int64 row (the
step, the clock, the sensors), so two threads rarely write into one cache line (which would cost both)."""

_setting: int | None = None
_from_environment: tuple[int, int] | None = None  # (pid, threads): what the environment said in this process
_pool: ThreadPoolExecutor | None = None
_pool_pid = -1
_pool_workers = 0
_pool_lock = threading.Lock()


def _positive(value: object, what: str) -> int:
    try:
        n = int(str(value).strip())
    except ValueError:
        raise ValueError(f"{what} must be a whole number >= 1, got {value!r}") from None
    if n < 1:
        raise ValueError(f"{what} must be a whole number >= 1, got {value!r}")
    return n


def set_threads(threads: int | None) -> None:
    """Set this process's default thread count for batches (None: back to the environment's default, read anew)."""
    global _setting, _from_environment
    _setting = None if threads is None else _positive(threads, "threads")
    _from_environment = None


def default_threads() -> int:
    """This process's default thread count (see the module's docstring; the environment is read once)."""
    global _from_environment
    if _setting is not None:
        return _setting
    if _from_environment is None or _from_environment[0] != os.getpid():
        _from_environment = (os.getpid(), _threads_from_environment())
    return _from_environment[1]


def _threads_from_environment() -> int:
    for name in (ENV_VAR, "OMP_NUM_THREADS"):
        value = os.environ.get(name, "").strip()
        if value:
            return _positive(value, name)
    if multiprocessing.parent_process() is not None:
        return 1
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # (no affinity on this platform)
        return max(1, os.cpu_count() or 1)


def check_threads(threads: int | None) -> int | None:
    """``threads`` as given to a simulator: None (the default) or a whole number >= 1; ``ValueError`` otherwise."""
    return None if threads is None else _positive(threads, "threads")


def shard_count(num_envs: int, threads: int | None) -> int:
    """How many shards a batch of ``num_envs`` environments is cut into: ``threads`` (at most one environment
    each) when given, else the default thread count, at least :data:`MIN_ENVS_PER_THREAD` environments each."""
    if threads is not None:
        return max(1, min(threads, num_envs))
    return max(1, min(default_threads(), num_envs // MIN_ENVS_PER_THREAD))


def _executor(workers: int) -> ThreadPoolExecutor:
    """The pool of this process, with at least ``workers`` threads (a forked child makes its own)."""
    global _pool, _pool_pid, _pool_workers
    with _pool_lock:
        pid = os.getpid()
        if _pool is None or _pool_pid != pid or _pool_workers < workers:
            old = _pool if _pool_pid == pid else None
            _pool = ThreadPoolExecutor(workers, thread_name_prefix="lcsim-shard")
            _pool_pid, _pool_workers = pid, workers
            if old is not None:
                old.shutdown(wait=False)
        return _pool


class _Chunks:
    """A range handed out in contiguous chunks to whichever thread asks first: each chunk a share of what is left
    (``1 / (CHUNKS_PER_THREAD x threads)``, at most :data:`MAX_CHUNK`, rounded up to a multiple of
    :data:`CHUNK_ALIGN`), so the chunks shrink towards the end and the threads finish close together."""

    def __init__(self, fn: Callable[[int, int], None], num: int, threads: int) -> None:
        self.fn, self.num, self.parts = fn, num, CHUNKS_PER_THREAD * threads
        self.cond = threading.Condition(threading.Lock())
        self.next = 0  # the first index not handed out
        self.claimed = self.finished = 0
        self.error: BaseException | None = None

    def work(self) -> None:
        """Compute chunks until none is left (or one failed)."""
        while True:
            with self.cond:
                start = self.next
                if start >= self.num or self.error is not None:
                    return
                size = min(MAX_CHUNK, -(-(self.num - start) // self.parts))
                stop = min(self.num, start + -(-size // CHUNK_ALIGN) * CHUNK_ALIGN)
                self.next = stop
                self.claimed += 1
            try:
                self.fn(start, stop)
            except BaseException as exc:  # (re-raised by the caller's thread)
                with self.cond:
                    self.error = self.error or exc
            finally:
                with self.cond:
                    self.finished += 1
                    if self.finished == self.claimed:
                        self.cond.notify_all()

    def wait(self) -> None:
        """Until every chunk taken is computed (a thread that starts later finds none left and takes none)."""
        with self.cond:
            while self.finished < self.claimed:
                self.cond.wait()


def run_shards(fn: Callable[[int, int], None], num: int, shards: int) -> None:
    """Call ``fn(start, stop)`` on contiguous chunks that cover ``range(num)`` once, on ``shards`` threads at the
    same time: this thread and ``shards - 1`` of the pool; returns when every chunk is done, and raises the first
    exception of any. With one shard, or no more than :data:`CHUNK_ALIGN` items, just ``fn(0, num)``.

    The range is handed out in chunks as the threads ask for them (:class:`_Chunks`), so a thread that the system
    leaves waiting (a busy machine) slows the call by at most its chunk in progress: the calling thread computes
    whatever is left, and never waits for a thread that has not started.
    """
    shards = min(shards, -(-num // CHUNK_ALIGN))  # (no more threads than chunks)
    if shards <= 1:
        fn(0, num)
        return
    chunks = _Chunks(fn, num, shards)
    pool = _executor(shards - 1)
    for _ in range(shards - 1):
        pool.submit(chunks.work)
    chunks.work()
    chunks.wait()
    if chunks.error is not None:
        raise chunks.error
