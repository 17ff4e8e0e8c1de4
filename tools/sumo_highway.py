#!/usr/bin/env python
"""SUMO highway traffic for the trajectory corpus: traffic the predictor was not trained on.

Writes a SUMO scenario in plain XML (a straight 4-lane highway along +x, built into a ``.net.xml`` by the
package's ``netconvert``), runs ``sumo`` once per seed with ``--fcd-output`` and imports every FCD file
with ``lcdata.importers.import_sumo_fcd`` into the corpus layout (one ``.mcap`` per 100 s at 20 Hz) that
``lc-train-predictor`` and ``tools/bench_transfer.py`` read.

The traffic is SUMO's own, with the paper's numbers where it has them: Ford-Crown-sized cars
(5.37 x 1.80 m) whose desired speed is 24 km/h times a speed factor drawn per vehicle (normal, 10 %
spread by default), Krauss car following with its default driver imperfection, LC2013 lane changes
(to overtake slower cars, to keep right; how eagerly: ``--lc-speed-gain``, ``--lc-keep-right``) over 3 s,
0.05 s steps. At t = 0 the road already holds the initial vehicles (placed at random free positions over its
first part), and a random inflow on every lane keeps the density up while cars leave at the end. Everything random comes from the episode's seed, so the same
seed writes the same FCD, and episodes differ by seed.

    python tools/sumo_highway.py --episodes 4 --seed 1000 --out runs/sumo     # runs/sumo/{sumo/,corpus/}
    lc-train-predictor --data runs/sumo/corpus --out runs/predictor-sumo

Needs ``pip install -e ".[sumo]"`` (the eclipse-sumo wheel ships ``sumo`` and ``netconvert``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import pathlib
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

__all__ = ["HighwayOptions", "generate", "import_fcd", "sumo_available", "sumo_binary", "write_network"]

PROG = "sumo_highway.py"


@dataclass(frozen=True, slots=True, kw_only=True)
class HighwayOptions:
    """The scenario: road, cars, traffic, simulation."""

    lanes: int = 4
    """Lanes of the carriageway (SUMO index 0 the rightmost)."""
    road_length_m: float = 1500.0
    """Length of the straight road, metres."""
    lane_width_m: float = 3.5
    """Lane width, metres (Town06's)."""
    desired_speed_kmh: float = 24.0
    """Mean desired speed (the road's speed limit; each car's is this times its speed factor), km/h."""
    speed_factor_dev: float = 0.1
    """Standard deviation of the per-car speed factor (normal around 1, cut to [0.5, 1.5])."""
    vehicle_length_m: float = 5.37
    """Car length, metres (CARLA's Ford Crown)."""
    vehicle_width_m: float = 1.80
    """Car width, metres."""
    sigma: float = 0.5
    """Krauss driver imperfection in [0, 1] (SUMO's default 0.5; 0 drives perfectly smoothly)."""
    initial_vehicles: int = 40
    """Cars on the road at t = 0, at random free places (SUMO's ``departPos="random_free"``)."""
    inflow_per_lane_hz: float = 0.12
    """Probability per second and lane that a car enters at the start of the road."""
    duration_s: float = 100.0
    """Simulated time, seconds (100 s = one 2000-step corpus episode at 20 Hz)."""
    step_length_s: float = 0.05
    """SUMO's step, seconds (the corpus's 20 Hz)."""
    action_step_s: float = 0.05
    """Drivers' decision interval (SUMO's action step length), seconds: each car picks its acceleration
    this often and holds it in between, like a reaction time (SUMO's default: every simulation step)."""
    precision: int = 2
    """Decimals of the FCD output (SUMO's default 2: positions to the centimetre, which at 20 Hz is a
    velocity noise of up to 0.2 m/s in a one-step difference, like a real sensor's)."""
    lane_change_duration_s: float = 3.0
    """Time a lane change takes, seconds: the car moves sideways over it (SUMO's default, 0, jumps)."""
    lc_speed_gain: float = 1.0
    """LC2013's eagerness to change lanes to gain speed (``lcSpeedGain``, SUMO's default 1; 0 never does)."""
    lc_keep_right: float = 1.0
    """LC2013's eagerness to return to the right (``lcKeepRight``, SUMO's default 1; 0 never does)."""

    def __post_init__(self) -> None:
        for name in ("lanes", "initial_vehicles", "precision"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < (1 if name == "lanes" else 0):
                raise ValueError(f"{name} must be an integer >= {1 if name == 'lanes' else 0}, got {value!r}")
        for name in ("road_length_m", "lane_width_m", "desired_speed_kmh", "vehicle_length_m", "vehicle_width_m",
                     "duration_s", "step_length_s", "lane_change_duration_s", "action_step_s"):  # fmt: skip
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        for name in ("lc_speed_gain", "lc_keep_right"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and 0 <= value <= 100):
                raise ValueError(f"{name} must be in [0, 100], got {value!r}")
        if not 0 <= self.speed_factor_dev < 0.5:
            raise ValueError(f"speed_factor_dev must be in [0, 0.5), got {self.speed_factor_dev!r}")
        if not 0 <= self.sigma <= 1:
            raise ValueError(f"sigma must be in [0, 1], got {self.sigma!r}")
        if not 0 <= self.inflow_per_lane_hz <= 1:
            raise ValueError(f"inflow_per_lane_hz must be in [0, 1], got {self.inflow_per_lane_hz!r}")


DEFAULTS = HighwayOptions()


def sumo_available() -> bool:
    """Whether the eclipse-sumo package (with its binaries) is installed."""
    try:
        sumo_binary("sumo")
        sumo_binary("netconvert")
    except RuntimeError:
        return False
    return True


def sumo_binary(name: str) -> pathlib.Path:
    """Path of a binary of the eclipse-sumo package (``sumo``, ``netconvert``); ``RuntimeError`` if missing."""
    try:
        import sumo  # the eclipse-sumo wheel
    except ImportError:
        raise RuntimeError('eclipse-sumo is not installed (pip install -e ".[sumo]")') from None
    path = pathlib.Path(sumo.SUMO_HOME) / "bin" / name
    if not path.is_file():
        raise RuntimeError(f"the eclipse-sumo package has no {name} binary at {path}")
    return path


def _run(cmd: Sequence[str | os.PathLike[str]], what: str) -> None:
    env = dict(os.environ)
    import sumo

    env["SUMO_HOME"] = str(sumo.SUMO_HOME)
    done = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        lines = [line for line in (done.stderr or done.stdout).splitlines() if line.strip()]
        raise RuntimeError(f"{what} failed (exit {done.returncode}): {lines[-1] if lines else 'no message'}")


def write_network(folder: pathlib.Path, options: HighwayOptions) -> pathlib.Path:
    """The road as plain XML (``highway.nod.xml``, ``highway.edg.xml``) and ``highway.net.xml`` from netconvert."""
    folder.mkdir(parents=True, exist_ok=True)
    o = options
    (folder / "highway.nod.xml").write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<nodes>\n'
        '    <node id="start" x="0.00" y="0.00" type="priority"/>\n'
        f'    <node id="end" x="{o.road_length_m:.2f}" y="0.00" type="priority"/>\n'
        "</nodes>\n"
    )
    speed = o.desired_speed_kmh / 3.6
    (folder / "highway.edg.xml").write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<edges>\n'
        f'    <edge id="road" from="start" to="end" priority="1" numLanes="{o.lanes}" speed="{speed:.4f}" '
        f'width="{o.lane_width_m:.2f}"/>\n'
        "</edges>\n"
    )
    net = folder / "highway.net.xml"
    _run([sumo_binary("netconvert"), "--node-files", folder / "highway.nod.xml", "--edge-files",
          folder / "highway.edg.xml", "--output-file", net, "--no-turnarounds", "true", "--no-warnings", "true"],
         "netconvert")  # fmt: skip
    return net


