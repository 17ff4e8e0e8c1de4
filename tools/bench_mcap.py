#!/usr/bin/env python
"""Recording overhead and read throughput of real simulator episodes.

Overhead: the same episodes (same seeds, same driver) run through the driver loop of
:func:`lcdata.record_episode` once bare and once recorded to MCAP; overhead = recorded / bare - 1.
Runs come in ``--pairs`` interleaved (bare, recorded) pairs per seed, the order inside a pair
alternating so that a drift of the machine's load hits both sides alike, after one warm-up pair that
is not counted. Each pair gives one overhead figure (times summed over the seeds); the result is the
median over the pairs, with the spread (min, quartiles, max) next to it, for wall-clock time
(``time.perf_counter``, the target) and for process CPU time (``time.process_time``: the simulation,
the recorder and, with ``--writer thread``, the compression thread; a shared machine disturbs it
less). With the default ``--writer process`` the encoding and compression run in a helper process
on the other core: its CPU time is reported separately, as a fraction of the bare CPU time. The
share of CPU time the hypervisor stole during the runs is printed too: on a busy host the wall
figures grow with it (``tools/bench_mcap_instructions.py`` counts instructions instead). Scenarios: the
paper's lane-change scenario with the rule-based driver (100 vehicles, image at every decision) and
the corpus scenario (20 autopilot vehicles, 2000 steps). The ratios move with the simulator's speed, so the
recorder's own CPU time per simulated second (main process and helper, from replays of a captured episode
without the simulator: ``tools/bench_mcap_recorder.py``) is printed too. Read throughput:
``read_episode(path).tracks`` on the recorded files, vehicle rows per second into pandas (best of
``--pairs``).

    python tools/bench_mcap.py           # human-readable
    python tools/bench_mcap.py --json    # one JSON object: overhead_lane_change, overhead_corpus (median
                                         # wall), *_cpu (median CPU), *_spread, read_rows_per_s,
                                         # *_recorder_cpu_ms_per_sim_s_{main,helper,total},
                                         # *_sim_cpu_ms_per_sim_s (the bare runs' CPU per simulated second)

Targets: overhead <= 1.0 (wall: recording at most doubles an episode's time), the recorder's CPU per simulated
second (main and helper) at most the simulation's own, reading >= 1,000,000 rows/s.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time

import numpy as np
from bench_mcap_recorder import SCENARIOS
from bench_mcap_recorder import measure as recorder_cpu

from lcdata import read_episode, record_episode
from lcdata.record import episode_seed, resolve_driver
from lcdata.writer_process import WRITER_MODES, writer_process_pid
from lcsim import corpus_scenario, paper_scenario
from lcsim.config import ScenarioConfig
from lcsim.core import LaneChangeCore


def _clock() -> tuple[float, float]:
    return time.process_time(), time.perf_counter()


def _since(start: tuple[float, float]) -> tuple[float, float]:
    cpu, wall = _clock()
    return cpu - start[0], wall - start[1]


def run_bare(config: ScenarioConfig, seed: int, driver: str) -> tuple[float, float]:
    """The loop of ``record_episode`` without a recorder; returns (CPU, wall) seconds."""
    start = _clock()
    policy, autopilot, _, _ = resolve_driver(driver, seed)
    core = LaneChangeCore(config, 1, autopilot_ego=autopilot)
    core.reset([0], [episode_seed(seed)])
    obs = core.observe()
    while True:
        mask = core.action_mask()
        actions = np.asarray(policy(obs, mask, core), dtype=np.int64).reshape(1)
        res = core.step(actions)
        if res.terminated[0] or res.truncated[0]:
            break
        obs = core.observe()
    return _since(start)


def _proc_cpu(pid: int | None) -> float:
    """CPU seconds (user + system) of process ``pid`` so far, from ``/proc`` (0.0 where unavailable)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError, TypeError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _steal_ticks() -> int:
    """Ticks all CPUs of this (virtual) machine waited for the hypervisor, from ``/proc/stat``."""
    try:
        with open("/proc/stat") as f:
            return int(f.readline().split()[8])
    except (OSError, IndexError, ValueError):
        return 0


def run_recorded(config: ScenarioConfig, seed: int, driver: str, path: pathlib.Path,
                 writer: str) -> tuple[float, float, float, float]:  # fmt: skip
    """``record_episode`` (with its close: the file is complete); returns (CPU, wall, writer process CPU, simulated
    seconds)."""
    helper = _proc_cpu(writer_process_pid())
    start = _clock()
    result = record_episode(config, seed, driver, path, overwrite=True, writer=writer)
    cpu, wall = _since(start)
    return cpu, wall, _proc_cpu(writer_process_pid()) - helper, result.steps * config.dt_s


def overhead(config: ScenarioConfig, driver: str, seeds: list[int], pairs: int, out: pathlib.Path,
             name: str, writer: str = "process") -> tuple[np.ndarray, np.ndarray, list[pathlib.Path]]:  # fmt: skip
    """Times of ``pairs`` interleaved (bare, recorded) runs, each summed over ``seeds``.

    Returns ``(bare, recorded, files)``; bare is a ``(pairs, 2)`` array of (CPU, wall) seconds,
    recorded ``(pairs, 4)`` with the writer process's CPU seconds and the simulated seconds as third and fourth
    columns. One uncounted warm-up pair runs first (it also starts the writer process).
    """
    paths = [out / f"{name}_{seed}.mcap" for seed in seeds]
    bare, rec = np.zeros((pairs, 2)), np.zeros((pairs, 4))
    for i in range(-1, pairs):
        for seed, path in zip(seeds, paths, strict=True):
            if i % 2:  # alternate which of the two runs first
                b = run_bare(config, seed, driver)
                r = run_recorded(config, seed, driver, path, writer)
            else:
                r = run_recorded(config, seed, driver, path, writer)
                b = run_bare(config, seed, driver)
            if i >= 0:
                bare[i] += b
                rec[i] += r
    return bare, rec, paths


