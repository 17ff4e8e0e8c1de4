#!/usr/bin/env python
"""The recorder's own CPU time per simulated second, whatever the simulator's speed.

An episode is simulated once while what the :class:`~lcdata.record.EpisodeRecorder` reads is captured
(copies of the simulator's step logs, of the state arrays it reads around every decision, the observations,
masks, actions and step results). The capture is then replayed into a real recorder and writer on a stand-in
core, with no simulation: what the replay costs is the recorder's work alone (the log hook, the hand-over to
the writer, encoding, chunking, compression, file I/O). The compiled call's own cost of writing the log is
not in it (the overhead of ``tools/bench_mcap.py`` has it). The replayed file is checked to be byte for byte the file :func:`lcdata.record_episode` writes.

Costs are CPU seconds per simulated second (``time.process_time`` of this process, all threads; the
helper process of ``--writer process`` from ``/proc/<pid>/schedstat``), the median of ``--repeats``
replays, minus the replay loop itself (the same loop with no recorder). Unlike the overhead ratios of
``tools/bench_mcap.py``, these figures do not change when the simulator becomes faster.

    python tools/bench_mcap_recorder.py                 # process writer, both scenarios
    python tools/bench_mcap_recorder.py --writer inline --json
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np

from lcdata.record import (
    EpisodeRecorder,
    episode_metadata,
    episode_seed,
    resolve_driver,
    seed_start_time_ns,
)
from lcdata.writer_process import WRITER_MODES, open_writer, writer_process_pid
from lcsim import corpus_scenario, paper_scenario
from lcsim.config import ScenarioConfig
from lcsim.core import LaneChangeCore

SIM_STATE = ("step", "t_s")
"""The simulator arrays the recorder reads at a decision (copied into the capture, with the rows x, y, yaw of the
vehicles' state block)."""


@dataclass
class Capture:
    """One simulated episode as the recorder sees it."""

    config: ScenarioConfig
    seed: int
    driver: str
    fixed: dict[str, Any]
    """What does not change in an episode: ids, length, width, road, and the step log row after the reset."""
    events: list[tuple[Any, ...]] = field(default_factory=list)
    """``("log", state, log, counts)``, ``("before", state, obs, mask, actions)``, ``("after", state, result)``;
    the first is ``("reset", state)``."""

    @property
    def simulated_s(self) -> float:
        last = self.events[-1][1]
        return float(last["t_s"][0] - self.events[0][1]["t_s"][0])


def _state(sim: Any) -> dict[str, np.ndarray]:
    return {name: np.array(getattr(sim, name)) for name in SIM_STATE} | {"vf": sim.vf[:3].copy()}


def capture(config: ScenarioConfig, seed: int, driver: str) -> Capture:
    """Simulate the episode ``record_episode(config, seed, driver, ...)`` records and capture it."""
    policy, autopilot, _, _ = resolve_driver(driver, seed)
    core = LaneChangeCore(config, 1, autopilot_ego=autopilot)
    core.reset([0], [episode_seed(seed)])
    sim = core.sim
    first = sim.log_row(0)
    fixed = {"ids": np.array(sim.ids), "length": np.array(sim.length), "width": np.array(sim.width),
             "road": sim.road, "log_row": lambda e: first.copy()}  # fmt: skip
    cap = Capture(config, seed, driver, fixed, [("reset", _state(sim))])
    sim.log_hooks.append(lambda s, log, counts: cap.events.append(("log", _state(s), log[:, : counts.max()].copy(),
                                                                   counts.copy())))  # fmt: skip
    obs = core.observe()
    while True:
        mask = core.action_mask()
        actions = np.asarray(policy(obs, mask, core), dtype=np.int64).reshape(1)
        cap.events.append(("before", _state(sim), {k: np.array(v) for k, v in obs.items()}, mask.copy(), actions))
        result = core.step(actions)
        cap.events.append(("after", _state(sim), result))
        if result.terminated[0] or result.truncated[0]:
            break
        obs = core.observe()
    return cap


def replay(cap: Capture, path: pathlib.Path | None, writer: str) -> None:
    """Feed the capture to an :class:`EpisodeRecorder` writing ``path`` (``None``: the loop alone)."""
    sim = SimpleNamespace(log_hooks=[], **cap.fixed)
    core = SimpleNamespace(sim=sim, config=cap.config, num_envs=1, seeds=np.array([episode_seed(cap.seed)]))
    state = sim.__dict__
    events = iter(cap.events)
    state.update(next(events)[1])
    if path is None:
        for event in events:
            state.update(event[1])
        return
    _, autopilot, name, desc = resolve_driver(cap.driver, cap.seed)
    metadata = episode_metadata(cap.config, cap.seed, driver=name, driver_description=desc, autopilot=autopilot)
    with open_writer(path, mode=writer, metadata=metadata, overwrite=True,
                     start_time_ns=seed_start_time_ns(cap.seed)) as w:  # fmt: skip
        rec = EpisodeRecorder(w, core, 0)  # type: ignore[arg-type]
        rec.attach()
        for event in events:
            state.update(event[1])
            if event[0] == "log":
                for hook in sim.log_hooks:
                    hook(sim, event[2], event[3])
            elif event[0] == "before":
                rec.before_step(*event[2:])
            else:
                rec.after_step(event[2])
        rec.detach()


def _helper_cpu_s() -> float:
    """CPU seconds the writer helper process has run so far (0.0 without one)."""
    pid = writer_process_pid()
    try:
        with open(f"/proc/{pid}/schedstat") as f:
            return int(f.read().split()[0]) / 1e9
    except (OSError, IndexError, ValueError, TypeError):
        return 0.0


def recorder_cpu(cap: Capture, writer: str, repeats: int, out: pathlib.Path) -> dict[str, float]:
    """Median CPU seconds per simulated second of ``repeats`` replays: ``main`` (this process, the
    replay loop subtracted), ``helper`` (the writer process) and ``total``."""
    path = out / f"replay_{cap.driver}_{cap.seed}.mcap"
    replay(cap, path, writer)  # warm-up (and the helper's start)
    loop = min(_timed(lambda: replay(cap, None, writer))[0] for _ in range(3))
    main, helper = [], []
    for _ in range(repeats):
        h0 = _helper_cpu_s()
        cpu, _ = _timed(lambda: replay(cap, path, writer))
        main.append(cpu - loop)
        helper.append(_helper_cpu_s() - h0)
    main_s, helper_s = float(np.median(main)), float(np.median(helper))
    sim_s = cap.simulated_s
    return {"main": main_s / sim_s, "helper": helper_s / sim_s, "total": (main_s + helper_s) / sim_s}


def _timed(fn: Any) -> tuple[float, float]:
    cpu, wall = time.process_time(), time.perf_counter()
    fn()
    return time.process_time() - cpu, time.perf_counter() - wall


def check_same_file(cap: Capture, out: pathlib.Path) -> bool:
    """Whether the replay writes the bytes ``record_episode`` writes for the same episode."""
    from lcdata import record_episode

    ours, theirs = out / "replay" / "check.mcap", out / "record" / "check.mcap"  # the stem is the episode id
    replay(cap, ours, "inline")
    record_episode(cap.config, cap.seed, cap.driver, theirs, overwrite=True, writer="inline")
    return ours.read_bytes() == theirs.read_bytes()


SCENARIOS = {"lane_change": (paper_scenario, "rule"), "corpus": (corpus_scenario, "autopilot")}


def measure(writer: str = "process", repeats: int = 5, seed: int = 0, check: bool = True) -> dict[str, Any]:
    """Recorder CPU per simulated second for each scenario of :data:`SCENARIOS` (see the module docstring)."""
    result: dict[str, Any] = {"writer": writer, "repeats": repeats}
    with tempfile.TemporaryDirectory(prefix="bench_mcap_recorder_") as tmp:
        out = pathlib.Path(tmp)
        for key, (make, driver) in SCENARIOS.items():
            cap = capture(make(), seed, driver)
            if check and not check_same_file(cap, out):
                raise SystemExit(f"{key}: the replayed file differs from record_episode's: the capture is stale")
            costs = recorder_cpu(cap, writer, repeats, out)
            result[f"{key}_simulated_s"] = round(cap.simulated_s, 2)
            for part, value in costs.items():
                result[f"{key}_recorder_cpu_ms_per_sim_s_{part}"] = round(1e3 * value, 3)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--writer", choices=WRITER_MODES, default="process", help="writer mode (default: process)")
    parser.add_argument("--repeats", type=int, default=5, help="replays, median of (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    result = measure(args.writer, args.repeats, args.seed)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"recorder CPU per simulated second, writer {args.writer}, median of {args.repeats} replays "
          f"(pid {os.getpid()})")  # fmt: skip
    for key in SCENARIOS:
        r = {part: result[f"{key}_recorder_cpu_ms_per_sim_s_{part}"] for part in ("main", "helper", "total")}
        print(f"{key:12s} main {r['main']:6.2f} ms  helper {r['helper']:6.2f} ms  total {r['total']:6.2f} ms "
              f"per simulated second ({result[f'{key}_simulated_s']:.0f} s simulated)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
