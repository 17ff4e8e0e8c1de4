"""``lc-import``: bring traffic recorded elsewhere (SUMO FCD, highD tracks) into the trajectory corpus."""

from __future__ import annotations

import argparse
import contextlib
import functools
import pathlib
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING

from lccli.common import fail, float_in, int_at_least, positive_float, setup_logging

if TYPE_CHECKING:
    from lcdata.importers import ImportedEpisode, ImportOptions

PROG = "lc-import"
EXAMPLES = """\
examples:
  sumo -c highway.sumocfg --fcd-output fcd.xml --step-length 0.1
  lc-import sumo-fcd fcd.xml --out data/sumo
  lc-import highd highD/data/01_tracks.csv --out data/highd      # 01_tracksMeta.csv is read beside it
  lc-train-predictor --data data/highd --out runs/predictor-highd

The episodes are the corpus's: 20 Hz (source samples interpolated linearly), 2000 steps (100 s) per
file, each vehicle's centre in a frame with x forward, y to the left and lane 0 the rightmost lane.
Files: OUT/sumo_<stem>_<i>.mcap, OUT/highd_<XX>_dir<1|2>_<i>.mcap (highD's two driving directions are
separate episodes, each turned to drive +x). The same input gives the same bytes. Files of an earlier
import of the same source are kept unless --overwrite; a failed import writes nothing.

Limits: a value that is not finite or not plausible (a time, position, speed, acceleration, vehicle size,
lane or id; lcdata.importers.limits) is refused, naming the file, line or data row and field. An import
spans at most --max-duration seconds of source time and writes at most --max-steps steps (by default
{per} per source sample read, and as many vehicle-steps per vehicle-step read: a gap in the source or a
small --dt cannot fill the disk). The episodes are written to OUT/.<name>.import-staging first and moved
into place at the end; Ctrl-C or SIGTERM removes that folder, and one left by an import that was killed
outright is removed by the next import of the same source (nothing is resumed).
See docs/INTERFACES.md (Importers) for the conventions and what is dropped.
"""


