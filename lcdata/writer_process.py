"""Episode writing on another core: :class:`ProcessEpisodeWriter`, an :class:`~lcdata.writer.EpisodeWriter`
whose encoding, chunking, compression and file I/O run in a helper process.

Why: on a 2-core machine the simulator uses one core and the other sits idle, while encoding, chunking and
compressing an episode costs more than simulating it. Here the simulator's process only copies the raw values of
each call into shared memory, and a persistent helper process (one per recording process, started on first use
and reused for every episode) runs the very same :class:`~lcdata.writer.EpisodeWriter` calls on them. The file is
byte for byte the file the in-process writer makes (tested).

Protocol: records ``<u32 payload bytes, u8 opcode, pad, u16 writer id>`` then the payload, padded to 8 bytes, are
laid out in segments of a ring of shared memory (a memfd); a segment goes to the helper with a notice on its stdin
(segment, bytes) and comes back, once its records have run, with a byte on a second pipe (records larger than a
segment follow their notice through the pipe). The frequent calls (:meth:`~ProcessEpisodeWriter.write_decision`,
:meth:`~ProcessEpisodeWriter.write_sim_log`, :meth:`~ProcessEpisodeWriter.write_rl_step`) are packed as float64
or raw arrays straight into the segment (float64 holds every value they carry exactly), a decision by one compiled
call; the helper writes a run of decision records in one compiled loop (:func:`_run_decisions`). The rare calls
travel pickled. Opening is not waited for. Closing, aborting and :attr:`message_count` wait for the helper's
answer on its stdout (a length-prefixed pickle), which carries the helper's exception, if any, to be raised here.

Failure semantics:

* The simulator's process killed (even with SIGKILL): the helper reads end-of-file, writes out the
  chunk it holds and leaves every open episode as ``.partial`` (recoverable); nothing is renamed.
* The helper killed, or failing on an episode: the next call that waits for it (at the latest
  :meth:`close`) raises ``RuntimeError`` with the cause, and the episode stays ``.partial``.
* Records in the segment this process is filling (at most :data:`SEGMENT_BYTES`) are lost when this
  process is killed, as the chunk in progress of the in-process writer is.
* A child this process forks (not spawns) holds the pipe open too: the helper then sees the end of
  its input only when that child exits as well. A forked child that records starts its own helper.
"""

from __future__ import annotations

import atexit
import fcntl
import logging
import math
import mmap
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
from numba import njit

from lcdata.sim_records import LOG_HEAD, RL_FIELDS, copy_into, decision_records, log_event_row
from lcdata.writer import OUTCOME_CODES, OUTCOMES, EpisodeSink, EpisodeWriter

log = logging.getLogger(__name__)

WRITER_MODES = ("process", "thread", "inline")
"""Where an episode is encoded and written: a helper process, a compression thread, or inline."""
SEGMENT_BYTES = 1 << 18
"""Records go to the helper in segments of shared memory of this size (a record larger than one goes through the
pipe). The segment being filled is lost when this process is killed, as the chunk in progress of the in-process
writer is."""
SEGMENTS = 16
"""Segments in the shared ring: the helper works on the ones sent while this process fills the next (small
segments keep what the helper has left to do when an episode closes short)."""
PIPE_BYTES = 1 << 20
"""Requested pipe capacity for the records too large for a segment (Linux ``F_SETPIPE_SZ``; the default is 64 KiB)."""

_HEADER = struct.Struct("<IBxH")  # payload bytes, opcode, pad, writer id
_LENGTH = struct.Struct("<I")
_NOTICE = struct.Struct("<II")  # segment (or _INLINE), bytes
_INLINE = 0xFFFFFFFF  # the bytes follow in the pipe
_F_SETPIPE_SZ = 1031

