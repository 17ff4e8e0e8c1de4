"""The process pool of every command that fans out (``lckit.pool``): its workers die with their parent, ignore
Ctrl-C and run one thread each; results come in job order, a failure or a dead worker ends the run at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lckit.pool import THREAD_VARIABLES, WorkerDied, WorkerPool, report

ROOT = Path(__file__).resolve().parent.parent
WAIT_S = 60.0
"""The bound on how long a worker may outlive its killed parent (it is gone within a fraction of a second; the
bound is loose for a loaded machine)."""


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not reaped yet, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    except OSError:  # no /proc: ask the kernel
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True
    return stat.rpartition(")")[2].split()[0] not in ("Z", "X")


def _wait_gone(pids: list[int]) -> list[int]:
    deadline = time.monotonic() + WAIT_S
    while (alive := [p for p in pids if _alive(p)]) and time.monotonic() < deadline:
        time.sleep(0.05)
    return alive


def _square(x: int) -> int:
    time.sleep(0.02 * (5 - x) if 0 <= x < 5 else 0)  # the first jobs end last
    return x * x


def _fail_on(x: int) -> int:
    if x == 2:
        raise ValueError("job 2 fails")
    return x


def _die(x: int) -> int:
    if x == 0:
        os._exit(3)
    time.sleep(0.5)
    return x


def _threads(_: int) -> tuple[dict[str, str | None], int]:
    import torch

    return {name: os.environ.get(name) for name in THREAD_VARIABLES}, torch.get_num_threads()


def _talk(x: int) -> int:
    report(f"job {x} here")
    return x


PARENT = """
import sys, time
from lckit.pool import WorkerPool
pool = WorkerPool(2)
futures = [pool.submit(time.sleep, 600) for _ in range(2)]
print(*pool.pids, flush=True)
time.sleep(600)
"""


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX signals")
def test_the_workers_die_when_their_parent_is_killed() -> None:
    parent = subprocess.Popen([sys.executable, "-c", PARENT], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        line = parent.stdout.readline() if parent.stdout else ""
        pids = [int(p) for p in line.split()]
        assert len(pids) == 2, line
        assert all(_alive(p) for p in pids)
        parent.kill()  # SIGKILL: no clean-up runs in the parent
        parent.wait(timeout=30)
        assert _wait_gone(pids) == []
    finally:
        parent.kill()
        for pid in pids if "pids" in locals() else []:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(not hasattr(signal, "SIGINT"), reason="needs POSIX signals")
def test_the_workers_ignore_ctrl_c() -> None:
    with WorkerPool(1) as pool:
        pid = pool.submit(os.getpid).result()
        if Path(f"/proc/{pid}/status").exists():  # the kernel's word: SIGINT (2) is in the ignored set
            ignored = next(line for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                           if line.startswith("SigIgn:"))
            assert int(ignored.split()[1], 16) & (1 << (signal.SIGINT - 1))
        for _ in range(3):
            os.kill(pid, signal.SIGINT)
            assert pool.submit(os.getpid).result() == pid  # the same worker goes on, no KeyboardInterrupt
    assert not _alive(pid)  # and it ends with the pool


def test_results_come_in_job_order_with_progress() -> None:
    seen: list[tuple[int, int]] = []
    with WorkerPool(2) as pool:
        assert list(pool.map(_square, range(6), progress=lambda k, n: seen.append((k, n)))) == [0, 1, 4, 9, 16, 25]
        assert sorted(pool.map(_square, range(6), ordered=False)) == [0, 1, 4, 9, 16, 25]
        assert list(pool.map(divmod, [(7, 2), (9, 4)], star=True)) == [(3, 1), (2, 1)]
    assert seen == [(k, 6) for k in range(1, 7)]


def test_the_first_failure_ends_the_run_and_a_dead_worker_names_the_jobs_left() -> None:
    with WorkerPool(2) as pool, pytest.raises(ValueError, match="job 2 fails"):
        list(pool.map(_fail_on, range(4)))
    with WorkerPool(1) as pool, pytest.raises(WorkerDied) as died:
        list(pool.map(_die, range(3)))
    assert isinstance(died.value, ChildProcessError) and died.value.unfinished == [0, 1, 2]
    assert "3 of 3 jobs unfinished" in str(died.value) and "\n" not in str(died.value)


def test_each_worker_runs_the_threads_it_is_given_and_reports_lines() -> None:
    before = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    with WorkerPool(1, threads=1) as pool:
        env, torch_threads = pool.submit(_threads, 0).result()
    assert env == dict.fromkeys(THREAD_VARIABLES, "1") and torch_threads == 1
    assert {name: os.environ.get(name) for name in THREAD_VARIABLES} == before  # the parent's are as they were
    lines: list[str] = []
    with WorkerPool(2, messages=lines.append) as pool:
        assert list(pool.map(_talk, range(3))) == [0, 1, 2]
    assert sorted(lines) == ["job 0 here", "job 1 here", "job 2 here"]
    with pytest.raises(ValueError, match="workers"):
        WorkerPool(0)


def test_jobs_submitted_while_a_worker_is_killed_end_as_a_dead_worker() -> None:
    """A worker killed while the pool starts another (the out-of-memory killer during a run) breaks the pool:
    the caller sees a dead worker (``BrokenProcessPool`` from ``submit``, :class:`WorkerDied` from ``map``),
    never the spawn's own error on the dead worker's pipes."""
    from concurrent.futures.process import BrokenProcessPool

    for _ in range(6):  # the race is not forced: several tries
        with WorkerPool(2) as pool:
            first = pool.submit(_square, 3)
            assert first.result() == 9
            os.kill(pool.pids[0], signal.SIGKILL)
            with pytest.raises((BrokenProcessPool, WorkerDied)):
                futures = [pool.submit(_square, k) for k in range(8)]
                list(pool._results(futures, True, None))
