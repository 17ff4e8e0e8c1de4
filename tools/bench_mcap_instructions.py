#!/usr/bin/env python
"""Recording overhead counted in instructions of the simulator's process (valgrind's callgrind): the
figure of ``tools/bench_mcap.py`` that a busy host (CPU steal) does not move, for comparing writers.

For each scenario (lane-change: the paper's, with the rule-based driver and the image; corpus: 20
autopilot vehicles, cut to ``--corpus-steps`` steps so that it runs in minutes) and each way of running
(``bare``: the driver loop of ``record_episode`` without a recorder; a writer mode: ``record_episode``
with that writer), the same script runs under callgrind with 0 and with ``--episodes`` measured
episodes, after one warm-up episode of the same kind; the difference divided by the episodes is the
cost of one episode (start-up, imports and first-time costs cancel out). Overhead = recorded / bare - 1.

Callgrind counts every thread of the traced process, so ``thread`` includes the compression thread.
It does not trace the helper of ``process`` (its work runs on the other core); ``tools/bench_mcap.py``
reports that helper's CPU time. Each run takes about a minute plus ~20 s per measured episode.
Needs valgrind (Debian package ``valgrind``).

    python tools/bench_mcap_instructions.py                       # process writer, 2 episodes
    python tools/bench_mcap_instructions.py --writers process thread --json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tempfile

from callgrind import instructions, require_valgrind

_WORKLOAD = """
import dataclasses, sys
sys.path.insert(0, {tools!r})
from bench_mcap import run_bare
from lcdata import record_episode
from lcsim import corpus_scenario, paper_scenario
scenario, mode, episodes, corpus_steps, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
if scenario == "corpus":
    config, driver = corpus_scenario(), "autopilot"
    config = dataclasses.replace(config, time_limit_s=corpus_steps * config.dt_s)
else:
    config, driver = paper_scenario(), "rule"
def one(seed):
    if mode == "bare":
        run_bare(config, seed, driver)
    else:
        record_episode(config, seed, driver, f"{{out}}/{{seed}}.mcap", overwrite=True, writer=mode)
one(0)
for seed in range(1, episodes + 1):
    one(seed)
"""


def _instructions(scenario: str, mode: str, episodes: int, corpus_steps: int, out: str) -> int:
    code = _WORKLOAD.format(tools=str(pathlib.Path(__file__).resolve().parent))
    return instructions(code, scenario, mode, str(episodes), str(corpus_steps), out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("--episodes", type=int, default=2, help="measured episodes per run (default 2)")
    parser.add_argument("--corpus-steps", type=int, default=400, help="steps of a corpus episode (default 400)")
    parser.add_argument("--writers", nargs="+", choices=("process", "thread", "inline"), default=["process"],
                        help="writer modes to measure (default: process)")  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    if args.episodes < 1 or args.corpus_steps < 1:
        parser.error("--episodes and --corpus-steps must be >= 1")
    require_valgrind()
    result: dict[str, object] = {"episodes": args.episodes, "corpus_steps": args.corpus_steps}
    with tempfile.TemporaryDirectory(prefix="bench_mcap_instructions_") as out:
        for scenario in ("lane_change", "corpus"):
            name = scenario.replace("_", "-")
            per_episode = {}
            for mode in ("bare", *args.writers):
                n = _instructions(name, mode, args.episodes, args.corpus_steps, out)
                n0 = _instructions(name, mode, 0, args.corpus_steps, out)
                per_episode[mode] = (n - n0) / args.episodes
                result[f"{scenario}_{mode}_instructions_per_episode"] = round(per_episode[mode])
            for mode in args.writers:
                result[f"overhead_{scenario}_{mode}"] = round(per_episode[mode] / per_episode["bare"] - 1, 4)
            if not args.json:
                line = ", ".join(f"{mode} {100 * (per_episode[mode] / per_episode['bare'] - 1):.1f}%"
                                 for mode in args.writers)  # fmt: skip
                print(f"{name}: bare {per_episode['bare'] / 1e6:.0f} M instructions per episode; recording "
                      f"overhead in the simulator's process: {line}", flush=True)  # fmt: skip
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
