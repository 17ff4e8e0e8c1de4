"""Record one simulated episode to an MCAP file (protobuf everywhere).

Topics (one schema each, see :mod:`lcdata.topics` and ``lcdata/proto/lc.proto``):

============================  =========================  ==========================================
topic                         schema                     rate
============================  =========================  ==========================================
``/vehicles``                 ``lc.VehicleTracks``       every simulation step
``/ego/state``                ``lc.EgoState``            every simulation step
``/ego/collision``            ``lc.EgoCollision``        steps with a collision
``/tf``                       ``foxglove.FrameTransform``  world -> ego, as often as wanted
``/camera/bev_semantic``      ``foxglove.RawImage``      rgb8, decision rate
``/scene``                    ``foxglove.SceneUpdate``   vehicles as cubes and the lane markings (decision rate)
``/log``                      ``foxglove.Log``           events (name = kind, file:line = step:<n>)
``/rl/step``                  ``lc.RLStep``              every RL decision
``/prediction``               ``lc.Prediction``          every RL decision, when a predictor runs
``/planner/decision``         ``lc.PlannerDecision``     decisions where a planning driver had a choice
============================  =========================  ==========================================

``log_time = publish_time = start_time_ns + round(t_s * 1e9)``. The file is written to
``<path>.partial`` and renamed to ``<path>`` by :meth:`EpisodeWriter.close`, so a killed run never
leaves a half file under the final name; :func:`lcdata.read_episode` recovers the complete chunks of
a partial file. The recorder writes a decision in one call (:meth:`EpisodeSink.write_decision`: its /tf, /scene,
image, the /vehicles and /ego/state of its steps with their events, and /rl/step), which :class:`EpisodeWriter`
lays out with one compiled call straight into the chunk buffer; the single calls (``write_vehicles``,
``write_scene``, ...) encode the same messages one at a time. zstd compression of the chunks can run on a
background thread (``background=True``). :class:`lcdata.writer_process.ProcessEpisodeWriter` runs all of it in a
helper process instead (what :func:`lcdata.record_episode` uses by default).

Every ``/scene`` message is a whole scene: once :meth:`EpisodeWriter.write_lane_markings` has run, each
message carries the entity ``lanes`` next to ``vehicles``. Foxglove's 3D panel clears on a seek and
shows the latest message of each topic, so markings written once would vanish after the first seek;
repeating them adds little to a file (zstd sees the same bytes every time) and little time.
"""

from __future__ import annotations

import json
import logging
import math
import os
import pathlib
import queue
import threading
import time
from collections.abc import Mapping, Sequence
from functools import cache
from types import TracebackType
from typing import Any, NamedTuple, Self

import numpy as np
from foxglove_schemas_protobuf.Log_pb2 import Log
from google.protobuf.message import Message
from mcap_protobuf.schema import build_file_descriptor_set

from lcdata import encode, mcap_write, sim_records, topics
from lcdata.decider_records import DeciderStreams
from lcdata.mcap_write import COMPRESSION_LEVEL, McapStreamWriter
from lcdata.proto import lc_pb2
from lcdata.sim_records import SimStepEncoder
from lcdata.wire import f_string
from lckit.fileio import PARTIAL_SUFFIX, open_partial
from lcsim import kernel
from lcsim.core import OUTCOMES as EPISODE_OUTCOMES
from lcsim.core import RUNNING

log = logging.getLogger(__name__)

MAX_START_TIME_NS = 9_214_646_400 * 1_000_000_000
"""The latest ``t = 0`` of a file: 2262-01-01T00:00:00Z. A message's time, ``t = 0`` plus the episode's, is a
64-bit count of nanoseconds since 1970 (signed, as most MCAP readers take it), which ends in April 2262; the
three months between leave room for the longest episode a scenario allows."""
LOG_LEVELS = {
    "debug": Log.DEBUG,
    "info": Log.INFO,
    "warning": Log.WARNING,
    "error": Log.ERROR,
    "fatal": Log.FATAL,
}
EGO_RGBA = (0.9, 0.2, 0.2, 1.0)
TRAFFIC_RGBA = (0.2, 0.45, 0.9, 1.0)


@cache
def package_version() -> str:
    """Installed lc-toolkit version, or ``0+unknown`` when running from a bare checkout."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lc-toolkit")
    except PackageNotFoundError:
        return "0+unknown"


def partial_path(path: str | os.PathLike[str]) -> pathlib.Path:
    """``episode.mcap`` -> ``episode.mcap.partial``."""
    path = pathlib.Path(path)
    return path.with_name(path.name + PARTIAL_SUFFIX)


def replace_file(source: pathlib.Path, target: pathlib.Path) -> None:
    """``os.replace(source, target)``, leaving the freeing of a replaced file's blocks to a background thread: the
    old file is held open across the rename, so the rename itself is quick (freeing a file of a few megabytes takes
    milliseconds), and closed afterwards. The rename is as atomic as ``os.replace``."""
    try:
        old = os.open(target, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except OSError:  # no file there, or a link (or one we cannot read: the rename frees it, as os.replace would)
        old = None
    try:
        os.replace(source, target)
    finally:
        if old is not None:
            _release_later(old)


_RELEASE: tuple[int, queue.SimpleQueue[int]] | None = None  # the release thread's process and queue of descriptors
_RELEASE_LOCK = threading.Lock()


def _release_later(fd: int) -> None:
    """Close ``fd`` on this process's release thread (started on first use; a forked child starts its own)."""
    global _RELEASE
    with _RELEASE_LOCK:
        if _RELEASE is None or _RELEASE[0] != os.getpid():
            _RELEASE = (os.getpid(), queue.SimpleQueue())
            threading.Thread(target=_release, args=(_RELEASE[1],), name="release-replaced-files", daemon=True).start()
        fds = _RELEASE[1]
    fds.put(fd)


