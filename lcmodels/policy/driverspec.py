"""A driver as a typed value: what drives, the safety layer in front of it, what the layer's futures follow.

The commands (``lc-eval``, ``lc-bench``, ``lc-record``, ...) read a driver from the words a person types; this
module holds that grammar, once, with every older spelling, and :func:`parse_driver_spec` turns the words into a
:class:`DriverSpec` that the library takes (:func:`lcmodels.policy.evaluate.driver_for`,
:func:`lcmodels.bench.run.resolve_driver`) without reading a string again::

    rule                              # a built-in driver (lcsim.registry.DRIVER_NAMES)
    runs/pure/policy.safetensors      # a policy file (policy:PATH the same)
    zoo:hybrid-ppo                    # a zoo entry: its policy file and, when it reads predictions, the predictor
    package.module:callable           # a user's driver (lc-bench)
    safety-layer:zoo:hybrid-ppo       # a policy behind the safety layer
    safety-layer:rule                 # the rule-based driver behind it

Older spellings mean what they meant: ``lookahead-blind:POLICY`` (the layer blind, not perceived),
``lookahead:POLICY`` (a privileged layer, which sees the traffic's coming random draws), the built-in drivers
``lookahead`` and ``lookahead-blind`` (the rule-based driver behind those). The simulator keeps the layer and its
settings (:class:`lcsim.planning.SafetyLayerConfig`), not these words.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from lcmodels.zoo import ZOO_PREFIX, ZooEntry, zoo_entry
from lcsim.planning.safety import SafetyLayerConfig
from lcsim.registry import DRIVER_NAMES

POLICY_PREFIX = "policy:"
"""A driver spec ``policy:PATH``: the policy file PATH (the prefix is optional)."""

SAFETY_LAYER_PREFIX = "safety-layer:"
"""A driver spec ``safety-layer:DRIVER``: DRIVER behind the safety layer."""

LEGACY_BASES: dict[str, dict[str, bool]] = {"lookahead-blind:": {"perceived": False},
                                            "lookahead:": {"blind": False, "perceived": False}}  # fmt: skip
"""Older driver-spec prefixes and the settings they mean (on top of :class:`SafetyLayerConfig`'s defaults)."""

LEGACY_DRIVERS: dict[str, dict[str, bool]] = {"lookahead-blind": {"perceived": False},
                                              "lookahead": {"blind": False, "perceived": False}}  # fmt: skip
"""Built-in driver names that are the rule-based driver behind the safety layer, and the settings they mean."""

POLICY_PREFIXES = (POLICY_PREFIX, SAFETY_LAYER_PREFIX, *LEGACY_BASES)
"""Prefixes of a driver spec that name a policy file: the policy itself, or the policy behind the safety layer."""

CALLABLE_SPEC = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
"""``package.module:callable``."""

Kind = Literal["driver", "policy", "callable"]


@dataclass(frozen=True, kw_only=True, slots=True)
class DriverSpec:
    """A driver, typed: built by :func:`parse_driver_spec` from the words a person gave.

    The layer may guard a policy or the rule-based driver (then following the rule): that rule is checked here,
    once, for every way of building one."""

    text: str
    """As the person spelt it (``zoo:hybrid-ppo``, ``lookahead-blind``, ...): its label in summaries and the
    ledger."""
    kind: Kind
    """``driver`` (built in), ``policy`` (a policy file) or ``callable`` (``package.module:callable``)."""
    name: str
    """The built-in driver's name, the policy file's path (a zoo entry's resolved) or ``package.module:callable``."""
    predictor: str | None = None
    """The zoo's predictor for a zoo entry that reads predictions, else None."""
    layer: SafetyLayerConfig | None = None
    """The safety layer it drives behind (None: none); ``layer.follow`` as spelt, :attr:`follow` parsed."""
    follow: DriverSpec | None = None
    """What the layer's imagined futures follow (None: the driver itself)."""

    def __post_init__(self) -> None:
        if self.layer is None:
            if self.follow is not None:
                raise ValueError(
                    f"a driver to follow applies to a driver behind the safety layer, not to {self.text}"
                )
            return
        if self.kind == "callable" or (self.kind == "driver" and self.name != "rule"):
            raise ValueError(f"the safety layer guards a policy or the rule-based driver (safety-layer:rule), not "
                             f"{self.name}")  # fmt: skip
        if self.kind == "driver" and self.follow is not None and self.follow.name != "rule":
            raise ValueError(
                f"a driver to follow applies to a policy behind the safety layer, not to {self.text}"
            )
        if self.follow is not None and self.follow.layer is not None:
            raise ValueError(f"driver to follow: {self.follow.text} drives behind a safety layer of its own")

    @property
    def path(self) -> Path:
        """The policy file (``ValueError`` for another kind)."""
        if self.kind != "policy":
            raise ValueError(f"{self.text} is no policy file")
        return Path(self.name)


def resolve_policy_spec(text: str) -> tuple[str, str | None]:
    """``(words, predictor)``: ``text`` with a ``zoo:NAME`` part (also after a prefix such as ``safety-layer:``)
    replaced by the entry's policy file, and the zoo's predictor when that policy reads predictions (else None): the
    words a command's flag or a stored record keeps (:func:`parse_driver_spec` resolves the entry itself)."""
    prefix, sep, rest = text.partition(":")
    if text.startswith(ZOO_PREFIX):
        entry = zoo_entry(text)
        return f"{POLICY_PREFIX}{entry.policy}", str(entry.predictor) if entry.predictor else None
    if sep and rest.startswith(ZOO_PREFIX):
        entry = zoo_entry(rest)
        return f"{prefix}:{entry.policy}", str(entry.predictor) if entry.predictor else None
    return text, None


def split_policy_spec(text: str) -> tuple[str, str] | None:
    """``(prefix, path)`` of words that name a policy file with one of :data:`POLICY_PREFIXES` and a path, else
    None (what a recorder checks before it builds anything)."""
    prefix = next((p for p in POLICY_PREFIXES if text.startswith(p) and len(text) > len(p)), None)
    return None if prefix is None else (prefix, text.removeprefix(prefix))


def split_safety_layer(text: str) -> tuple[str, SafetyLayerConfig | None]:
    """``(driver, layer)``: the driver a spec names and the safety layer it drives behind (``None``: none), the
    layer's settings those the spelling means (:data:`LEGACY_BASES`, :data:`LEGACY_DRIVERS`), else the defaults.
    ``safety-layer:X`` and ``lookahead-blind:X`` give ``X``; the built-in ``lookahead`` drivers give ``rule``."""
    if text.startswith(SAFETY_LAYER_PREFIX) and len(text) > len(SAFETY_LAYER_PREFIX):
        return text.removeprefix(SAFETY_LAYER_PREFIX), SafetyLayerConfig()
    for prefix, base in LEGACY_BASES.items():
        if text.startswith(prefix) and len(text) > len(prefix):
            return text.removeprefix(prefix), SafetyLayerConfig(**base)
    if text in LEGACY_DRIVERS:
        return "rule", SafetyLayerConfig(**LEGACY_DRIVERS[text])
    return text, None


def safety_layer_of(text: str, table: Mapping[str, Any] | None = None, follow: str | None = None, *,
                    where: str = "safety layer") -> SafetyLayerConfig | None:  # fmt: skip
    """The safety layer a driver spec drives behind (:func:`split_safety_layer`) with the settings ``table`` (a
    ``[safety]`` table, or the settings a zoo card or an older record holds) and the follower ``follow`` on top;
    ``None`` for a spec behind no layer. ``ValueError`` when settings are given for a spec behind none. (What a
    stored record or card needs: it reads the layer without the driver, whose file may be gone.)"""
    _, layer = split_safety_layer(text)
    if layer is None:
        if table or follow:
            raise ValueError(f"{where}: settings of the safety layer given for {text}, which drives behind none "
                             f"(name it {SAFETY_LAYER_PREFIX}{text})")  # fmt: skip
        return None
    if table:
        layer = SafetyLayerConfig.from_table(table, where=where, base=layer)
    if follow:
        layer = dataclasses.replace(layer, follow=str(follow))
    return layer


def parse_driver_spec(text: str, *, safety_table: Mapping[str, Any] | SafetyLayerConfig | None = None,
                      follow: str | None = None, where: str = "safety layer") -> DriverSpec:  # fmt: skip
    """The :class:`DriverSpec` the words ``text`` name (the grammar above, older spellings included).
    ``safety_table``: the layer's settings on top of what the spelling means (a ``[safety]`` table, named ``where``
    in errors), or the layer itself in place of it; ``follow``: the driver the layer's imagined futures follow (else
    the layer's own ``follow``). ``ValueError`` in one line for settings given to a driver behind no layer, a zoo
    name that is no entry, or a driver the layer may not guard."""
    if isinstance(safety_table, SafetyLayerConfig):
        if split_safety_layer(text)[1] is None:
            raise ValueError(f"settings of the safety layer apply to a driver behind it (safety-layer:{text}), "
                             f"not to {text}")  # fmt: skip
        layer: SafetyLayerConfig | None = (
            safety_table if not follow else dataclasses.replace(safety_table, follow=str(follow))
        )
    else:
        layer = safety_layer_of(text, safety_table or None, follow, where=where)
    rest = split_safety_layer(text)[0]
    followed = parse_driver_spec(layer.follow) if layer is not None and layer.follow else None
    policy = rest.startswith(POLICY_PREFIX) and len(rest) > len(POLICY_PREFIX)
    rest = rest.removeprefix(POLICY_PREFIX) if policy else rest
    if rest.startswith(ZOO_PREFIX):
        entry = zoo_entry(rest)
        return DriverSpec(text=text, kind="policy", name=str(entry.policy), layer=layer, follow=followed,
                          predictor=str(entry.predictor) if entry.predictor else None)  # fmt: skip
    kind: Kind = "policy"
    if not policy and rest in DRIVER_NAMES:
        kind = "driver"
    elif not policy and layer is None and CALLABLE_SPEC.match(rest):
        kind = "callable"
    return DriverSpec(text=text, kind=kind, name=rest, layer=layer, follow=followed)


def policy_spec(
    path: str | os.PathLike[str],
    *,
    behind: Mapping[str, Any] | None = None,
    follow: str | os.PathLike[str] | None = None,
) -> DriverSpec:
    """A policy file as a :class:`DriverSpec`, built typed (the experiment's stages name their drivers so):
    alone, or, with ``behind`` (the layer's settings: a ``[safety]`` table, a card's), behind the safety layer those
    stages have always measured (blind, not perceived unless the settings say: what ``lookahead-blind:`` spells),
    its imagined futures following the policy file ``follow`` (None: the policy itself)."""
    if behind is None:
        return DriverSpec(text=str(path), kind="policy", name=str(path))
    prefix = "lookahead-blind:"
    layer = SafetyLayerConfig.from_table(behind, base=SafetyLayerConfig(**LEGACY_BASES[prefix]))
    followed = None if follow is None else policy_spec(follow)
    if followed is not None:
        layer = dataclasses.replace(layer, follow=followed.name)
    return DriverSpec(text=f"{prefix}{path}", kind="policy", name=str(path), layer=layer, follow=followed)


def zoo_safety_layer(entry: ZooEntry, follow: str = "") -> SafetyLayerConfig | None:
    """The safety layer a zoo card's figure behind the layer was measured with (its recorded driver's spelling and
    settings), its imagined futures following ``follow``; None when the card has none."""
    config = (entry.card.get("safety_layer") or {}).get("config") or {}
    if not config.get("lookahead"):
        return None
    spelling = str(config.get("driver") or "safety-layer:policy")
    return safety_layer_of(spelling, config["lookahead"], follow or None, where=f"zoo:{entry.name}'s card")


def as_driver_spec(spec: DriverSpec | str, safety: SafetyLayerConfig | None = None) -> DriverSpec:
    """``spec`` as a :class:`DriverSpec`: the words parsed (``safety``: the layer in place of what the spelling
    means), or the typed value as it is (``safety`` then refused: its layer is in it). What the library's public
    functions that also take the words (scripts, tests and stored records name drivers so) call first, once."""
    if isinstance(spec, DriverSpec):
        if safety is not None:
            raise ValueError(
                f"{spec.text}: the safety layer of a parsed driver spec is in it, not given apart"
            )
        return spec
    return parse_driver_spec(spec, safety_table=safety)


__all__ = [
    "CALLABLE_SPEC",
    "LEGACY_BASES",
    "LEGACY_DRIVERS",
    "POLICY_PREFIX",
    "POLICY_PREFIXES",
    "SAFETY_LAYER_PREFIX",
    "DriverSpec",
    "as_driver_spec",
    "parse_driver_spec",
    "policy_spec",
    "resolve_policy_spec",
    "safety_layer_of",
    "split_policy_spec",
    "split_safety_layer",
    "zoo_safety_layer",
]