def write_routes(path: pathlib.Path, options: HighwayOptions) -> pathlib.Path:
    """The car type, the initial cars and one random inflow per lane (``highway.rou.xml``)."""
    o = options
    lo, hi = max(0.5, 1 - 4 * o.speed_factor_dev), 1 + 4 * o.speed_factor_dev
    speed_factor = f"normc(1.00,{o.speed_factor_dev:.3f},{lo:.2f},{hi:.2f})" if o.speed_factor_dev else "1"
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<routes>",
        f'    <vType id="crown" vClass="passenger" length="{o.vehicle_length_m:.2f}" width="{o.vehicle_width_m:.2f}" '
        f'minGap="2.5" accel="2.6" decel="4.5" sigma="{o.sigma:.3f}" speedFactor={quoteattr(speed_factor)} '
        f'carFollowModel="Krauss" laneChangeModel="LC2013" lcSpeedGain="{o.lc_speed_gain:g}" '
        f'lcKeepRight="{o.lc_keep_right:g}"/>',
        '    <route id="straight" edges="road"/>',
    ]
    for i in range(o.initial_vehicles):  # SUMO draws lane and place from the run's seed
        lines.append(f'    <vehicle id="init{i:03d}" type="crown" route="straight" depart="0" departLane="random" '
                     'departPos="random_free" departSpeed="desired" arrivalPos="max"/>')  # fmt: skip
    if o.inflow_per_lane_hz > 0:
        for lane in range(o.lanes):
            lines.append(f'    <flow id="in{lane}" type="crown" route="straight" begin="0" end="{o.duration_s:.2f}" '
                         f'probability="{o.inflow_per_lane_hz:.4f}" departLane="{lane}" departPos="base" '
                         'departSpeed="desired" arrivalPos="max"/>')  # fmt: skip
    lines.append("</routes>\n")
    path.write_text("\n".join(lines))
    return path


