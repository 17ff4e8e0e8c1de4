"""Read recorded episodes back into pandas DataFrames.

``read_episode(path)`` scans the whole file once (:func:`lcdata.mcap_scan.scan_mcap`); tables are
decoded on first access and cached. ``/vehicles`` is decoded straight from the protobuf wire bytes
into numpy (one ``np.frombuffer`` per column over all messages), the low-rate topics with the
protobuf runtime. A truncated or ``.partial`` file yields every complete chunk and a
:class:`TruncatedFileWarning` saying how many messages were recovered. What one file may cost to read is
bounded by its size (:class:`lcdata.mcap_scan.Limits`); chunks compressed with zstd, lz4 or not at all read,
whichever writer made them, and each topic's messages come in log-time order.
"""

from __future__ import annotations

import functools
import json
import os
import pathlib
import warnings
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy as np
import pandas as pd
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from lcdata import decider_records, topics
from lcdata.fast_tracks import decode_tracks_fast
from lcdata.mcap_scan import ChannelData, ScanResult, scan_mcap
from lcdata.proto import lc_pb2
from lcdata.wire import WIRE_I32, WIRE_I64, WIRE_LEN, WIRE_VARINT, iter_fields, to_int64

TRACK_COLUMNS = ["episode", "step", "t", "vehicle_id", "x", "y", "yaw", "speed", "accel", "lane",
                 "target_lane", "length", "width", "is_ego"]  # fmt: skip
EGO_COLUMNS = [
    "step",
    "t",
    "speed",
    "lane",
    "collision_with",
    "lane_invasion",
    "off_road",
    "steer",
    "throttle",
    "brake",
]
STEP_COLUMNS = ["step", "t", "decision", "action", "mask_right", "mask_keep", "mask_left", "reward", "r_collision",
                "r_off_road", "r_forward", "r_success", "terminated", "truncated", "outcome"]  # fmt: skip
EVENT_COLUMNS = ["step", "t", "kind", "text", "level"]
PREDICTION_COLUMNS = ["step", "t", "slot", "vehicle_id", "k", "x", "y"]
COLLISION_COLUMNS = ["step", "t", "other_id", "ego_x", "ego_y", "ego_speed", "other_speed"]

# VehicleTracks field number -> (column, numpy wire dtype)
_TRACK_FIELDS: dict[int, tuple[str, str]] = {
    3: ("vehicle_id", "<i4"), 4: ("x", "<f8"), 5: ("y", "<f8"), 6: ("yaw", "<f8"), 7: ("speed", "<f8"),
    8: ("accel", "<f8"), 9: ("lane", "<i4"), 10: ("target_lane", "<i4"), 11: ("length", "<f8"), 12: ("width", "<f8"),
}  # fmt: skip
_LEVEL_NAMES = {v: k.lower() for k, v in Log.Level.items()}
T = TypeVar("T")


class TruncatedFileWarning(UserWarning):
    """A file ended early (killed writer, ``.partial`` file); complete chunks were recovered."""



def _decoding(method: Callable[..., T]) -> Callable[..., T]:
    """Turn any error of decoding a damaged file (a flipped byte the chunk CRCs cannot see, a foreign writer's
    message) into one ``ValueError`` that names the file: recordings come from elsewhere."""

    @functools.wraps(method)
    def wrapper(self: Episode, *args: Any, **kwargs: Any) -> T:
        try:
            return method(self, *args, **kwargs)
        except ValueError as exc:
            if str(self.path) in str(exc):
                raise
            raise ValueError(f"{self.path}: corrupt data ({' '.join(str(exc).split())[:200]})") from None
        except Exception as exc:
            raise ValueError(f"{self.path}: corrupt data ({type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:200]})") from None

    return wrapper

