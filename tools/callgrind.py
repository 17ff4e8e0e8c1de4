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

    String hashing is seeded the same in every run (``PYTHONHASHSEED=0``): with random seeds the counts
    of the same work differ by a few percent from run to run.
    """
    cmd = ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, "-c", code, *args]
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    run = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    found = re.search(r"Collected\s*:\s*([\d,]+)", run.stderr)
    if run.returncode != 0 or found is None:
        raise SystemExit(f"valgrind failed (exit {run.returncode}): {run.stderr.strip().splitlines()[-1:]}")
    return int(found.group(1).replace(",", ""))