def run_episode(folder: pathlib.Path, net: pathlib.Path, routes: pathlib.Path, options: HighwayOptions,
                seed: int) -> pathlib.Path:  # fmt: skip
    """Simulate one episode with ``seed``; returns its FCD file ``fcd_s<seed>.xml`` in ``folder``."""
    fcd = folder / f"fcd_s{seed:07d}.xml"
    _run([sumo_binary("sumo"), "--net-file", net, "--route-files", routes, "--begin", "0",
          "--end", f"{options.duration_s:.3f}", "--step-length", f"{options.step_length_s:.4f}", "--seed", str(seed),
          "--default.action-step-length", f"{options.action_step_s:.4f}",
          "--fcd-output", fcd, "--fcd-output.acceleration", "true",
          "--fcd-output.attributes", "x,y,angle,speed,lane,type,acceleration",
          "--precision", str(options.precision),
          "--lanechange.duration", f"{options.lane_change_duration_s:.3f}", "--collision.action", "warn", "--no-step-log", "true",
          "--no-warnings", "true", "--duration-log.disable", "true"], f"sumo (seed {seed})")  # fmt: skip
    return fcd


def generate(out: pathlib.Path, episodes: int, seed: int, options: HighwayOptions | None = None,
             progress: Callable[[int, int], None] | None = None) -> list[pathlib.Path]:  # fmt: skip
    """Write the scenario under ``out`` and simulate ``episodes`` episodes with seeds ``seed, seed+1, ...``.

    Returns the FCD files, one per episode, in seed order. ``RuntimeError`` if SUMO is missing or fails.
    """
    if not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    options = options or HighwayOptions()
    out.mkdir(parents=True, exist_ok=True)
    net = write_network(out, options)
    routes = write_routes(out / "highway.rou.xml", options)
    (out / "options.json").write_text(_options_json(options))
    files = []
    for i in range(episodes):
        files.append(run_episode(out, net, routes, options, seed + i))
        if progress is not None:
            progress(i + 1, episodes)
    return files


def _options_json(options: HighwayOptions) -> str:
    import json

    return json.dumps(dataclasses.asdict(options), indent=2, sort_keys=True) + "\n"


def import_fcd(files: Sequence[pathlib.Path], corpus: pathlib.Path, *, overwrite: bool = False) -> list[pathlib.Path]:
    """Import FCD files into ``corpus`` as 20 Hz episodes (``lcdata.importers.import_sumo_fcd``); the files written."""
    from lcdata.importers import SumoOptions, import_sumo_fcd

    written = []
    for fcd in files:
        written += [e.path for e in import_sumo_fcd(fcd, corpus, sumo=SumoOptions(vehicle_length_m=5.37,
                                                                                  vehicle_width_m=1.80),
                                                    overwrite=overwrite)]  # fmt: skip
    return written


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        print(f"{PROG}: error: {message} (see --help)", file=sys.stderr)
        raise SystemExit(2)


