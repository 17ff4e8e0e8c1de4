"""The stage store of an experiment directory: which stages are complete, the record of each, the lock that keeps
a second invocation out, and the list of invocations.

``stages/<stage>.json`` is written when a stage completes: its config, the content hashes of its inputs (the
outputs of the stages it reads) and the SHA-256 of each of its own outputs. A stage whose record matches the
current config and inputs and whose outputs still hash to the recorded values is complete; anything else is
redone. ``stages/<stage>.pending.json`` is written when a stage starts: a stage interrupted with the same config
and inputs continues from what it left (``keep``); one whose config or inputs changed starts from an empty
directory.

Records are files anyone can edit: a stage's folder and every output its record names must resolve inside the
experiment directory (else one line refuses the run, naming the record), and a record that does not read as
one (outputs null, times that are not numbers) makes its stage stale. Folders are emptied and records written
with :mod:`lckit.fileio`'s helpers: never through a link, never out of the directory.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lckit.fileio import UnsafePathError, check_inside, make_folder, remove_file, remove_tree
from lcmodels.experiment.keys import StageKey
from lcmodels.fileio import file_sha256, read_json, write_json
from lcmodels.presets import INVOCATIONS, LOCK_NAME, MARKER, STAGES_DIR, StageResult, canonical

Config = dict[str, Any]
Upgrade = Callable[[Config], Config]
"""A stored config in today's form (a field added since it was recorded, at the value it stood for)."""
Resumable = Callable[[Config, Config], bool]
"""Whether a stage interrupted (or complete) under the first config continues under the second."""


def record_paths(out: str | Path, key: StageKey) -> tuple[Path, Path]:
    """``(complete record, pending record)`` of stage ``key`` in the experiment directory ``out``."""
    base = Path(out) / STAGES_DIR / key.record_name
    return base.with_suffix(".json"), base.with_suffix(".pending.json")


def well_formed(rec: Any) -> bool:
    """Whether ``rec`` reads as a stage record: a dict whose config and inputs are tables, whose ``outputs`` (when
    complete) map names to hashes and whose times are numbers. Anything else (a file edited, or written by
    something else) is no record: the stage reruns."""
    if not isinstance(rec, dict):
        return False
    outputs = rec.get("outputs", {})
    times = [rec[k] for k in ("wall_s", "wall_s_parts") if k in rec]
    return (isinstance(outputs, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in outputs.items())
            and all(isinstance(rec.get(k, {}), dict) for k in ("config", "inputs"))
            and all(isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t) for t in times))


def read_record(out: str | Path, key: StageKey) -> dict[str, Any] | None:
    """The complete record of stage ``key`` in ``out`` (None when it has none, or none that reads as one)."""
    rec = read_json(record_paths(out, key)[0])
    return rec if well_formed(rec) else None


def hash_outputs(base: Path, names: Sequence[str]) -> dict[str, str] | None:
    """SHA-256 of each file ``names`` under ``base``; None when one is missing. A name that leads out of ``base``
    (an absolute path, ``..``, a link to elsewhere: a record edited by hand) is refused in one line
    (:class:`~lckit.fileio.UnsafePathError`): a stage's outputs are its own files."""
    out = {}
    for name in names:
        p = check_inside(base / name, base, f"output {name!r} of {base}")
        if not p.is_file():
            return None
        out[name] = file_sha256(p)
    return out


@dataclass(frozen=True)
class Verdict:
    """What the store holds of a stage against its current config and inputs."""

    complete: bool
    why: str
    """``new``, ``resuming an interrupted run``, ``stale: ...``, ``outputs missing or changed`` (empty if complete)."""
    keep: bool = False
    """The stage's directory holds a prefix of the work (same inputs, same or a resumable config)."""
    wall_before: float = 0.0
    """Recorded wall time of the interrupted parts that ``keep`` goes on from."""
    record: dict[str, Any] | None = None
    """The complete record (when ``complete``)."""


