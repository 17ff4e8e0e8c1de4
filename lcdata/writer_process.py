"""Episode writing on another core: :class:`ProcessEpisodeWriter`, an :class:`~lcdata.writer.EpisodeWriter`
whose encoding, chunking, compression and file I/O run in a helper process.

Why: on a 2-core machine the simulator uses one core and the other sits idle, while recording in
the simulator's process costs a good share of its time (``tools/bench_mcap.py``; the per-step ``/vehicles`` encoding, the
per-decision image and scene encoding, and the GIL hand-offs with the compression thread). Here the
simulator's process only copies the raw values of each call into a buffer for a pipe, and a persistent
helper process (one per recording process, started on first use and reused for every episode) runs
the very same :class:`~lcdata.writer.EpisodeWriter` calls on them. The file is byte for byte the file
the in-process writer makes (tested).

Protocol: the helper reads records from its stdin, a pipe: ``<u32 payload bytes, u8 opcode, pad,
u16 writer id>`` then the payload, padded to 8 bytes. The frequent calls (:meth:`write_sim_rows`,
:meth:`write_image`, :meth:`write_scene`, :meth:`write_transform`, :meth:`write_rl_step`) are packed
as float64 or raw arrays straight into the outgoing buffer (float64 holds every value they carry
exactly); the rare ones travel pickled. Opening is not waited for. Closing, aborting and
:attr:`message_count` wait for the helper's answer on its stdout (a length-prefixed pickle), which
carries the helper's exception, if any, to be raised here.

Failure semantics:

* The simulator's process killed (even with SIGKILL): the helper reads end-of-file, writes out the
  chunk it holds and leaves every open episode as ``.partial`` (recoverable); nothing is renamed.
* The helper killed, or failing on an episode: the next call that waits for it (at the latest
  :meth:`close`) raises ``RuntimeError`` with the cause, and the episode stays ``.partial``.
* Data still in this process's buffer (at most :data:`BUFFER_BYTES`) is lost when this process is
  killed, as the chunk in progress of the in-process writer is.
* A child this process forks (not spawns) holds the pipe open too: the helper then sees the end of
  its input only when that child exits as well. A forked child that records starts its own helper.
"""

from __future__ import annotations

import atexit
import fcntl
import logging
import os
import pathlib
import pickle
import signal
import struct
import subprocess
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any, BinaryIO

import numpy as np

from lcdata.writer import ROW_FIELDS, EpisodeSink, EpisodeWriter
from lcsim.core import OUTCOMES, RUNNING

log = logging.getLogger(__name__)

WRITER_MODES = ("process", "thread", "inline")
"""Where an episode is encoded and written: a helper process, a compression thread, or inline."""
BUFFER_BYTES = 64 << 10
"""Records are collected in a buffer of this size and written to the helper's pipe when it is full."""
PIPE_BYTES = 1 << 20
"""Requested pipe capacity (Linux ``F_SETPIPE_SZ``; the default is 64 KiB)."""

_HEADER = struct.Struct("<IBxH")  # payload bytes, opcode, pad, writer id
_LENGTH = struct.Struct("<I")
_IMAGE_HEAD = struct.Struct("<qdQQQ")  # step, t, channels, height, width; the pixels follow
_F_SETPIPE_SZ = 1031

OP_OPEN, OP_ROWS, OP_IMAGE, OP_SCENE, OP_TF, OP_CALL, OP_CLOSE, OP_ABORT, OP_COUNT, OP_RL = range(1, 11)
_RL_SCALARS = 17  # step, t, decision, action, mask x 3, reward, 4 components, terminated, truncated, outcome, rows, cols
_OUTCOMES = (RUNNING, *OUTCOMES)
_OUTCOME_CODES = {name: code for code, name in enumerate(_OUTCOMES)}
_REWARD_KEYS = frozenset(("collision", "off_road", "forward", "success"))
_SCENE_SCALARS = 5  # step, t, height_m, ego_id, N
_ROW_DTYPES = (np.dtype(np.float64),) * 5 + (np.dtype(np.int64),) * 2  # the simulator's, see write_sim_rows


