"""Statistics of the simulated traffic, next to the published figures they are chosen after.

Runs the traffic of a scenario (every vehicle on autopilot, the ego included) for a number of episodes and
measures what docs/simulator.md tabulates: speed, acceleration, time gap to the leader, lateral offset from
the lane centre, lane changes per vehicle and km, and lane-change duration; with human-like drivers
(the default) and, with ``--compare``, with exact IDM beside them.

    python tools/traffic_stats.py                 # paper scenario, human-like traffic
    python tools/traffic_stats.py --compare       # human-like and exact IDM side by side
    python tools/traffic_stats.py --json          # one JSON object
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from lcsim.registry import TASK_SCENARIOS, scenario
from lcsim.stats import WARMUP_S, traffic_statistics

ROWS = (
    ("speed (km/h)", "speed_mean_kmh", "speed_sd_kmh", "mean / sd"),
    ("acceleration (m/s^2)", "accel_sd_mps2", None, "sd"),
    ("acceleration p5 / p95 (m/s^2)", "accel_p05_mps2", "accel_p95_mps2", "p5 / p95"),
    ("time gap to the leader (s)", "time_gap_median_s", None, "median"),
    ("time gap p15 / p85 (s)", "time_gap_p15_s", "time_gap_p85_s", "p15 / p85"),
    ("time gaps under 1 s", "time_gap_under_1s", None, "share"),
    ("lateral offset in the lane (m)", "lateral_offset_sd_m", "lateral_offset_max_m", "sd / max"),
    ("lane changes per vehicle-km", "lane_changes_per_vehicle_km", None, "rate"),
    ("lane-change duration (s)", "lane_change_duration_mean_s", "lane_change_duration_sd_s", "mean / sd"),
    ("traffic collisions", "traffic_collisions", None, "count"),
)


def _cell(stats: dict[str, float], a: str, b: str | None) -> str:
    return f"{stats[a]:.3g}" + (f" / {stats[b]:.3g}" if b else "")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="paper", help=f"scenario name ({', '.join(TASK_SCENARIOS)}) or file "
                   "(default paper)")
    p.add_argument("--episodes", type=int, default=16, help="environments run side by side (default 16)")
    p.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per episode (default 60)")
    p.add_argument("--seed", type=int, default=0, help="seed of the episodes (default 0)")
    p.add_argument("--compare", action="store_true", help="also measure exact IDM (human_like = false)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    try:
        if args.episodes < 1 or not args.seconds > WARMUP_S:
            raise ValueError(f"--episodes must be >= 1 and --seconds > {WARMUP_S}")
        cfg = scenario(args.scenario)
    except ValueError as exc:
        print(f"traffic_stats: {exc}", file=sys.stderr)
        return 2
    variants = {"human-like": cfg}
    if args.compare:
        variants["exact IDM"] = dataclasses.replace(cfg, traffic=dataclasses.replace(cfg.traffic, human_like=False))
    results = {}
    for name, c in variants.items():
        print(f"traffic_stats: {name}: {args.episodes} episodes x {args.seconds:g} s ...", file=sys.stderr)
        results[name] = traffic_statistics(c, args.episodes, args.seconds, args.seed)
    if args.json:
        print(json.dumps({"scenario": args.scenario, "episodes": args.episodes, "seconds": args.seconds,
                          "seed": args.seed, "results": results}, indent=2))
        return 0
    names = list(results)
    print("| statistic | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for label, a, b, what in ROWS:
        print(f"| {label} ({what}) | " + " | ".join(_cell(results[n], a, b) for n in names) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
