"""Worker processes that die with the process that started them.

A pool worker whose parent is killed (even with SIGKILL, which runs no clean-up) would otherwise go on
with the tasks it holds, writing files nobody asked for any more, and keep the parent's inherited pipes
open, so that ``lc-record ... | cat`` never returns. :func:`die_with_parent`, a pool initializer, asks
the kernel to kill the worker when its parent goes (Linux ``prctl(PR_SET_PDEATHSIG)``) and, on every
system, watches the parent's pid from a daemon thread as well.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

_PR_SET_PDEATHSIG = 1
WATCH_INTERVAL_S = 0.2
"""How often the watchdog thread looks at the parent's pid."""


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


def stop_pool(pool: Any, *, kill: bool = False) -> None:
    """Shut a ``concurrent.futures`` process pool down, its queued work cancelled; ``kill``: its processes
    terminated first, so that work under way stops now (an error or an interrupt: a rerun resumes it)."""
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