class WriterProcessError(RuntimeError):
    """The helper process is gone or could not be started."""


# -- the simulator's side ---------------------------------------------------------------------------
class _Service:
    """The helper process of this process and the buffer of records on their way to it."""

    def __init__(self) -> None:
        env = dict(os.environ)
        root = str(pathlib.Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        self.pid_owner = os.getpid()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from lcdata.writer_process import serve; serve()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, bufsize=0,
        )  # fmt: skip
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self._fd = self.proc.stdin.fileno()
        self._replies: BinaryIO = self.proc.stdout  # type: ignore[assignment]
        try:
            fcntl.fcntl(self._fd, _F_SETPIPE_SZ, PIPE_BYTES)
        except OSError:  # a capped pipe-max-size: the default pipe works, with more hand-offs
            pass
        self._new_buffer(BUFFER_BYTES)
        self.pos = 0
        self.next_id = 1

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def reserve(self, op: int, wid: int, nbytes: int) -> int:
        """Put a record header in the buffer and return the byte offset of its ``nbytes`` payload."""
        size = 8 + ((nbytes + 7) & ~7)
        pos = self.pos
        if pos + size > len(self.buf):
            self.flush()
            pos = 0
            if size > len(self.buf):
                self._new_buffer(size)
        _HEADER.pack_into(self.buf, pos, nbytes, op, wid)
        self.pos = pos + size
        return pos + 8

    def _new_buffer(self, size: int) -> None:
        """The outgoing buffer and its float64 and uint8 views (a record larger than it gets a larger one)."""
        self.buf = bytearray(size)
        self.f64 = np.frombuffer(self.buf, dtype=np.float64)
        self.u8 = np.frombuffer(self.buf, dtype=np.uint8)

    def send_pickled(self, op: int, wid: int, obj: Any) -> None:
        data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        at = self.reserve(op, wid, len(data))
        self.buf[at : at + len(data)] = data

    def flush(self) -> None:
        view = memoryview(self.buf)[: self.pos]
        self.pos = 0
        try:
            while view:
                view = view[os.write(self._fd, view) :]
        except (BrokenPipeError, OSError) as exc:
            raise WriterProcessError(self._gone()) from exc

    def request(self, op: int, wid: int, obj: Any = None) -> Any:
        """Send a record, flush, and wait for the helper's answer (an exception in it is raised here)."""
        self.send_pickled(op, wid, obj)
        self.flush()
        (size,) = _LENGTH.unpack(self._read(_LENGTH.size))
        ok, value = pickle.loads(self._read(size))
        if not ok:
            raise value
        return value

    def _read(self, size: int) -> bytes:
        data = bytearray()
        while len(data) < size:
            part = self._replies.read(size - len(data))
            if not part:
                raise WriterProcessError(self._gone())
            data += part
        return bytes(data)

    def _gone(self) -> str:
        try:
            code = self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            code = None
        return f"the MCAP writer process (pid {self.proc.pid}) stopped answering (exit code {code})"

    def shutdown(self) -> None:
        """End of input for the helper: it aborts what is still open (``.partial``) and exits."""
        try:
            if self.pos:
                self.flush()
        except WriterProcessError:
            pass
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                stream.close()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()


_service: _Service | None = None
_service_lock = threading.Lock()


def _get_service() -> _Service:
    global _service
    with _service_lock:
        if _service is None or _service.pid_owner != os.getpid() or not _service.alive():
            _service = _Service()  # a forked child never writes into its parent's pipe
        return _service


@atexit.register
def _shutdown() -> None:
    if _service is not None and _service.pid_owner == os.getpid():
        _service.shutdown()


def writer_process_pid() -> int | None:
    """Pid of this process's helper, or None before the first :class:`ProcessEpisodeWriter`."""
    return _service.pid if _service is not None and _service.pid_owner == os.getpid() else None