OP_OPEN, OP_LOG, OP_DECISION, OP_CALL, OP_CLOSE, OP_ABORT, OP_COUNT, OP_RL = range(1, 9)
_RL_SCALARS = 17  # step, t, decision, action, mask x 3, reward, 4 components, terminated, truncated, outcome, rows, cols
_REWARD_KEYS = frozenset(("collision", "off_road", "forward", "success"))
_LOG_SCALARS = 5  # K, row width, N, off_road, lc_active; ids, length, width and the K rows follow
_DECISION_SCALARS = 15  # step, t, N, K, W, pose?, image?, C, H, W, off_road, lc_active, rows, cols, rl?; then RL_FIELDS,
# ids, length, width, the pose (3 N), the log (K W), the observation (rows cols) and the pixels
_RL_COUNT = len(RL_FIELDS)
_DECISION_HEAD = struct.Struct(f"<{_DECISION_SCALARS + _RL_COUNT}d")  # the scalars, then the values of /rl/step
_NO_RL_VALUES = (0.0,) * _RL_COUNT
_STEP_BYTES_BASE = 2 * 31 + 20 + 10 * 11 + 84  # lcdata.writer._step_bytes(0)
_NO_LOG = np.zeros((0, 0))
_NO_RL = np.zeros(0)
_NO_POSE = np.zeros((0, 0))
_NO_CURRENT = np.zeros((0, 0), dtype=np.float32)
_NO_IMAGE = np.zeros((0, 0, 0), dtype=np.uint8)


@njit(cache=True)
def _put_2d(f: np.ndarray, at: int, values: np.ndarray) -> int:
    """Copy ``values`` (R, C) (any layout, cast to float64) to ``f[at:]`` in row-major order."""
    rows, cols = values.shape
    dst = f[at : at + rows * cols]
    for r in range(rows):
        row = dst[r * cols : (r + 1) * cols]
        for c in range(cols):
            row[c] = values[r, c]
    return at + rows * cols


@njit(cache=True)
def _pack_arrays(u8: np.ndarray, at: int, ids: np.ndarray, length: np.ndarray, width: np.ndarray, pose: np.ndarray,
                 log: np.ndarray, current: np.ndarray, image: np.ndarray) -> None:  # fmt: skip
    """The arrays of a :meth:`ProcessEpisodeWriter.write_decision` record (see _DECISION_SCALARS), from byte ``at``:
    ids, length, width, the pose (when it has rows), the log, the observation and the image (when not empty)."""
    f = u8.view(np.float64)
    a = at // 8
    a = copy_into(f, a, ids)
    a = copy_into(f, a, length)
    a = copy_into(f, a, width)
    if pose.shape[0]:
        a = _put_2d(f, a, pose)
    a = _put_2d(f, a, log)
    a = _put_2d(f, a, current)
    if image.size:
        pixels, flat = u8[8 * a : 8 * a + image.size], image.ravel()  # (a view when the image is contiguous)
        for i in range(image.size):
            pixels[i] = flat[i]


