"""The library behind ``lc-view``: recorded episodes (MCAP) to Rerun recordings, files and servers.

:func:`open_episodes` reads our MCAP files with :func:`lcdata.read_episode`, logs them with the columnar API
(:mod:`lcdata.viewer`) and sends them to the native viewer (default), an ``.rrd`` file (``--save``)
or a web viewer served on localhost (``--web``). ``--headless`` never opens a viewer.
"""

from __future__ import annotations

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
from lcdata.viewer import blueprint, describe, log_episode, views_with_data
from lcdata.viewer.geometry import check_grid_size
from lcdata.viewer.streams import road_shape, road_x_range

log = logging.getLogger(__name__)

APPLICATION_ID = "lc-view"
EXIT_BAD_INPUT = 2


class ViewError(Exception):
    """Bad input a person can fix (the message is one line)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Recording:
    """A Rerun recording and the episodes it holds (with their entity prefixes)."""

    stream: rr.RecordingStream
    episodes: list[tuple[Episode, str]]
    save_path: pathlib.Path | None = None


def open_episodes(paths: Sequence[pathlib.Path]) -> list[Episode]:
    """Read every episode; directories expand to the ``*.mcap`` files under them.

    Raises:
        ViewError: a missing path, an empty directory, a file that is not an lc-toolkit MCAP file or that the
            reader refuses (over its limits, duplicated messages), tracks no viewer grid could hold, a road
            that cannot be drawn.
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
                tracks = episode.tracks  # decode now, so that a corrupt file fails here with its name
                check_grid_size(tracks["step"].nunique(), tracks["vehicle_id"].nunique(), len(tracks))
                road_shape(episode.metadata["config"], road_x_range(tracks))
            except (ValueError, OSError) as exc:
                raise ViewError(_one_line(exc, f)) from None
        for w in caught:
            if issubclass(w.category, TruncatedFileWarning):
                log.warning("%s; showing the recovered part", w.message)
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
    """The recording's blueprint, with views only for the data its episodes have."""
    prefixes = [p for _, p in recording.episodes]
    titles = [p.rsplit("/", 1)[-1] for p in prefixes] if len(prefixes) > 1 else []
    return blueprint(prefixes, titles, [views_with_data(e) for e, _ in recording.episodes])


def log_recording(recording: Recording) -> None:
    """Name the recording, store the episode summaries as properties and log every episode."""
    rec = recording.stream
    names = [e.episode_id for e, _ in recording.episodes]
    rec.send_recording_name(" | ".join(names))
    for index, (episode, prefix) in enumerate(recording.episodes):
        summary = describe(episode)
        key = prefix.rsplit("/", 1)[-1] if prefix else "episode"
        rec.send_property(key, rr.AnyValues(**summary))
        start = time.perf_counter()
        log_episode(rec, episode, prefix, index)
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


def have_display() -> bool:
    """Whether a native viewer window could open here (on Linux: an X11 or Wayland display is set)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
