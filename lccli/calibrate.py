"""``lc-calibrate``: fit the simulator's human-like traffic to recorded tracks and write a scenario file."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import pathlib
import sys
from collections.abc import Sequence
from typing import Any

from lccli.common import fail, int_at_least, positive_float, setup_logging

PROG = "lc-calibrate"
EXAMPLES = """\
examples:
  python tools/sumo_highway.py --out runs/sumo --episodes 8 --speed-kmh 60     # or: lc-import highd ... --out DATA
  lc-calibrate runs/sumo/corpus --out scenarios/sumo.toml
  lc-eval rule --scenario scenarios/sumo.toml --episodes 100 --no-record

DATA is a folder of corpus episodes (every *.mcap below it: what lc-import and lc-record --scenario corpus
write) or one episode file, with the traffic driving along +x and lane 0 the rightmost (the corpus frame).
The statistics, recorded and simulated alike, are those of lcsim.stats (tools/traffic_stats.py prints them
for a scenario): speed, acceleration, time gap to the leader, lateral offset, lane changes per vehicle-km and
their duration. The scenario file is the base scenario with the recording's road and vehicle size and the
fitted traffic (the ego is the base's); lc-record, lc-eval and lc-bench take it as --scenario.
"""

ROWS = (
    ("speed, mean (km/h)", "speed_mean_kmh"), ("speed, sd (km/h)", "speed_sd_kmh"),
    ("acceleration, sd (m/s^2)", "accel_sd_mps2"), ("acceleration, p5 (m/s^2)", "accel_p05_mps2"),
    ("acceleration, p95 (m/s^2)", "accel_p95_mps2"), ("time gap, p15 (s)", "time_gap_p15_s"),
    ("time gap, median (s)", "time_gap_median_s"), ("time gap, p85 (s)", "time_gap_p85_s"),
    ("time gaps under 1 s (share)", "time_gap_under_1s"), ("lateral offset, sd (m)", "lateral_offset_sd_m"),
    ("lane changes per vehicle-km", "lane_changes_per_vehicle_km"),
    ("lane-change duration, mean (s)", "lane_change_duration_mean_s"),
    ("lane-change duration, sd (s)", "lane_change_duration_sd_s"),
)  # fmt: skip
"""The compared statistics (:data:`lcsim.stats.COMPARED`), as the table names them."""
INFO_ROWS = (
    ("free-flow speed, mean (km/h)", "free_speed_mean_kmh"), ("lateral offset, max (m)", "lateral_offset_max_m"),
    ("lane changes (count)", "lane_changes"), ("vehicle-km", "vehicle_km"),
)  # fmt: skip
"""Shown below the table, not fitted."""


class UsageError(Exception):
    """Bad command-line input: one line on stderr, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see {self.prog} --help)")