class Episode:
    """One recorded episode. Tables are pandas DataFrames built on first access.

    Attributes:
        path: the file read.
        metadata: ``config`` (dict), ``seed`` (int), ``driver``, ``scenario``, ``version``,
            ``episode_id`` (str), ``start_time_ns`` (int); from :func:`lcdata.record_episode` also
            ``episode_seed`` (int), ``autopilot`` (bool), ``steps_per_decision`` (int) and
            ``driver_description`` (str); any other keys as str.
        complete: False when the file was truncated and only complete chunks were recovered.
        message_count: messages read.
    """

    def __init__(self, path: pathlib.Path, scan: ScanResult) -> None:
        self.path = path
        self._scan = scan
        self.metadata = _parse_metadata(scan.metadata.get(topics.METADATA_NAME, {}), path)
        self.complete = scan.complete
        self.message_count = scan.messages
        self.episode_id: str = self.metadata["episode_id"]

    def __repr__(self) -> str:
        return f"Episode({self.episode_id!r}, path={str(self.path)!r}, messages={self.message_count})"

    @property
    def topics(self) -> list[str]:
        """Topics present in the file."""
        return sorted(self._scan.channels)

    def _payloads(self, topic: str) -> ChannelData | None:
        return self._scan.channels.get(topic)

    def _t(self, log_times: list[int]) -> np.ndarray:
        return (np.asarray(log_times, dtype=np.int64) - self.metadata["start_time_ns"]) / 1e9

    @functools.cached_property
    @_decoding
    def tracks(self) -> pd.DataFrame:
        """Long form, one row per vehicle per simulation step: ``TRACK_COLUMNS``."""
        channel = self._payloads(topics.VEHICLES)
        cols = _decode_tracks(channel.payloads if channel else [], self.path)
        n = len(cols["x"])
        cols["episode"] = pd.Categorical.from_codes(np.zeros(n, dtype=np.int8), categories=[self.episode_id])
        cols["is_ego"] = cols["vehicle_id"] == 0
        return pd.DataFrame({name: cols[name] for name in TRACK_COLUMNS})

    @functools.cached_property
    @_decoding
    def ego(self) -> pd.DataFrame:
        """One row per simulation step: ``EGO_COLUMNS``."""
        channel = self._payloads(topics.EGO_STATE)
        rows = [lc_pb2.EgoState.FromString(p) for p in (channel.payloads if channel else [])]
        data = {name: [getattr(m, name) for m in rows] for name in EGO_COLUMNS}
        return _frame(
            data, EGO_COLUMNS, ints=("step", "lane", "collision_with", "lane_invasion"), bools=("off_road",)
        )

    @functools.cached_property
    @_decoding
    def steps(self) -> pd.DataFrame:
        """One row per RL decision: ``STEP_COLUMNS``."""
        channel = self._payloads(topics.RL_STEP)
        rows = [lc_pb2.RLStep.FromString(p) for p in (channel.payloads if channel else [])]
        data: dict[str, list[Any]] = {name: [] for name in STEP_COLUMNS}
        for m in rows:
            mask = list(m.action_mask) + [False] * (3 - len(m.action_mask))
            for name in STEP_COLUMNS:
                if name.startswith("mask_"):
                    data[name].append(mask[("mask_right", "mask_keep", "mask_left").index(name)])
                else:
                    data[name].append(getattr(m, name))
        return _frame(data, STEP_COLUMNS, ints=("step", "decision", "action"),
                      bools=("mask_right", "mask_keep", "mask_left", "terminated", "truncated"))  # fmt: skip

    @_decoding
    def observations(self) -> dict[int, np.ndarray]:
        """The ``current`` observation matrices of the RL steps that carry one: step -> float32 array."""
        channel = self._payloads(topics.RL_STEP)
        out = {}
        for p in channel.payloads if channel else []:
            m = lc_pb2.RLStep.FromString(p)
            if m.obs_current_shape:
                out[m.step] = np.asarray(m.obs_current, dtype=np.float32).reshape(tuple(m.obs_current_shape))
        return out

    @functools.cached_property
    @_decoding
    def events(self) -> pd.DataFrame:
        """``/log`` events: ``EVENT_COLUMNS`` (``kind`` is the Log name)."""
        channel = self._payloads(topics.LOG)
        data: dict[str, list[Any]] = {name: [] for name in EVENT_COLUMNS}
        if channel:
            for p, t in zip(channel.payloads, self._t(channel.log_times), strict=True):
                m = Log.FromString(p)
                data["step"].append(m.line if m.file == "step" else self._step_at(int(t * 1e9)))
                data["t"].append(t)
                data["kind"].append(m.name)
                data["text"].append(m.message)
                data["level"].append(_LEVEL_NAMES.get(m.level, "unknown"))
        return _frame(data, EVENT_COLUMNS, ints=("step",))

    @functools.cached_property
    @_decoding
    def collisions(self) -> pd.DataFrame:
        """``/ego/collision`` messages: ``COLLISION_COLUMNS``."""
        channel = self._payloads(topics.EGO_COLLISION)
        rows = [lc_pb2.EgoCollision.FromString(p) for p in (channel.payloads if channel else [])]
        data = {name: [getattr(m, name) for m in rows] for name in COLLISION_COLUMNS}
        return _frame(data, COLLISION_COLUMNS, ints=("step", "other_id"))

    @functools.cached_property
    @_decoding
    def predictions(self) -> pd.DataFrame:
        """``/prediction`` in long form: ``PREDICTION_COLUMNS`` (k = 1..F steps ahead); empty if absent."""
        channel = self._payloads(topics.PREDICTION)
        parts = []
        for p in channel.payloads if channel else []:
            m = lc_pb2.Prediction.FromString(p)
            xy = np.asarray(m.xy, dtype=np.float64).reshape(m.slots, m.horizon, 2)
            slot, k = np.meshgrid(np.arange(m.slots), np.arange(1, m.horizon + 1), indexing="ij")
            ids = np.asarray(m.vehicle_ids, dtype=np.int64)
            parts.append(
                pd.DataFrame(
                    {
                        "step": m.step,
                        "t": m.t,
                        "slot": slot.ravel(),
                        "vehicle_id": ids[slot.ravel()],
                        "k": k.ravel(),
                        "x": xy[..., 0].ravel(),
                        "y": xy[..., 1].ravel(),
                    }
                )
            )
        if not parts:
            return _frame(
                {name: [] for name in PREDICTION_COLUMNS}, PREDICTION_COLUMNS, ints=("step", "slot", "k")
            )
        return pd.concat(parts, ignore_index=True)

    @functools.cached_property
    @_decoding
    def decisions(self) -> pd.DataFrame:
        """``/planner/decision``: one row per decision where a planning driver had a choice,
        :data:`lcdata.decider_records.DECISION_COLUMNS` (``score_right|keep|left``: the share of its imagined futures
        each candidate survived, NaN where not scored); empty if absent."""
        channel = self._payloads(topics.PLANNER_DECISION)
        return decider_records.planner_decisions(channel.payloads if channel else [])

    @functools.cached_property
    @_decoding
    def imagined_paths(self) -> pd.DataFrame:
        """The ego's paths in the futures the planner imagined (``lc-record --imagined-paths``), decoded on first
        access: :data:`lcdata.decider_records.IMAGINED_PATH_COLUMNS`, one row per point; empty if none."""
        channel = self._payloads(topics.PLANNER_DECISION)
        return decider_records.imagined_paths(channel.payloads if channel else [])

    # -- images -----------------------------------------------------------------------------------
    @functools.cached_property
    @_decoding
    def _image_index(self) -> dict[int, memoryview]:
        channel = self._payloads(topics.CAMERA_BEV)
        if channel is None:
            return {}
        return {
            self._step_at(t - self.metadata["start_time_ns"]): p
            for t, p in zip(channel.log_times, channel.payloads, strict=True)
        }

    @property
    def image_steps(self) -> np.ndarray:
        """(M,) int64 steps that have a bird's-eye image, ascending."""
        return np.array(sorted(self._image_index), dtype=np.int64)

    def image(self, step: int) -> np.ndarray:
        """The (3, H, W) uint8 bird's-eye image recorded at ``step`` (decoded now). KeyError if none."""
        try:
            payload = self._image_index[int(step)]
        except KeyError:
            raise KeyError(f"{self.path}: no image at step {step}") from None
        return decode_raw_image(payload)

    def images(self) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(step, (3, H, W) uint8)`` in step order, decoding one image at a time."""
        for step in self.image_steps:
            yield int(step), self.image(int(step))

    @functools.cached_property
    @_decoding
    def _time_to_step(self) -> tuple[np.ndarray, np.ndarray]:
        for topic in (topics.EGO_STATE, topics.VEHICLES):
            channel = self._payloads(topic)
            if channel and channel.payloads:
                times = np.asarray(channel.log_times, dtype=np.int64) - self.metadata["start_time_ns"]
                steps = np.array([_leading_step(p) for p in channel.payloads], dtype=np.int64)
                order = np.argsort(times, kind="stable")
                return times[order], steps[order]
        return np.zeros(0, np.int64), np.zeros(0, np.int64)

    def _step_at(self, rel_ns: int) -> int:
        """Step of the latest per-step message at or before ``rel_ns`` (ns since the start); -1 if none."""
        times, steps = self._time_to_step
        i = int(np.searchsorted(times, rel_ns, side="right")) - 1
        return int(steps[i]) if i >= 0 else -1


def _leading_step(payload: memoryview) -> int:
    for field, wire_type, value in iter_fields(payload):
        if field == 1 and wire_type == WIRE_VARINT:
            return to_int64(int(value))  # type: ignore[arg-type]
    return 0


def decode_raw_image(payload: bytes | memoryview) -> np.ndarray:
    """``foxglove.RawImage`` (rgb8 or mono8) -> (3, H, W) uint8 (mono8 repeated on 3 channels)."""
    m = RawImage.FromString(payload)
    channels = {"rgb8": 3, "mono8": 1}.get(m.encoding)
    if channels is None:
        raise ValueError(f"unsupported image encoding {m.encoding!r} (expected rgb8 or mono8)")
    rows = np.frombuffer(m.data, dtype=np.uint8).reshape(m.height, m.step)
    hwc = rows[:, : m.width * channels].reshape(m.height, m.width, channels)
    return np.ascontiguousarray(np.broadcast_to(hwc.transpose(2, 0, 1), (3, m.height, m.width)))


def _frame(data: dict[str, list[Any]], columns: list[str], *, ints: tuple[str, ...] = (),
           bools: tuple[str, ...] = ()) -> pd.DataFrame:  # fmt: skip
    out = {}
    for name in columns:
        dtype = np.int64 if name in ints else bool if name in bools else None
        values = data[name]
        out[name] = (
            np.asarray(values, dtype=dtype) if dtype or values else np.asarray(values, dtype=np.float64)
        )
        if name in ("kind", "text", "level", "outcome"):
            out[name] = np.asarray(values, dtype=object)
    return pd.DataFrame(out, columns=columns)


def _decode_tracks(payloads: list[memoryview], path: pathlib.Path) -> dict[str, np.ndarray]:
    """Decode ``lc.VehicleTracks`` payloads into column arrays of total length R (rows)."""
    fast = decode_tracks_fast(payloads)
    if fast is not None:
        return fast
    pieces: dict[str, list[bytes | memoryview]] = {name: [] for name, _ in _TRACK_FIELDS.values()}
    steps = np.zeros(len(payloads), dtype=np.int64)
    times = np.zeros(len(payloads), dtype=np.float64)
    counts = np.zeros(len(payloads), dtype=np.int64)
    widths = {name: np.dtype(dtype).itemsize for name, dtype in _TRACK_FIELDS.values()}
    for i, payload in enumerate(payloads):
        found: dict[str, list[bytes | memoryview]] = {}
        for field, wire_type, value in iter_fields(payload):
            spec = _TRACK_FIELDS.get(field)
            if spec is not None and wire_type in (WIRE_LEN, WIRE_I64, WIRE_I32):
                found.setdefault(spec[0], []).append(value)  # type: ignore[arg-type]
            elif field == 1 and wire_type == WIRE_VARINT:
                steps[i] = to_int64(value)  # type: ignore[arg-type]
            elif field == 2 and wire_type == WIRE_I64:
                times[i] = np.frombuffer(value, "<f8")[0]  # type: ignore[arg-type]
        x = found.get("x", [])
        n = sum(len(v) for v in x) // 8
        counts[i] = n
        for name, width in widths.items():
            got = found.get(name)
            if got is None:
                pieces[name].append(bytes(n * width))  # proto3 default: an empty repeated field
                continue
            size = sum(len(v) for v in got)
            if size != n * width:
                raise ValueError(
                    f"{path}: /vehicles message {i} has {size // width} {name} values for {n} vehicles"
                )
            pieces[name].extend(got)
    cols: dict[str, np.ndarray] = {}
    for name, dtype in _TRACK_FIELDS.values():
        target = np.int64 if dtype == "<i4" else np.float64
        cols[name] = np.frombuffer(b"".join(pieces[name]), dtype=dtype).astype(target)
    cols["step"] = np.repeat(steps, counts)
    cols["t"] = np.repeat(times, counts)
    return cols


def _parse_metadata(raw: dict[str, str], path: pathlib.Path) -> dict[str, Any]:
    meta: dict[str, Any] = dict(raw)
    try:
        meta["config"] = json.loads(raw.get("config", "{}"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: metadata 'config' is not valid JSON ({exc})") from None
    meta["seed"] = int(raw.get("seed", "-1"))
    meta["start_time_ns"] = int(raw.get("start_time_ns", "0"))
    if "episode_seed" in raw:
        meta["episode_seed"] = int(raw["episode_seed"])
    if "autopilot" in raw:
        meta["autopilot"] = raw["autopilot"] == "true"
    if "steps_per_decision" in raw:
        meta["steps_per_decision"] = int(raw["steps_per_decision"])
    for key in ("driver", "scenario", "version"):
        meta.setdefault(key, "")
    meta.setdefault("episode_id", path.name.removesuffix(".partial").removesuffix(".mcap"))
    return meta


def read_episode(path: str | os.PathLike[str]) -> Episode:
    """Read one episode file (``.mcap`` or ``.mcap.partial``).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not an MCAP file, or an MCAP file without lc-toolkit data; a file the scan refuses whole
            (:class:`lcdata.mcap_scan.McapRefused`: chunks over the limits of :class:`lcdata.mcap_scan.Limits`,
            a compression the MCAP specification does not define, a message recorded twice, a channel redefined).
    Warns:
        TruncatedFileWarning: the file ended early; the complete chunks were recovered.
    """
    path = pathlib.Path(path)
    scan = scan_mcap(path)
    ours = topics.METADATA_NAME in scan.metadata or any(
        c.schema_name in topics.SCHEMA_TYPES for c in scan.channels.values()
    )
    # a scan stops early at the file's end (truncated) or at a record it cannot decode (damaged)
    broken = "damaged" if scan.stop_reason.startswith("corrupt record") else "truncated"
    if not ours and not scan.complete and scan.messages == 0:
        raise ValueError(f"{path}: {broken} MCAP file ({path.stat().st_size} bytes, {scan.stop_reason}) with no "
                         "complete lc-toolkit record to recover")
    if not ours:
        raise ValueError(
            f"{path}: MCAP file holds no lc-toolkit data (no 'lc' metadata, no lc.*/foxglove.* channels)"
        )
    for topic, channel in scan.channels.items():
        expected = topics.TOPIC_TYPES.get(topic)
        if expected is not None and channel.schema_name != expected.DESCRIPTOR.full_name:
            raise ValueError(f"{path}: topic {topic} has schema {channel.schema_name!r}, expected "
                             f"{expected.DESCRIPTOR.full_name!r}")  # fmt: skip
    if not scan.complete:
        warnings.warn(
            f"{path}: {broken} MCAP file ({scan.stop_reason}); recovered {scan.messages} messages "
            f"from {scan.chunks} complete chunks",
            TruncatedFileWarning,
            stacklevel=2,
        )
    try:
        return Episode(path, scan)
    except ValueError as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"{path}: corrupt data ({' '.join(str(exc).split())[:200]})") from None
    except Exception as exc:  # a damaged metadata record: decoding it fails in many ways
        raise ValueError(f"{path}: corrupt metadata ({type(exc).__name__})") from None


def list_episodes(directory: str | os.PathLike[str], *, include_partial: bool = False) -> list[pathlib.Path]:
    """Episode files under ``directory`` (recursive), sorted by path. ``FileNotFoundError`` when
    ``directory`` is missing or not a directory (an empty result would hide a mistyped path)."""
    root = pathlib.Path(directory)
    if not root.is_dir():
        what = "is a file, not a directory" if root.exists() else "does not exist"
        raise FileNotFoundError(f"episode directory {root} {what}")
    files = list(root.rglob("*.mcap"))
    if include_partial:
        files += root.rglob("*.mcap.partial")
    return sorted(files)


def iter_episodes(directory: str | os.PathLike[str], *, include_partial: bool = False) -> Iterator[Episode]:
    """Read the episodes of :func:`list_episodes` one at a time."""
    for path in list_episodes(directory, include_partial=include_partial):
        yield read_episode(path)
