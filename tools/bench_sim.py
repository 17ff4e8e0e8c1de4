#!/usr/bin/env python
"""Simulator throughput: simulated seconds per wall-clock second.

Measures the paper scenario (100 vehicles, 20 Hz, a decision and a rendered 3x120x120 bird's-eye image
every 0.5 s) through the gymnasium API, for one environment (``LaneChangeEnv``) and for a batch of 64
(``LaneChangeVectorEnv``), with autoreset. Actions: keep lane, with a valid lane change 15% of the time.
When highway-env is installed, measures its ``highway-v0`` with 100 vehicles on the same machine.

    python tools/bench_sim.py            # human-readable
    python tools/bench_sim.py --json     # one JSON object
    python tools/bench_sim.py --repeat 5 # median of 5 measurements each (for a busy machine)
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from lcsim.config import ScenarioConfig
from lcsim.envs import LaneChangeEnv, LaneChangeVectorEnv


def _actions(rng: np.random.Generator, mask: np.ndarray) -> np.ndarray:
    mask = mask.reshape(-1, 3)
    change = rng.random(len(mask)) < 0.15
    pick = (rng.random(mask.shape) * mask).argmax(axis=1)
    return np.where(change, pick, 1)


def bench_single(seconds: float, config: ScenarioConfig) -> float:
    env = LaneChangeEnv(config)
    rng = np.random.default_rng(0)
    _, info = env.reset(seed=0)
    for _ in range(20):  # warm-up
        _, _, term, trunc, info = env.step(int(_actions(rng, info["action_mask"])[0]))
        if term or trunc:
            _, info = env.reset()
    decisions, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, term, trunc, info = env.step(int(_actions(rng, info["action_mask"])[0]))
        decisions += 1
        if term or trunc:
            _obs, info = env.reset()
    return decisions * config.decision_period_s / (time.perf_counter() - t0)


def bench_batch(seconds: float, config: ScenarioConfig, num_envs: int = 64) -> float:
    env = LaneChangeVectorEnv(num_envs, config)
    rng = np.random.default_rng(0)
    _, info = env.reset(seed=0)
    for _ in range(3):
        *_, info = env.step(_actions(rng, info["action_mask"]))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _obs, *_, info = env.step(_actions(rng, info["action_mask"]))
        steps += 1
    return steps * num_envs * config.decision_period_s / (time.perf_counter() - t0)


def bench_highway_env(seconds: float) -> float | None:
    try:
        import gymnasium as gym
        import highway_env  # noqa: F401
    except ImportError:
        return None
    env = gym.make("highway-v0", config={"vehicles_count": 100, "duration": 10_000})
    env.reset(seed=0)
    freq = env.unwrapped.config["policy_frequency"]
    decisions, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, term, trunc, _ = env.step(1)  # IDLE
        decisions += 1
        if term or trunc:
            env.reset()
    return decisions / freq / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0, help="wall time per measurement (default 10)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--no-highway-env", action="store_true", help="skip the highway-env comparison")
    parser.add_argument("--repeat", type=int, default=1,
                        help="measure each lcsim figure this many times, interleaved, and report the median (default 1)")
    args = parser.parse_args(argv)
    if args.seconds <= 0:
        parser.error("--seconds must be > 0")
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    config = ScenarioConfig()
    singles, batches = [], []
    for _ in range(args.repeat):
        singles.append(bench_single(args.seconds, config))
        batches.append(bench_batch(args.seconds, config))
    single, batch = statistics.median(singles), statistics.median(batches)
    hwy = None if args.no_highway_env else bench_highway_env(args.seconds)
    result = {
        "single_env_sim_s_per_s": round(single, 1),
        "batch64_sim_s_per_s": round(batch, 1),
        "highway_env_sim_s_per_s": None if hwy is None else round(hwy, 2),
        "ratio_batch64_vs_highway_env": None if hwy is None else round(batch / hwy, 1),
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(f"lcsim, 100 vehicles, image every decision, one env : {single:8.1f} simulated s per wall s")
        print(f"lcsim, 100 vehicles, image every decision, batch 64: {batch:8.1f} simulated s per wall s")
        if hwy is None:
            print("highway-env not installed (pip install -e '.[bench]') - no comparison")
        else:
            print(f"highway-env highway-v0, 100 vehicles             : {hwy:8.2f} simulated s per wall s")
            print(f"batch 64 vs highway-v0: x{batch / hwy:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
