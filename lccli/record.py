"""``lc-record``: run the simulator with a driver and write one MCAP file per episode."""

from __future__ import annotations

import argparse
import collections
import contextlib
import dataclasses
import json
import pathlib
import sys
import time
from collections.abc import Sequence

from tqdm import tqdm

from lccli.common import (
    add_executor_arguments,
    add_safety_layer_arguments,
    given_safety_settings,
    int_at_least,
    safety_layer_from_args,
    setup_logging,
    zoo_spec,
)
from lcdata.record import DRIVERS, MAX_USER_SEED, episode_filename, iter_record_episodes
from lcdata.writer import MAX_START_TIME_NS
from lcdata.writer_process import WRITER_MODES
from lcmodels.policy.driverspec import DriverSpec, parse_driver_spec, split_policy_spec, split_safety_layer
from lcsim.config import ScenarioConfig
from lcsim.planning import MAX_IMAGINED_FUTURES, rule_behind_layer
from lcsim.registry import SCENARIOS, scenario, scenario_label
from lcsim.suite import SEALED_SEED_BASE, SEALED_SEED_END, is_sealed


def default_driver(scenario_name: str) -> str:
    """Who drives when ``--driver`` is not given: the traffic's autopilot in the corpus, else the rule."""
    return "autopilot" if scenario_name == "corpus" else "rule"


EXAMPLES = """\
examples:
  lc-record --scenario paper --episodes 100 --seed 0 --driver rule --out runs/rule --workers 2
  lc-record --scenario corpus --episodes 50 --out data/corpus      # 20 autopilot vehicles, 2000 steps
  lc-record --scenario light --driver safety-layer:rule --imagined-paths 1 --out runs/thought   # what it thought

Episode i uses seed S+i and is written to OUT/<scenario>_<driver>_s<seed>.mcap (7-digit seed), e.g.
runs/rule/paper_rule_s0000003.mcap, so the files do not depend on --workers. Files are written
as .mcap.partial and renamed when the episode ends. The same command gives the same bytes: each
file's start time derives from its seed (--start-time changes that).

OUT/record.json keeps, per scenario and driver, the flags that decide the files' content. Rerunning
the same command on an interrupted OUT records only the missing episodes and leaves the finished ones
as they are; other flags for the same scenario and driver there are refused, naming the difference.
"""
RECORD_JSON = "record.json"
LOCK_NAME = ".lc-record.lock"
"""Held (``flock``) while a recording writes in ``--out``: a second ``lc-record`` there is refused."""


class UsageError(Exception):
    """Bad command-line input: reported as one line on stderr, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(message)


positive_int = int_at_least(1)
_non_negative_int = int_at_least(0)


def _driver_spec(text: str) -> str:
    """The words of ``--driver`` that lc-record takes (a built-in driver, or a policy file or the rule-based driver
    named with a prefix); :func:`_parse_driver` reads them, with the safety layer's settings."""
    text = zoo_spec(text)
    if text in DRIVERS or split_policy_spec(text):
        return text
    raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from {', '.join(DRIVERS)}, policy:CKPT, "
                                     "zoo:NAME, safety-layer:CKPT, safety-layer:rule)")


def _imagined_paths(text: str) -> int:
    value = _non_negative_int(text)
    if value > MAX_IMAGINED_FUTURES:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_IMAGINED_FUTURES}, got {value}")
    return value


def _parse_driver(text: str, args: argparse.Namespace) -> DriverSpec:
    """The driver ``text`` names, parsed once with the safety layer's settings (``--follow``, ``--set``)."""
    if text == "autopilot":  # the simulator's mode: the traffic's autopilot drives the ego
        return DriverSpec(text=text, kind="driver", name=text)
    if not split_policy_spec(text) and (args.follow is not None or args.settings):
        raise UsageError("--follow and --set safety.KEY=VALUE need --driver safety-layer:CKPT (a policy behind "
                         "the safety layer) or safety-layer:rule")
    try:
        layer = safety_layer_from_args(text, args) if split_policy_spec(text) else None
        return parse_driver_spec(text, safety_table=layer)
    except ValueError as exc:
        raise UsageError(str(exc).splitlines()[0]) from None