class UsageError(Exception):
    """Bad command-line input: one line on stderr, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see {self.prog} --help)")


def _common(p: argparse.ArgumentParser) -> None:
    from lcdata.importers import CORPUS_DT_S, CORPUS_EPISODE_STEPS
    from lcdata.importers.limits import (
        DEFAULT_MAX_DURATION_S,
        MAX_ABS_TIME_S,
        MAX_DT_S,
        MIN_DT_S,
        STEPS_PER_SAMPLE,
    )
    from lcsim.config import ScenarioConfig

    p.add_argument("--out", type=pathlib.Path, required=True, help="output directory (created if missing)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the episodes of an earlier import of the same source in --out")
    p.add_argument("--dt", type=float_in(MIN_DT_S, MAX_DT_S), default=CORPUS_DT_S, metavar="SECONDS",
                   help=f"step of the written episodes, {MIN_DT_S:g} to {MAX_DT_S:g} (default {CORPUS_DT_S:g}: the "
                   "corpus's 20 Hz)")
    p.add_argument("--episode-steps", type=int_at_least(1, ScenarioConfig.MAX_STEPS), default=CORPUS_EPISODE_STEPS,
                   metavar="N", help=f"steps per episode file; a longer recording is cut (default "
                   f"{CORPUS_EPISODE_STEPS}, at most {ScenarioConfig.MAX_STEPS})")
    p.add_argument("--min-episode-steps", type=int_at_least(1, ScenarioConfig.MAX_STEPS), default=20, metavar="N",
                   help="skip an episode whose traffic spans fewer steps (default 20: 1 s)")
    p.add_argument("--max-duration", type=float_in(MIN_DT_S, 2 * MAX_ABS_TIME_S), default=DEFAULT_MAX_DURATION_S,
                   metavar="SECONDS", help=f"refuse a source whose times span more than this (default "
                   f"{DEFAULT_MAX_DURATION_S:g}: a day)")
    p.add_argument("--max-steps", type=int_at_least(1), default=None, metavar="N",
                   help=f"refuse an import that would write more steps than this, all episodes together (default: "
                   f"{STEPS_PER_SAMPLE} per source sample read, and {STEPS_PER_SAMPLE} vehicle-steps per vehicle-step "
                   "read; raise it to bridge a long gap in the source)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="log what was read")


def build_parser() -> argparse.ArgumentParser:
    from lcdata.importers.limits import STEPS_PER_SAMPLE

    p = _Parser(
        prog=PROG,
        description="Import traffic recorded elsewhere into the trajectory corpus: one MCAP episode file per\n"
        "100 s, as lc-record --scenario corpus writes them, for lc-train-predictor and lc-view.\n"
        "lc-import FORMAT --help describes a format.",
        epilog=EXAMPLES.format(per=STEPS_PER_SAMPLE),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="format", metavar="FORMAT", required=True, parser_class=_Parser)
    sumo = sub.add_parser(
        "sumo-fcd", help="SUMO floating car data (sumo --fcd-output FILE.xml)",
        description="Import the XML of sumo --fcd-output (read as a stream: any size). Positions are SUMO's\n"
        "front bumper moved half a vehicle length back; angle is SUMO's heading (degrees clockwise from\n"
        "north); lane <edge>_<i> keeps SUMO's index (0 = rightmost), internal (junction) lanes are -1.",
        epilog="example:\n  lc-import sumo-fcd fcd.xml --out data/sumo",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    sumo.add_argument("file", type=pathlib.Path, metavar="FILE.xml", help="the FCD output file")
    _common(sumo)
    sumo.add_argument("--vehicle-length", type=positive_float, default=5.0, metavar="M",
                      help="length of a vehicle whose element has no length attribute (default 5.0, SUMO's car)")
    sumo.add_argument("--vehicle-width", type=positive_float, default=1.8, metavar="M",
                      help="width of a vehicle whose element has no width attribute (default 1.8)")
    highd = sub.add_parser(
        "highd", help="highD-layout drone tracks (XX_tracks.csv and XX_tracksMeta.csv)",
        description="Import a highD recording: XX_tracks.csv with XX_tracksMeta.csv beside it. Bounding-box\n"
        "corners become centres; the two driving directions become separate episodes, each turned (not\n"
        "mirrored) to drive +x with lane 0 the rightmost.",
        epilog="example:\n  lc-import highd highD/data/01_tracks.csv --out data/highd",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    highd.add_argument("file", type=pathlib.Path, metavar="TRACKS.csv", help="the XX_tracks.csv file")
    highd.add_argument("--meta", type=pathlib.Path, default=None, metavar="META.csv",
                       help="the tracks meta file (default: XX_tracksMeta.csv beside TRACKS.csv)")
    _common(highd)
    highd.add_argument("--frame-rate", type=positive_float, default=25.0, metavar="HZ",
                       help="video frame rate of the recording (default 25, highD's)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``lc-import``; returns the exit code (2 for bad input, one line on stderr)."""
    error = functools.partial(fail, PROG)
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:
        return error(str(exc))
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    setup_logging(PROG, verbose=args.verbose)
    from tqdm import tqdm

    from lcdata.importers import ImportOptions

    bar: tqdm | None = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        if args.quiet:
            return
        if bar is None:
            unit = ("B", True) if args.format == "sumo-fcd" else ("frame", False)
            bar = tqdm(total=total, unit=unit[0], unit_scale=unit[1], desc=args.file.name, disable=None)
        bar.update(done - bar.n)

    from lckit.fileio import check_output_folder

    try:
        check_output_folder(args.out)
    except ValueError as exc:
        return error(str(exc))
    if args.format == "highd" and args.meta is None and not args.file.name.endswith("_tracks.csv"):
        return error(f"{args.file}: a highD tracks file is named XX_tracks.csv, its meta file XX_tracksMeta.csv "
                     "beside it; name the meta file with --meta")
    stopped: list[int] = []
    try:
        options = ImportOptions(dt_s=args.dt, episode_steps=args.episode_steps, min_episode_steps=args.min_episode_steps,
                                max_duration_s=args.max_duration, max_steps=args.max_steps)  # fmt: skip
        with _sigterm_interrupts(stopped):
            written = _import(args, options, progress)
    except FileExistsError as exc:
        return error(str(exc).replace("overwrite=True", "--overwrite"))
    except (ValueError, OSError) as exc:
        return error(str(exc))
    except KeyboardInterrupt as exc:
        what = "SIGTERM" if stopped else "interrupted"
        done = "its episodes were all written" if getattr(exc, "published", False) else "nothing was written"
        print(f"{PROG}: {what}; {done}", file=sys.stderr)
        return 128 + (stopped[0] if stopped else signal.SIGINT)
    finally:
        if bar is not None:
            bar.close()
    steps = sum(e.steps for e in written)
    print(f"imported {len(written)} episode{'s' * (len(written) != 1)} ({steps} steps, {steps * args.dt:.1f} s of "
          f"traffic, {sum(e.rows for e in written)} vehicle-steps) from {args.file} to {args.out}")  # fmt: skip
    return 0


def _import(args: argparse.Namespace, options: ImportOptions, progress: Callable[[int, int], None]
            ) -> list[ImportedEpisode]:  # fmt: skip
    from lcdata.importers import HighdOptions, SumoOptions, import_highd, import_sumo_fcd

    if args.format == "sumo-fcd":
        sumo = SumoOptions(vehicle_length_m=args.vehicle_length, vehicle_width_m=args.vehicle_width)
        return import_sumo_fcd(args.file, args.out, options, sumo, overwrite=args.overwrite, progress=progress)
    return import_highd(args.file, args.out, options, HighdOptions(frame_rate_hz=args.frame_rate), meta=args.meta,
                        overwrite=args.overwrite, progress=progress)  # fmt: skip


@contextlib.contextmanager
def _sigterm_interrupts(stopped: list[int]) -> Iterator[None]:
    """SIGTERM raises ``KeyboardInterrupt`` in the block, as Ctrl-C does, so that the import cleans up as it does
    for Ctrl-C (its staging folder removed); ``stopped`` gets the signal's number. The handler before is put
    back at the end (no handler outside the main thread, where Python cannot set one)."""

    def handler(signum: int, _frame: object) -> None:
        stopped.append(signum)
        raise KeyboardInterrupt

    try:
        before = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


if __name__ == "__main__":
    raise SystemExit(main())
