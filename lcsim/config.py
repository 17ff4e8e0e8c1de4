"""Frozen, validated, JSON-serialisable configuration of the simulator and its environments.

Every config is a ``@dataclass(frozen=True, slots=True, kw_only=True)``; a bad value raises
``ValueError`` naming the field. Variants are made with :func:`dataclasses.replace`; the full config
goes into every recording and checkpoint as JSON (:meth:`ScenarioConfig.to_json`).

Units are in the field names (``_m``, ``_s``, ``_kmh``, ``_mps``, ``_mps2``, ``_deg``).
Defaults follow the paper (Hybrid-PPO, CARLA Town06) where it says something, and CARLA's own
code where it does not; ``docs/simulator.md`` lists the choices.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

DATA_FILE_MAX_BYTES = 16 << 20
"""The largest config, scenario, sweep or recipe file read (16 MiB: a hand-written table is a few KiB)."""


def loads_data(text: str | bytes, suffix: str = ".json") -> Any:
    """The value a TOML (``suffix`` ``.toml``) or JSON text holds. ``ValueError`` for text that does not parse,
    including nesting too deep for the parser (Python's TOML and JSON readers recurse once per level), so that
    no crafted file ends in a ``RecursionError``."""
    try:
        if suffix == ".toml":
            return tomllib.loads(text.decode() if isinstance(text, bytes) else text)
        return json.loads(text)
    except RecursionError:
        raise ValueError("nested too deeply") from None


def read_data_file(path: str | os.PathLike[str], what: str = "file") -> dict[str, Any]:
    """The table a ``.toml`` or ``.json`` file holds (a config, a scenario, a sweep). ``ValueError`` in one line
    naming the file: another suffix, a missing file, one over :data:`DATA_FILE_MAX_BYTES`, text that does not
    parse (nesting too deep included), or no table at the top."""
    path = pathlib.Path(path)
    if path.suffix not in (".toml", ".json"):
        raise ValueError(f"{what} {path}: the name must end in .toml or .json")
    try:
        if path.is_file() and path.stat().st_size > DATA_FILE_MAX_BYTES:
            raise ValueError(f"{what} {path} is {path.stat().st_size} bytes, more than a {what} can be "
                             f"({DATA_FILE_MAX_BYTES >> 20} MiB)")
        text = path.read_text()
        data = loads_data(text, path.suffix)
    except FileNotFoundError:
        raise ValueError(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"{what} {path} is a directory") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:  # tomllib's and json's errors are ValueErrors
        if str(exc).startswith(f"{what} {path}"):
            raise
        raise ValueError(f"{what} {path} is not valid {path.suffix[1:].upper()}: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{what} {path} holds no table at the top")
    return data


def _toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{v!r} has no TOML form")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ValueError(f"{v!r} has no TOML form")


def _toml_table(data: dict[str, object], path: list[str], lines: list[str]) -> None:
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict)}
    if path and (scalars or not data):
        lines += ["", f"[{'.'.join(path)}]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in scalars.items()]
    for k, v in data.items():
        if isinstance(v, dict):
            _toml_table(v, [*path, k], lines)


def toml_text(data: dict[str, object]) -> str:
    """A table (nested tables as TOML tables) as TOML text that ``tomllib`` reads back equal."""
    lines: list[str] = []
    _toml_table(data, [], lines)
    return "\n".join(lines).strip() + "\n"


def parse_value(text: str, like: object, what: str, declared: str = "") -> object:
    """``text`` read as the field's declared type (else as the type of its current value ``like``)."""
    if declared in ("float", "int", "bool", "str"):
        like = {"float": 0.0, "int": 0, "bool": False, "str": ""}[declared]
    try:
        if isinstance(like, bool):
            lowered = text.lower()
            if lowered not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                raise ValueError("expected true or false")
            return lowered in ("true", "1", "yes", "on")
        if isinstance(like, int):
            return int(text)
        if isinstance(like, float):
            return float(text)
        if isinstance(like, tuple):
            items = json.loads(text)
            if not isinstance(items, list):
                raise ValueError("expected a JSON list such as [1, 2]")
            return tuple(items)
        return text
    except (ValueError, json.JSONDecodeError) as exc:
        wanted = f"a value of type {declared}" if declared else f"a value like {like!r}"
        raise ValueError(f"{what}: expected {wanted} ({exc})") from None


_SCALAR_TYPES: dict[str, tuple[type, ...]] = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}
_TUPLE_TYPES: dict[str, tuple[type, ...]] = {"tuple[float, ...]": (int, float), "tuple[int, ...]": (int,),
                                              "tuple[str, ...]": (str,)}