def _pickled(name: str) -> Callable[..., None]:
    """A :class:`ProcessEpisodeWriter` method that sends the call ``name`` pickled, for the rare calls."""

    def call(self: ProcessEpisodeWriter, *args: Any, **kwargs: Any) -> None:
        self._call(name, *args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"See :meth:`lcdata.writer.EpisodeWriter.{name}` (sent to the helper pickled)."
    return call


class ProcessEpisodeWriter(EpisodeSink):
    """Stream one episode to ``path`` from a helper process; the same interface as
    :class:`~lcdata.writer.EpisodeWriter` (see the module docstring). Use as a context manager.

    Arguments are those of :class:`~lcdata.writer.EpisodeWriter`; ``options`` (``chunk_size``,
    ``compression_level``) go to the one in the helper, which compresses on its own core (so
    ``background`` does not apply). Errors the in-process writer raises when a call is made (a bad
    argument) surface at :meth:`close` here, as ``RuntimeError``, with the file left as ``.partial``.
    Several writers may be open at once (one helper serves them all), but use them from one thread:
    the buffer they share has no lock.
    """

    def __init__(self, path: str | os.PathLike[str], *, metadata: Mapping[str, Any], overwrite: bool = False,
                 start_time_ns: int | None = None, **options: Any) -> None:  # fmt: skip
        self._claim(path, overwrite, start_time_ns)  # a bad folder or an existing file fails here
        self._svc = svc = _get_service()
        self._wid = svc.next_id
        svc.next_id = svc.next_id % 0xFFFF + 1
        self._closed = False
        self._count: int | None = None
        kwargs = {**options, "metadata": dict(metadata), "overwrite": overwrite,
                  "start_time_ns": self.start_time_ns, "background": False}  # fmt: skip
        svc.send_pickled(OP_OPEN, self._wid, (str(self.path), kwargs))  # a failure in the helper: at close()

    def _check(self) -> _Service:
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        return self._svc

    def _call(self, name: str, *args: Any, **kwargs: Any) -> None:
        self._check().send_pickled(OP_CALL, self._wid, (name, args, kwargs))

    # -- frequent calls: raw values into the shared buffer --------------------------------------------
    def write_sim_rows(self, steps: Sequence[int], ts: Sequence[float], rows: Sequence[np.ndarray],
                       fixed: Sequence[np.ndarray], ego: Sequence[float]) -> None:  # fmt: skip
        """See :meth:`lcdata.writer.EpisodeSink.write_sim_rows`: one record. Rows of the simulator's dtypes
        (float64 state, int64 lanes, judged by the first step) go in as raw bytes, joined in one call;
        others are cast to float64 (one ``np.concatenate``)."""
        svc = self._check()
        k = len(steps)
        if not k:
            return
        first = rows[0]
        n = first.size
        size = ROW_FIELDS * k * n
        base = svc.reserve(OP_ROWS, self._wid, 8 * (3 + 10 * k + 3 * n + size)) >> 3
        f64 = svc.f64
        f64[base : base + 2] = (k, n)  # base + 2: how the rows are stored
        at = base + 3
        f64[at : at + k] = steps
        f64[at + k : at + 2 * k] = ts
        at += 2 * k
        f64[at : at + 8 * k] = ego
        at += 8 * k
        for column in fixed:
            f64[at : at + n] = column
            at += n
        try:
            raw = b"".join(rows) if tuple(row.dtype for row in rows[:ROW_FIELDS]) == _ROW_DTYPES else b""
        except (BufferError, TypeError):  # a row that is not contiguous
            raw = b""
        if len(raw) == 8 * size:
            f64[base + 2] = 1.0
            svc.buf[8 * at : 8 * (at + size)] = raw
        else:  # (1, N) rows stack to (7 K, N), (N,) rows to (7 K N,)
            f64[base + 2] = 0.0
            np.concatenate(rows, out=f64[at : at + size].reshape(-1, *first.shape[1:]), casting="same_kind")

    def write_image(self, step: int, t_s: float, chw: np.ndarray) -> None:
        """See :meth:`lcdata.writer.EpisodeWriter.write_image` (copies the uint8 image here)."""
        svc = self._check()
        chw = np.asarray(chw)
        if chw.dtype != np.uint8 or chw.ndim != 3:
            self._call("write_image", step, t_s, chw)  # the writer raises on it, as it would in-process
            return
        c, h, w = chw.shape
        at = svc.reserve(OP_IMAGE, self._wid, _IMAGE_HEAD.size + chw.size)
        _IMAGE_HEAD.pack_into(svc.buf, at, step, t_s, c, h, w)
        at += _IMAGE_HEAD.size
        svc.u8[at : at + chw.size].reshape(c, h, w)[...] = chw

    def write_scene(
        self, step: int, t_s: float, ids: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
        length: np.ndarray, width: np.ndarray, *, height_m: float = 1.5, ego_id: int = 0,
    ) -> None:  # fmt: skip
        """See :meth:`lcdata.writer.EpisodeWriter.write_scene`."""
        svc = self._check()
        n = len(ids)
        at = svc.reserve(OP_SCENE, self._wid, 8 * (_SCENE_SCALARS + 6 * n)) >> 3
        f64 = svc.f64
        f64[at : at + _SCENE_SCALARS] = (step, t_s, height_m, ego_id, n)
        at += _SCENE_SCALARS
        for column in (ids, x, y, yaw, length, width):
            f64[at : at + n] = column
            at += n

    def write_transform(self, step: int, t_s: float, x: float, y: float, yaw: float) -> None:
        """See :meth:`lcdata.writer.EpisodeWriter.write_transform`."""
        svc = self._check()
        at = svc.reserve(OP_TF, self._wid, 40) >> 3
        svc.f64[at : at + 5] = (step, t_s, x, y, yaw)

    # -- the rest, pickled (see :meth:`_call`) -------------------------------------------------------
    write_sim_step = _pickled("write_sim_step")
    write_sim_steps = _pickled("write_sim_steps")
    write_vehicles = _pickled("write_vehicles")
    write_ego = _pickled("write_ego")
    write_collision = _pickled("write_collision")
    write_lane_markings = _pickled("write_lane_markings")
    write_event = _pickled("write_event")
    write_prediction = _pickled("write_prediction")

    def write_rl_step(
        self, step: int, t_s: float, *, action: int, action_mask: np.ndarray, reward: float,
        reward_components: Mapping[str, float], terminated: bool = False, truncated: bool = False,
        outcome: str = "", decision: int = 0, obs_current: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """See :meth:`lcdata.writer.EpisodeWriter.write_rl_step` (packed as float64 here)."""
        svc = self._check()
        mask = np.asarray(action_mask, dtype=bool).reshape(-1)
        code = _OUTCOME_CODES.get(outcome)
        current = None if obs_current is None else np.asarray(obs_current)
        if code is None or mask.size != 3 or not _REWARD_KEYS.issuperset(reward_components) or (
                current is not None and current.ndim != 2):  # fmt: skip
            self._call("write_rl_step", step, t_s, action=action, action_mask=action_mask, reward=reward,
                       reward_components=dict(reward_components), terminated=terminated, truncated=truncated,
                       outcome=outcome, decision=decision, obs_current=obs_current)  # fmt: skip
            return
        rows, cols = (-1, 0) if current is None else current.shape
        at = svc.reserve(OP_RL, self._wid, 8 * (_RL_SCALARS + max(rows, 0) * cols)) >> 3
        get = reward_components.get
        svc.f64[at : at + _RL_SCALARS] = (
            step, t_s, decision, action, mask[0], mask[1], mask[2], reward, get("collision", 0.0),
            get("off_road", 0.0), get("forward", 0.0), get("success", 0.0), terminated, truncated, code, rows, cols,
        )  # fmt: skip
        if current is not None:
            svc.f64[at + _RL_SCALARS : at + _RL_SCALARS + rows * cols] = current.reshape(-1)

    # -- life cycle -------------------------------------------------------------------------------
    @property
    def message_count(self) -> int:
        """Messages written so far (all topics); asks the helper unless the file is closed."""
        if self._count is not None:
            return self._count
        return int(self._check().request(OP_COUNT, self._wid))

    @property
    def writer_pid(self) -> int:
        """Pid of the helper process that writes this file."""
        return self._svc.pid

    def close(self) -> pathlib.Path:
        """Wait for the helper to finish the file and rename ``.partial`` to the final name."""
        if not self._closed:
            self._closed = True
            self._count = int(self._svc.request(OP_CLOSE, self._wid))
            log.debug("wrote %s", self.path)
        return self.path

    def abort(self) -> None:
        """Stop writing without finishing: the ``.partial`` file stays (recoverable)."""
        if not self._closed:
            self._closed = True
            try:
                self._svc.request(OP_ABORT, self._wid)
            except RuntimeError as exc:  # the helper is gone or failed: the file stays .partial either way
                log.warning("%s: %s", self.partial_path, exc)
            log.info("episode aborted; partial file left at %s", self.partial_path)  # the caller says why



# -- the helper's side ------------------------------------------------------------------------------
def _read_into(stream: BinaryIO, view: memoryview) -> bool:
    """Fill ``view`` from ``stream``; False at the end of the input."""
    while view:
        n = stream.readinto(view)
        if not n:
            return False
        view = view[n:]
    return True


def _rows(writer: EpisodeWriter, a: np.ndarray) -> None:
    k, n, raw = int(a[0]), int(a[1]), a[2] == 1.0
    at = 3
    steps, ts = a[at : at + k].astype(np.int64), a[at + k : at + 2 * k]
    at += 2 * k
    ego = a[at : at + 8 * k].reshape(k, 8)
    at += 8 * k
    ids, length, width = a[at : at + 3 * n].reshape(3, n)
    at += 3 * n
    state = a[at : at + ROW_FIELDS * k * n].reshape(k, ROW_FIELDS, n)
    columns = [state[:, j] for j in range(ROW_FIELDS)]
    if raw:  # the bytes of the simulator's arrays: lane and target_lane are int64
        columns[5:] = [column.view(np.int64) for column in columns[5:]]
    writer.write_sim_steps(steps, ts, (ids, *columns, length, width), ego)


def _scene(writer: EpisodeWriter, a: np.ndarray) -> None:
    step, t, height_m, ego_id, n = a[:_SCENE_SCALARS].tolist()
    n = int(n)
    ids, x, y, yaw, length, width = a[_SCENE_SCALARS : _SCENE_SCALARS + 6 * n].reshape(6, n)
    writer.write_scene(int(step), t, ids.astype(np.int64), x, y, yaw, length, width, height_m=height_m,
                       ego_id=int(ego_id))  # fmt: skip


def _image(writer: EpisodeWriter, payload: memoryview) -> None:
    step, t, c, h, w = _IMAGE_HEAD.unpack_from(payload)
    image = np.frombuffer(payload, dtype=np.uint8, count=c * h * w, offset=_IMAGE_HEAD.size).reshape(c, h, w)
    writer.write_image(int(step), t, image)


def _rl_step(writer: EpisodeWriter, a: np.ndarray) -> None:
    (step, t, decision, action, m0, m1, m2, reward, collision, off_road, forward, success, terminated, truncated,
     code, rows, cols) = a[:_RL_SCALARS].tolist()  # fmt: skip
    rows, cols = int(rows), int(cols)
    current = None if rows < 0 else a[_RL_SCALARS : _RL_SCALARS + rows * cols].reshape(rows, cols)
    components = {"collision": collision, "off_road": off_road, "forward": forward, "success": success}
    writer.write_rl_step(int(step), t, action=int(action), action_mask=np.array([m0, m1, m2], dtype=bool),
                         reward=reward, reward_components=components, terminated=bool(terminated),
                         truncated=bool(truncated), outcome=_OUTCOMES[int(code)], decision=int(decision),
                         obs_current=current)  # fmt: skip


def _transform(writer: EpisodeWriter, a: np.ndarray) -> None:
    step, t, x, y, yaw = a.tolist()
    writer.write_transform(int(step), t, x, y, yaw)


_FLOAT64_RECORDS = {OP_ROWS: _rows, OP_SCENE: _scene, OP_TF: _transform, OP_RL: _rl_step}
"""Decoders of the records packed as float64."""


def serve() -> None:
    """The helper's loop: read records from stdin, run them on :class:`EpisodeWriter` objects."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it tells us
    logging.getLogger().addHandler(logging.NullHandler())  # the parent logs and raises what happens here
    replies = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)  # a stray print must not corrupt the answers
    stream = os.fdopen(0, "rb", buffering=PIPE_BYTES)
    writers: dict[int, EpisodeWriter] = {}
    failed: dict[int, BaseException] = {}

    def answer(ok: bool, value: Any) -> None:
        data = pickle.dumps((ok, value), protocol=pickle.HIGHEST_PROTOCOL)
        replies.write(_LENGTH.pack(len(data)) + data)

    def fail(wid: int, exc: BaseException) -> None:
        failed[wid] = exc
        writer = writers.pop(wid, None)
        if writer is not None:
            writer.abort()

    buf = bytearray(BUFFER_BYTES)  # the payload of the record at hand, read in place (the writers copy what they keep)
    head = bytearray(_HEADER.size)
    while _read_into(stream, memoryview(head)):
        size, op, wid = _HEADER.unpack(head)
        padded = (size + 7) & ~7
        if padded > len(buf):
            buf = bytearray(padded)
        if not _read_into(stream, memoryview(buf)[:padded]):
            break
        payload = memoryview(buf)[:size]
        if op == OP_OPEN:
            path, kwargs = pickle.loads(payload)
            failed.pop(wid, None)
            try:
                writers[wid] = EpisodeWriter(path, **kwargs)
            except Exception as exc:  # reported when the caller closes the episode
                failed[wid] = exc
            continue
        if op in (OP_CLOSE, OP_ABORT, OP_COUNT):
            exc = failed.pop(wid, None) if op != OP_COUNT else failed.get(wid)
            writer = writers.get(wid)
            if exc is not None:
                answer(False, _reported(exc))
                continue
            try:
                assert writer is not None, f"no open writer {wid}"
                count = writer.message_count
                if op == OP_CLOSE:
                    writers.pop(wid).close()
                elif op == OP_ABORT:
                    writers.pop(wid).abort()
                answer(True, count)
            except Exception as exc:
                writers.pop(wid, None)
                answer(False, _reported(exc))
            continue
        writer = writers.get(wid)
        if writer is None:
            continue  # an episode that failed earlier: its records are dropped
        try:
            if (decode := _FLOAT64_RECORDS.get(op)) is not None:
                decode(writer, np.frombuffer(payload, dtype=np.float64))
            elif op == OP_IMAGE:
                _image(writer, payload)
            elif op == OP_CALL:
                name, args, kwargs = pickle.loads(payload)
                getattr(writer, name)(*args, **kwargs)
            else:
                raise ValueError(f"unknown record type {op}")
        except Exception as exc:  # reported when the caller closes the episode
            fail(wid, exc)
    # End of input. With writers still open, the parent died: keep what it sent, leave them .partial.
    for writer in writers.values():
        try:
            writer.flush()
        except Exception:  # a file we cannot write stays as it is
            pass
        writer.abort()


def _reported(exc: BaseException) -> Exception:
    """A failure of the helper as its caller gets it: an ``OSError`` (a full disk, a folder gone) stays one, with
    its ``errno``, so that a command reports it like any other write error; anything else a ``RuntimeError``."""
    if isinstance(exc, OSError):
        return OSError(exc.errno, f"MCAP writing failed: {exc.strerror or exc}", exc.filename)
    return RuntimeError(f"MCAP writing failed: {type(exc).__name__}: {exc}")


def open_writer(path: str | os.PathLike[str], *, mode: str = "process",
                **kwargs: Any) -> EpisodeWriter | ProcessEpisodeWriter:  # fmt: skip
    """An episode writer for ``path``: :class:`ProcessEpisodeWriter` (``mode="process"``) or
    :class:`~lcdata.writer.EpisodeWriter` compressing on a thread (``"thread"``) or inline (``"inline"``).
    ``kwargs`` are :class:`~lcdata.writer.EpisodeWriter`'s. All three write the same bytes."""
    if mode == "process":
        return ProcessEpisodeWriter(path, **kwargs)
    if mode in ("thread", "inline"):
        return EpisodeWriter(path, background=mode == "thread", **kwargs)
    raise ValueError(f"writer mode must be one of {', '.join(WRITER_MODES)}, got {mode!r}")
