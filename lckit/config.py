"""The configuration kit every package may use: frozen dataclasses that validate themselves and read and write
TOML and JSON.

- :func:`read_data_file` / :func:`loads_data`: the table a ``.toml`` or ``.json`` file (or text) holds, with its
  size bounded and every parse error one ``ValueError`` naming the file; :func:`toml_text` writes a table back.
- :class:`JsonConfig`: the base of a ``@dataclass(frozen=True, slots=True, kw_only=True)`` config: dict and
  JSON round trips with unknown keys refused, nested configs (``NESTED``), fields added later
  (``LEGACY_DEFAULTS``), a file of its fields (:meth:`JsonConfig.from_file`) and ``key=value`` settings
  (:meth:`JsonConfig.with_settings`).
- :func:`check_limits`, :func:`check_field`, :func:`require_positive`, :func:`require_non_negative`: the checks a
  config's ``__post_init__`` makes, each a ``ValueError`` naming ``Class.field``.

It sits below every package of the project (``lcsim`` included) and imports none of them.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import tomllib
from collections.abc import Sequence
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

    NESTED: ClassVar[dict[str, type[JsonConfig]]] = {}
    """The fields that hold a config of their own, by name, with its class: ``{"road": RoadConfig}`` (a
    table in TOML, an object in JSON)."""
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
            for name, sub in cls.NESTED.items():
                if name not in data and sub.LEGACY_DEFAULTS:
                    kwargs[name] = sub.from_dict({}, stored=True)
        for name, value in data.items():
            sub = cls.NESTED.get(name)
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