def check_types(obj: object) -> None:
    """``ValueError`` naming the field when a field declared ``int``, ``float``, ``bool`` or ``str`` holds a
    value of another type (``True`` is no ``int`` here, ``2.5`` no ``int``, ``"no"`` no ``bool``), or a field
    declared ``tuple[float, ...]`` (``int``, ``str``) something else than a tuple of those."""
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        v = getattr(obj, f.name)
        want = _SCALAR_TYPES.get(str(f.type))
        if want is not None and (not isinstance(v, want) or (isinstance(v, bool) and bool not in want)):
            raise ValueError(f"{type(obj).__name__}.{f.name} must be of type {f.type}, got {v!r}")
        items = _TUPLE_TYPES.get(str(f.type))
        if items is not None and (not isinstance(v, tuple) or any(
                not isinstance(x, items) or isinstance(x, bool) for x in v)):
            raise ValueError(f"{type(obj).__name__}.{f.name} must be a list of {items[-1].__name__}s, got {v!r}")


NUMBER_LIMIT = 1e9
"""No number in a config is larger in magnitude than this unless its class's ``LIMITS`` says otherwise: a
value such as 1e308 is a slip or a crafted file, and a loop or an allocation sized by it would not end."""


def _shown(limit: float) -> str:
    return str(int(limit)) if float(limit).is_integer() and abs(limit) < 1e15 else f"{limit:g}"


def check_limits(obj: object) -> None:
    """The types of a config's fields (:func:`check_types`), then its numbers: each finite and, in magnitude, at
    most its class's ``LIMITS[name]`` (a plausible upper bound), else :data:`NUMBER_LIMIT`; a tuple's items
    likewise. ``ValueError`` naming ``Class.field``, the bound and the value. Called first by every config's
    ``__post_init__``, before the rules of the field themselves (which then compare sane numbers)."""
    check_types(obj)
    limits: dict[str, float] = getattr(type(obj), "LIMITS", {})
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        v = getattr(obj, f.name)
        hi = limits.get(f.name, NUMBER_LIMIT)
        for x in v if isinstance(v, tuple) else (v,):
            if isinstance(x, bool) or not isinstance(x, int | float):
                continue
            if isinstance(x, float) and not math.isfinite(x):
                check_field(False, obj, f.name, "must be a finite number", v)
            check_field(x <= hi, obj, f.name, f"must be at most {_shown(hi)}", v)
            check_field(x >= -NUMBER_LIMIT, obj, f.name, f"must be at least {_shown(-NUMBER_LIMIT)}", v)


def field_type(obj: object, name: str) -> str:
    """The declared type of field ``name`` of a config, as written (``"float"``, ``"tuple[float, ...]"``)."""
    return str(next(f.type for f in dataclasses.fields(obj) if f.name == name))  # type: ignore[arg-type]


WANDER_CLIP_SIGMAS = 2.5
"""A human-like driver's lateral offset from the lane centre is clipped at this many standard deviations."""


def check_field(cond: bool, cls: object, name: str, msg: str, value: object) -> None:
    """``ValueError`` naming ``Class.name``, the rule ``msg`` and the ``value``, unless ``cond``."""
    if not cond:
        raise ValueError(f"{type(cls).__name__}.{name} {msg}, got {value!r}")


def require_positive(obj: object, *names: str) -> None:
    """``ValueError`` unless each field ``names`` of ``obj`` is a finite number > 0."""
    for n in names:
        v = getattr(obj, n)
        check_field(isinstance(v, int | float) and math.isfinite(v) and v > 0, obj, n, "must be > 0", v)


def require_non_negative(obj: object, *names: str) -> None:
    """``ValueError`` unless each field ``names`` of ``obj`` is a finite number >= 0."""
    for n in names:
        v = getattr(obj, n)
        check_field(isinstance(v, int | float) and math.isfinite(v) and v >= 0, obj, n, "must be >= 0", v)