def _is_layered_rule(spec: DriverSpec) -> bool:
    """Whether a driver is the rule-based driver behind the safety layer built here (``safety-layer:rule`` and
    its older spellings with a prefix; the built-in ``lookahead`` drivers are made by name where they record)."""
    return spec.text not in DRIVERS and spec.kind == "driver" and spec.layer is not None


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="lc-record",
        description="Run the lane-change simulator with a driver and record one MCAP file per episode\n"
        "(tracks and ego sensors at 20 Hz; image, scene and RL step per decision).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scenario", default=None, metavar="{" + ",".join(SCENARIOS) + ",FILE}",
                   help="paper: the paper's task (100 vehicles, 600 m route); light, tiny: smaller versions of it; "
                   "corpus: the trajectory corpus (20 autopilot vehicles, 2000 steps, no image); or a scenario "
                   "file (.toml/.json of ScenarioConfig fields). Default: paper; a policy drives in its own")  # fmt: skip
    p.add_argument("--episodes", type=positive_int, default=1, help="number of episodes (default: 1)")
    p.add_argument("--seed", type=int_at_least(0, MAX_USER_SEED), default=0,
                   help=f"seed of the first episode (default: 0; at most {MAX_USER_SEED})")
    p.add_argument("--driver", type=_driver_spec, default=None,
                   metavar="{" + ",".join(DRIVERS) + ",policy:CKPT,safety-layer:CKPT,safety-layer:rule}",
                   help="who drives the ego (default: autopilot for corpus, else rule); "
                   "policy:CKPT drives with a trained policy (a policy.safetensors from lc-train-policy); "
                   "safety-layer:CKPT with that policy behind the safety layer (older spellings: lookahead:CKPT, "
                   "lookahead-blind:CKPT), safety-layer:rule the rule-based driver behind it. Behind the layer, "
                   "/planner/decision holds what the layer scored for right / keep / left at each decision with a "
                   "choice (lc-view draws it)")  # fmt: skip
    add_safety_layer_arguments(p)
    p.add_argument("--imagined-paths", type=_imagined_paths, default=0, metavar="K",
                   help="behind the safety layer: also record the ego's path in K of the futures the layer imagined "
                   f"for each candidate decision (at most {MAX_IMAGINED_FUTURES}, and there are safety.samples; "
                   "default 0: none). The decisions are the same with and without")  # fmt: skip
    p.add_argument("--out", type=pathlib.Path, required=True, help="output directory (created if missing)")
    p.add_argument("--workers", type=positive_int, default=1, help="parallel processes (default: 1)")
    p.add_argument("--overwrite", action="store_true", help="replace episode files that already exist")
    p.add_argument("--vehicles", type=_non_negative_int, default=None,
                   help="override the number of traffic vehicles (default: the scenario's)")  # fmt: skip
    p.add_argument("--steps", type=positive_int, default=None,
                   help="override the episode time limit, in simulation steps (default: the scenario's)")  # fmt: skip
    p.add_argument("--no-images", action="store_true", help="do not record the bird's-eye image")
    p.add_argument("--start-time", default="seed", metavar="{seed,now,ISO-8601}",
                   help="the wall-clock time of t = 0 in each file: seed (default: 2024-01-01T00:00:00Z plus the "
                   "episode's seed in seconds, so that the same command writes the same bytes), now, or a time "
                   "such as 2025-06-01T12:00:00Z for every episode")
    add_executor_arguments(p, "each episode a Ray task (built-in drivers)", "--workers processes here")
    p.add_argument("--writer", choices=WRITER_MODES, default=None,
                   help="where files are encoded and compressed: process (a helper process, on the core "
                   "the simulator leaves idle), thread, or inline; the files are the same. Default: process "
                   "with --workers 1, thread with more")  # fmt: skip
    p.add_argument("-v", "--verbose", action="store_true", help="log every episode")
    return p


def scenario_config(name: str, *, vehicles: int | None = None, steps: int | None = None) -> ScenarioConfig:
    """The scenario of a name or file (:func:`lcsim.registry.scenario`) with optional overrides (ValueError
    names an unknown scenario or an impossible value)."""
    config = scenario(name)
    if vehicles is not None:
        config = dataclasses.replace(config, traffic=dataclasses.replace(config.traffic, num_vehicles=vehicles))
    if steps is not None:
        config = dataclasses.replace(config, time_limit_s=steps * config.dt_s)
    return config