class Attempt:
    """A stage under way: its pending record, kept up to date with the time spent (:meth:`save_wall`)."""

    def __init__(self, key: StageKey, path: Path, pending_path: Path, pending: dict[str, Any], before: float,
                 keep: bool, out: Path | None = None) -> None:  # fmt: skip
        self.key, self.path, self.keep, self.out = key, path, keep, out
        self._pending_path, self.pending, self._before = pending_path, pending, before
        self.t0 = time.perf_counter()

    def elapsed(self) -> float:
        """The stage's wall time so far: the interrupted parts and this one."""
        return self._before + time.perf_counter() - self.t0

    def save_wall(self) -> None:
        """Put the time spent so far into the pending record (an interrupted stage keeps the time of its parts)."""
        write_json(self._pending_path, self.pending | {"wall_s_parts": self.elapsed()}, root=self.out)


class StageStore:
    """The records of the experiment directory ``out``."""

    def __init__(self, out: str | Path) -> None:
        self.out = Path(out)

    # -- the directory -----------------------------------------------------------------------------
    def check_out(self) -> None:
        """``ValueError`` when ``out`` is a file, a non-empty directory that is not an experiment, the filesystem
        root or the home directory, or a folder nothing can be written in."""
        from lckit.fileio import check_output_folder

        check_output_folder(self.out)
        if self.out.is_dir() and any(q.name != LOCK_NAME for q in self.out.iterdir()) and not (
                self.out / MARKER).exists():
            raise ValueError(f"--out {self.out} is a non-empty directory without {MARKER}; "
                             "choose a new or an experiment directory")  # fmt: skip

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold ``DIR/.lock`` (an advisory ``flock``, released when the process ends however it ends).

        ``ValueError`` when another process holds it: two runs in one directory would overwrite each other.
        """
        from lckit.fileio import folder_lock

        with folder_lock(self.out, "lc-experiment", LOCK_NAME, doing="is running in"):
            yield

    def marker(self) -> dict[str, Any]:
        """``experiment.json`` (empty when missing)."""
        data = read_json(self.out / MARKER)
        return data if isinstance(data, dict) else {}

    def write_marker(self, data: dict[str, Any]) -> None:
        write_json(self.out / MARKER, data, root=self.out)

    # -- the records -------------------------------------------------------------------------------
    def check(self, key: StageKey, config: Config, inputs: dict[str, str], *, upgrade: Upgrade | None = None,
              resumable: Resumable | None = None) -> Verdict:  # fmt: skip
        """Whether stage ``key`` is complete under ``config`` and ``inputs`` (both canonical) and, if not, why and
        whether its directory can be kept."""
        rec_path, pend_path = record_paths(self.out, key)
        check_inside(key.path(self.out), self.out, f"the folder of stage {key}")

        def stored(rec: Any) -> dict[str, Any] | None:
            if not well_formed(rec):
                return None
            # a config stored before a field was added compares as the config it stands for today
            if upgrade is None or not isinstance(rec.get("config"), dict):
                return rec
            return rec | {"config": canonical(upgrade(rec["config"]))}

        raw = read_json(rec_path)
        record = stored(raw)
        pending = None
        if record is not None and record.get("config") == config and record.get("inputs") == inputs:
            try:
                current = hash_outputs(key.path(self.out), list(record.get("outputs", {})))
            except UnsafePathError as exc:
                raise UnsafePathError(f"{rec_path}: {exc}; remove the record to rerun the stage") from None
            if current is not None and current == record.get("outputs"):
                return Verdict(True, "", record=record)
            why = "outputs missing or changed"
        elif record is not None:
            why = "stale: " + ("config changed" if record.get("config") != config else "inputs changed")
        elif raw is not None:
            why = f"stale: {rec_path.name} does not read as a stage record"
        elif (pending := stored(read_json(pend_path))) is None:
            why = "new"
        elif pending.get("config") == config and pending.get("inputs") == inputs:
            why = "resuming an interrupted run"
        else:
            why = "stale: config or inputs changed since an interrupted run"
        prior = None if why == "outputs missing or changed" else (record or pending)
        keep = prior is not None and prior.get("inputs") == inputs and (
            prior.get("config") == config or (resumable is not None and resumable(prior.get("config", {}), config)))
        before = float(prior.get("wall_s_parts", 0.0)) if keep and prior is not None else 0.0
        return Verdict(False, why, keep, before)

    def skipped(self, key: StageKey, verdict: Verdict, t0: float) -> StageResult:
        """The result of a complete stage (its recorded time and outputs)."""
        assert verdict.record is not None
        return StageResult(key.name, "skipped", key.path(self.out), float(verdict.record.get("wall_s", 0.0)),
                           time.perf_counter() - t0, dict(verdict.record["outputs"]))  # fmt: skip

    def begin(self, key: StageKey, verdict: Verdict, config: Config, inputs: dict[str, str]) -> Attempt:
        """Make stage ``key`` pending: its directory emptied unless ``verdict.keep`` (a link there goes as the link,
        never what it points at; nothing out of ``out`` is deleted or written), its pending record written."""
        path = key.path(self.out)
        rec_path, pend_path = record_paths(self.out, key)
        if not verdict.keep:
            remove_tree(path, self.out)
        make_folder(path, self.out)
        remove_file(rec_path, self.out)
        pending = {"stage": key.name, "config": config, "inputs": inputs}
        write_json(pend_path, pending | {"wall_s_parts": verdict.wall_before}, root=self.out)
        return Attempt(key, path, pend_path, pending, verdict.wall_before, verdict.keep, self.out)

    def finish(self, attempt: Attempt, outputs: Sequence[str], wall: float | None, t0: float) -> StageResult:
        """Record the finished stage of ``attempt``: its outputs' hashes and ``wall`` (the compute time behind them;
        None: the time of its parts). ``RuntimeError`` when an output is missing."""
        wall = attempt.elapsed() if wall is None else wall
        hashes = hash_outputs(attempt.path, outputs)
        if hashes is None:
            raise RuntimeError(f"stage {attempt.key.name} finished without all of its outputs in {attempt.path}")
        rec_path, pend_path = record_paths(self.out, attempt.key)
        write_json(rec_path, {**attempt.pending, "outputs": hashes, "wall_s": wall,
                              "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}, root=self.out)  # fmt: skip
        remove_file(pend_path, self.out)
        return StageResult(attempt.key.name, "done", attempt.path, wall, time.perf_counter() - t0, hashes)


class Invocations:
    """``invocations.json``: every run of the directory, its command, wall time so far and whether it finished
    (kept up to date by each progress line, so that a killed invocation keeps the time until its last line)."""

    def __init__(self, out: str | Path) -> None:
        self.path = Path(out) / INVOCATIONS
        self.entries: list[dict[str, Any]] = []
        self._t0: float | None = None
        self._lock = threading.Lock()  # progress lines of the worker processes come from another thread

    def start(self, command: str, t0: float) -> None:
        from lcmodels.bench.ledger import git_commit

        previous = read_json(self.path)
        commit, dirty = git_commit()  # the code the stages of this run are computed with (None: no checkout)
        self.entries = [*(previous if isinstance(previous, list) else []),
                        {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "command": command, "commit": commit,
                         "dirty": dirty}]  # fmt: skip
        self._t0 = t0
        self.save(finished=False)

    @property
    def active(self) -> bool:
        return self._t0 is not None

    def save(self, *, finished: bool) -> None:
        if self._t0 is None:
            return
        with self._lock:
            self.entries[-1].update(wall_s=time.perf_counter() - self._t0, finished=finished)
            write_json(self.path, self.entries, root=self.path.parent)

    def stop(self) -> None:
        self._t0 = None
