"""Statistics of the simulated traffic: what ``tools/traffic_stats.py`` prints and docs/simulator.md tabulates."""

from __future__ import annotations

import dataclasses

import numpy as np

from lcsim.config import ScenarioConfig
from lcsim.sim import HighwaySim

WARMUP_S = 5.0
"""Seconds left out at the start of every episode (the spawn's even spacing settles)."""


def traffic_statistics(config: ScenarioConfig, episodes: int, seconds: float, seed: int = 0) -> dict[str, float]:
    """Run ``episodes`` environments of ``config``'s traffic (all on autopilot) for ``seconds`` and measure it."""
    sim = HighwaySim(dataclasses.replace(config, render_image=False), episodes, autopilot_ego=True)
    sim.reset(np.arange(episodes), [seed * 100_000 + k for k in range(episodes)])
    lw, dt = sim.road.lane_width, sim.dt
    steps, warm = round(seconds / dt), round(WARMUP_S / dt)
    speeds, accels, gaps, offsets = [], [], [], []
    starts = np.zeros(sim.x.shape, dtype=np.int64) - 1
    durations: list[float] = []
    changes, distance_m = 0, 0.0
    active_before = sim.lc_active.copy()
    for k in range(steps):
        x_before = sim.x.copy()
        sim.substep()
        active = sim.lc_active.copy()
        started, ended = active & ~active_before, ~active & active_before
        active_before = active.copy()
        if k < warm:
            starts[started] = -1
            continue
        starts[started] = k
        done = ended & (starts >= 0)
        durations.extend(((k + 1 - starts[done]) * dt).tolist())  # (steps k_start .. k: the change's own steps)
        starts[ended] = -1
        changes += int(started.sum())
        distance_m += float((sim.x - x_before).sum())
        if k % 10 == 0:  # samples every 0.5 s (consecutive steps are strongly correlated)
            speeds.append(sim.speed.ravel().copy())
            accels.append(sim.accel.ravel().copy())
            index = sim.index
            assert index is not None
            follow = (index.gap < 60.0) & (sim.speed > 2.0)
            gaps.append((index.gap[follow] / sim.speed[follow]).copy())
            keep = ~active
            centre = (np.floor(sim.y / lw) + 0.5) * lw
            offsets.append((sim.y - centre)[keep])
    speed, accel = np.concatenate(speeds) * 3.6, np.concatenate(accels)
    gap, offset = np.concatenate(gaps), np.concatenate(offsets)
    dur = np.asarray(durations) if durations else np.full(1, np.nan)
    return {
        "speed_mean_kmh": float(speed.mean()), "speed_sd_kmh": float(speed.std()),
        "accel_sd_mps2": float(accel.std()), "accel_p05_mps2": float(np.percentile(accel, 5)),
        "accel_p95_mps2": float(np.percentile(accel, 95)),
        "time_gap_p15_s": float(np.percentile(gap, 15)), "time_gap_median_s": float(np.median(gap)),
        "time_gap_p85_s": float(np.percentile(gap, 85)), "time_gap_under_1s": float((gap < 1.0).mean()),
        "lateral_offset_sd_m": float(offset.std()), "lateral_offset_max_m": float(np.abs(offset).max()),
        "lane_changes_per_vehicle_km": changes / (distance_m / 1000.0),
        "lane_change_duration_mean_s": float(dur.mean()), "lane_change_duration_sd_s": float(dur.std()),
        "lane_changes": changes, "vehicle_km": distance_m / 1000.0,
        "traffic_collisions": int(sim.traffic_collisions.sum()),
    }