def _check_out_dir(out: pathlib.Path) -> None:
    """``UsageError`` when ``--out`` cannot take the recording (the filesystem root, the home directory, a file,
    a folder nothing can be written in); nothing is created."""
    from lckit.fileio import check_output_folder

    try:
        check_output_folder(out)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _check_targets(paths: list[pathlib.Path]) -> None:
    """``UsageError`` when a file lc-record writes (or its ``.partial``) is a symbolic link: nothing is written
    through one (:func:`lckit.fileio.check_target`)."""
    from lckit.fileio import UnsafePathError, check_target

    try:
        for path in paths:
            check_target(path)
    except UnsafePathError as exc:
        raise UsageError(str(exc)) from None


def _make_out_dir(out: pathlib.Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"cannot create output directory {out}: {exc.strerror or exc}") from None


def start_time_ns(text: str) -> int | None:
    """``--start-time``: None for ``seed`` (each file's own, from its seed), the clock for ``now``, else an
    ISO-8601 time (UTC when it names no zone). ``UsageError`` for anything else."""
    import datetime

    if text == "seed":
        return None
    if text == "now":
        return time.time_ns()
    try:
        when = datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise UsageError(f"--start-time {text!r} is not seed, now or an ISO-8601 time "
                         "(e.g. 2025-06-01T12:00:00Z)") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=datetime.UTC)
    ns = int(when.timestamp()) * 1_000_000_000 + when.microsecond * 1000
    if ns < 0:
        raise UsageError(f"--start-time {text!r} is before 1970")
    if ns > MAX_START_TIME_NS:  # a message's time is t = 0 plus the episode's, in 64-bit nanoseconds
        raise UsageError(f"--start-time {text!r} is after 2262-01-01, the last time a recording's 64-bit "
                         "nanosecond clock can hold")
    return ns


def record_flags(args: argparse.Namespace, driver: DriverSpec, scenario_name: str,
                 content: dict[str, object] | None = None) -> dict[str, object]:
    """The flags that decide what the episode files hold (``OUT/record.json``); --seed, --episodes,
    --workers and --writer only decide which files are written, and how fast. ``content``: the scenario's
    fields when they come from elsewhere than its name (a policy's card), else read from the name."""
    flags: dict[str, object] = {
        "scenario": scenario_name, "driver": driver.text,
        "scenario_config": content if content is not None else _scenario_content(scenario_name),
        "vehicles": args.vehicles, "steps": args.steps,
        "images": not args.no_images, "start_time": args.start_time if args.start_time != "now" else None,
        "lookahead_follow": args.follow,  # the safety layer's follower and settings given (names kept: resumable)
        "lookahead": given_safety_settings(args),
    }  # fmt: skip
    if args.imagined_paths:  # only when asked: the flags of earlier recordings stay what they were
        flags["imagined_paths"] = args.imagined_paths
    if driver.kind == "policy":
        from lckit.fileio import file_sha256

        for key, spec in (("driver_sha256", driver), ("lookahead_follow_sha256", driver.follow)):
            if spec is not None and spec.kind == "policy" and spec.path.is_file():
                flags[key] = file_sha256(spec.path)
    return json.loads(json.dumps(flags))  # as record.json holds them (lists, not tuples)


def _read_record_json(out: pathlib.Path) -> dict[str, dict[str, object]]:
    """``OUT/record.json``: the flags of each set of episodes there, by file-name prefix (scenario_driver)."""
    from lckit.fileio import loads_json

    record = out / RECORD_JSON
    if not record.exists():
        return {}
    try:
        runs = loads_json(record.read_text()).get("runs")
        if not isinstance(runs, dict) or not all(isinstance(v, dict) for v in runs.values()):
            raise ValueError("no 'runs' object of flags")
    except (OSError, ValueError, AttributeError) as exc:
        raise UsageError(f"{record} is corrupt ({exc}); remove it or choose another --out") from None
    return runs


def _scenario_content(name: str) -> dict[str, object] | None:
    """What a scenario name or file holds now (so that an edited scenario file is a difference)."""
    try:
        return scenario(name).to_dict()
    except ValueError:
        return None


