"""``kill -9`` of a long command leaves no process behind, keeps what was finished, and the same command
resumes it: ``lc-record --workers 2`` and ``lc-train-policy``."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lccli.record import scenario_config
from lcdata import read_episode
from lcdata.record import record_episode

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
RECORD = ["--vehicles", "20", "--steps", "300", "--episodes", "10", "--workers", "2"]


def _command(module_main: str, argv: list[str]) -> list[str]:
    module, main = module_main.split(":")
    return [sys.executable, "-c", f"from {module} import {main}; raise SystemExit({main}())", *argv]


def _children(pid: int) -> set[int]:
    """Every descendant of ``pid`` (Linux /proc)."""
    found: set[int] = set()
    todo = [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = {int(k) for k in (task / "children").read_text().split()}
            except OSError:
                continue
            todo += list(kids - found)
            found |= kids
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def _wait_for(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_kill_9_of_lc_record_with_workers_leaves_no_process_and_resumes(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    argv = ["--out", str(out), *RECORD]
    proc = subprocess.Popen(_command("lccli.record:record_main", argv), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    _wait_for(lambda: len(list(out.glob("*.mcap"))) >= 2, 120, "two finished episodes")
    workers = _children(proc.pid)
    assert len(workers) >= 2  # the pool's processes
    os.kill(proc.pid, signal.SIGKILL)
    # Every worker dies with it, and so the caller's pipes close: `lc-record ... | cat` returns.
    proc.communicate(timeout=30)
    _wait_for(lambda: not any(_alive(w) for w in workers), 10, "the workers to die")
    finished = {p: _sha(p) for p in out.glob("*.mcap")}
    time.sleep(1.0)
    assert {p: _sha(p) for p in out.glob("*.mcap")} == finished  # nobody writes after the kill
    for p in finished:
        assert len(read_episode(p).tracks) > 0  # the finished episodes are intact
    # The same command records the missing episodes and leaves the finished ones as they are.
    done = subprocess.run(_command("lccli.record:record_main", argv), cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert "resuming" in done.stderr and f"{len(finished)} of 10 episodes are there already" in done.stderr
    files = sorted(out.glob("*.mcap"))
    assert len(files) == 10 and not list(out.glob("*.partial"))
    assert all(_sha(p) == sha for p, sha in finished.items())
    # ... and each is the file one uninterrupted recording of its seed gives, byte for byte.
    config = scenario_config("paper", vehicles=20, steps=300)
    ref = record_episode(config, 9, "rule", tmp_path / "ref" / files[-1].name, scenario="paper",
                         writer="inline")
    assert _sha(ref.path) == _sha(files[-1])


def test_kill_9_of_lc_train_policy_resumes_the_step_count(tmp_path: Path) -> None:
    out = tmp_path / "run"
    base = ["--obs", "pure", "--scenario", "tiny", "--set", "n_envs=2", "--set", "checkpoint_every=128",
            "--set", "eval_episodes=0", "--threads", "1", "--out", str(out), "-q"]
    proc = subprocess.Popen(_command("lccli.policy:train_policy_main", [*base, "--timesteps", "1000000"]), cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    state_file = out / "checkpoints" / "latest.json"

    def two_checkpoints() -> bool:
        try:
            return json.loads(state_file.read_text())["timesteps"] >= 512
        except (OSError, ValueError, KeyError):
            return False

    _wait_for(two_checkpoints, 240, "two checkpoints")
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=30)
    state = json.loads(state_file.read_text())
    at = int(state["timesteps"])
    assert (out / "checkpoints" / state["weights"]).is_file() and (out / "checkpoints" / state["optimizer"]).is_file()
    target = at + 256
    done = subprocess.run(_command("lccli.policy:train_policy_main", [*base, "--timesteps", str(target)]), cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["train"]["resumed_from"] == at and metrics["train"]["timesteps"] >= target
    steps = [int(float(r.split(",")[0])) for r in (out / "progress.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and steps[-1] == metrics["train"]["timesteps"]
    # only the last checkpoint's files are kept
    assert sorted(p.name for p in (out / "checkpoints").glob("step-*")) == sorted(
        [f"step-{metrics['train']['timesteps']}.safetensors", f"step-{metrics['train']['timesteps']}.card.json",
         f"step-{metrics['train']['timesteps']}.optim.pt"])
