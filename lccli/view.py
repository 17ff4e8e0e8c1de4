"""``lc-view``: show recorded episodes (MCAP) in Rerun: the native viewer (default), an ``.rrd`` file
(``--save``) or a web viewer served on localhost (``--web``); ``--headless`` never opens a viewer."""

from __future__ import annotations

import argparse
import pathlib
import sys
import time
from collections.abc import Sequence

from lccli.common import setup_logging
from lcdata.viewer.app import (
    EXIT_BAD_INPUT,
    ViewError,
    describe,
    have_display,
    layout,
    log_recording,
    make_recordings,
    open_episodes,
    serve,
)

_EXAMPLES = """\
examples:
  lc-view runs/demo/lane-change_rule_s0000001.mcap          # open the native viewer
  lc-view runs/eval/*.mcap --side-by-side                   # compare episodes in one recording
  lc-view ep.mcap --save ep.rrd                             # write a Rerun file (open: rerun ep.rrd)
  lc-view ep.mcap --web --headless                          # serve a web viewer, print its address

A directory stands for every *.mcap file under it. With several episodes as separate recordings,
--save out.rrd writes one file per episode: out.<episode id>.rrd.
"""


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid port {text!r}: not a whole number") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"invalid port {port}: must be in 1..65535")
    return port


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lc-view",
        description="Show recorded lane-change episodes (lc-toolkit MCAP files) in Rerun: the top-down "
        "scene, the bird's-eye semantic image, speed / reward / return / lane plots and the event log; for a driver "
        "behind the safety layer, what it scored for each candidate decision and the futures it imagined "
        "(lc-record --imagined-paths).",
        epilog=_EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("paths", nargs="+", type=pathlib.Path, metavar="PATH",
                        help="episode files (.mcap or .mcap.partial) or directories of them, or zoo:NAME (a shipped "
                        "policy: one held-out episode of it is recorded into a temporary directory and shown)")  # fmt: skip
    parser.add_argument("--save", type=pathlib.Path, metavar="OUT.rrd",
                        help="write the recording(s) to this .rrd file instead of opening the native viewer")  # fmt: skip
    parser.add_argument("--web", action="store_true",
                        help="serve a web viewer on localhost and keep running until Ctrl-C")  # fmt: skip
    parser.add_argument("--headless", action="store_true",
                        help="never open a viewer (with --web: serve without opening a browser)")  # fmt: skip
    parser.add_argument("--side-by-side", action="store_true",
                        help="put several episodes side by side in one recording (default: one recording each)")  # fmt: skip
    parser.add_argument("--web-port", type=_port, default=9090, help="web viewer port (default: %(default)s)")
    parser.add_argument(
        "--grpc-port", type=_port, default=9876, help="data server port for --web (default: %(default)s)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace .rrd files that --save would write")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    return parser



def _zoo_episode(name: str) -> pathlib.Path:
    """One held-out episode (lc-eval's seed 0, the first) driven by zoo policy ``name``, recorded into a temporary
    directory; ``ViewError`` for a name the zoo does not have."""
    import tempfile

    from lcmodels.policy.driverspec import parse_driver_spec
    from lcmodels.policy.evaluate import driver_for, evaluate

    try:
        driver, config = driver_for(parse_driver_spec(name))
    except ValueError as exc:
        raise ViewError(str(exc).splitlines()[0]) from None
    out = pathlib.Path(tempfile.mkdtemp(prefix="lc-view-zoo-"))
    evaluate(driver, config, episodes=1, seed=0, out_dir=out, scenario=name.replace(":", "-"))
    print(f"lc-view: recorded one held-out episode of {name} in {out}", flush=True)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``lc-view``; returns the exit status (2 for bad input)."""
    args = build_parser().parse_args(argv)
    setup_logging("lc-view", verbose=args.verbose)
    if args.save is not None and args.save.suffix != ".rrd":
        print(f"lc-view: error: --save {args.save}: the file name must end in .rrd", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not args.web and not args.headless and args.save is None and not have_display():
        print("lc-view: error: no display to open the native viewer on (DISPLAY is not set); write a file with "
              "--save OUT.rrd, or serve one with --web --headless", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        paths = [_zoo_episode(str(p)) if str(p).startswith("zoo:") else p for p in args.paths]
        episodes = open_episodes(paths)
    except ViewError as exc:
        print(f"lc-view: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    for e in episodes:
        s = describe(e)
        print(f"{e.path}: {s['episode_id']} driver={s['driver']} seed={s['seed']} outcome={s['outcome']} "
              f"return={s['return']:.1f}")  # fmt: skip
    recordings = make_recordings(episodes, side_by_side=args.side_by_side, save=args.save)
    existing = [r.save_path for r in recordings if r.save_path is not None and r.save_path.exists()]
    if existing and not args.overwrite:
        print(f"lc-view: error: {existing[0]} already exists; pass --overwrite or choose another --save",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.web:
        try:
            url = serve(
                recordings, grpc_port=args.grpc_port, web_port=args.web_port, open_browser=not args.headless
            )
        except (OSError, RuntimeError, ValueError) as exc:  # a port in use, a server that would not start
            print(f"lc-view: error: could not serve the web viewer: {str(exc).splitlines()[0] if str(exc) else exc!r}",
                  file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f"lc-view: web viewer at {url} (Ctrl-C to stop)", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        return 0
    for r in recordings:
        if r.save_path is not None:
            r.save_path.parent.mkdir(parents=True, exist_ok=True)
            r.stream.save(r.save_path, default_blueprint=layout(r))
        elif not args.headless:
            try:
                r.stream.spawn(default_blueprint=layout(r))
            except Exception as exc:  # no viewer binary, a display that refuses the window
                print(f"lc-view: error: could not open the native viewer ({type(exc).__name__}: "
                      f"{' '.join(str(exc).split())[:200]}); use --save OUT.rrd or --web --headless", file=sys.stderr)
                return EXIT_BAD_INPUT
        log_recording(r)
        r.stream.flush()
        if r.save_path is not None:
            r.stream.disconnect()
            print(f"lc-view: wrote {r.save_path}")
    return 0


