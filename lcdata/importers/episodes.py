"""Resampled frames -> corpus episode files, written all together or not at all.

:func:`write_episodes` cuts the grid frames of :func:`~lcdata.importers.resample.resample` into episodes
of ``episode_steps`` steps and writes each with :class:`~lcdata.writer.EpisodeWriter` (``/vehicles`` at
every step, the metadata record ``lc``), as ``lc-record --scenario corpus`` does, so every reader of
recorded episodes reads them. The files go to a staging folder inside the output folder first and are
moved into place when the whole source has been read: a bad line near the end of a big file leaves the
output folder as it was, and no file is ever half-written under its final name.

The staging folder ``.<stem>.import-staging`` holds a lock (``flock``) while its import runs. An import that
ends by an exception, Ctrl-C or SIGTERM (``lc-import`` turns SIGTERM into the same path as Ctrl-C) removes it;
one killed outright (SIGKILL, a power cut) leaves it, and the next import of the same source into the same
folder finds its lock free and removes it (the import starts again from the beginning: nothing is resumed),
while one whose lock is held, by an import still running, is refused. Moving the staged files into place runs
with SIGINT and SIGTERM held back, so a signal cannot leave some episodes of an import published and others
not.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import pathlib
import re
import shutil
import signal
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lcdata.importers.limits import (
    DEFAULT_MAX_DURATION_S,
    MAX_ABS_TIME_S,
    MAX_DT_S,
    MIN_DT_S,
    STEPS_PER_SAMPLE,
)
from lcdata.importers.resample import Frame
from lcdata.record import SEED_EPOCH_NS
from lcdata.writer import EpisodeWriter
from lckit.fileio import folder_lock
from lcsim.config import ScenarioConfig, corpus_scenario

log = logging.getLogger(__name__)

_CORPUS = corpus_scenario()
CORPUS_DT_S: float = _CORPUS.dt_s
"""The corpus step (``lc-record --scenario corpus``): 0.05 s, 20 Hz."""
CORPUS_EPISODE_STEPS: int = _CORPUS.max_steps
"""Steps of one corpus episode: 2000 (100 s)."""

Progress = Callable[[int, int], None]
"""``progress(done, total)``: how far an import is (units are the importer's: bytes read, frames)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class ImportOptions:
    """How recorded traffic becomes corpus episodes (every format)."""

    dt_s: float = CORPUS_DT_S
    """Step of the written episodes, s (the corpus's 0.05 s unless a predictor is trained at another rate)."""
    episode_steps: int = CORPUS_EPISODE_STEPS
    """Steps per episode file: a longer recording is cut into consecutive episodes of this length."""
    min_episode_steps: int = 20
    """An episode (the last piece of a recording, or a stretch with little traffic) whose vehicles span
    fewer steps than this is not written."""
    max_duration_s: float = DEFAULT_MAX_DURATION_S
    """The source time an import may span, first sample to last (a day): a later time is refused."""
    max_steps: int | None = None
    """The most grid steps an import writes, all episodes together; None: at most
    :data:`~lcdata.importers.limits.STEPS_PER_SAMPLE` per source sample read so far (and as many vehicle-rows
    per vehicle-row read), what a gap in the source or a small ``dt_s`` would otherwise exceed."""

    def __post_init__(self) -> None:
        if not (isinstance(self.dt_s, int | float) and MIN_DT_S <= self.dt_s <= MAX_DT_S):
            raise ValueError(f"dt_s must be in [{MIN_DT_S:g}, {MAX_DT_S:g}] s, got {self.dt_s!r}")
        for name in ("episode_steps", "min_episode_steps"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= ScenarioConfig.MAX_STEPS:
                raise ValueError(f"{name} must be an integer in [1, {ScenarioConfig.MAX_STEPS}], got {value!r}")
        span = self.max_duration_s
        if not (isinstance(span, int | float) and math.isfinite(span) and 0 < span <= 2 * MAX_ABS_TIME_S):
            raise ValueError(f"max_duration_s must be in (0, {2 * MAX_ABS_TIME_S:g}] s, got {span!r}")
        steps = self.max_steps
        if steps is not None and (not isinstance(steps, int) or isinstance(steps, bool) or steps < 1):
            raise ValueError(f"max_steps must be an integer >= 1 or None ({STEPS_PER_SAMPLE} per source sample), "
                             f"got {steps!r}")  # fmt: skip
        if self.min_episode_steps > self.episode_steps:
            raise ValueError(f"min_episode_steps ({self.min_episode_steps}) must be <= episode_steps "
                             f"({self.episode_steps})")  # fmt: skip


@dataclass(frozen=True, slots=True)
class ImportedEpisode:
    """One episode file an import wrote."""

    path: pathlib.Path
    steps: int
    """Steps written (the first and last hold at least one vehicle)."""
    vehicles: int
    rows: int
    """Vehicle-steps (rows of ``Episode.tracks``)."""


HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""Held back while the staged episodes move into place (:meth:`EpisodeFiles._publish`)."""


class EpisodeFiles:
    """The episode files of one source in ``out``, named ``<stem><part>_<index:04d>.mcap`` where ``part``
    matches the regular expression ``parts`` (e.g. ``_dir[12]``; :attr:`pattern` matches every name).

    A context: the files are written to :meth:`staged` paths and moved into ``out`` when the block ends
    normally (the files of an earlier import of the source that this one did not rewrite are removed then);
    when it raises, nothing in ``out`` changes.
    """

    STAGING_SUFFIX = ".import-staging"
    STAGED_SUFFIX = ".staged"
    LOCK_NAME = ".lock"

    def __init__(self, out: str | os.PathLike[str], stem: str, *, overwrite: bool, parts: str = "") -> None:
        self.out = pathlib.Path(out)
        self.stem = stem
        self.pattern = re.compile(rf"{re.escape(stem)}{parts}_\d{{4,}}\.mcap")
        self.overwrite = overwrite
        if self.out.exists() and not self.out.is_dir():
            raise NotADirectoryError(f"output {self.out} exists and is not a directory")
        self.existing = sorted(p for p in self.out.glob("*.mcap") if self.pattern.fullmatch(p.name)) \
            if self.out.is_dir() else []  # fmt: skip
        if self.existing and not overwrite:
            raise FileExistsError(f"{len(self.existing)} episode file(s) of this source already exist in {self.out} "
                                  f"(e.g. {self.existing[0].name}); pass overwrite=True to replace them")  # fmt: skip
        self.staging = self.out / f".{stem}{self.STAGING_SUFFIX}"

    def __enter__(self) -> EpisodeFiles:
        self.created = not self.out.exists()  # a failed import removes an output folder it made
        self.out.mkdir(parents=True, exist_ok=True)
        if self.staging.is_dir() and not self.staging.is_symlink():
            self._remove_stale()
        try:
            self.staging.mkdir()
        except FileExistsError:
            raise ValueError(f"{self.staging} is in the way: another import of this source into {self.out} is "
                             "starting, or a file of that name is there") from None  # fmt: skip
        self._lock = contextlib.ExitStack()
        try:
            self._lock.enter_context(folder_lock(self.staging, "import of this source", self.LOCK_NAME,
                                                 doing="is writing into"))  # fmt: skip
        except BaseException:
            shutil.rmtree(self.staging, ignore_errors=True)
            raise
        return self

    def _remove_stale(self) -> None:
        """Remove a staging folder whose import is gone (its lock free); refuse while its import runs, and when its
        lock file is a link (no import made it: opening it would write where it points)."""
        if (self.staging / self.LOCK_NAME).is_symlink():
            raise ValueError(f"{self.staging / self.LOCK_NAME} is a link, not a lock an import made; remove "
                             f"{self.staging} if nothing is importing into {self.out}")  # fmt: skip
        with folder_lock(self.staging, "import of this source", self.LOCK_NAME, doing="is writing into"):
            left = len(list(self.staging.glob(f"*{self.STAGED_SUFFIX}")))
            shutil.rmtree(self.staging)  # with the lock held: no other import starts in it meanwhile
        log.warning("removed %s, left by an import that did not finish (%d staged files; not resumed)",
                    self.staging, left)  # fmt: skip

    def __exit__(self, exc_type: type[BaseException] | None, *_: object) -> None:
        try:
            if exc_type is None:
                self._publish()
        finally:
            shutil.rmtree(self.staging, ignore_errors=True)  # with its lock held: no other import removes it
            self._lock.close()
            if exc_type is not None and self.created and not any(self.out.iterdir()):
                self.out.rmdir()

    def staged(self, name: str) -> pathlib.Path:
        """Where the episode file ``name`` is written until the import succeeds (not ``*.mcap``: a reader of
        the output folder, which looks into subfolders too, does not see it)."""
        return self.staging / f"{name}{self.STAGED_SUFFIX}"

    def _publish(self) -> None:
        written = sorted(self.staging.glob(f"*{self.STAGED_SUFFIX}"))
        names = {p.name.removesuffix(self.STAGED_SUFFIX) for p in written}
        stale = [p for p in self.existing if p.name not in names]
        try:
            with _signals_held():  # all of them in place, or (killed outright) each one whole
                for path in written:
                    os.replace(path, self.out / path.name.removesuffix(self.STAGED_SUFFIX))
                for path in stale:  # an earlier import of the same source cut into more episodes
                    path.unlink()
        except KeyboardInterrupt as exc:  # held back while the files moved: they are all in place
            exc.published = True  # type: ignore[attr-defined]
            raise
        if stale:
            log.info("removed %d episode files of an earlier import of this source", len(stale))


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back in the block: their handlers run when it ends (Python handles signals in the
    main thread only; elsewhere nothing is held)."""
    caught: list[int] = []
    try:
        before = {s: signal.signal(s, lambda signum, _frame: caught.append(signum)) for s in HELD_SIGNALS}
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        for s in dict.fromkeys(caught):
            signal.raise_signal(s)


def write_episodes(grid: Iterable[tuple[int, Frame]], files: EpisodeFiles, prefix: str,
                   metadata: Mapping[str, Any], options: ImportOptions,
                   vehicle_info: Callable[[np.ndarray], dict[str, Any]]) -> list[ImportedEpisode]:  # fmt: skip
    """Write the grid frames ``(k, frame)`` (ascending ``k``) as episodes ``<prefix>_<k // E:04d>.mcap``.

    Episode ``i`` holds the grid steps ``i * E .. (i + 1) * E - 1`` (``E = options.episode_steps``), renumbered
    from 0, without the empty steps before its first vehicle and after its last; it is written when that span
    is at least ``options.min_episode_steps``. The metadata record holds ``metadata`` and, per episode,
    ``episode_index``, ``source_start_s`` (source time of step 0) and ``vehicles`` (``vehicle_info(ids)``:
    where each vehicle id comes from). ``t = 0`` of the file is 2024-01-01T00:00:00Z plus ``source_start_s``,
    so the same input gives the same bytes.
    """
    e = options.episode_steps
    written: list[ImportedEpisode] = []
    pending: list[tuple[int, Frame]] = []
    episode = -1

    def flush() -> None:
        rows = [(k, f) for k, f in pending if len(f.ids)]
        if not rows or rows[-1][0] - rows[0][0] + 1 < options.min_episode_steps:
            return
        first, last = rows[0][0], rows[-1][0]
        start = episode * e
        start_s = pending[0][1].t_s - (pending[0][0] - start) * options.dt_s
        ids = np.unique(np.concatenate([f.ids for _, f in rows]))
        name = f"{prefix}_{episode:04d}.mcap"
        path = files.staged(name)
        meta = {**metadata, "episode_id": name.removesuffix(".mcap"), "episode_index": episode,
                "source_start_s": round(start_s, 9), "vehicles": vehicle_info(ids)}  # fmt: skip
        with EpisodeWriter(path, metadata=meta, start_time_ns=SEED_EPOCH_NS + round(start_s * 1e9)) as writer:
            for k, f in pending:
                if first <= k <= last:
                    step = k - start
                    writer.write_vehicles(step, step * options.dt_s, f.ids, f.x, f.y, f.yaw, f.speed, f.accel,
                                          f.lane, f.lane, f.length, f.width)  # fmt: skip
        written.append(ImportedEpisode(files.out / name, last - first + 1, len(ids),
                                       sum(len(f.ids) for _, f in rows)))  # fmt: skip

    for k, frame in grid:
        if k // e != episode:
            flush()
            pending, episode = [], k // e
        pending.append((k, frame))
    flush()
    return written


def check_written(source: pathlib.Path, written: list[ImportedEpisode], options: ImportOptions) -> None:
    """``ValueError`` when an import with vehicles wrote no episode (every stretch shorter than the minimum)."""
    if not written:
        raise ValueError(f"{source}: no stretch of traffic lasts {options.min_episode_steps} steps "
                         f"({options.min_episode_steps * options.dt_s:g} s); nothing written")  # fmt: skip