def spread(bare: np.ndarray, rec: np.ndarray, column: int) -> dict[str, float]:
    """Overhead quantiles over the pairs (``column`` 0: CPU, 1: wall): min, q25, median, q75, max."""
    ratio = rec[:, column] / bare[:, column] - 1
    q = np.quantile(ratio, [0.0, 0.25, 0.5, 0.75, 1.0])
    return {k: round(float(v), 4) for k, v in zip(("min", "q25", "median", "q75", "max"), q, strict=True)}


def read_throughput(paths: list[pathlib.Path], repeats: int) -> tuple[float, int]:
    """(rows per second, rows) of ``read_episode(p).tracks`` over ``paths``, best of ``repeats``."""
    best, rows = float("inf"), 0
    for _ in range(repeats):
        start = time.perf_counter()
        rows = sum(len(read_episode(p).tracks) for p in paths)
        best = min(best, time.perf_counter() - start)
    return rows / best, rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=2, help="episodes per scenario (seeds 0..n-1)")
    parser.add_argument("--pairs", type=int, default=5, help="interleaved (bare, recorded) pairs, median of")
    parser.add_argument("--writer", choices=WRITER_MODES, default="process",
                        help="where the recorded runs encode and compress (default: process)")  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.pairs < 1:
        parser.error("--episodes and --pairs must be >= 1")
    seeds = list(range(args.episodes))
    steal, start = _steal_ticks(), time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_mcap_") as tmp:
        out = pathlib.Path(tmp)
        lc = overhead(paper_scenario(), "rule", seeds, args.pairs, out, "paper", args.writer)
        corpus = overhead(corpus_scenario(), "autopilot", seeds, args.pairs, out, "corpus", args.writer)
        steal_fraction = (_steal_ticks() - steal) / os.sysconf("SC_CLK_TCK") / (time.perf_counter() - start)
        steal_fraction /= os.cpu_count() or 1
        rows_per_s, rows = read_throughput(lc[2] + corpus[2], args.pairs)
        size_mb = sum(p.stat().st_size for p in lc[2] + corpus[2]) / 1e6
    result: dict[str, object] = {"writer": args.writer}
    spreads = {}
    for key, (bare, rec, _) in (("overhead_lane_change", lc), ("overhead_corpus", corpus)):
        wall, cpu = spreads[key, 1], spreads[key, 0] = spread(bare, rec, 1), spread(bare, rec, 0)
        result[key] = wall["median"]
        result[f"{key}_cpu"] = cpu["median"]
        result[f"{key}_spread"] = wall
        result[f"{key}_cpu_spread"] = cpu
        result[f"{key}_writer_process_cpu"] = round(float(np.median(rec[:, 2] / bare[:, 0])), 4)
        result[f"{key.removeprefix('overhead_')}_sim_cpu_ms_per_sim_s"] = round(
            float(np.median(1e3 * bare[:, 0] / rec[:, 3])), 3)
    costs = recorder_cpu(args.writer, repeats=args.pairs)
    for key in SCENARIOS:
        for part in ("main", "helper", "total"):
            result[f"{key}_recorder_cpu_ms_per_sim_s_{part}"] = costs[f"{key}_recorder_cpu_ms_per_sim_s_{part}"]
    result["pairs"] = args.pairs
    result["episodes"] = args.episodes
    result["steal_fraction"] = round(steal_fraction, 4)
    result["read_rows_per_s"] = round(rows_per_s)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"{args.pairs} interleaved pairs x {args.episodes} episodes, writer {args.writer}; overhead = recorded / "
          "bare - 1, median [min, q25, q75, max] over the pairs")  # fmt: skip
    for label, key, (bare, rec, _) in (("lane-change (rule, 100 veh)", "overhead_lane_change", lc),
                                       ("corpus (autopilot, 20 veh)", "overhead_corpus", corpus)):  # fmt: skip
        for kind, column in (("wall", 1), ("CPU ", 0)):
            s = spreads[key, column]
            print(f"{label:28s} {kind} bare {np.median(bare[:, column]):5.2f} s recorded "
                  f"{np.median(rec[:, column]):5.2f} s overhead {100 * s['median']:5.1f}% "
                  f"[{100 * s['min']:.1f}, {100 * s['q25']:.1f}, {100 * s['q75']:.1f}, {100 * s['max']:.1f}]"
                  + ("  (target <= 100%)" if column == 1 else ""))  # fmt: skip
        if args.writer == "process":
            print(f"{label:28s} writer process CPU: {100 * result[f'{key}_writer_process_cpu']:.1f}% of the bare "
                  "CPU time, on the other core")  # fmt: skip
    for key in SCENARIOS:
        r = [result[f"{key}_recorder_cpu_ms_per_sim_s_{part}"] for part in ("main", "helper", "total")]
        print(f"{key:28s} recorder CPU per simulated second: main {r[0]:.2f} ms + helper {r[1]:.2f} ms = "
              f"{r[2]:.2f} ms (replayed, no simulation); the simulation's own: "
              f"{result[f'{key}_sim_cpu_ms_per_sim_s']:.2f} ms (bare runs; target: recorder <= simulation)")  # fmt: skip
    print(f"CPU time stolen by the hypervisor during the runs: {100 * steal_fraction:.1f}% (a noisy host; "
          "it inflates the wall figures)")  # fmt: skip
    print(f"read {rows} vehicle rows from {size_mb:.1f} MB: {rows_per_s / 1e6:.2f} M rows/s  (target >= 1 M rows/s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