def _release(fds: queue.SimpleQueue[int]) -> None:
    while True:
        os.close(fds.get())


@cache
def _schema(topic: str) -> tuple[str, bytes]:
    """The schema name and serialized ``FileDescriptorSet`` of a topic (built once per process)."""
    cls: type[Message] = topics.TOPIC_TYPES[topic]
    return cls.DESCRIPTOR.full_name, build_file_descriptor_set(cls).SerializeToString()


LOG_VEHICLE_ROWS = len(kernel.LOG_VEHICLE_ROWS)
"""Per-vehicle rows of a step log row (:mod:`lcsim.kernel`): x, y, yaw, speed, accel, lane, target_lane."""
_EGO_COLUMNS = slice(kernel.LOG_SPEED, kernel.LOG_BRAKE + 1)  # the ego rows of write_sim_steps, in their order
assert kernel.LOG_NAMES[_EGO_COLUMNS] == ("speed", "lane", "collision_with", "lane_invasion", "off_road", "steer",
                                          "throttle", "brake")  # fmt: skip


_NO_POSE = np.zeros((0, 0))
_INT64, _FLOAT64, _UINT8 = np.dtype(np.int64), np.dtype(np.float64), np.dtype(np.uint8)
_NO_IMAGE = np.zeros((0, 0, 0), dtype=np.uint8)


class DecisionBatch(NamedTuple):
    """See :meth:`EpisodeWriter.decision_batch`: the layout of the decisions (:func:`lcdata.sim_records.
    decision_records`' constants, the vehicles' ids, whether there is a pose, the image's shape or zeros), the time
    origin, and the chunk buffer, position, message index and its length, and the chunk size."""

    channels: np.ndarray
    consts: np.ndarray
    spans: np.ndarray
    quaternions: np.ndarray
    ids: np.ndarray
    with_pose: bool
    image_shape: tuple[int, int, int]
    origin_ns: int
    out: np.ndarray
    end: int
    index: np.ndarray
    messages: int
    chunk_size: int


