#!/usr/bin/env python
"""Simulator throughput: simulated seconds per wall-clock second.

Measures the paper scenario (100 vehicles, 20 Hz, a decision and a rendered 3x120x120 bird's-eye image
every 0.5 s) through the gymnasium API, for one environment (``LaneChangeEnv``) and for a batch of 64
(``LaneChangeVectorEnv``), with autoreset. Actions: keep lane, with a valid lane change 15% of the time.
When highway-env is installed, measures its ``highway-v0`` with 100 vehicles on the same machine.

With ``--full``, also: batches of 8 and 256, every size without the image, the lookahead planner's cost per
decision (perceived, as the safety layer runs it), and the floor of a compiled simulator: a bare IDM sub-step
(per-lane leaders from an insertion sort of the previous order, as the simulator keeps it; no lane changes,
controller, sensors or observation) compiled with numba, for one environment and for 64, next to the batch of 64 with the image as a ratio (``floor_over_image_envs64``: how many
times the bare sub-step's speed the whole simulator is from). The simulator itself is compiled too
(:mod:`lcsim.kernel`); its first call compiles once per machine (``tools/bench_compile.py`` times it).

Batches step on the process's default threads (:mod:`lcsim.threads`: ``LC_THREADS``, else every core for batches
of at least 8 environments per thread) unless ``--threads`` says how many. With ``--serial-vs-parallel``, the
batches of 8, 64 and 256 with the image are measured on one thread and on ``--threads`` (default: every core),
interleaved, and printed side by side with their ratio (the figures of both are the same bytes).

    python tools/bench_sim.py            # human-readable
    python tools/bench_sim.py --json     # one JSON object
    python tools/bench_sim.py --repeat 5 # median of 5 measurements each (for a busy machine)
    python tools/bench_sim.py --full --seconds 5   # every size, with and without the image, planner, floor
    python tools/bench_sim.py --serial-vs-parallel --repeat 3   # batches on one thread and on every core
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
from lcsim.threads import default_threads, shard_count


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


def bench_batch(seconds: float, config: ScenarioConfig, num_envs: int = 64, threads: int | None = None) -> float:
    env = LaneChangeVectorEnv(num_envs, config, threads=threads)
    rng = np.random.default_rng(0)
    _, info = env.reset(seed=0)
    for _ in range(3):
        *_, info = env.step(_actions(rng, info["action_mask"]))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _obs, *_, info = env.step(_actions(rng, info["action_mask"]))
        steps += 1
    return steps * num_envs * config.decision_period_s / (time.perf_counter() - t0)


def bench_planner(seconds: float) -> float:
    """Milliseconds per decision of the perceived lookahead planner (blind, perceived, horizon 16) in one env."""
    from lcsim.planning import LookaheadDriver, SafetyLayerConfig

    env = LaneChangeEnv(ScenarioConfig(render_image=False))
    driver = LookaheadDriver(SafetyLayerConfig())
    obs, info = env.reset(seed=0)
    decisions, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or decisions < 3:
        action = driver({k: v[None] for k, v in obs.items()}, info["action_mask"][None], env.core)[0]
        obs, _, term, trunc, info = env.step(int(action))
        decisions += 1
        if term or trunc:
            obs, info = env.reset()
    return 1000.0 * (time.perf_counter() - t0) / decisions


def bench_numba_floor(seconds: float, num_envs: int) -> float | None:
    """Simulated s per wall s of a bare IDM sub-step compiled with numba (None without numba): the limit."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=True)
    def substeps(x, v, v0, lane, length, order, steps, dt, lanes):  # pragma: no cover - compiled
        e_count, n = x.shape
        lead = np.empty(lanes, dtype=np.int64)
        acc = np.empty(n)
        for _ in range(steps):
            for e in range(e_count):
                o = order[e]
                for k in range(1, n):  # insertion sort from the previous sub-step's order, as lcsim.kernel does
                    i, m = o[k], k - 1
                    while m >= 0 and x[e, o[m]] > x[e, i]:
                        o[m + 1] = o[m]
                        m -= 1
                    o[m + 1] = i
                lead[:] = -1
                for k in range(n - 1, -1, -1):  # front to back: the last vehicle seen in a lane leads
                    i = o[k]
                    j = lead[lane[e, i]]
                    gap, dv = 1e9, 0.0
                    if j >= 0:
                        gap = x[e, j] - x[e, i] - 0.5 * (length[e, i] + length[e, j])
                        dv = v[e, i] - v[e, j]
                    s_star = 2.0 + v[e, i] * 2.0 + v[e, i] * dv / (2.0 * np.sqrt(1.5 * 2.0))
                    r = v[e, i] / v0[e, i]
                    a = 1.5 * (1.0 - r ** 4 - (max(s_star, 2.0) / max(gap, 0.1)) ** 2)
                    acc[i] = min(max(a, -8.0), 1.5)
                    lead[lane[e, i]] = i
                for i in range(n):
                    nv = max(v[e, i] + acc[i] * dt, 0.0)
                    x[e, i] += 0.5 * (v[e, i] + nv) * dt
                    v[e, i] = nv

    rng = np.random.default_rng(0)
    n = 101
    x = np.sort(rng.uniform(-300.0, 1300.0, (num_envs, n)), axis=1)
    v = np.full((num_envs, n), 24.0 / 3.6)
    v0 = v + rng.normal(0.0, 0.5, (num_envs, n))
    lane = rng.integers(0, 4, (num_envs, n)).astype(np.int64)
    length = np.full((num_envs, n), 5.37)
    order = np.tile(np.arange(n), (num_envs, 1))
    substeps(x, v, v0, lane, length, order, 1, 0.05, 4)  # compile (or load the cache)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        substeps(x, v, v0, lane, length, order, 100, 0.05, 4)
        steps += 100
    return steps * num_envs * 0.05 / (time.perf_counter() - t0)


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
    parser.add_argument("--full", action="store_true",
                        help="also batches of 8 and 256, every size without the image, the planner's cost per "
                        "decision and the numba floor (pip install numba)")
    parser.add_argument("--threads", type=int, default=None,
                        help="threads that step a batch (default: lcsim's default, LC_THREADS or every core)")
    parser.add_argument("--serial-vs-parallel", action="store_true",
                        help="also the batches of 8, 64 and 256 with the image on one thread and on --threads "
                        "(default every core), interleaved, side by side")
    args = parser.parse_args(argv)
    if args.seconds <= 0:
        parser.error("--seconds must be > 0")
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    if args.threads is not None and args.threads < 1:
        parser.error("--threads must be >= 1")
    try:
        default = default_threads()
    except ValueError as exc:
        parser.error(str(exc))
    threads = args.threads
    config = ScenarioConfig()
    singles, batches = [], []
    for _ in range(args.repeat):
        singles.append(bench_single(args.seconds, config))
        batches.append(bench_batch(args.seconds, config, threads=threads))
    single, batch = statistics.median(singles), statistics.median(batches)
    hwy = None if args.no_highway_env else bench_highway_env(args.seconds)
    result = {
        "batch_threads": shard_count(64, threads),
        "single_env_sim_s_per_s": round(single, 1),
        "batch64_sim_s_per_s": round(batch, 1),
        "highway_env_sim_s_per_s": None if hwy is None else round(hwy, 2),
        "ratio_batch64_vs_highway_env": None if hwy is None else round(batch / hwy, 1),
    }
    if args.full:
        for images in (True, False):
            cfg = ScenarioConfig(render_image=images)
            for size in (1, 8, 64, 256):
                key = f"{'image' if images else 'no_image'}_envs{size}_sim_s_per_s"
                if images and size == 1:
                    result[key] = result["single_env_sim_s_per_s"]
                elif images and size == 64:
                    result[key] = result["batch64_sim_s_per_s"]
                else:
                    fig = (bench_single(args.seconds, cfg) if size == 1
                           else bench_batch(args.seconds, cfg, size, threads))
                    result[key] = round(fig, 1)
        result["planner_perceived_ms_per_decision"] = round(bench_planner(args.seconds), 1)
        for size in (1, 64):
            floor = bench_numba_floor(args.seconds, size)
            result[f"numba_floor_envs{size}_sim_s_per_s"] = None if floor is None else round(floor, 1)
        floor64 = result["numba_floor_envs64_sim_s_per_s"]
        result["floor_over_image_envs64"] = None if not floor64 else round(floor64 / batch, 2)
        result["ratio_single_vs_highway_env"] = None if hwy is None else round(single / hwy, 1)
    if args.serial_vs_parallel:
        parallel = args.threads or max(default, 2)
        result["parallel_threads"] = parallel
        for size in (8, 64, 256):
            serial_runs, parallel_runs = [], []
            for _ in range(args.repeat):  # interleaved: a drift of the host's speed touches both alike
                serial_runs.append(bench_batch(args.seconds, config, size, 1))
                parallel_runs.append(bench_batch(args.seconds, config, size, parallel))
            s, p = statistics.median(serial_runs), statistics.median(parallel_runs)
            result[f"image_envs{size}_serial_sim_s_per_s"] = round(s, 1)
            result[f"image_envs{size}_parallel_sim_s_per_s"] = round(p, 1)
            result[f"image_envs{size}_parallel_over_serial"] = round(p / s, 2)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"lcsim, 100 vehicles, image every decision, one env : {single:8.1f} simulated s per wall s")
        print(f"lcsim, 100 vehicles, image every decision, batch 64: {batch:8.1f} simulated s per wall s "
              f"({result['batch_threads']} thread{'s' if result['batch_threads'] > 1 else ''})")
        if hwy is None:
            print("highway-env not installed (pip install -e '.[bench]') - no comparison")
        else:
            print(f"highway-env highway-v0, 100 vehicles             : {hwy:8.2f} simulated s per wall s")
            print(f"batch 64 vs highway-v0: x{batch / hwy:.0f}")
        if args.full:
            for key, value in result.items():
                if key.startswith(("image_", "no_image_", "numba_", "planner_", "floor_", "ratio_single")):
                    missing = "numba not installed" if key.startswith(("numba_", "floor_")) else "n/a"
                    print(f"{key:42s}: {missing if value is None else value}")
        if args.serial_vs_parallel:
            print(f"batch with the image, simulated s per wall s: one thread | {result['parallel_threads']} threads "
                  "| ratio")
            for size in (8, 64, 256):
                print(f"  batch {size:3d}: {result[f'image_envs{size}_serial_sim_s_per_s']:9.1f} | "
                      f"{result[f'image_envs{size}_parallel_sim_s_per_s']:9.1f} | "
                      f"x{result[f'image_envs{size}_parallel_over_serial']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