def main(argv: Sequence[str] | None = None) -> int:
    p = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=pathlib.Path, required=True,
                   help="output folder: OUT/sumo (scenario, FCD files) and OUT/corpus (.mcap episodes)")
    p.add_argument("--episodes", type=int, default=4, help="episodes, one SUMO run each (default 4)")
    p.add_argument("--seed", type=int, default=1000, help="seed of the first episode (default 1000)")
    p.add_argument("--duration", type=float, default=DEFAULTS.duration_s, metavar="S",
                   help=f"simulated seconds per episode (default {DEFAULTS.duration_s:g})")
    p.add_argument("--initial-vehicles", type=int, default=DEFAULTS.initial_vehicles,
                   help=f"cars on the road at t = 0 (default {DEFAULTS.initial_vehicles})")
    p.add_argument("--inflow", type=float, default=DEFAULTS.inflow_per_lane_hz, metavar="P",
                   help=f"probability per second and lane of a new car (default {DEFAULTS.inflow_per_lane_hz:g})")
    p.add_argument("--speed-kmh", type=float, default=DEFAULTS.desired_speed_kmh,
                   help=f"mean desired speed (default {DEFAULTS.desired_speed_kmh:g})")
    p.add_argument("--speed-dev", type=float, default=DEFAULTS.speed_factor_dev,
                   help=f"spread of the speed factor (default {DEFAULTS.speed_factor_dev:g})")
    p.add_argument("--sigma", type=float, default=DEFAULTS.sigma,
                   help=f"Krauss driver imperfection in [0, 1] (default {DEFAULTS.sigma:g})")
    p.add_argument("--action-step", type=float, default=DEFAULTS.action_step_s, metavar="S",
                   help=f"drivers' decision interval, seconds (default {DEFAULTS.action_step_s:g})")
    p.add_argument("--lane-change-duration", type=float, default=DEFAULTS.lane_change_duration_s, metavar="S",
                   help=f"time a lane change takes, seconds (default {DEFAULTS.lane_change_duration_s:g})")
    p.add_argument("--lc-speed-gain", type=float, default=DEFAULTS.lc_speed_gain, metavar="X",
                   help=f"eagerness to change lanes for speed, LC2013's lcSpeedGain (default {DEFAULTS.lc_speed_gain:g})")
    p.add_argument("--lc-keep-right", type=float, default=DEFAULTS.lc_keep_right, metavar="X",
                   help=f"eagerness to return to the right, LC2013's lcKeepRight (default {DEFAULTS.lc_keep_right:g})")
    p.add_argument("--overwrite", action="store_true", help="replace the episodes of an earlier run in OUT/corpus")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress")
    try:
        args = p.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)

    def error(msg: str) -> int:
        print(f"{PROG}: error: {' '.join(str(msg).split())}", file=sys.stderr)
        return 2

    if args.episodes < 1:
        return error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        options = HighwayOptions(duration_s=args.duration, initial_vehicles=args.initial_vehicles,
                                 inflow_per_lane_hz=args.inflow, desired_speed_kmh=args.speed_kmh,
                                 speed_factor_dev=args.speed_dev, sigma=args.sigma,
                                 action_step_s=args.action_step, lane_change_duration_s=args.lane_change_duration,
                                 lc_speed_gain=args.lc_speed_gain, lc_keep_right=args.lc_keep_right)  # fmt: skip
        if not sumo_available():
            sumo_binary("sumo")  # raises with the reason
        corpus = args.out / "corpus"
        if corpus.exists() and any(corpus.glob("*.mcap")) and not args.overwrite:
            return error(f"{corpus} already holds episodes; choose another --out or pass --overwrite")

        def progress(done: int, total: int) -> None:
            if not args.quiet:
                print(f"sumo episode {done}/{total}", file=sys.stderr)

        files = generate(args.out / "sumo", args.episodes, args.seed, options, progress)
        written = import_fcd(files, corpus, overwrite=args.overwrite)
    except (ValueError, RuntimeError, OSError) as exc:
        return error(str(exc))
    print(f"wrote {len(files)} SUMO episodes to {args.out / 'sumo'} and {len(written)} corpus files to {corpus}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
