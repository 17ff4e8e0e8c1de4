"""Torch threads under a co-tenant: PPO steps per second with 1 and 2 torch threads, quiet and beside a busy process.

A co-tenant (another training, an evaluation, a browser) takes a core; torch's intra-op threads then wait on
one another at every operation. This measures ``lc-train-policy`` (PPO, 8,192 steps by default) with each
thread count, first alone, then beside a process that keeps one core busy with numpy, and prints steps/s.

    python tools/bench_threads.py                  # pure observation, 8192 steps
    python tools/bench_threads.py --obs hybrid --timesteps 2048
    python tools/bench_threads.py --json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _busy(stop: mp.Event) -> None:  # type: ignore[valid-type]
    import numpy as np

    a = np.random.default_rng(0).standard_normal((400, 400))
    while not stop.is_set():  # type: ignore[attr-defined]
        a = np.tanh(a @ a.T * 1e-3)


def _train(obs: str, timesteps: int, threads: int) -> float:
    """Steps per second of one ``lc-train-policy`` run (wall time of the whole command)."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [str(Path(sys.executable).with_name("lc-train-policy")), "--obs", obs, "--timesteps", str(timesteps),
               "--threads", str(threads), "--out", str(Path(tmp) / "run"), "-q", "--set", "eval_episodes=0"]
        if obs in ("prediction", "hybrid"):
            raise ValueError(f"--obs {obs} needs a predictor; measure pure or image")
        start = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        return timesteps / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--obs", default="pure", choices=("pure", "image"), help="observation mode (default pure)")
    p.add_argument("--timesteps", type=int, default=8192, help="PPO steps per run (default 8192)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    if args.timesteps < 512:
        print("bench_threads: --timesteps must be >= 512", file=sys.stderr)
        return 2
    results: dict[str, float] = {}
    for tenant in ("quiet", "co-tenant"):
        stop = mp.Event()
        proc = mp.Process(target=_busy, args=(stop,), daemon=True) if tenant == "co-tenant" else None
        if proc is not None:
            proc.start()
        try:
            for threads in (1, 2):
                print(f"bench_threads: {tenant}, {threads} thread(s) ...", file=sys.stderr)
                results[f"{tenant}_threads{threads}_steps_per_s"] = _train(args.obs, args.timesteps, threads)
        finally:
            if proc is not None:
                stop.set()
                proc.join()
    if args.json:
        print(json.dumps({"obs": args.obs, "timesteps": args.timesteps, **results}, indent=2))
        return 0
    print(f"PPO {args.obs}, {args.timesteps} steps (whole command, steps/s)")
    print("| torch threads | quiet | beside a busy process |")
    print("|---|---|---|")
    for threads in (1, 2):
        print(f"| {threads} | {results[f'quiet_threads{threads}_steps_per_s']:.0f} | "
              f"{results[f'co-tenant_threads{threads}_steps_per_s']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