@njit(cache=True)
def _run_decisions(seg: np.ndarray, pos: int, end: int, wid: int, channels: np.ndarray, consts: np.ndarray,
                   spans: np.ndarray, quaternions: np.ndarray, ids: np.ndarray, with_pose: bool, c: int, h: int,
                   w: int, origin_ns: int, out: np.ndarray, p: int, index: np.ndarray, m: int,
                   chunk_size: int) -> tuple[int, int, int]:  # fmt: skip
    """The helper's fast path: the records of ``seg`` (8-aligned) from ``pos`` to ``end`` that are decisions of
    writer ``wid`` in the layout given (:meth:`lcdata.writer.EpisodeWriter.decision_batch`), with no event in their
    steps, written into the chunk buffer ``out`` as ``write_decision`` would write them. Stops at the first other
    record, when ``out`` or ``index`` could overflow, and after the record that fills the chunk. Returns ``(pos, p,
    m)``: where it stopped in ``seg``, and the chunk buffer's and the index's new ends."""
    f = seg.view(np.float64)
    n = ids.size
    scratch = np.empty(1, dtype=np.int64)
    while pos < end:
        size = np.int64(seg[pos]) | (np.int64(seg[pos + 1]) << 8) | (np.int64(seg[pos + 2]) << 16) | (
            np.int64(seg[pos + 3]) << 24)  # fmt: skip
        if seg[pos + 4] != OP_DECISION or (np.int64(seg[pos + 6]) | (np.int64(seg[pos + 7]) << 8)) != wid:
            break
        a = (pos + 8) // 8
        head = f[a : a + _DECISION_SCALARS]
        k, width, rows, cols = np.int64(head[3]), np.int64(head[4]), np.int64(head[12]), np.int64(head[13])
        if (np.int64(head[2]) != n or (head[5] != 0.0) != with_pose or (head[6] != 0.0) != (c > 0)
                or np.int64(head[7]) != c or np.int64(head[8]) != h or np.int64(head[9]) != w or head[14] == 0.0
                or rows < 0 or cols < 0 or k < 0 or width != LOG_HEAD + 7 * n):  # fmt: skip
            break
        floats = _DECISION_SCALARS + _RL_COUNT + (6 if with_pose else 3) * n + k * width + rows * cols
        if 8 * floats + c * h * w > size or pos + 8 + size > end:  # (a record that does not hold what it says)
            break
        at = a + _DECISION_SCALARS
        rl = f[at : at + _RL_COUNT]
        at += _RL_COUNT
        same = True
        for v in range(n):
            same = same and f[at + v] == ids[v]
        if not same:
            break
        length, wide = f[at + n : at + 2 * n], f[at + 2 * n : at + 3 * n]
        at += 3 * n
        pose = f[at : at + 3 * n].reshape(3, n) if with_pose else f[at:at].reshape(0, n)
        at += 3 * n if with_pose else 0
        log = f[at : at + k * width].reshape(k, width)
        at += k * width
        current = f[at : at + rows * cols].reshape(rows, cols)
        at += rows * cols
        image = seg[8 * at : 8 * at + c * h * w].reshape(c, h, w)
        off_road, lc_active = head[10] != 0.0, head[11] != 0.0
        bound = consts.size + 512 + c * h * w + k * _STEP_BYTES_BASE + k * 68 * n + 4 * rows * cols
        if p + bound > out.size or m + 4 + 2 * k > index.shape[1] or log_event_row(log, off_road, lc_active) >= 0:
            break
        step, t = np.int64(head[0]), head[1]
        x = y = qz = qw = 0.0
        if with_pose:
            x, y, yaw = pose[0, 0], pose[1, 0], pose[2, 0]
            qz, qw = math.sin(yaw / 2), math.cos(yaw / 2)
            for v in range(n):
                half = pose[2, v] / 2
                quaternions[0, v] = math.sin(half)
                quaternions[1, v] = math.cos(half)
        scratch[0] = origin_ns + np.int64(np.rint(t * 1e9))
        p, m, _ = decision_records(out, p, index, m, channels, consts, spans, scratch[0], origin_ns, step, t, pose,
                                   ids, length, wide, x, y, qz, qw, quaternions, image, log, off_road, lc_active, rl,
                                   current)  # fmt: skip
        pos += 8 + ((size + 7) & ~7)
        if p >= chunk_size:
            break
    return pos, p, m


class WriterProcessError(RuntimeError):
    """The helper process is gone or could not be started."""