def _check_resume(out: pathlib.Path, key: str, flags: dict[str, object], paths: list[pathlib.Path],
                  overwrite: bool) -> bool:
    """Whether this run resumes the one in ``out`` (same flags, some of its episodes there). ``UsageError``
    when the episodes of this scenario and driver there were recorded with other flags, or when episode
    files are there without their flags in ``record.json`` (unless ``overwrite``)."""
    existing = [p for p in paths if p.exists()]
    before = _read_record_json(out).get(key)
    if overwrite:
        others = sorted(set(out.glob(f"{key}_s*.mcap")) - set(paths))
        if before is not None and before != flags and others:
            raise UsageError(f"{len(others)} other episodes of this scenario and driver in {out} (e.g. "
                             f"{others[0].name}) were recorded with other flags, which --overwrite of these seeds "
                             "would leave behind; overwrite them too or use another --out")
        return False
    if before is not None:
        diffs = [f"{k}: {before.get(k)!r} there, {flags.get(k)!r} now" for k in sorted(set(before) | set(flags))
                 if before.get(k) != flags.get(k)]
        if diffs:
            raise UsageError(f"{out} holds a recording with other flags ({'; '.join(diffs)}); use another --out, "
                             "or --overwrite to replace these episodes")
        return bool(existing)
    if existing:
        raise UsageError(f"{len(existing)} of {len(paths)} episodes already exist in {out} "
                         f"(e.g. {existing[0].name}); pass --overwrite to replace them")  # fmt: skip
    return False


def _policy_driver(spec: DriverSpec, args: argparse.Namespace, config: ScenarioConfig):
    """A trained policy as the driver, and the scenario it was trained on (images as asked)."""
    if args.scenario is not None or args.vehicles is not None or args.steps is not None:
        raise UsageError("a policy drives in the scenario it was trained on; drop --scenario / --vehicles / --steps")
    if not spec.path.is_file():
        raise UsageError(f"policy checkpoint {spec.path} does not exist")
    from lcmodels.policy.evaluate import driver_for  # lcmodels builds on lcdata: import only when asked

    try:
        policy, policy_config = driver_for(spec)
    except ValueError as exc:
        raise UsageError(str(exc).splitlines()[0]) from None
    return policy, dataclasses.replace(policy_config, render_image=policy_config.render_image or not args.no_images)


def _policy_scenario_label(spec: DriverSpec) -> str:
    """The scenario name a policy was trained in, from its card (the label of its recordings)."""
    from lcmodels.policy.checkpoint import read_meta

    return str(read_meta(spec.path).get("scenario_name") or "paper")


