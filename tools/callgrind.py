"""Instruction counts of a Python run under valgrind's callgrind, for the ``*_instructions`` benchmarks
(imported by them: they run as scripts from this folder)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys


def require_valgrind() -> None:
    """Exit with a one-line message when valgrind is not installed."""
    if shutil.which("valgrind") is None:
        raise SystemExit("valgrind not found (apt-get install valgrind)")


def instructions(code: str, *args: str) -> int:
    """Instructions executed by ``python -c code *args`` (every thread of that process, not its children).

    String hashing is seeded the same in every run (``PYTHONHASHSEED=0``), and the BLAS and OpenMP
    libraries numpy (and torch) load get one thread: their idle worker threads spin for a while, which
    callgrind counts too, so that with the default pools the same work varied by +-3% from run to run
    (and by 0.002% with one thread).
    """
    cmd = ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, "-c", code, *args]
    one = {name: "1" for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env = {**os.environ, "PYTHONHASHSEED": "0", **one}
    run = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    found = re.search(r"Collected\s*:\s*([\d,]+)", run.stderr)
    if run.returncode != 0 or found is None:
        raise SystemExit(f"valgrind failed (exit {run.returncode}): {run.stderr.strip().splitlines()[-1:]}")
    return int(found.group(1).replace(",", ""))
