"""``lc-view``: show recorded episodes (MCAP) in Rerun.

The command reads our MCAP files with :func:`lcdata.read_episode`, logs them with the columnar API
(:mod:`lcdata.viewer`) and sends them to the native viewer (default), an ``.rrd`` file (``--save``)
or a web viewer served on localhost (``--web``). ``--headless`` never opens a viewer.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import pathlib
import sys
import time
import warnings
from collections.abc import Sequence

import rerun as rr

from lcdata.reader import Episode, TruncatedFileWarning, list_episodes, read_episode
from lcdata.viewer import blueprint, describe, log_episode

log = logging.getLogger(__name__)

APPLICATION_ID = "lc-view"
EXIT_BAD_INPUT = 2

_EXAMPLES = """\
examples:
  lc-view runs/demo/lane-change_rule_s0000001.mcap          # open the native viewer
  lc-view runs/eval/*.mcap --side-by-side                   # compare episodes in one recording
  lc-view ep.mcap --save ep.rrd                             # write a Rerun file (open: rerun ep.rrd)
  lc-view ep.mcap --web --headless                          # serve a web viewer, print its address

A directory stands for every *.mcap file under it. With several episodes as separate recordings,
--save out.rrd writes one file per episode: out.<episode id>.rrd.
"""


class ViewError(Exception):
    """Bad input a person can fix (the message is one line)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Recording:
    """A Rerun recording and the episodes it holds (with their entity prefixes)."""

    stream: rr.RecordingStream
    episodes: list[tuple[Episode, str]]
    save_path: pathlib.Path | None = None


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid port {text!r}: not a whole number") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"invalid port {port}: must be in 1..65535")
    return port


def have_display() -> bool:
    """Whether a native viewer window could open here (on Linux: an X11 or Wayland display is set)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lc-view",
        description="Show recorded lane-change episodes (lc-toolkit MCAP files) in Rerun: the top-down "
        "scene, the bird's-eye semantic image, speed / reward / return / lane plots and the event log.",
        epilog=_EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("paths", nargs="+", type=pathlib.Path, metavar="PATH",
                        help="episode files (.mcap or .mcap.partial) or directories of them")  # fmt: skip
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


def open_episodes(paths: Sequence[pathlib.Path]) -> list[Episode]:
    """Read every episode; directories expand to the ``*.mcap`` files under them.

    Raises:
        ViewError: a missing path, an empty directory, or a file that is not an lc-toolkit MCAP file.
    Truncated files are read up to their last complete chunk, with a warning on stderr.
    """
    files: list[pathlib.Path] = []
    for p in paths:
        if p.is_dir():
            found = list_episodes(p, include_partial=True)
            if not found:
                raise ViewError(f"{p}: no .mcap files in this directory")
            files += found
        elif not p.exists():
            raise ViewError(f"{p}: no such file")
        else:
            files.append(p)
    episodes = []
    for f in files:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TruncatedFileWarning)
            try:
                episode = read_episode(f)
                _ = episode.tracks  # decode now, so that a corrupt file fails here with its name
            except (ValueError, OSError) as exc:
                raise ViewError(_one_line(exc, f)) from None
        for w in caught:
            if issubclass(w.category, TruncatedFileWarning):
                print(f"lc-view: warning: {w.message}; showing the recovered part", file=sys.stderr)
        episodes.append(episode)
    return episodes


def _one_line(exc: BaseException, path: pathlib.Path) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if str(path) in text else f"{path}: {text}"


def _unique_ids(episodes: Sequence[Episode]) -> list[str]:
    ids: list[str] = []
    for e in episodes:
        base = name = e.episode_id or e.path.stem
        k = 2
        while name in ids:
            name, k = f"{base}-{k}", k + 1
        ids.append(name)
    return ids


def make_recordings(episodes: Sequence[Episode], *, side_by_side: bool,
                    save: pathlib.Path | None = None) -> list[Recording]:  # fmt: skip
    """One recording per episode (recording id = episode id), or one with every episode side by side."""
    ids = _unique_ids(episodes)
    if side_by_side and len(episodes) > 1:
        rec = rr.RecordingStream(APPLICATION_ID, recording_id="side-by-side-" + "-".join(ids))
        pairs = [(e, f"episodes/{rr.escape_entity_path_part(i)}") for e, i in zip(episodes, ids, strict=True)]
        return [Recording(rec, pairs, save)]
    out = []
    for e, i in zip(episodes, ids, strict=True):
        target = save
        if save is not None and len(episodes) > 1:
            target = save.with_name(f"{save.name.removesuffix('.rrd')}.{i}.rrd")
        out.append(Recording(rr.RecordingStream(APPLICATION_ID, recording_id=i), [(e, "")], target))
    return out


def layout(recording: Recording) -> rr.blueprint.Blueprint:
    prefixes = [p for _, p in recording.episodes]
    return blueprint(prefixes, [p.rsplit("/", 1)[-1] for p in prefixes] if len(prefixes) > 1 else ())


def log_recording(recording: Recording) -> None:
    """Name the recording, store the episode summaries as properties and log every episode."""
    rec = recording.stream
    names = [e.episode_id for e, _ in recording.episodes]
    rec.send_recording_name(" | ".join(names))
    for episode, prefix in recording.episodes:
        summary = describe(episode)
        key = prefix.rsplit("/", 1)[-1] if prefix else "episode"
        rec.send_property(key, rr.AnyValues(**summary))
        start = time.perf_counter()
        log_episode(rec, episode, prefix)
        log.info("%s: logged in %.2f s", episode.path, time.perf_counter() - start)


def convert(
    paths: Sequence[pathlib.Path], save: pathlib.Path, *, side_by_side: bool = False
) -> list[pathlib.Path]:
    """Read episodes and write them to ``.rrd`` file(s); returns the files written (see ``--save``)."""
    recordings = make_recordings(open_episodes(paths), side_by_side=side_by_side, save=save)
    for r in recordings:
        assert r.save_path is not None
        r.save_path.parent.mkdir(parents=True, exist_ok=True)
        r.stream.save(r.save_path, default_blueprint=layout(r))
        log_recording(r)
        r.stream.flush()
        r.stream.disconnect()
    return [r.save_path for r in recordings if r.save_path is not None]


def serve(recordings: Sequence[Recording], *, grpc_port: int = 9876, web_port: int = 9090,
          open_browser: bool = False) -> str:  # fmt: skip
    """Serve ``recordings`` (also saving those with a ``save_path``) to a web viewer on localhost.

    Returns the web viewer's address. The servers live as long as the recording streams do.
    """
    uri = ""
    for i, r in enumerate(recordings):
        sinks: list[object] = []
        if i == 0:
            server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=grpc_port)
            uri = server.uri
            sinks.append(server)
        else:
            sinks.append(rr.GrpcSink(uri))
        if r.save_path is not None:
            sinks.append(rr.FileSink(r.save_path))
        rr.set_sinks(*sinks, default_blueprint=layout(r), recording=r.stream)
        log_recording(r)
        r.stream.flush()
    rr.serve_web_viewer(web_port=web_port, open_browser=open_browser, connect_to=uri)
    return f"http://localhost:{web_port}/?url={uri}"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``lc-view``; returns the exit status (2 for bad input)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    if args.save is not None and args.save.suffix != ".rrd":
        print(f"lc-view: error: --save {args.save}: the file name must end in .rrd", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not args.web and not args.headless and args.save is None and not have_display():
        print("lc-view: error: no display to open the native viewer on (DISPLAY is not set); write a file with "
              "--save OUT.rrd, or serve one with --web --headless", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        episodes = open_episodes(args.paths)
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


if __name__ == "__main__":
    sys.exit(main())
