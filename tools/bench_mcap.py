#!/usr/bin/env python
"""Recording overhead and read throughput of real simulator episodes.

Overhead: the same episodes (same seeds, same driver) run through the driver loop of
:func:`lcdata.record_episode` once bare and once recorded to MCAP; overhead = recorded / bare - 1,
best of ``--repeats`` per episode, bare and recorded runs interleaved. Time is the process CPU time
(``time.process_time``: the simulation, the recorder and the writer's compression thread), which a
shared machine disturbs far less than wall-clock time; wall-clock figures are printed as well. Scenarios: the
paper's lane-change scenario with the rule-based driver (100 vehicles, image at every decision) and
the corpus scenario (20 autopilot vehicles, 2000 steps). Read throughput: ``read_episode(path).tracks``
on the recorded files, vehicle rows per second into pandas (best of ``--repeats``).

    python tools/bench_mcap.py           # human-readable
    python tools/bench_mcap.py --json    # one JSON object: overhead_lane_change, overhead_corpus, read_rows_per_s

Targets: overhead <= 0.20, reading >= 1,000,000 rows/s.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

from lcdata import read_episode, record_episode
from lcdata.record import episode_seed, resolve_driver
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


def run_recorded(config: ScenarioConfig, seed: int, driver: str, path: pathlib.Path) -> tuple[float, float]:
    start = _clock()
    record_episode(config, seed, driver, path, overwrite=True)
    return _since(start)


def overhead(config: ScenarioConfig, driver: str, seeds: list[int], repeats: int, out: pathlib.Path,
             name: str) -> tuple[np.ndarray, np.ndarray, list[pathlib.Path]]:  # fmt: skip
    """((CPU, wall) bare s, (CPU, wall) recorded s, files) summed over ``seeds``, best of ``repeats`` each."""
    bare, rec, paths = np.zeros(2), np.zeros(2), []
    for seed in seeds:
        path = out / f"{name}_{seed}.mcap"
        b = r = np.full(2, np.inf)
        for _ in range(repeats):
            b = np.minimum(b, run_bare(config, seed, driver))
            r = np.minimum(r, run_recorded(config, seed, driver, path))
        bare, rec = bare + b, rec + r
        paths.append(path)
    return bare, rec, paths


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
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (best of)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.repeats < 1:
        parser.error("--episodes and --repeats must be >= 1")
    seeds = list(range(args.episodes))
    with tempfile.TemporaryDirectory(prefix="bench_mcap_") as tmp:
        out = pathlib.Path(tmp)
        lc = overhead(paper_scenario(), "rule", seeds, args.repeats, out, "lane-change")
        corpus = overhead(corpus_scenario(), "autopilot", seeds, args.repeats, out, "corpus")
        rows_per_s, rows = read_throughput(lc[2] + corpus[2], args.repeats)
        size_mb = sum(p.stat().st_size for p in lc[2] + corpus[2]) / 1e6
    result = {
        "overhead_lane_change": round(float(lc[1][0] / lc[0][0] - 1), 4),
        "overhead_corpus": round(float(corpus[1][0] / corpus[0][0] - 1), 4),
        "read_rows_per_s": round(rows_per_s),
    }
    if args.json:
        print(json.dumps(result))
        return 0
    for label, (bare, rec, _) in (("lane-change (rule, 100 veh)", lc), ("corpus (autopilot, 20 veh)", corpus)):
        cpu, wall = rec / bare - 1
        print(f"{label:28s} CPU bare {bare[0]:5.2f} s recorded {rec[0]:5.2f} s overhead {100 * cpu:5.1f}% "
              f"(target <= 20%) | wall {bare[1]:5.2f} s -> {rec[1]:5.2f} s ({100 * wall:+.1f}%)")
    print(f"read {rows} vehicle rows from {size_mb:.1f} MB: {rows_per_s / 1e6:.2f} M rows/s  (target >= 1 M rows/s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
