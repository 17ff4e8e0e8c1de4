"""Benchmark ``lc-view``'s conversion: a recorded 2000-step lane-change episode with 100 vehicles -> .rrd.

Records the episode once with the simulator (paper scenario, rule-based driver, a route long enough
that the episode runs to its 100 s time limit), then times :func:`lcdata.view.convert` (reading the
MCAP file, logging every stream with ``rr.send_columns`` and writing the ``.rrd``). Target: < 3 s.

    python tools/bench_view.py            # human-readable
    python tools/bench_view.py --json     # {"seconds": ..., ...}
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lcdata.record import record_episode  # noqa: E402
from lcdata.view import convert  # noqa: E402
from lcsim.config import paper_scenario  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="simulation steps (time limit = steps x dt)")
    parser.add_argument("--vehicles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3, help="conversions timed; the best is reported")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    base = paper_scenario()
    config = dataclasses.replace(
        base, traffic=dataclasses.replace(base.traffic, num_vehicles=args.vehicles),
        time_limit_s=args.steps * base.dt_s, route_length_m=5000.0,
    )  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        mcap = pathlib.Path(tmp) / "bench.mcap"
        t0 = time.perf_counter()
        result = record_episode(config, args.seed, "rule", mcap, scenario="paper")
        record_s = time.perf_counter() - t0
        times = []
        for i in range(args.repeat):
            start = time.perf_counter()
            (rrd,) = convert([mcap], pathlib.Path(tmp) / f"bench{i}.rrd")
            times.append(time.perf_counter() - start)
        out = {
            "seconds": min(times), "all_seconds": times, "steps": result.steps, "vehicles": args.vehicles + 1,
            "decisions": result.decisions, "mcap_bytes": result.bytes, "rrd_bytes": rrd.stat().st_size,
            "record_seconds": record_s,
        }  # fmt: skip
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{out['steps']} steps x {out['vehicles']} vehicles ({out['mcap_bytes'] / 1e6:.1f} MB MCAP): "
              f"converted to .rrd ({out['rrd_bytes'] / 1e6:.1f} MB) in {out['seconds']:.2f} s "
              f"(best of {len(times)}: {', '.join(f'{t:.2f}' for t in times)})")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