def build_parser() -> argparse.ArgumentParser:
    from lcsim.calibrate import CalibrationOptions
    from lcsim.registry import SCENARIOS
    from lcsim.stats import MAX_BOOTSTRAP_DRAWS, MAX_TRACK_BYTES

    d = CalibrationOptions()
    p = _Parser(
        prog=PROG,
        description="Fit the simulator's human-like traffic (desired speeds and their spread, time gap, density,\n"
        "acceleration noise, lane-change propensity, duration and its spread, lateral wander) to recorded tracks\n"
        "by moment matching, write the scenario file, and print the recorded, the default and the calibrated\n"
        "statistics side by side. Deterministic for a given seed.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("data", type=pathlib.Path, metavar="DATA", help="folder of corpus episodes, or one .mcap file")
    p.add_argument("--out", type=pathlib.Path, required=True, metavar="SCENARIO",
                   help="the scenario file to write (.toml or .json); an existing one is kept unless --overwrite")
    p.add_argument("--base", default="paper", metavar="{" + ",".join(SCENARIOS) + ",FILE}",
                   help="the scenario whose traffic is fitted and whose other settings the file keeps; its own "
                   "traffic is the 'default' column (default paper)")
    p.add_argument("--iterations", type=int_at_least(1, d.MAX_ITERATIONS), default=d.iterations, metavar="N",
                   help=f"simulated evaluations of the search, the start included (default {d.iterations}, at most "
                   f"{d.MAX_ITERATIONS}); each simulates --episodes x --seconds")
    p.add_argument("--episodes", type=int_at_least(1, d.MAX_EPISODES), default=d.episodes, metavar="N",
                   help=f"environments simulated side by side per evaluation (default {d.episodes}, at most "
                   f"{d.MAX_EPISODES}, and no more than {MAX_TRACK_BYTES >> 30} GiB of tracks with --seconds: the "
                   "command says so before it simulates)")
    p.add_argument("--seconds", type=positive_float, default=None, metavar="S",
                   help="simulated seconds per episode, the first 5 left out (default: the base scenario's time limit, "
                   "75 s for paper)")
    p.add_argument("--report-episodes", type=int_at_least(1, d.MAX_EPISODES), default=d.report_episodes,
                   metavar="N", help=f"episodes of the final measurement of the default and the result, on other "
                   f"seeds than the search's (default {d.report_episodes}, at most {d.MAX_EPISODES}, as --episodes)")
    p.add_argument("--seed", type=int_at_least(0), default=d.seed,
                   help="seed of the search's episodes (the report uses SEED + 1) and of the bootstrap (default 0)")
    p.add_argument("--bootstrap", type=int_at_least(10, MAX_BOOTSTRAP_DRAWS), default=200, metavar="N",
                   help="bootstrap draws of the recorded statistics' 95%% intervals, resampling vehicles (default 200, "
                   f"at most {MAX_BOOTSTRAP_DRAWS})")
    p.add_argument("--keep-road", action="store_true",
                   help="keep the base scenario's lanes and lane width instead of the recording's")
    p.add_argument("--json", type=pathlib.Path, default=None, metavar="FILE",
                   help="also write every figure (statistics, intervals, tolerances, the search) as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out (and --json) file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress")
    p.add_argument("-v", "--verbose", action="store_true", help="log what was read")
    return p


def _cell(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.3g}"


def _off(value: float, recorded: float, tolerance: float) -> str:
    """The difference from the recorded figure in % of it (in tolerances where it is 0), and a tick if within."""
    if not (math.isfinite(value) and math.isfinite(recorded)):
        return "-"
    diff = value - recorded
    text = f"{100.0 * diff / abs(recorded):+.0f}%" if recorded else f"{diff / tolerance:+.1f} tol"
    return f"{text} {'ok' if abs(diff) <= tolerance else 'OUT'}"


def table(result: Any) -> str:
    """The side-by-side table of a :class:`lcsim.calibrate.CalibrationResult` (Markdown)."""
    rec, tol, iv = result.recorded, result.tolerance, result.intervals
    lines = ["| statistic | recorded [95% interval] | tolerance | default | default off by | calibrated | "
             "calibrated off by |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for label, key in ROWS:
        lo, hi = iv.get(key, (math.nan, math.nan))
        lines.append(f"| {label} | {_cell(rec[key])} [{_cell(lo)}, {_cell(hi)}] | {_cell(tol[key])} | "
                     f"{_cell(result.default[key])} | {_off(result.default[key], rec[key], tol[key])} | "
                     f"{_cell(result.calibrated[key])} | {_off(result.calibrated[key], rec[key], tol[key])} |")  # fmt: skip
    for label, key in INFO_ROWS:
        lines.append(f"| {label} (not fitted) | {_cell(rec[key])} | | {_cell(result.default[key])} | | "
                     f"{_cell(result.calibrated[key])} | |")  # fmt: skip
    lines.append(f"| traffic collisions (not fitted) | | | {result.default['traffic_collisions']} | | "
                 f"{result.calibrated['traffic_collisions']} | |")  # fmt: skip
    return "\n".join(lines)


def summary_lines(result: Any) -> list[str]:
    lines = []
    for name, stats in (("default", result.default), ("calibrated", result.calibrated)):
        within = result.within(stats)
        out = [k for k, ok in within.items() if not ok]
        lines.append(f"{name}: {sum(within.values())} of {len(within)} statistics within tolerance, distance "
                     f"{result.distance(stats):.3g}" + (f" (out: {', '.join(out)})" if out else ""))  # fmt: skip
    return lines


def scenario_text(result: Any, out: pathlib.Path, header: Sequence[str]) -> str:
    if out.suffix == ".json":
        return json.dumps(result.scenario.to_dict(), indent=2, sort_keys=True) + "\n"
    return "".join(f"# {line}\n" for line in header) + result.scenario.to_toml()


def _finite(value: Any) -> Any:
    """``value`` with every NaN or infinity (a statistic with nothing to measure) as None: strict JSON."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``lc-calibrate``; returns the exit code (2 for bad input, one line on stderr)."""
    error = functools.partial(fail, PROG)
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:
        return error(str(exc))
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    setup_logging(PROG, verbose=args.verbose)
    from lcdata.recorded import recorded_traffic
    from lckit.fileio import check_output_file, check_target, write_file, write_json
    from lcsim.calibrate import (
        CalibrationOptions,
        RecordedRoad,
        calibrate,
        check_memory,
        distance,
        tolerances,
    )
    from lcsim.registry import scenario, scenario_label
    from lcsim.stats import WARMUP_S, sampling_intervals, summarise, traffic_samples

    def say(text: str) -> None:
        if not args.quiet:
            print(f"{PROG}: {text}", file=sys.stderr, flush=True)

    try:
        if args.out.suffix not in (".toml", ".json"):
            raise ValueError(f"--out {args.out}: a scenario file's name ends in .toml or .json")
        for flag, path in (("--out", args.out), ("--json", args.json)):
            if path is None:
                continue
            check_output_file(path, flag)
            check_target(path)  # never written through a link
            if path.exists() and not args.overwrite:
                raise ValueError(f"{flag} {path} already exists; pass --overwrite to replace it")
        if args.json is not None and args.json.resolve() == args.out.resolve():
            raise ValueError("--json and --out name the same file")
        if args.seconds is not None and not args.seconds > WARMUP_S + 5.0:
            raise ValueError(f"--seconds must be more than {WARMUP_S + 5.0:g} (the first {WARMUP_S:g} are left out)")
        base = scenario(args.base)
        options = CalibrationOptions(iterations=args.iterations, episodes=args.episodes, seconds=args.seconds,
                                     seed=args.seed, report_episodes=args.report_episodes, keep_road=args.keep_road)
        if not args.data.exists():
            raise ValueError(f"{args.data} does not exist")
        say(f"reading {args.data} ...")
        rec = recorded_traffic(args.data)
        samples = traffic_samples(rec.tracks)
        if samples.vehicles == 0 or not len(samples.speed):
            raise ValueError(f"{args.data}: no vehicles")
        size = RecordedRoad(num_lanes=rec.num_lanes, lane_width_m=rec.lane_width_m, length_m=rec.length_m,
                            width_m=rec.width_m, density_per_lane_km=rec.density_per_lane_km)  # fmt: skip
        check_memory(options, base, size)  # before the bootstrap: a refusal comes first
        say(f"{len(rec.tracks)} episodes, {rec.seconds:.0f} s, {samples.vehicles} vehicles, {rec.num_lanes} lanes of "
            f"{rec.lane_width_m:.2f} m, {rec.density_per_lane_km:.1f} vehicles per lane-km; bootstrap of the "
            f"recorded statistics ({args.bootstrap} draws) ...")  # fmt: skip
        intervals = sampling_intervals(samples, reps=args.bootstrap, seed=args.seed)
        samples_stats = summarise(samples)
        tol = tolerances(samples_stats, intervals)

        def progress(it: int, total: int, cost: float, stats: dict[str, float]) -> None:
            within = sum(abs(stats[k] - samples_stats[k]) <= tol[k] for k in tol)
            crash = f", {stats['traffic_collisions']} traffic collisions" if stats["traffic_collisions"] else ""
            say(f"iteration {it}/{total}: {within} of {len(tol)} statistics within tolerance, distance "
                f"{distance(stats, samples_stats, tol):.3g}{crash}")

        result = calibrate(samples, intervals, size, base, options, progress)
    except (ValueError, FileNotFoundError, OSError) as exc:
        return error(str(exc))
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing was written", file=sys.stderr)
        return 130
    seconds = options.seconds_for(base)
    header = [f"lc-calibrate: the {scenario_label(args.base)} scenario with its traffic fitted to {args.data}",
              f"({len(rec.tracks)} episodes, {rec.seconds:.0f} s of traffic; seed {args.seed}, "
              f"{args.iterations} iterations of {args.episodes} x {seconds:g} s)"]  # fmt: skip
    text = scenario_text(result, args.out, header)
    report = {
        "data": str(args.data), "base": args.base, "options": dataclasses.asdict(options), "seconds": seconds,
        "bootstrap": args.bootstrap,
        "recorded_road": {"num_lanes": rec.num_lanes, "lane_width_m": rec.lane_width_m, "length_m": rec.length_m,
                          "width_m": rec.width_m, "density_per_lane_km": rec.density_per_lane_km,
                          "episodes": len(rec.tracks), "seconds": rec.seconds},
        "recorded": result.recorded, "intervals": result.intervals, "tolerance": result.tolerance,
        "default": result.default, "calibrated": result.calibrated,
        "within": {"default": result.within(result.default), "calibrated": result.within(result.calibrated)},
        "distance": {"default": result.distance(result.default), "calibrated": result.distance(result.calibrated)},
        "history": result.history, "scenario": result.scenario.to_dict(),
    }  # fmt: skip
    try:
        write_file(args.out, text)
        if args.json is not None:
            write_json(args.json, _finite(report))
    except OSError as exc:
        return error(str(exc))
    print(table(result))
    print()
    for line in summary_lines(result):
        print(line)
    t = result.scenario.traffic
    print(f"wrote {args.out}: {t.num_vehicles} vehicles on {result.scenario.road.num_lanes} lanes, desired speed "
          f"{t.speed_kmh:.1f} km/h (sd {t.speed_spread_kmh:.1f}), time gap {t.idm_time_headway_s:.2f} s, "
          f"lane changes {t.lane_change_duration_s:.1f} s" + (f"; {args.json}" if args.json else ""))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