def record_main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``lc-record``; returns the exit code (2 for bad input)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        scenario_name = args.scenario or "paper"
        try:
            config = scenario_config(scenario_name, vehicles=args.vehicles, steps=args.steps)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        text = args.driver or default_driver(scenario_name)
        if args.imagined_paths and split_safety_layer(text)[1] is None:
            raise UsageError(f"--imagined-paths: {text} imagines no futures; a driver behind the safety layer does "
                             "(safety-layer:rule, safety-layer:CKPT, lookahead-blind)")  # fmt: skip
        spec = _parse_driver(text, args)
        driver: object = spec.text  # a built-in driver records by name
        content = None
        if _is_layered_rule(spec):
            if args.executor == "ray":
                raise UsageError(f"--executor ray records built-in drivers by name; {text} is built here "
                                 "(record it with the local executor)")  # fmt: skip
            assert spec.layer is not None
            driver = rule_behind_layer(spec.layer, spec.text)
        elif spec.kind == "policy":
            if args.executor == "ray":
                raise UsageError("--executor ray records built-in drivers; a policy drives in this process "
                                 "(lc-eval --executor ray shards a policy's episodes)")
            driver, config = _policy_driver(spec, args, config)
            scenario_name = _policy_scenario_label(spec)
            if scenario_name not in SCENARIOS:  # a scenario file's name: its fields are the card's, not the file's
                content = config.to_dict()
        label = scenario_label(scenario_name)
        start_ns = start_time_ns(args.start_time)
        if args.seed + args.episodes - 1 > MAX_USER_SEED:
            raise UsageError(f"--seed {args.seed} with --episodes {args.episodes} reaches seed "
                             f"{args.seed + args.episodes - 1}; seeds go up to {MAX_USER_SEED} (the last whose "
                             "start time, 2024 plus the seed in seconds, a recording can hold)")  # fmt: skip
        seeds = [args.seed + i for i in range(args.episodes)]
        if any(is_sealed(s) for s in (seeds[0], seeds[-1])) or seeds[0] < SEALED_SEED_BASE <= seeds[-1]:
            raise UsageError(f"seeds {SEALED_SEED_BASE} to {SEALED_SEED_END - 1} are the benchmark's sealed test "
                             "episodes, which only lc-bench --final runs; choose others")
        name = driver if isinstance(driver, str) else driver.name
        paths = [args.out / episode_filename(label, name, s) for s in seeds]
        flags = record_flags(args, spec, scenario_name, content)
        _check_out_dir(args.out)
        _check_targets([args.out / RECORD_JSON, args.out / LOCK_NAME, *paths])
        key = paths[0].name.rsplit("_s", 1)[0]  # the scenario_driver prefix of the file names
        if args.out.is_dir():
            _check_resume(args.out, key, flags, paths, args.overwrite)
    except UsageError as exc:
        print(f"lc-record: error: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    # Every check has passed: from here on --out is written, by this process alone (a second lc-record there is
    # refused rather than recording the same files at once).
    from lckit.fileio import UnsafePathError, folder_lock

    try:
        _make_out_dir(args.out)
        with folder_lock(args.out, "lc-record", LOCK_NAME):
            return _record(args, config, driver, label, seeds, paths, key, flags, start_ns)
    except (UsageError, ValueError, UnsafePathError) as exc:  # a link or a foreign lock: refused, not failed
        print(f"lc-record: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except (OSError, RuntimeError) as exc:  # a full disk, a folder removed while recording, the writer failing
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc).splitlines()[0]
        print(f"lc-record: error: recording into {args.out} failed: {why}; the episodes not finished are left as "
              ".partial files: rerun the same command to record them", file=sys.stderr)
        return 1


def _record(args: argparse.Namespace, config: ScenarioConfig, driver: object, label: str, seeds: list[int],
            paths: list[pathlib.Path], key: str, flags: dict[str, object], start_ns: int | None) -> int:
    """Record the episodes (``--out`` made and locked): ``record.json``, then the missing episode files."""
    from lckit.fileio import write_json

    name = driver if isinstance(driver, str) else driver.name  # type: ignore[attr-defined]
    resume = _check_resume(args.out, key, flags, paths, args.overwrite)  # again: another run may have finished
    setup_logging("lc-record", verbose=args.verbose)
    write_json(args.out / RECORD_JSON, {"runs": {**_read_record_json(args.out), key: flags}})
    todo = [s for s, p in zip(seeds, paths, strict=True) if args.overwrite or not p.exists()]
    if resume:
        print(f"lc-record: resuming {args.out}: {len(seeds) - len(todo)} of {len(seeds)} episodes are there "
              f"already (kept as they are), recording the {len(todo)} missing", file=sys.stderr)
    outcomes: collections.Counter[str] = collections.Counter()
    messages = size = 0
    start = time.perf_counter()
    workers = args.workers if isinstance(driver, str) else 1  # a loaded policy stays in this process
    session = contextlib.nullcontext()
    if args.executor == "ray":
        from lcdata.executors import ray_session

        session = ray_session(args.ray_address)
    try:
        with session, tqdm(total=len(todo), unit="ep", desc=f"{label}/{name}", disable=None) as bar:
            for result in iter_record_episodes(config, todo, driver, args.out, scenario=label, workers=workers,
                                               overwrite=args.overwrite, images=not args.no_images,
                                               writer=args.writer, start_time_ns=start_ns,
                                               executor=args.executor,
                                               imagined_paths=args.imagined_paths):  # fmt: skip
                outcomes[result.outcome] += 1
                messages += result.messages
                size += result.bytes
                bar.set_postfix_str(", ".join(f"{k} {v}" for k, v in sorted(outcomes.items())))
                bar.update()
    except ValueError as exc:  # Ray missing or unreachable
        print(f"lc-record: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lc-record: interrupted; unfinished episodes are left as .partial files; rerun the same command to "
              "record the missing ones", file=sys.stderr)
        return 130
    seconds = time.perf_counter() - start
    done = sum(outcomes.values())
    if done == 0:
        print(f"all {len(seeds)} episodes are in {args.out} already; nothing to record")
        return 0
    summary = ", ".join(f"{k} {v} ({100 * v / done:.1f}%)" for k, v in sorted(outcomes.items()))
    print(f"recorded {done} episodes to {args.out}: {summary}")
    print(f"{messages} messages, {size / 1e6:.1f} MB, {seconds:.1f} s ({done / seconds:.2f} episodes/s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(record_main())
