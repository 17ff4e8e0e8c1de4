"""Stopping process pools: :class:`lckit.pool.WorkerPool` (every pool of the project) and a plain
``concurrent.futures`` process pool alike.

New code uses :class:`lckit.pool.WorkerPool` itself (a context manager that kills its workers when its block
ends in an exception); :func:`die_with_parent` is :func:`lckit.pool.die_with_parent`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from lckit.pool import WorkerPool, die_with_parent

__all__ = ["closing_pool", "die_with_parent", "stop_pool"]


def stop_pool(pool: Any, *, kill: bool = False) -> None:
    """Shut a pool down, its queued work cancelled; ``kill``: its processes terminated first, so that work under
    way stops now (an error or an interrupt: a rerun resumes it)."""
    if isinstance(pool, WorkerPool) or callable(getattr(pool, "close", None)):
        pool.close(kill=kill)
        return
    if kill:
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()
    pool.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def closing_pool(pool: Any) -> Iterator[Any]:
    """``pool`` for a ``with`` block: stopped at its end, killed (:func:`stop_pool`) when it ends in an exception."""
    try:
        yield pool
    except BaseException:
        stop_pool(pool, kill=True)
        raise
    stop_pool(pool)