# -- the simulator's side ---------------------------------------------------------------------------
class _Service:
    """The helper process of this process and the records on their way to it.

    Records are laid out in a ring of :data:`SEGMENTS` segments of shared memory (a memfd both processes map); a
    full segment is handed over with a notice on the helper's stdin (segment, bytes), and the helper hands it back
    with a byte on a second pipe once it has run its records, in place. A record larger than a segment goes
    through the pipe after its notice. Without a memfd every record goes through the pipe."""

    def __init__(self) -> None:
        env = dict(os.environ)
        root = str(pathlib.Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        self.pid_owner = os.getpid()
        try:
            ring = os.memfd_create("lc-record", os.MFD_CLOEXEC)
            os.ftruncate(ring, SEGMENTS * SEGMENT_BYTES)
            self._ring: mmap.mmap | None = mmap.mmap(ring, SEGMENTS * SEGMENT_BYTES)
        except (AttributeError, OSError):  # no memfd here: every record goes through the pipe
            ring, self._ring = -1, None
        tokens, tokens_w = os.pipe()
        fds = (tokens_w,) if ring < 0 else (ring, tokens_w)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-c", "from lcdata.writer_process import serve; "
                                       f"serve({ring}, {tokens_w}, {SEGMENT_BYTES}, {SEGMENTS})"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, bufsize=0, pass_fds=fds,
            )  # fmt: skip
        finally:
            for fd in fds:
                os.close(fd)
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self._fd = self.proc.stdin.fileno()
        self._tokens = tokens
        self._replies: BinaryIO = self.proc.stdout  # type: ignore[assignment]
        try:
            fcntl.fcntl(self._fd, _F_SETPIPE_SZ, PIPE_BYTES)
        except OSError:  # a capped pipe-max-size: the default pipe works, with more hand-offs
            pass
        self._segment_bytes, self._segments = SEGMENT_BYTES, SEGMENTS
        self._segment = 0  # the segment being filled
        self._outstanding = 0  # segments sent whose return this process has not read yet
        self._inline = False  # the buffer goes through the pipe (a record too large for a segment, or no ring)
        self._pipe_buffer = bytearray(self._segment_bytes if self._ring is None else 0)
        self._views(0)
        self.pos = 0
        self.next_id = 1

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def _views(self, size: int) -> None:
        """The buffer records are laid out in (the next free segment, or a buffer of ``size`` bytes for one record
        too large for a segment) and its float64 and uint8 views."""
        if size:  # exactly its size: the next record does not fit, and this one goes on its own
            self.buf: bytearray | memoryview = bytearray(size)
            self._inline = True
        elif self._ring is None:
            self.buf = self._pipe_buffer
            self._inline = True
        else:
            if self._outstanding == self._segments:  # the segment to fill next was sent last round: its return
                self._wait_token()
            start = self._segment * self._segment_bytes
            self.buf = memoryview(self._ring)[start : start + self._segment_bytes]
            self._inline = False
        self.f64 = np.frombuffer(self.buf, dtype=np.float64)
        self.u8 = np.frombuffer(self.buf, dtype=np.uint8)

    def _wait_token(self) -> None:
        try:
            token = os.read(self._tokens, 1)
        except OSError as exc:
            raise WriterProcessError(self._gone()) from exc
        if not token:
            raise WriterProcessError(self._gone())
        self._outstanding -= 1

    def reserve(self, op: int, wid: int, nbytes: int) -> int:
        """Put a record header in the buffer and return the byte offset of its ``nbytes`` payload."""
        size = 8 + ((nbytes + 7) & ~7)
        pos = self.pos
        if pos + size > len(self.buf):
            self.flush()
            pos = 0
            if size > len(self.buf):
                self._views(size)
        _HEADER.pack_into(self.buf, pos, nbytes, op, wid)
        self.pos = pos + size
        return pos + 8

    def send_pickled(self, op: int, wid: int, obj: Any) -> None:
        data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        at = self.reserve(op, wid, len(data))
        self.buf[at : at + len(data)] = data

    def flush(self) -> None:
        """Hand what the buffer holds to the helper (a segment: its notice; a large record: through the pipe)."""
        if not self.pos:
            return
        size, self.pos = self.pos, 0
        try:
            if self._inline:
                self._write(_NOTICE.pack(_INLINE, size))
                self._write(memoryview(self.buf)[:size])
                self._views(0)
                return
            self._write(_NOTICE.pack(self._segment, size))
        except (BrokenPipeError, OSError) as exc:
            raise WriterProcessError(self._gone()) from exc
        self._outstanding += 1
        self._segment = (self._segment + 1) % self._segments
        self._views(0)

    def _write(self, data: bytes | memoryview) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view) :]

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
        """End of input for the helper: it aborts what is still open (``.partial``) and exits. Safe to call twice."""
        if self._tokens < 0:
            return
        try:
            if self.pos:
                self.flush()
        except WriterProcessError:
            pass
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                stream.close()
        os.close(self._tokens)
        self._tokens = -1
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
    def write_sim_log(self, log: np.ndarray, fixed: Sequence[np.ndarray], off_road: bool, lc_active: bool) -> None:
        """See :meth:`lcdata.writer.EpisodeSink.write_sim_log`: one record, the rows copied as they are."""
        svc = self._check()
        k, width = np.shape(log)
        if not k:
            return
        n = len(fixed[0])
        at = svc.reserve(OP_LOG, self._wid, 8 * (_LOG_SCALARS + 3 * n + k * width)) >> 3
        f64 = svc.f64
        f64[at : at + _LOG_SCALARS] = (k, width, n, off_road, lc_active)
        at += _LOG_SCALARS
        for column in fixed:
            f64[at : at + n] = column
            at += n
        f64[at : at + k * width].reshape(k, width)[...] = log

    def write_view(self, step: int, t_s: float, pose: np.ndarray | None, fixed: Sequence[np.ndarray],
                   image: np.ndarray | None = None) -> None:  # fmt: skip
        """See :meth:`lcdata.writer.EpisodeSink.write_view`: one record (the uint8 image copied here)."""
        self.write_decision(step, t_s, pose, image, _NO_LOG, fixed, False, False, _NO_RL, None)

    def write_decision(self, step: int, t_s: float, pose: np.ndarray | None, image: np.ndarray | None,
                       log: np.ndarray, fixed: Sequence[np.ndarray], off_road: bool, lc_active: bool, rl: Sequence[float],
                       current: np.ndarray | None) -> None:  # fmt: skip
        """See :meth:`lcdata.writer.EpisodeSink.write_decision`: one record, the values copied as they are (an
        empty ``rl``: no ``/rl/step``, as :meth:`write_view` sends it)."""
        svc = self._check()
        if image is not None:
            image = np.asarray(image)
            if image.dtype != np.uint8 or image.ndim != 3:  # the writer raises on it, as it would in-process
                if pose is not None:
                    self.write_view(step, t_s, pose, fixed)
                self._call("write_image", step, t_s, image)
                if len(rl):
                    self.write_decision(step, t_s, None, None, log, fixed, off_road, lc_active, rl, current)
                return
        k, width = log.shape
        ids, length, width_m = fixed
        n = len(ids)
        rows, cols = (-1, 0) if current is None else current.shape
        c, h, w = (0, 0, 0) if image is None else image.shape
        floats = (_DECISION_SCALARS + _RL_COUNT + (6 if pose is not None else 3) * n + k * width
                  + max(rows, 0) * cols)  # fmt: skip
        at = svc.reserve(OP_DECISION, self._wid, 8 * floats + c * h * w)
        has_rl = len(rl) > 0
        _DECISION_HEAD.pack_into(svc.buf, at, step, t_s, n, k, width, pose is not None, image is not None, c, h, w,
                                 off_road, lc_active, rows, cols, has_rl, *(rl if has_rl else _NO_RL_VALUES))  # fmt: skip
        _pack_arrays(svc.u8, at + 8 * (_DECISION_SCALARS + _RL_COUNT), ids, length, width_m,
                     _NO_POSE if pose is None else pose, log, _NO_CURRENT if current is None else current,
                     _NO_IMAGE if image is None else image)  # fmt: skip

    # -- the rest, pickled (see :meth:`_call`) -------------------------------------------------------
    write_sim_step = _pickled("write_sim_step")
    write_sim_steps = _pickled("write_sim_steps")
    write_transform = _pickled("write_transform")
    write_scene = _pickled("write_scene")
    write_image = _pickled("write_image")
    write_vehicles = _pickled("write_vehicles")
    write_ego = _pickled("write_ego")
    write_collision = _pickled("write_collision")
    write_lane_markings = _pickled("write_lane_markings")
    write_event = _pickled("write_event")
    write_prediction, write_planner_decision = _pickled("write_prediction"), _pickled("write_planner_decision")

    def write_rl_step(
        self, step: int, t_s: float, *, action: int, action_mask: np.ndarray, reward: float,
        reward_components: Mapping[str, float], terminated: bool = False, truncated: bool = False,
        outcome: str = "", decision: int = 0, obs_current: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """See :meth:`lcdata.writer.EpisodeWriter.write_rl_step` (packed as float64 here)."""
        svc = self._check()
        mask = np.asarray(action_mask, dtype=bool).reshape(-1)
        code = OUTCOME_CODES.get(outcome)
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


def _sim_log(writer: EpisodeWriter, a: np.ndarray) -> None:
    k, width, n, off_road, lc_active = a[:_LOG_SCALARS].tolist()
    k, width, n = int(k), int(width), int(n)
    at = _LOG_SCALARS
    ids, length, width_m = a[at : at + 3 * n].reshape(3, n)
    at += 3 * n
    writer.write_sim_log(a[at : at + k * width].reshape(k, width), (ids.astype(np.int64), length, width_m),
                         bool(off_road), bool(lc_active))  # fmt: skip


def _decision(writer: EpisodeWriter, payload: memoryview) -> None:
    head = np.frombuffer(payload, dtype=np.float64, count=_DECISION_SCALARS + len(RL_FIELDS))
    step, t, n, k, width, has_pose, has_image, c, h, w, off_road, lc_active, rows, cols, has_rl = head[
        :_DECISION_SCALARS].tolist()  # fmt: skip
    n, k, width, c, h, w, rows, cols = int(n), int(k), int(width), int(c), int(h), int(w), int(rows), int(cols)
    at = _DECISION_SCALARS + len(RL_FIELDS)
    size = at + (6 if has_pose else 3) * n + k * width + max(rows, 0) * cols
    a = np.frombuffer(payload, dtype=np.float64, count=size)
    ids, length, width_m = a[at : at + 3 * n].reshape(3, n)
    at += 3 * n
    pose = None
    if has_pose:
        pose = a[at : at + 3 * n].reshape(3, n)
        at += 3 * n
    log = a[at : at + k * width].reshape(k, width)
    at += k * width
    current = None
    if rows >= 0:
        current = a[at : at + rows * cols].reshape(rows, cols)
        at += rows * cols
    image = None
    if has_image:
        image = np.frombuffer(payload, dtype=np.uint8, count=c * h * w, offset=8 * at).reshape(c, h, w)
    fixed = (ids.astype(np.int64), length, width_m)
    if has_rl:
        writer.write_decision(int(step), t, pose, image, log, fixed, bool(off_road), bool(lc_active),
                              head[_DECISION_SCALARS:], current)  # fmt: skip
    else:
        writer.write_view(int(step), t, pose, fixed, image)


def _decisions(writer: EpisodeWriter, u8: np.ndarray, pos: int, end: int, wid: int) -> int:
    """Write the decision records of ``writer`` from ``pos`` on in one compiled call (:func:`_run_decisions`) as
    far as it goes; returns where it stopped (``pos``: the record is for :func:`_decision`)."""
    try:
        batch = writer.decision_batch()
    except Exception:  # a writer that cannot take them: _decision reports it
        return pos
    if batch is None:
        return pos
    c, h, w = batch.image_shape
    after, p, m = _run_decisions(u8, pos, end, wid, batch.channels, batch.consts, batch.spans, batch.quaternions,
                                 batch.ids, batch.with_pose, c, h, w, batch.origin_ns, batch.out, batch.end,
                                 batch.index, batch.messages, batch.chunk_size)  # fmt: skip
    writer.decisions_written(p, m)
    return after


def _rl_step(writer: EpisodeWriter, a: np.ndarray) -> None:
    (step, t, decision, action, m0, m1, m2, reward, collision, off_road, forward, success, terminated, truncated,
     code, rows, cols) = a[:_RL_SCALARS].tolist()  # fmt: skip
    rows, cols = int(rows), int(cols)
    current = None if rows < 0 else a[_RL_SCALARS : _RL_SCALARS + rows * cols].reshape(rows, cols)
    components = {"collision": collision, "off_road": off_road, "forward": forward, "success": success}
    writer.write_rl_step(int(step), t, action=int(action), action_mask=np.array([m0, m1, m2], dtype=bool),
                         reward=reward, reward_components=components, terminated=bool(terminated),
                         truncated=bool(truncated), outcome=OUTCOMES[int(code)], decision=int(decision),
                         obs_current=current)  # fmt: skip


_FLOAT64_RECORDS = {OP_LOG: _sim_log, OP_RL: _rl_step}
"""Decoders of the records packed as float64."""


def serve(ring: int = -1, tokens: int = -1, segment_bytes: int = SEGMENT_BYTES, segments: int = SEGMENTS) -> None:
    """The helper's loop: read records (from the shared ring ``ring``, a memfd of ``segments`` segments of
    ``segment_bytes``, or the pipe on stdin, see :class:`_Service`), run them on :class:`EpisodeWriter` objects,
    hand every segment back on ``tokens``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it tells us
    logging.getLogger().addHandler(logging.NullHandler())  # the parent logs and raises what happens here
    replies = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)  # a stray print must not corrupt the answers
    stream = os.fdopen(0, "rb", buffering=PIPE_BYTES)
    shared = memoryview(mmap.mmap(ring, segments * segment_bytes)) if ring >= 0 else None
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

    def run(op: int, wid: int, payload: memoryview) -> None:
        if op == OP_OPEN:
            path, kwargs = pickle.loads(payload)
            failed.pop(wid, None)
            try:
                writers[wid] = EpisodeWriter(path, **kwargs)
            except Exception as exc:  # reported when the caller closes the episode
                failed[wid] = exc
            return
        if op in (OP_CLOSE, OP_ABORT, OP_COUNT):
            exc = failed.pop(wid, None) if op != OP_COUNT else failed.get(wid)
            writer = writers.get(wid)
            if exc is not None:
                answer(False, _reported(exc))
                return
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
            return
        writer = writers.get(wid)
        if writer is None:
            return  # an episode that failed earlier: its records are dropped
        try:
            if (decode := _FLOAT64_RECORDS.get(op)) is not None:
                decode(writer, np.frombuffer(payload, dtype=np.float64))
            elif op == OP_DECISION:
                _decision(writer, payload)
            elif op == OP_CALL:
                name, args, kwargs = pickle.loads(payload)
                getattr(writer, name)(*args, **kwargs)
            else:
                raise ValueError(f"unknown record type {op}")
        except Exception as exc:  # reported when the caller closes the episode
            fail(wid, exc)

    notice = bytearray(_NOTICE.size)
    inline = bytearray(segment_bytes)
    while _read_into(stream, memoryview(notice)):
        segment, size = _NOTICE.unpack(notice)
        if segment == _INLINE:
            if size > len(inline):
                inline = bytearray(size)
            if not _read_into(stream, memoryview(inline)[:size]):
                break
            records = memoryview(inline)[:size]
        else:
            assert shared is not None
            records = shared[segment * segment_bytes : segment * segment_bytes + size]
        pos, u8 = 0, np.frombuffer(records, dtype=np.uint8)
        while pos < size:  # the records, read in place (the writers copy what they keep)
            nbytes, op, wid = _HEADER.unpack_from(records, pos)
            if op == OP_DECISION and (writer := writers.get(wid)) is not None:
                after = _decisions(writer, u8, pos, size, wid)  # a run of them at once, if it can
                if after != pos:
                    pos = after
                    continue
            run(op, wid, records[pos + 8 : pos + 8 + nbytes])
            pos += 8 + ((nbytes + 7) & ~7)
        if segment != _INLINE:
            try:
                os.write(tokens, bytes((segment,)))
            except OSError:  # the recording process is gone: the end of the input follows
                pass
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