class JsonConfig:
    """Nested dataclass <-> dict/JSON with unknown keys rejected (a misspelt key is an error)."""

    LIMITS: ClassVar[dict[str, float]] = {}
    """Plausible upper bounds of number fields (:func:`check_limits`; others: :data:`NUMBER_LIMIT`)."""
    LEGACY_DEFAULTS: ClassVar[dict[str, Any]] = {}
    """Values of fields added after configs were first stored, for stored configs that lack them: what
    the code did before the field existed (so old recordings replay and old checkpoints compare as they
    were)."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    def to_json(self, **kwargs: Any) -> str:
        return json.dumps(self.to_dict(), sort_keys=True, **kwargs)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, stored: bool = True) -> Self:
        """The config a dict describes; ``ValueError`` naming the problem for an unknown field, a value of
        the wrong type or out of range, or anything that is not such a dict (stored files are untrusted).
        ``stored``: the dict was stored by an earlier version (a recording, a run), so a field it lacks takes
        its ``LEGACY_DEFAULTS`` value; a file a person writes (``stored=False``) gets today's defaults."""
        if not isinstance(data, dict):
            raise ValueError(f"{cls.__name__}: expected a JSON object, got {type(data).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = set(data) - set(fields)
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown field(s) {sorted(unknown)}")
        legacy = cls.LEGACY_DEFAULTS if stored else {}
        kwargs: dict[str, Any] = {name: value for name, value in legacy.items() if name not in data}
        if stored:  # a nested table a stored config lacks is that table's legacy values too, not today's defaults
            for (owner, name), sub in _NESTED.items():
                if owner == cls.__name__ and name not in data and sub.LEGACY_DEFAULTS:
                    kwargs[name] = sub.from_dict({}, stored=True)
        for name, value in data.items():
            sub = _NESTED.get((cls.__name__, name))
            if sub is not None:
                if not isinstance(value, dict):
                    raise ValueError(f"{cls.__name__}.{name} must be a JSON object, got {value!r}")
                value = sub.from_dict(value, stored=stored)
            elif isinstance(value, list):
                value = tuple(value)
            kwargs[name] = value
        try:
            return cls(**kwargs)
        except (TypeError, AttributeError, OverflowError, RecursionError) as exc:  # a value of the wrong type
            raise ValueError(f"{cls.__name__}: a value of the wrong type ({exc})") from None

    def to_toml(self, table: str | None = None) -> str:
        """The config as TOML (nested configs as tables; under ``[table]`` when given): what
        :meth:`from_file` reads back to an equal config."""
        lines: list[str] = []
        _toml_table(self.to_dict(), [table] if table else [], lines)
        return "\n".join(lines).strip() + "\n"

    @classmethod
    def from_file(cls, path: str | os.PathLike[str], table: str | None = None) -> Self:
        """The config of a TOML or JSON file of its fields (those missing keep their defaults); with
        ``table``, the fields may also sit under that top-level table (``[policy]``). ``ValueError`` naming
        the file and the problem."""
        data = read_data_file(path, "config file")
        if table is not None and isinstance(data.get(table), dict):
            data = data[table]
        try:
            return cls.from_dict(data, stored=False)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None

    def with_settings(self, settings: Sequence[str]) -> Self:
        """This config with ``key=value`` settings (``traffic.num_vehicles=30`` reaches a nested config),
        validated together once all are applied (so that fields that must agree can change together). Each
        value is read as its field's type (``true``/``false`` for a flag, a JSON list for a tuple).
        ``ValueError`` naming the setting for an unknown key or a value of the wrong type, and naming the
        settings for a combination the config refuses."""
        if not settings:
            return self
        data = self.to_dict()
        for text in settings:
            key, sep, value = text.partition("=")
            if not sep or not key.strip():
                raise ValueError(f"--set {text!r}: expected KEY=VALUE")
            *parents, name = key.strip().split(".")
            node: dict[str, Any] = data
            owner, obj = type(self).__name__, self
            for part in parents:
                child = node.get(part)
                if not isinstance(child, dict):
                    what = "has no field" if part not in node else "has no fields of its own under"
                    raise ValueError(f"--set {text}: {owner} {what} {part!r}")
                node, owner, obj = child, part, getattr(obj, part)
            if name not in node:
                raise ValueError(f"--set {text}: {owner} has no field {name!r} (fields: {', '.join(sorted(node))})")
            if isinstance(node[name], dict):
                raise ValueError(f"--set {text}: {name} is a nested config; set its fields ({name}.field=value)")
            node[name] = parse_value(value.strip(), node[name], f"--set {text}", field_type(obj, name))
        try:
            return type(self).from_dict(data)
        except ValueError as exc:
            raise ValueError(f"--set {', '.join(settings)}: {exc}") from None

    @classmethod
    def from_json(cls, text: str) -> Self:
        """:meth:`from_dict` of a JSON text (``ValueError`` for text that is not JSON, too)."""
        return cls.from_dict(loads_data(text))


@dataclass(frozen=True, slots=True, kw_only=True)
class RoadConfig(JsonConfig):
    """A straight, Town06-like carriageway along +x. Lane 0 is the rightmost lane."""

    num_lanes: int = 4
    lane_width_m: float = 3.5
    shoulder_width_m: float = 2.5
    marking_width_m: float = 0.15
    dash_length_m: float = 3.0
    dash_gap_m: float = 6.0

    LIMITS: ClassVar[dict[str, float]] = {"lane_width_m": 10.0, "shoulder_width_m": 20.0, "marking_width_m": 1.0,
                                          "dash_length_m": 100.0, "dash_gap_m": 100.0}

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(isinstance(self.num_lanes, int) and 2 <= self.num_lanes <= 6, self, "num_lanes",
               "must be an integer in [2, 6]", self.num_lanes)
        require_positive(self, "lane_width_m", "marking_width_m", "dash_length_m", "dash_gap_m")
        require_non_negative(self, "shoulder_width_m")
        check_field(self.lane_width_m >= 2.5, self, "lane_width_m", "must be >= 2.5 m", self.lane_width_m)

    @property
    def width_m(self) -> float:
        """Width of the carriageway between the two solid edge lines."""
        return self.num_lanes * self.lane_width_m


@dataclass(frozen=True, slots=True, kw_only=True)
class TrafficConfig(JsonConfig):
    """Autopilot traffic: IDM car following with a Traffic-Manager-like gap and lane changes."""

    num_vehicles: int = 100
    speed_kmh: float = 24.0
    speed_spread_kmh: float = 2.0
    """Standard deviation of the per-vehicle desired speed (clipped at 2.5 sigma)."""
    length_m: float = 5.37  # Ford Crown
    width_m: float = 1.80
    spawn_behind_m: float = 300.0
    """Traffic is spawned from this far behind the ego's start ..."""
    spawn_ahead_m: float = 1300.0
    """... to this far ahead of it. The ego gains only ~1.7 m/s on the traffic, so ~200 m ahead already
    keeps traffic around it for the whole 600 m route; the window sets the density (100 vehicles on
    4 lanes over 1.6 km: about 64 m between vehicles; a saturated lane at 24 km/h has ~21 m)."""
    min_spawn_gap_m: float = 6.0
    ego_clearance_m: float = 20.0
    """Free space kept ahead of (and half of it behind) the ego in its lane at spawn."""
    idm_time_headway_s: float = 2.0
    idm_min_gap_m: float = 2.0
    idm_max_accel_mps2: float = 1.5
    idm_comfort_decel_mps2: float = 2.0
    idm_delta: float = 4.0
    max_decel_mps2: float = 8.0
    lane_changes: bool = True
    lane_change_duration_s: float = 5.0
    """Duration of a traffic lane change (the median across drivers when ``human_like``): naturalistic
    highway lane changes take 5 to 6 s on average (docs/simulator.md)."""
    lane_change_check_period_s: float = 0.5
    blocked_gap_min_m: float = 0.0
    blocked_gap_max_m: float = 50.0
    """A leader whose gap is in [min, max] and who is slower than the desired speed blocks."""
    blocked_speed_margin_kmh: float = 1.5
    lane_change_front_gap_m: float = 12.0
    lane_change_rear_gap_m: float = 8.0
    lane_change_rear_headway_s: float = 1.0
    random_lane_change_rate_per_min: float = 0.3
    """Rate of spontaneous lane changes (when the side lane is free), for variety in the corpus."""
    human_like: bool = True
    """Human-like drivers, as the fields below describe (docs/simulator.md gives their sources and the
    statistics they produce). False: every vehicle follows IDM exactly with the parameters above, no
    noise and no delay, and changes lanes in exactly ``lane_change_duration_s`` (with a duration of 3 s, the
    traffic of earlier versions, which configs stored before this field existed keep)."""
    driver_spread: float = 0.25
    """Per-driver spread of the car-following parameters: each driver's desired time gap, maximum
    acceleration and comfortable deceleration are lognormal with the medians above and this log-sd."""
    accel_noise_mps2: float = 0.2
    """Standard deviation of the stochastic acceleration each driver adds to IDM's (an Ornstein-Uhlenbeck
    process sampled every lane-change check and interpolated linearly in between)."""
    accel_noise_time_s: float = 2.0
    """Correlation time of that acceleration noise."""
    reaction_time_s: float = 0.5
    """Median per-driver reaction time: the applied acceleration follows the commanded one with this first
    order lag (lognormal across drivers with log-sd ``driver_spread``)."""
    lane_wander_m: float = 0.15
    """Standard deviation of each driver's lateral offset from the lane centre (an Ornstein-Uhlenbeck
    process like the acceleration noise, clipped at 2.5 standard deviations)."""
    lane_wander_time_s: float = 4.0
    """Correlation time of the lateral offset."""
    lane_change_spread: float = 0.25
    """Per-driver log-sd of the lane-change duration (lognormal, median ``lane_change_duration_s``)."""
    lane_change_eagerness_min: float = 0.3
    """Per-driver probability of acting on a blocked leader at a check, uniform in [this, 1] (1: always)."""

    LEGACY_DEFAULTS: ClassVar[dict[str, Any]] = {"human_like": False}
    LIMITS: ClassVar[dict[str, float]] = {
        "num_vehicles": 1_000_000, "speed_kmh": 300.0, "speed_spread_kmh": 100.0, "length_m": 30.0, "width_m": 5.0,
        "spawn_behind_m": 100_000.0, "spawn_ahead_m": 100_000.0, "min_spawn_gap_m": 1_000.0,
        "ego_clearance_m": 1_000.0, "idm_time_headway_s": 60.0, "idm_min_gap_m": 1_000.0, "idm_max_accel_mps2": 50.0,
        "idm_comfort_decel_mps2": 50.0, "idm_delta": 100.0, "max_decel_mps2": 100.0, "lane_change_duration_s": 60.0,
        "lane_change_check_period_s": 60.0, "blocked_gap_min_m": 10_000.0, "blocked_gap_max_m": 10_000.0,
        "blocked_speed_margin_kmh": 300.0, "lane_change_front_gap_m": 1_000.0, "lane_change_rear_gap_m": 1_000.0,
        "lane_change_rear_headway_s": 60.0, "random_lane_change_rate_per_min": 60.0, "driver_spread": 5.0,
        "accel_noise_mps2": 20.0, "accel_noise_time_s": 3_600.0, "reaction_time_s": 10.0, "lane_wander_m": 10.0,
        "lane_wander_time_s": 3_600.0, "lane_change_spread": 5.0, "lane_change_eagerness_min": 1.0,
    }  # fmt: skip
    """Plausible upper bounds (a highway's speeds, a car's size and accelerations, a human's times)."""

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(isinstance(self.num_vehicles, int) and self.num_vehicles >= 0, self, "num_vehicles",
               "must be an integer >= 0", self.num_vehicles)
        check_field(isinstance(self.human_like, bool), self, "human_like", "must be true or false", self.human_like)
        require_positive(self, "accel_noise_time_s", "lane_wander_time_s")
        require_non_negative(self, "driver_spread", "accel_noise_mps2", "reaction_time_s", "lane_wander_m",
                             "lane_change_spread")
        check_field(0.0 <= self.lane_change_eagerness_min <= 1.0, self, "lane_change_eagerness_min",
                    "must be in [0, 1]", self.lane_change_eagerness_min)
        require_positive(self, "speed_kmh", "length_m", "width_m", "idm_time_headway_s", "idm_max_accel_mps2",
                  "idm_comfort_decel_mps2", "idm_delta", "max_decel_mps2", "lane_change_duration_s",
                  "lane_change_check_period_s")
        require_non_negative(self, "speed_spread_kmh", "spawn_behind_m", "spawn_ahead_m", "min_spawn_gap_m",
                      "ego_clearance_m", "idm_min_gap_m", "blocked_gap_min_m", "blocked_gap_max_m",
                      "blocked_speed_margin_kmh", "lane_change_front_gap_m", "lane_change_rear_gap_m",
                      "lane_change_rear_headway_s", "random_lane_change_rate_per_min")
        check_field(self.blocked_gap_max_m >= self.blocked_gap_min_m, self, "blocked_gap_max_m",
               "must be >= blocked_gap_min_m", self.blocked_gap_max_m)


@dataclass(frozen=True, slots=True, kw_only=True)
class PIDGains(JsonConfig):
    """Gains of one CARLA ``PID*Controller``; ``dt_s`` is the controller's own dt parameter."""

    kp: float
    ki: float
    kd: float
    dt_s: float = 0.1

    LIMITS: ClassVar[dict[str, float]] = {"kp": 1_000.0, "ki": 1_000.0, "kd": 1_000.0, "dt_s": 10.0}

    def __post_init__(self) -> None:
        check_limits(self)
        require_non_negative(self, "kp", "ki", "kd")
        require_positive(self, "dt_s")


NEIGHBOUR_SELECTIONS = ("lanes", "nearest")
# The observation's vehicle slots with neighbour_selection="lanes", in order: (lane offset from the ego's
# target lane, -1 right / +1 left; ahead (True) or behind; rank in that lane, 1 = the nearest).
LANE_SLOTS: tuple[tuple[int, bool, int], ...] = (
    (0, True, 1), (0, False, 1),      # leader and follower in the ego's lane
    (-1, True, 1), (-1, False, 1),    # ... in the lane to its right
    (1, True, 1), (1, False, 1),      # ... in the lane to its left
    (-1, True, 2), (1, True, 2),      # the second leaders right and left: how long the gap there is
    # Wider views (num_neighbours up to 16): what the next 10-20 s bring, beyond the gaps beside the ego.
    (0, True, 2),                     # the leader's leader: a queue closing up ahead
    (-1, False, 2), (1, False, 2),    # the second followers right and left
    (-2, True, 1), (-2, False, 1),    # leader and follower two lanes right: who may move in beside the ego
    (2, True, 1), (2, False, 1),      # ... two lanes left
    (0, True, 3),                     # the third leader in the ego's lane
)

# The paper's gains. Its Ki/Kd labels may be swapped relative to CARLA's BasicAgent code
# (lateral K_I 0.05 / K_D 0.2 there), so the swapped reading is kept as a named variant.
PAPER_LATERAL = PIDGains(kp=1.95, ki=0.2, kd=0.07)
PAPER_LONGITUDINAL = PIDGains(kp=1.0, ki=0.0, kd=0.75)
SWAPPED_LATERAL = PIDGains(kp=1.95, ki=0.07, kd=0.2)
SWAPPED_LONGITUDINAL = PIDGains(kp=1.0, ki=0.75, kd=0.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class EgoConfig(JsonConfig):
    """The ego (Audi TT): kinematic bicycle model tracked by CARLA's ``VehiclePIDController``."""

    length_m: float = 4.18
    width_m: float = 1.99
    wheelbase_m: float = 2.65
    target_speed_kmh: float = 30.0
    initial_speed_kmh: float = 30.0
    start_lane: int = -1
    """Lane the ego starts in; -1 draws it from the episode seed."""
    max_steer_angle_deg: float = 70.0
    max_accel_mps2: float = 4.5
    """Acceleration at full throttle (Audi TT: 0-100 km/h in about 6 s)."""
    max_brake_decel_mps2: float = 8.0
    powertrain_lag_s: float = 0.3
    """First-order lag from pedal command to acceleration. It stands in for the engine and
    transmission dynamics of CARLA's PhysX vehicle; without it the paper's longitudinal gains
    (Kd 0.75 at dt 0.1) limit-cycle between full throttle and full brake."""
    rolling_resistance_mps2: float = 0.15
    drag_per_speed2: float = 4.0e-4
    lateral_pid: PIDGains = field(default_factory=lambda: PAPER_LATERAL)
    longitudinal_pid: PIDGains = field(default_factory=lambda: PAPER_LONGITUDINAL)
    max_throttle: float = 0.75
    max_brake: float = 0.3
    max_steer: float = 0.8
    max_steer_change: float = 0.1
    """Largest change of the steering command per control (simulation) step."""
    pid_window: int = 10
    """Errors kept for the integral and derivative terms, as CARLA's ``deque(maxlen=10)``."""
    lane_change_time_s: float = 2.0
    same_lane_time_s: float = 0.0
    waypoint_spacing_m: float = 2.0
    base_min_distance_m: float = 3.0
    distance_ratio: float = 0.5
    """Look-ahead of the local planner: base_min_distance_m + distance_ratio * speed (m/s)."""
    lane_change_tolerance_m: float = 0.3
    adaptive_cruise: bool = False
    """Off by default: the ego does not brake for a slower leader; the decision must avoid it."""
    acc_time_headway_s: float = 1.5
    acc_min_gap_m: float = 4.0

    LIMITS: ClassVar[dict[str, float]] = {
        "length_m": 30.0, "width_m": 5.0, "wheelbase_m": 30.0, "target_speed_kmh": 300.0, "initial_speed_kmh": 300.0,
        "start_lane": 5, "max_accel_mps2": 50.0, "max_brake_decel_mps2": 100.0, "powertrain_lag_s": 10.0,
        "rolling_resistance_mps2": 10.0, "drag_per_speed2": 1.0, "max_steer_change": 2.0, "pid_window": 10_000,
        "lane_change_time_s": 60.0, "same_lane_time_s": 3_600.0, "waypoint_spacing_m": 100.0,
        "base_min_distance_m": 1_000.0, "distance_ratio": 100.0, "lane_change_tolerance_m": 10.0,
        "acc_time_headway_s": 60.0, "acc_min_gap_m": 1_000.0,
    }  # fmt: skip

    def __post_init__(self) -> None:
        check_limits(self)
        require_positive(self, "length_m", "width_m", "wheelbase_m", "target_speed_kmh", "max_steer_angle_deg",
                  "max_accel_mps2", "max_brake_decel_mps2", "max_throttle", "max_brake", "max_steer",
                  "max_steer_change", "lane_change_time_s", "waypoint_spacing_m",
                  "lane_change_tolerance_m", "acc_time_headway_s")
        require_non_negative(self, "initial_speed_kmh", "powertrain_lag_s", "rolling_resistance_mps2", "drag_per_speed2",
                      "same_lane_time_s", "base_min_distance_m", "distance_ratio", "acc_min_gap_m")
        check_field(self.wheelbase_m < self.length_m, self, "wheelbase_m", "must be shorter than length_m",
               self.wheelbase_m)
        for name in ("max_throttle", "max_brake", "max_steer"):
            check_field(getattr(self, name) <= 1.0, self, name, "must be <= 1", getattr(self, name))
        check_field(self.max_steer_angle_deg < 90, self, "max_steer_angle_deg", "must be < 90", self.max_steer_angle_deg)
        check_field(isinstance(self.pid_window, int) and self.pid_window >= 2, self, "pid_window",
               "must be an integer >= 2", self.pid_window)
        check_field(isinstance(self.start_lane, int) and self.start_lane >= -1, self, "start_lane",
               "must be -1 (random) or a lane index", self.start_lane)
        for name in ("lateral_pid", "longitudinal_pid"):
            check_field(isinstance(getattr(self, name), PIDGains), self, name, "must be a PIDGains", getattr(self, name))


@dataclass(frozen=True, slots=True, kw_only=True)
class RewardConfig(JsonConfig):
    """The paper's reward: collision, out of road, go-forward (metres) and success milestones."""

    collision: float = -500.0
    off_road: float = -10.0
    forward_per_m: float = 1.0
    milestones: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0)
    """Fractions of the route at which a success reward is paid; reaching 1.0 ends the episode."""
    milestone_rewards: tuple[float, ...] = (100.0, 150.0, 200.0, 1000.0)

    MAX_MILESTONES: ClassVar[int] = 100

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(len(self.milestones) <= self.MAX_MILESTONES, self, "milestones",
                    f"must be at most {self.MAX_MILESTONES} fractions", len(self.milestones))
        check_field(len(self.milestones) == len(self.milestone_rewards) and len(self.milestones) > 0, self,
               "milestone_rewards", "must have one reward per milestone", self.milestone_rewards)
        ms = list(self.milestones)
        check_field(all(0 < m <= 1 for m in ms) and ms == sorted(ms) and ms[-1] == 1.0, self, "milestones",
               "must be increasing fractions in (0, 1] ending with 1.0", self.milestones)


@dataclass(frozen=True, slots=True, kw_only=True)
class RenderConfig(JsonConfig):
    """Ego-centred, heading-up bird's-eye semantic image."""

    image_size_px: int = 120
    resolution_m_per_px: float = 0.5
    max_vehicles_drawn: int = 32

    LIMITS: ClassVar[dict[str, float]] = {"image_size_px": 1024, "resolution_m_per_px": 100.0,
                                          "max_vehicles_drawn": 10_000}

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(isinstance(self.image_size_px, int) and 16 <= self.image_size_px <= 1024, self,
               "image_size_px", "must be an integer in [16, 1024]", self.image_size_px)
        require_positive(self, "resolution_m_per_px")
        check_field(isinstance(self.max_vehicles_drawn, int) and self.max_vehicles_drawn >= 1, self,
               "max_vehicles_drawn", "must be an integer >= 1", self.max_vehicles_drawn)


@dataclass(frozen=True, slots=True, kw_only=True)
class ScenarioConfig(JsonConfig):
    """Everything that defines an episode, given its seed."""

    LEGACY_DEFAULTS: ClassVar[dict[str, Any]] = {"neighbour_selection": "nearest"}

    road: RoadConfig = field(default_factory=RoadConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    dt_s: float = 0.05
    """Simulation step (20 Hz)."""
    decision_period_s: float = 0.5
    route_length_m: float = 600.0
    time_limit_s: float = 75.0
    """Episode time limit (truncation): the route takes 72 s at 30 km/h, so a lane keeper with
    adaptive cruise, held up by slower traffic, almost never makes it (docs/simulator.md)."""
    history_steps: int = 10
    num_neighbours: int = 8
    neighbour_selection: str = "lanes"
    """Which K vehicles the observation shows (within ``sensing_range_m``): ``lanes`` (fixed slots: the
    leader and follower in the ego's lane and in the lanes right and left of it, then the second leaders
    right and left; :data:`LANE_SLOTS`; K <= 16, the slots after the eighth a wider view) or ``nearest``
    (the K nearest by distance, nearest first). PPO on ``pure`` observations won 59.0% of the held-out episodes with ``lanes`` and
    25.5% with ``nearest`` (300k steps, docs/simulator.md). Configs stored before this field existed
    read as ``nearest``."""
    sensing_range_m: float = 80.0
    observe_acceleration: bool = False
    """``current`` gets a tenth column, ``accel_mps2``: each vehicle's acceleration along its heading over
    the last step (what a radar track or CARLA's ``get_acceleration`` shows). The traffic's acceleration
    tells its intent (an IDM follower closing on its desired speed, a leader braking), which speeds alone do
    not; off by default, so stored observations keep their nine columns. Shown to PPO (``pure`` and
    ``hybrid``), it made no difference beyond the spread of training seeds (docs/results/accel)."""
    render_image: bool = True
    invalid_lane_change: str = "refuse"
    """A change towards a lane that does not exist: ``refuse`` (not carried out, rewarded ``reward.off_road``,
    the episode goes on: CARLA's agent finds no waypoint there, and the paper's outcomes have no off-road)
    or ``leave_road`` (carried out; the ego leaves the road and the episode ends ``off_road``)."""

    LIMITS: ClassVar[dict[str, float]] = {"dt_s": 1.0, "decision_period_s": 60.0, "route_length_m": 100_000.0,
                                          "time_limit_s": 86_400.0, "history_steps": 1_000, "num_neighbours": 64,
                                          "sensing_range_m": 10_000.0}
    """Plausible upper bounds: a day-long episode, a 100 km route, 1000 steps of history, 64 vehicles shown."""
    MIN_DT_S: ClassVar[float] = 1e-3
    MAX_STEPS: ClassVar[int] = 1_000_000
    """The most simulation steps an episode may have (``time_limit_s / dt_s``): 14 hours at 20 Hz."""

    def __post_init__(self) -> None:
        check_limits(self)
        for name in ("road", "traffic", "ego", "reward", "render"):
            want = _NESTED[("ScenarioConfig", name)]
            check_field(isinstance(getattr(self, name), want), self, name, f"must be a {want.__name__}",
                        getattr(self, name))
        require_positive(self, "dt_s", "decision_period_s", "route_length_m", "time_limit_s", "sensing_range_m")
        check_field(self.dt_s >= self.MIN_DT_S, self, "dt_s", f"must be >= {self.MIN_DT_S}", self.dt_s)
        check_field(self.time_limit_s / self.dt_s <= self.MAX_STEPS, self, "time_limit_s",
                    f"must be at most {self.MAX_STEPS} steps of dt_s ({self.MAX_STEPS * self.dt_s:g} s)",
                    self.time_limit_s)
        tc = self.traffic
        if tc.human_like:  # the wander (clipped) must keep a car (the ego too, on autopilot) and the neighbour
            # index's margin strictly inside its lane
            width = max(tc.width_m, self.ego.width_m)
            check_field(2 * WANDER_CLIP_SIGMAS * tc.lane_wander_m + width + 0.2 < self.road.lane_width_m - 1e-6, tc,
                        "lane_wander_m",
                        f"lets a {width} m wide vehicle leave its {self.road.lane_width_m} m lane; lower it",
                        tc.lane_wander_m)
        ratio = self.decision_period_s / self.dt_s
        check_field(abs(ratio - round(ratio)) < 1e-9, self, "decision_period_s", "must be a multiple of dt_s",
               self.decision_period_s)
        check_field(self.invalid_lane_change in ("refuse", "leave_road"), self, "invalid_lane_change",
               "must be 'refuse' or 'leave_road'", self.invalid_lane_change)
        check_field(isinstance(self.history_steps, int) and self.history_steps >= 1, self, "history_steps",
               "must be an integer >= 1", self.history_steps)
        check_field(isinstance(self.num_neighbours, int) and self.num_neighbours >= 1, self, "num_neighbours",
               "must be an integer >= 1", self.num_neighbours)
        check_field(self.neighbour_selection in NEIGHBOUR_SELECTIONS, self, "neighbour_selection",
               f"must be one of {', '.join(NEIGHBOUR_SELECTIONS)}", self.neighbour_selection)
        check_field(self.neighbour_selection != "lanes" or self.num_neighbours <= len(LANE_SLOTS), self,
               "num_neighbours", f"must be <= {len(LANE_SLOTS)} with neighbour_selection='lanes'",
               self.num_neighbours)
        check_field(self.time_limit_s >= self.decision_period_s, self, "time_limit_s",
               "must be >= decision_period_s", self.time_limit_s)
        if self.ego.start_lane >= self.road.num_lanes:
            raise ValueError(f"EgoConfig.start_lane must be < road.num_lanes ({self.road.num_lanes}), "
                             f"got {self.ego.start_lane}")
        # Spawn feasibility: every lane must hold its share of vehicles at the minimum spacing.
        t = self.traffic
        window = t.spawn_behind_m + t.spawn_ahead_m - t.ego_clearance_m * 1.5
        per_lane = math.ceil(t.num_vehicles / self.road.num_lanes)
        need = per_lane * (t.length_m + t.min_spawn_gap_m)
        if t.num_vehicles and need > window:
            raise ValueError(
                f"TrafficConfig.num_vehicles={t.num_vehicles} does not fit: {per_lane} vehicles per lane "
                f"need {need:.0f} m but the spawn window is {window:.0f} m (raise spawn_ahead_m/"
                f"spawn_behind_m or lower min_spawn_gap_m)")

    @property
    def steps_per_decision(self) -> int:
        return round(self.decision_period_s / self.dt_s)

    @property
    def max_steps(self) -> int:
        """Simulation steps in the time limit."""
        return round(self.time_limit_s / self.dt_s)


_NESTED: dict[tuple[str, str], type[JsonConfig]] = {
    ("ScenarioConfig", "road"): RoadConfig,
    ("ScenarioConfig", "traffic"): TrafficConfig,
    ("ScenarioConfig", "ego"): EgoConfig,
    ("ScenarioConfig", "reward"): RewardConfig,
    ("ScenarioConfig", "render"): RenderConfig,
    ("EgoConfig", "lateral_pid"): PIDGains,
    ("EgoConfig", "longitudinal_pid"): PIDGains,
}


def paper_scenario(**overrides: Any) -> ScenarioConfig:
    """The paper's lane-change scenario (100 vehicles at ~24 km/h, ego targeting 30 km/h)."""
    return ScenarioConfig(**overrides)


def corpus_scenario(**overrides: Any) -> ScenarioConfig:
    """The paper's trajectory corpus: 20 autopilot vehicles, 20 Hz, 2000 steps (100 s).

    The ego is driven by the autopilot too when recording it (``lc-record --driver autopilot``).
    """
    traffic = TrafficConfig(num_vehicles=20, spawn_behind_m=80.0, spawn_ahead_m=220.0)
    kwargs: dict[str, Any] = dict(traffic=traffic, route_length_m=5000.0, time_limit_s=100.0,
                                  render_image=False)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)


def light_scenario(**overrides: Any) -> ScenarioConfig:
    """A smaller version of the paper's task (30 vehicles, 300 m route) for quick experiments."""
    kwargs: dict[str, Any] = dict(traffic=TrafficConfig(num_vehicles=30, spawn_behind_m=80.0, spawn_ahead_m=200.0),
                                  route_length_m=300.0, time_limit_s=40.0)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)


def tiny_scenario(**overrides: Any) -> ScenarioConfig:
    """8 vehicles on a 150 m route (25 s): for tests and smoke runs, not for results."""
    kwargs: dict[str, Any] = dict(traffic=TrafficConfig(num_vehicles=8, spawn_behind_m=40.0, spawn_ahead_m=100.0),
                                  route_length_m=150.0, time_limit_s=25.0)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)