def _fixed_arrays(fixed: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``ids`` (int64), ``length``, ``width`` (float64) as contiguous arrays."""
    ids, length, width = fixed
    return (np.ascontiguousarray(ids, dtype=np.int64), np.ascontiguousarray(length, dtype=np.float64),
            np.ascontiguousarray(width, dtype=np.float64))


def _step_bytes(n: int) -> int:
    """An upper bound of the bytes of one step's ``/vehicles`` and ``/ego/state`` records for N vehicles."""
    return 2 * mcap_write.MESSAGE_HEADER_BYTES + sim_records.HEAD_MAX_BYTES + 10 * 11 + 68 * n + sim_records.EGO_MAX_BYTES


OUTCOMES = (RUNNING, *EPISODE_OUTCOMES)
"""The ``/rl/step`` outcomes by code (:data:`lcdata.sim_records.RL_FIELDS`' ``outcome``)."""
OUTCOME_CODES = {name: code for code, name in enumerate(OUTCOMES)}
_REWARD_KEYS = ("collision", "off_road", "forward", "success")


class EpisodeSink:
    """What the episode writers share: the file names, the refusal to overwrite, the time origin, the recorder's
    composite calls (:meth:`write_sim_log`, :meth:`write_view`) made of the single ones, and ``with`` support
    (:meth:`close` when the block ends normally, :meth:`abort` when it raises: the file stays ``.partial``)."""

    path: pathlib.Path
    partial_path: pathlib.Path
    start_time_ns: int

    def _claim(self, path: str | os.PathLike[str], overwrite: bool, start_time_ns: int | None) -> None:
        """Set :attr:`path`, :attr:`partial_path` and :attr:`start_time_ns` (default: now); raise
        ``FileExistsError`` for an existing file unless ``overwrite``; create the folder."""
        self.path = pathlib.Path(path)
        self.partial_path = partial_path(self.path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} already exists; pass overwrite=True to replace it")
        self.start_time_ns = time.time_ns() if start_time_ns is None else int(start_time_ns)
        if not 0 <= self.start_time_ns <= MAX_START_TIME_NS:
            raise ValueError(f"start_time_ns must be in [0, {MAX_START_TIME_NS}] (1970 to 2262-01-01), got "
                             f"{self.start_time_ns}")
        self.path.parent.mkdir(parents=True, exist_ok=True)

    def write_sim_steps(self, steps: Sequence[int], ts: Sequence[float], vehicles: Sequence[Any],
                        ego: Sequence[Sequence[float]]) -> None:  # fmt: skip
        raise NotImplementedError

    def write_collision(self, step: int, t_s: float, *, other_id: int, ego_x: float, ego_y: float, ego_speed: float,
                        other_speed: float) -> None:  # fmt: skip
        raise NotImplementedError

    def write_event(self, step: int, t_s: float, kind: str, text: str = "", level: str = "info") -> None:
        raise NotImplementedError

    def write_transform(self, step: int, t_s: float, x: float, y: float, yaw: float) -> None:
        raise NotImplementedError

    def write_scene(self, step: int, t_s: float, ids: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                    length: np.ndarray, width: np.ndarray, *, height_m: float = 1.5, ego_id: int = 0) -> None:  # fmt: skip
        raise NotImplementedError

    def write_image(self, step: int, t_s: float, chw: np.ndarray) -> None:
        raise NotImplementedError

    def write_rl_step(self, step: int, t_s: float, *, action: int, action_mask: np.ndarray, reward: float,
                      reward_components: Mapping[str, float], terminated: bool = False, truncated: bool = False,
                      outcome: str = "", decision: int = 0, obs_current: np.ndarray | None = None) -> None:  # fmt: skip
        raise NotImplementedError

    def write_sim_log(self, log: np.ndarray, fixed: Sequence[np.ndarray], off_road: bool, lc_active: bool) -> None:
        """K simulation steps of one environment as the simulator logs them (the recorder's hot path): each step's
        ``/vehicles`` and ``/ego/state`` (:meth:`write_sim_steps`), and right after a step where the ego meets one,
        its events: ``/ego/collision`` and ``/log`` ``collision``, ``lane_invasion``, ``off_road``/``on_road``,
        ``lane_change_start``/``_end``.

        Args:
            log: (K, W) float64 rows of :func:`lcsim.kernel.log_state` (the ego is vehicle 0 of N), C-contiguous.
            fixed: ``ids``, ``length``, ``width``, (N,) each, the same at every step.
            off_road, lc_active: the ego's state before the first step (after them, the last row's).
        """
        log = np.ascontiguousarray(log, dtype=np.float64)
        while len(log):
            i = sim_records.log_event_row(log, bool(off_road), bool(lc_active))
            if i < 0:
                self._write_log_steps(log, fixed)
                return
            self._write_log_steps(log[: i + 1], fixed)
            self._write_log_events(log[i], off_road, lc_active)
            off_road, lc_active = log[i, kernel.LOG_OFF_ROAD] != 0, log[i, kernel.LOG_LC_ACTIVE] != 0
            log = log[i + 1 :]

    def _write_log_steps(self, log: np.ndarray, fixed: Sequence[np.ndarray]) -> None:
        """The ``/vehicles`` and ``/ego/state`` records of the steps of a log, no events."""
        k = len(log)
        n = (log.shape[1] - kernel.LOG_HEAD) // LOG_VEHICLE_ROWS
        state = log[:, kernel.LOG_HEAD :].reshape(k, LOG_VEHICLE_ROWS, n)
        ids, length, width = fixed
        columns = (ids, *(state[:, j] for j in range(LOG_VEHICLE_ROWS)), length, width)
        self.write_sim_steps(log[:, kernel.LOG_STEP], log[:, kernel.LOG_T], columns, log[:, _EGO_COLUMNS])

    def _write_log_events(self, row: np.ndarray, off_road: bool, lc_active: bool) -> None:
        """The events of one step log row (the ego's state before it: ``off_road``, ``lc_active``)."""
        n = (len(row) - kernel.LOG_HEAD) // LOG_VEHICLE_ROWS
        step, t = int(row[kernel.LOG_STEP]), float(row[kernel.LOG_T])
        collision_with, invasion = int(row[kernel.LOG_COLLISION]), int(row[kernel.LOG_INVASION])
        off, active = bool(row[kernel.LOG_OFF_ROAD]), bool(row[kernel.LOG_LC_ACTIVE])
        vehicles = row[kernel.LOG_HEAD :].reshape(LOG_VEHICLE_ROWS, n)  # x, y, yaw, speed, accel, lane, target_lane
        if collision_with >= 0:
            self.write_collision(step, t, other_id=collision_with, ego_x=float(vehicles[0, 0]),
                                 ego_y=float(vehicles[1, 0]), ego_speed=float(vehicles[3, 0]),
                                 other_speed=float(vehicles[3, collision_with]))  # fmt: skip
            self.write_event(step, t, "collision", f"ego hit vehicle {collision_with}", "warning")
        if invasion >= 0:
            self.write_event(step, t, "lane_invasion", f"ego crossed marking {invasion}", "debug")
        if off != off_road:
            self.write_event(step, t, "off_road" if off else "on_road",
                             "ego left the road" if off else "ego back on the road",
                             "warning" if off else "info")  # fmt: skip
        if active != lc_active:
            lane, target = int(vehicles[5, 0]), int(vehicles[6, 0])
            if active:
                self.write_event(step, t, "lane_change_start", f"lane {lane} -> {target}")
            else:
                self.write_event(step, t, "lane_change_end", f"in lane {lane}")

    def write_view(self, step: int, t_s: float, pose: np.ndarray | None, fixed: Sequence[np.ndarray],
                   image: np.ndarray | None = None) -> None:  # fmt: skip
        """What the recorder writes at the start of a decision: ``/tf`` (the pose of vehicle 0, the ego) and
        ``/scene`` (:meth:`write_transform`, :meth:`write_scene`) from ``pose`` (3, N) x, y, yaw unless it is None,
        then the bird's-eye ``image`` (:meth:`write_image`) when given. ``fixed``: ``ids``, ``length``, ``width``."""
        if pose is not None:
            x, y, yaw = pose
            ids, length, width = fixed
            self.write_transform(step, t_s, x[0], y[0], yaw[0])
            self.write_scene(step, t_s, ids, x, y, yaw, length, width)
        if image is not None:
            self.write_image(step, t_s, image)

    def write_decision(self, step: int, t_s: float, pose: np.ndarray | None, image: np.ndarray | None,
                       log: np.ndarray, fixed: Sequence[np.ndarray], off_road: bool, lc_active: bool, rl: Sequence[float],
                       current: np.ndarray | None) -> None:  # fmt: skip
        """One decision of the recorder in one call: :meth:`write_view`, :meth:`write_sim_log` (its K >= 0 steps),
        :meth:`write_rl_step`.

        Args:
            step, t_s: the decision's. pose, image: :meth:`write_view`'s. log, fixed, off_road, lc_active:
                :meth:`write_sim_log`'s.
            rl: the values :data:`lcdata.sim_records.RL_FIELDS` of ``/rl/step`` (the outcome by its code in
                :data:`OUTCOMES`). current: the observation's ``current`` matrix (or None).
        """
        if pose is not None or image is not None:
            self.write_view(step, t_s, pose, fixed, image)
        self.write_sim_log(log, fixed, off_road, lc_active)
        values = np.asarray(rl, dtype=np.float64).tolist()
        self.write_rl_step(step, t_s, action=int(values[sim_records.RL_ACTION]),
                           action_mask=np.asarray(rl[sim_records.RL_MASK : sim_records.RL_MASK + 3]) != 0,
                           reward=values[sim_records.RL_REWARD],
                           reward_components=dict(zip(_REWARD_KEYS, values[sim_records.RL_REWARD + 1 :
                                                                           sim_records.RL_TERMINATED], strict=True)),
                           terminated=bool(values[sim_records.RL_TERMINATED]),
                           truncated=bool(values[sim_records.RL_TRUNCATED]),
                           outcome=OUTCOMES[int(values[sim_records.RL_OUTCOME])],
                           decision=int(values[sim_records.RL_DECISION]), obs_current=current)  # fmt: skip

    def close(self) -> pathlib.Path:
        raise NotImplementedError

    def abort(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class EpisodeWriter(EpisodeSink, DeciderStreams):
    """Stream one episode to ``path`` (an ``.mcap`` file). Use as a context manager.

    Args:
        path: final file name; data goes to ``path + ".partial"`` until :meth:`close`.
        metadata: episode description, stored in the MCAP metadata record ``"lc"``. Known keys:
            ``config`` (dict, stored as JSON), ``seed`` (int), ``driver`` (str), ``scenario`` (str),
            ``episode_id`` (str, default: the file stem), ``version`` (default: package version).
            Other keys are stored too (JSON-encoded unless they are strings).
        overwrite: replace an existing ``path`` instead of raising ``FileExistsError``.
        start_time_ns: time of ``t_s = 0`` (default: wall clock now).
        chunk_size: uncompressed chunk size in bytes (about 1 MiB by default).
        compression_level: zstd level (:data:`lcdata.mcap_write.COMPRESSION_LEVEL` by default).
        chunk_crc: store each chunk's CRC-32 (see :class:`~lcdata.mcap_write.McapStreamWriter`).
        background: compress and write chunks on a worker thread.

    If the ``with`` block raises, the file is left as ``.partial`` (still readable) and not renamed.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        metadata: Mapping[str, Any],
        overwrite: bool = False,
        start_time_ns: int | None = None,
        chunk_size: int = 1 << 20,
        compression_level: int = COMPRESSION_LEVEL,
        chunk_crc: bool = False,
        background: bool = True,
    ) -> None:
        self._claim(path, overwrite, start_time_ns)
        self.metadata = self._metadata_record(metadata)
        self._mcap = McapStreamWriter(
            open_partial(self.path),  # new, never through a link; closed by McapStreamWriter.finish/abort
            chunk_size=chunk_size,
            compression_level=compression_level,
            chunk_crc=chunk_crc,
            background=background,
            library=f"lc-toolkit/{self.metadata['version']}",
        )
        self._mcap.add_metadata(topics.METADATA_NAME, self.metadata)
        self._channels: dict[str, int] = {}
        self._vehicle_encoder = encode.VehicleEncoder()
        self._cube_encoder = encode.CubeEncoder()
        self._image_encoder = encode.ImageEncoder()
        self._step_encoder = SimStepEncoder()
        self._scene_ids: np.ndarray | None = None
        self._scene_ego = 0
        self._scene_rgba = np.zeros((0, 4))
        self._lane_primitives = b""  # the lane markings, repeated in every /scene message
        self._layouts: dict[tuple[Any, ...], tuple[Any, ...]] = {}  # write_decision's, by N, pose?, image shape
        self._last_layout: tuple[Any, ...] | None = None
        self._closed = False

    def _metadata_record(self, metadata: Mapping[str, Any]) -> dict[str, str]:
        record = {
            "config": "{}",
            "seed": "-1",
            "driver": "",
            "scenario": "",
            "version": package_version(),
            "episode_id": self.path.name.removesuffix(".mcap"),
        }
        for key, value in metadata.items():
            record[key] = value if isinstance(value, str) else json.dumps(value, sort_keys=True)
        record["start_time_ns"] = str(self.start_time_ns)
        return record

    # -- plumbing ---------------------------------------------------------------------------------
    def _channel(self, topic: str) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is None:
            name, schema = _schema(topic)
            schema_id = self._mcap.register_schema(name, "protobuf", schema)
            channel_id = self._channels[topic] = self._mcap.register_channel(topic, "protobuf", schema_id)
        return channel_id

    def _time_ns(self, t_s: float) -> int:
        return self.start_time_ns + round(t_s * 1e9)

    def _write(self, topic: str, t_s: float, data: bytes) -> None:
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        channel_id = self._channels.get(topic) or self._channel(topic)
        time_ns = self.start_time_ns + round(t_s * 1e9)
        self._mcap.add_message(channel_id, time_ns, data, time_ns)

    # -- per-step streams -------------------------------------------------------------------------
    def write_vehicles(
        self,
        step: int,
        t_s: float,
        ids: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        yaw: np.ndarray,
        speed: np.ndarray,
        accel: np.ndarray,
        lane: np.ndarray,
        target_lane: np.ndarray,
        length: np.ndarray,
        width: np.ndarray,
    ) -> None:
        """``/vehicles``: all vehicles, each argument (N,) (row ``e`` of the simulator's (E, N) arrays)."""
        data = self._vehicle_encoder.encode(step, t_s, ids, x, y, yaw, speed, accel, lane, target_lane, length, width)
        self._write(topics.VEHICLES, t_s, data)

    def write_ego(
        self,
        step: int,
        t_s: float,
        *,
        speed: float,
        lane: int,
        collision_with: int = -1,
        lane_invasion: int = -1,
        off_road: bool = False,
        steer: float = 0.0,
        throttle: float = 0.0,
        brake: float = 0.0,
    ) -> None:
        """``/ego/state``: ego sensors and controls (scalars)."""
        data = encode.encode_ego(
            step, t_s, speed, lane, collision_with, lane_invasion, off_road, steer, throttle, brake
        )
        self._write(topics.EGO_STATE, t_s, data)

    def write_sim_step(
        self, step: int, t_s: float, vehicles: Sequence[np.ndarray], ego_speed: float, ego_lane: int,
        collision_with: int, lane_invasion: int, off_road: bool, steer: float, throttle: float, brake: float,
    ) -> None:  # fmt: skip
        """:meth:`write_vehicles` and :meth:`write_ego` of one simulation step in one call.

        ``vehicles``: the (N,) arrays :data:`~lcdata.encode.VEHICLE_COLUMNS`, as :meth:`write_vehicles` takes them.
        """
        ego = ((ego_speed, ego_lane, collision_with, lane_invasion, off_road, steer, throttle, brake),)
        self.write_sim_steps((step,), (t_s,), vehicles, ego)

    def write_sim_steps(self, steps: Sequence[int], ts: Sequence[float], vehicles: Sequence[Any],
                        ego: Sequence[Sequence[float]]) -> None:  # fmt: skip
        """K consecutive simulation steps in one call (the recorder's hot path): what :meth:`write_vehicles`
        and :meth:`write_ego` write for each step in turn, encoded together.

        Args:
            steps: K ints. ts: K floats, seconds.
            vehicles: the columns :data:`~lcdata.encode.VEHICLE_COLUMNS`, each given as a (K, N) array,
                as a list of K arrays of N values (one per step, e.g. (1, N) rows of a simulator's
                arrays), or as one (N,) array when it is the same at every step of the call.
            ego: K rows of 8 numbers: speed, lane, collision_with, lane_invasion, off_road, steer,
                throttle, brake.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        steps = np.asarray(steps).astype(np.int64, copy=False).reshape(-1)
        ts = np.asarray(ts, dtype=np.float64).reshape(-1)
        ego = np.asarray(ego, dtype=np.float64)
        k = len(steps)
        if len(ts) != k or len(ego) != k or (k and ego.shape != (k, 8)):
            raise ValueError(f"steps, ts and ego must have one entry per step (ego 8 numbers each), got {k}, "
                             f"{len(ts)}, {ego.shape}")  # fmt: skip
        if not k:
            return
        columns = [np.reshape(c, (k, np.size(c[0]))) if isinstance(c, (list, tuple)) else c for c in vehicles]
        channels = self._channels
        vehicles_id = channels.get(topics.VEHICLES) or self._channel(topics.VEHICLES)
        ego_id = channels.get(topics.EGO_STATE) or self._channel(topics.EGO_STATE)
        records, times, sizes = self._step_encoder.encode(steps, ts, ego, columns, self.start_time_ns, vehicles_id,
                                                          ego_id)  # fmt: skip
        ids = np.empty(2 * k, dtype=np.int64)
        ids[0::2], ids[1::2] = vehicles_id, ego_id
        self._mcap.add_message_records(records, ids, times, sizes)

    # -- the recorder's hot path: compiled straight into the chunk buffer -------------------------------------------
    def _write_log_steps(self, log: np.ndarray, fixed: Sequence[np.ndarray]) -> None:
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        channels = self._channels
        vehicles_id = channels.get(topics.VEHICLES) or self._channel(topics.VEHICLES)
        ego_id = channels.get(topics.EGO_STATE) or self._channel(topics.EGO_STATE)
        ids, length, width = _fixed_arrays(fixed)
        k = len(log)
        out, p, index, m = self._mcap.records_target(k * _step_bytes(ids.size), 2 * k)
        p, m = sim_records.log_records(out, p, index, m, np.ascontiguousarray(log, dtype=np.float64), ids, length,
                                       width, self.start_time_ns, vehicles_id, ego_id)  # fmt: skip
        self._mcap.records_written(p, m)

    def write_decision(self, step: int, t_s: float, pose: np.ndarray | None, image: np.ndarray | None,
                       log: np.ndarray, fixed: Sequence[np.ndarray], off_road: bool, lc_active: bool, rl: Sequence[float],
                       current: np.ndarray | None) -> None:  # fmt: skip
        """See :meth:`EpisodeSink.write_decision`: one compiled call lays the records out in the chunk buffer, once
        every topic has its channel (the first decision registers them) and unless an event happens in the steps."""
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        ids, length, width = fixed
        layout = self._decision_layout(pose, image, fixed, log, current)
        if layout is not None:
            channels, consts, spans, quaternions = layout
            if pose is not None:
                yaw = pose.item(2, 0)
                x, y, qz, qw = pose.item(0, 0), pose.item(1, 0), math.sin(yaw / 2), math.cos(yaw / 2)
                half = pose[2] / 2  # the quaternions of the cubes, as CubeEncoder computes them
                np.sin(half, out=quaternions[0])
                np.cos(half, out=quaternions[1])
            else:
                pose, x, y, qz, qw = _NO_POSE, 0.0, 0.0, 0.0, 0.0
            pixels = _NO_IMAGE if image is None else image
            values = np.asarray(rl, dtype=np.float64)
            time_ns = self.start_time_ns + round(t_s * 1e9)
            off_road, lc_active = bool(off_road), bool(lc_active)
            while True:  # once, or once more after each step with events (written one call at a time)
                k = len(log)
                nbytes = consts.size + 512 + pixels.size + k * _step_bytes(len(ids)) + 4 * current.size
                out, p, index, m = self._mcap.records_target(nbytes, 4 + 2 * k)
                p, m, event = sim_records.decision_records(out, p, index, m, channels, consts, spans, time_ns,
                                                           self.start_time_ns, step, t_s, pose, ids, length, width, x,
                                                           y, qz, qw, quaternions, pixels, log, off_road, lc_active,
                                                           values, current)  # fmt: skip
                self._mcap.records_written(p, m)
                if event < 0:
                    return
                row = log[event]
                self._write_log_events(row, off_road, lc_active)
                off_road, lc_active = row[kernel.LOG_OFF_ROAD] != 0, row[kernel.LOG_LC_ACTIVE] != 0
                pose, pixels, log = _NO_POSE, _NO_IMAGE, log[event + 1 :]
        super().write_decision(step, t_s, pose, image, log, fixed, off_road, lc_active, rl, current)

    def _decision_layout(self, pose: np.ndarray | None, image: np.ndarray | None, fixed: Sequence[np.ndarray],
                         log: np.ndarray, current: np.ndarray | None,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:  # fmt: skip
        """``(channels, consts, spans, quaternions)`` of :func:`lcdata.sim_records.decision_records` for such a
        decision, or None when it goes through the single calls: a topic without its channel yet, arrays that are
        not contiguous or not of the recorder's types, an image or an observation that those calls check."""
        ids, length, width = fixed
        floats = (length, width, log) if pose is None else (length, width, log, pose)
        if (current is None or current.ndim != 2 or not current.flags.c_contiguous or ids.dtype != _INT64
                or not ids.flags.c_contiguous or not all(a.dtype == _FLOAT64 and a.flags.c_contiguous for a in floats)
                or (image is not None and (image.dtype != _UINT8 or image.ndim != 3 or image.shape[0] != 3
                                           or not image.flags.c_contiguous))):  # fmt: skip
            return None
        key = (len(ids), pose is not None, None if image is None else image.shape)
        cached = self._layouts.get(key)
        self._last_layout = key
        if cached is not None and cached[4] is self._lane_primitives and cached[5] == ids.tobytes():
            return cached[:4]
        channels = self._channels
        wanted = (topics.VEHICLES, topics.EGO_STATE, topics.RL_STEP, *((topics.TF, topics.SCENE) if pose is not None
                                                                         else ()),
                  *((topics.CAMERA_BEV,) if image is not None else ()))  # fmt: skip
        if not all(topic in channels for topic in wanted):
            return None
        parts = [b""] * (sim_records.S_OUTCOMES + len(OUTCOMES))
        parts[sim_records.S_TF_HEAD] = encode.TRANSFORM_HEAD
        parts[sim_records.S_TF_ROTATION] = encode.TRANSFORM_ROTATION
        parts[sim_records.S_VEHICLES_ENTITY] = f_string(2, topics.WORLD_FRAME) + f_string(3, "vehicles")
        parts[sim_records.S_LANES_ENTITY] = f_string(2, topics.WORLD_FRAME) + f_string(3, "lanes")
        parts[sim_records.S_LANES] = self._lane_primitives
        rgba = np.where((ids == 0)[:, None], EGO_RGBA, TRAFFIC_RGBA)  # as write_scene colours them
        records, offsets = encode.CubeEncoder().template(len(ids), 1.5, rgba)
        parts[sim_records.S_CUBES] = records.tobytes()
        if image is not None:
            parts[sim_records.S_IMAGE_HEAD], parts[sim_records.S_IMAGE_TAIL] = self._image_encoder.parts(
                image.shape[1], image.shape[2])
        for code, name in enumerate(OUTCOMES):
            parts[sim_records.S_OUTCOMES + code] = f_string(13, name)
        ends = np.cumsum([len(part) for part in parts])
        spans = np.stack((ends - [len(part) for part in parts], ends), axis=1)
        spans[sim_records.S_CUBE_FIELDS : sim_records.S_CUBE_FIELDS + 6] = np.array(offsets)[:, None]
        ids_of = [channels.get(topic, 0) for topic in (topics.TF, topics.SCENE, topics.CAMERA_BEV, topics.VEHICLES,
                                                       topics.EGO_STATE, topics.RL_STEP)]  # fmt: skip
        layout = (np.array(ids_of, dtype=np.int64), np.frombuffer(b"".join(parts), dtype=np.uint8), spans,
                  np.empty((2, len(ids))), self._lane_primitives, ids.tobytes(), ids.copy(), key)  # fmt: skip
        self._layouts[key] = layout
        return layout[:4]

    def decision_batch(self) -> DecisionBatch | None:
        """What a compiled loop over many decisions of the last layout :meth:`write_decision` used needs to write
        them straight into this writer's chunk buffer (the process writer's helper runs such a loop over the
        records it receives), or None before the first decision or after the lane markings changed."""
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        layout = self._layouts.get(self._last_layout) if self._last_layout is not None else None
        if layout is None or layout[4] is not self._lane_primitives:
            return None
        channels, consts, spans, quaternions, _, _, ids, (_, with_pose, image_shape) = layout
        out, p, index, m = self._mcap.records_target(0, 0)
        return DecisionBatch(channels, consts, spans, quaternions, ids, with_pose, image_shape or (0, 0, 0),
                             self.start_time_ns, out, p, index, m, self._mcap.chunk_size)

    def decisions_written(self, end: int, messages: int) -> None:
        """After a compiled loop given :meth:`decision_batch`: its records end at ``end``, the index has
        ``messages`` entries (:meth:`lcdata.mcap_write.McapStreamWriter.records_written`)."""
        self._mcap.records_written(end, messages)

    def write_collision(
        self,
        step: int,
        t_s: float,
        *,
        other_id: int,
        ego_x: float,
        ego_y: float,
        ego_speed: float,
        other_speed: float,
    ) -> None:
        """``/ego/collision``: call only on steps where the ego collides."""
        msg = lc_pb2.EgoCollision(
            step=int(step), t=float(t_s), other_id=int(other_id), ego_x=float(ego_x), ego_y=float(ego_y),
            ego_speed=float(ego_speed), other_speed=float(other_speed),
        )  # fmt: skip
        self._write(topics.EGO_COLLISION, t_s, msg.SerializeToString())

    def write_transform(self, step: int, t_s: float, x: float, y: float, yaw: float) -> None:
        """``/tf``: world -> ego frame transform (ego pose on the road plane). ``step`` is unused."""
        del step
        self._write(
            topics.TF, t_s, encode.encode_transform(self._time_ns(t_s), float(x), float(y), float(yaw))
        )

    def write_image(self, step: int, t_s: float, chw: np.ndarray) -> None:
        """``/camera/bev_semantic``: a (3, H, W) uint8 bird's-eye image as ``foxglove.RawImage`` rgb8.

        The step is recovered from the timestamp by the reader (images share the time of the step).
        """
        del step
        self._write(topics.CAMERA_BEV, t_s, self._image_encoder.encode(self._time_ns(t_s), chw))

    def write_scene(
        self,
        step: int,
        t_s: float,
        ids: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        yaw: np.ndarray,
        length: np.ndarray,
        width: np.ndarray,
        *,
        height_m: float = 1.5,
        ego_id: int = 0,
    ) -> None:
        """``/scene``: vehicles as cubes (entity ``vehicles``, replaced at every call) and the lane markings
        of :meth:`write_lane_markings` (entity ``lanes``), so that each message is the whole scene. Arrays (N,)."""
        del step
        ids = np.asarray(ids)
        if self._scene_ids is None or self._scene_ego != ego_id or not np.array_equal(self._scene_ids, ids):
            self._scene_ids, self._scene_ego = ids.copy(), ego_id
            self._scene_rgba = np.where((ids == ego_id)[:, None], EGO_RGBA, TRAFFIC_RGBA)
        cubes = self._cube_encoder.encode(x, y, yaw, length, width, height_m, self._scene_rgba)
        time_ns = self._time_ns(t_s)
        data = encode.encode_scene_entity_update(time_ns, "vehicles", cubes)
        if self._lane_primitives:  # two encoded SceneUpdates joined are one with both entities
            data += encode.encode_scene_entity_update(time_ns, "lanes", self._lane_primitives)
        self._write(topics.SCENE, t_s, data)

    def write_lane_markings(
        self, t_s: float, lines: Sequence[np.ndarray], solid: Sequence[bool], *, thickness_m: float = 0.15
    ) -> None:
        """``/scene``: the static lane markings (entity ``lanes``), call once per episode: written now and
        repeated in every later :meth:`write_scene` message. ``lines``: (K, 2) polylines."""
        self._lane_primitives = b"".join(
            encode.encode_line_strip(points, thickness_m, (1, 1, 1, 1) if is_solid else (0.8, 0.8, 0.8, 0.7))
            for points, is_solid in zip(lines, solid, strict=True)
        )
        self._write(topics.SCENE, t_s, encode.encode_scene_entity_update(self._time_ns(t_s), "lanes",
                                                                         self._lane_primitives))

    def write_event(self, step: int, t_s: float, kind: str, text: str = "", level: str = "info") -> None:
        """``/log``: an event (``kind`` in the Log ``name``; the step in ``file``/``line`` as ``step:<n>``)."""
        if level not in LOG_LEVELS:
            raise ValueError(f"level must be one of {sorted(LOG_LEVELS)}, got {level!r}")
        msg = Log(level=LOG_LEVELS[level], message=text, name=kind, file="step", line=int(step))
        msg.timestamp.FromNanoseconds(self._time_ns(t_s))
        self._write(topics.LOG, t_s, msg.SerializeToString())

    def write_rl_step(
        self,
        step: int,
        t_s: float,
        *,
        action: int,
        action_mask: np.ndarray,
        reward: float,
        reward_components: Mapping[str, float],
        terminated: bool = False,
        truncated: bool = False,
        outcome: str = "",
        decision: int = 0,
        obs_current: np.ndarray | None = None,
    ) -> None:
        """``/rl/step``: one decision. ``action_mask`` (3,) bool (right, keep, left);
        ``reward_components`` keys ``collision, off_road, forward, success`` (missing = 0);
        ``obs_current``: the observation's ``current`` matrix, e.g. (9, 9), stored as float32."""
        unknown = set(reward_components) - {"collision", "off_road", "forward", "success"}
        if unknown:
            raise ValueError(f"unknown reward components {sorted(unknown)}")
        data = encode.encode_rl_step(
            int(step), float(t_s), int(decision), int(action), np.asarray(action_mask, dtype=bool).tolist(),
            float(reward), float(reward_components.get("collision", 0.0)),
            float(reward_components.get("off_road", 0.0)), float(reward_components.get("forward", 0.0)),
            float(reward_components.get("success", 0.0)), bool(terminated), bool(truncated), outcome,
            None if obs_current is None else np.asarray(obs_current, dtype=np.float32),
        )  # fmt: skip
        self._write(topics.RL_STEP, t_s, data)

    # -- life cycle -------------------------------------------------------------------------------
    @property
    def message_count(self) -> int:
        """Messages written so far (all topics)."""
        return sum(self._mcap.message_counts.values())

    def close(self) -> pathlib.Path:
        """Finish the file and rename ``.partial`` to the final name; return the final path."""
        if not self._closed:
            self._closed = True
            self._mcap.finish()
            replace_file(self.partial_path, self.path)
            log.debug("wrote %s", self.path)
        return self.path

    def flush(self) -> None:
        """Close the chunk in progress and write it out now (before it is full), so that it is
        recoverable from the ``.partial`` file whatever happens next."""
        if not self._closed:
            self._mcap.flush_chunk()

    def abort(self) -> None:
        """Stop writing without finishing: the ``.partial`` file stays (recoverable)."""
        if not self._closed:
            self._closed = True
            self._mcap.abort()
            log.info("episode aborted; partial file left at %s", self.partial_path)  # the caller says why

