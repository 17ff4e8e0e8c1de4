"""The safety layer's configuration: one type for recipes, commands, zoo cards and training behind the layer.

The *safety layer* checks each decision of a driver (a policy, or the rule-based driver) against futures it
imagines in copies of the simulator (:class:`~lcsim.planning.LookaheadDriver`) and executes another decision
when the proposed one does not survive them as well. :class:`SafetyLayerConfig` says how it imagines; its fields
are a recipe's ``[safety]`` table, ``lc-eval --config``'s ``[safety]`` table and the commands'
``--set safety.KEY=VALUE`` (a table's older ``horizon`` is read too). Which driver drives behind the layer is the
commands' words (``safety-layer:zoo:hybrid-ppo``), read in :mod:`lcmodels.policy.driverspec`, not here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from lckit.config import JsonConfig, check_field, check_limits, field_type, parse_value

LEGACY_KEYS: dict[str, str] = {"horizon": "horizon_decisions"}
"""Older names of fields (a recipe's ``[safety]`` table said ``horizon``)."""

RESEARCH_KEYS: dict[str, Any] = {"driver_draws": False, "estimate_drivers": False, "known_drivers": (), "margin_m": 0.0}
"""Settings the safety layer had as research options (and their neutral values, still read where a stored table
spells them out): measured in ``docs/results/safety-samples``, none changed a figure beyond the noise; they run in
``experiments/imagined_drivers``."""

REFERENCE: dict[str, Any] = {"horizon_decisions": 16, "blind": False, "samples": 1, "perceived": False}
"""The settings against which :meth:`SafetyLayerConfig.ledger_settings` names the ones that differ: the
privileged layer's (the first safety layer the ledger knew), so that every identity written stays the same."""


@dataclass(frozen=True, slots=True, kw_only=True)
class SafetyLayerConfig(JsonConfig):
    """How the safety layer imagines the future of each candidate decision (:class:`~lcsim.planning.LookaheadDriver`).

    The defaults are the layer a car could have: blind to the traffic's coming random draws and seeing only what
    the ego's sensors show. ``blind = false`` is a privileged layer, which sees the future exactly: an upper
    reference, not a layer to deploy."""

    LIMITS: ClassVar[dict[str, float]] = {"horizon_decisions": 1_000, "samples": 1_000}

    follow: str = ""
    """Who drives on in the imagined futures after the candidate decision: a built-in driver (``rule``), a policy
    file or ``zoo:NAME`` that does not read the image (the imagined futures are not rendered); in a recipe, the
    name of the recipe whose policy of the same training seed. '' (default): the driver behind the layer itself,
    which must then not read the image."""
    horizon_decisions: int = 16
    """Decisions imagined after each candidate (16 x 0.5 s = 8 s): the ego gains only ~1.7 m/s on the traffic,
    so a trap (a slow leader with both side lanes occupied) closes over seconds."""
    blind: bool = True
    """Imagine futures with the traffic's random draws redrawn (:func:`~lcsim.planning.perception.redraw_future`):
    the layer knows the traffic's rules and present state, not its coming random lane changes. ``false``: the
    layer is privileged: it sees them."""
    samples: int = 1
    """Blind only: futures imagined per candidate decision, each redrawn with its own salt. A decision's survival is
    the share of them it survives; the proposed decision stands unless another survives more of them."""
    perceived: bool = True
    """Blind only: imagine each future from what the ego's sensors show (:func:`~lcsim.planning.perception.perceive`
    with the scenario's ``sensing_range_m``): no traffic beyond that range, each vehicle's unseen desired speed
    read from its motion, every unseen driver the median one. The layer then needs no privileged state, only the
    traffic's rules and the ego's perception."""

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(self.horizon_decisions >= 1, self, "horizon_decisions", "must be >= 1", self.horizon_decisions)
        check_field(self.samples >= 1, self, "samples", "must be >= 1", self.samples)
        check_field(self.blind or self.samples == 1, self, "samples",
                    "> 1 needs blind = true (futures not redrawn are all the same future)", self.samples)
        check_field(self.blind or not self.perceived, self, "perceived",
                    "needs blind = true (a privileged layer, blind = false, sees the whole true future: set "
                    "perceived = false with it)", self.perceived)  # fmt: skip

    def ledger_settings(self) -> dict[str, Any]:
        """How the layer imagines (every field but ``follow``) where it differs from :data:`REFERENCE`, each value
        of its field's type: the safety layer's identity in the benchmark's ledger (``lcmodels.bench``), the same
        however the settings were spelt (``32`` or a default given or left out)."""
        return {name: getattr(self, name) for name in REFERENCE if getattr(self, name) != REFERENCE[name]}

    @classmethod
    def from_table(cls, table: Mapping[str, Any], *, where: str = "[safety]",
                   base: SafetyLayerConfig | None = None) -> SafetyLayerConfig:  # fmt: skip
        """The layer of a ``[safety]`` table (a recipe's, ``lc-eval --config``'s), of a zoo card's or a record's
        settings: ``base`` (default: the defaults) with the table's fields. Older names are read (``horizon``);
        a research option at its neutral value is ignored, set otherwise it is refused with where it went.
        ``ValueError`` in one line naming ``where`` and the key."""
        if not isinstance(table, Mapping):
            raise ValueError(f"{where}: expected a table of safety layer settings, got {table!r}")
        data = (base or cls()).to_dict()
        names = set(data)
        for key, value in table.items():
            if key in RESEARCH_KEYS:
                neutral = RESEARCH_KEYS[key]
                if value == neutral or (isinstance(neutral, tuple) and value in ([], ())):
                    continue
                raise ValueError(f"{where}: {key} was a research option of the safety layer and is no longer one: "
                                 "python -m experiments.imagined_drivers.imagined_drivers runs it "
                                 "(docs/results/safety-samples)")  # fmt: skip
            name = LEGACY_KEYS.get(key, key)
            if name not in names:
                raise ValueError(f"{where}: the safety layer has no setting {key!r} (settings: "
                                 f"{', '.join(sorted(names))})")  # fmt: skip
            data[name] = value
        try:
            return cls.from_dict(data, stored=False)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

    def with_named_settings(self, settings: Sequence[str], prefix: str = "safety.") -> SafetyLayerConfig:
        """This layer with ``--set`` settings ``safety.KEY=VALUE`` (``prefix`` then a field or an older name),
        each value read as its field's type. ``ValueError`` naming the setting."""
        table: dict[str, Any] = {}
        for text in settings:
            key, sep, value = text.partition("=")
            key = key.strip().removeprefix(prefix)
            if not sep or not key:
                raise ValueError(f"--set {text!r}: expected {prefix}KEY=VALUE ({prefix}horizon_decisions=32)")
            name = LEGACY_KEYS.get(key, key)
            if name in RESEARCH_KEYS or not any(f.name == name for f in dataclasses.fields(self)):
                table[key] = value  # from_table names what is wrong with it
                continue
            table[name] = parse_value(value.strip(), getattr(self, name), f"--set {text}", field_type(self, name))
        return SafetyLayerConfig.from_table(table, where=f"--set {', '.join(settings)}", base=self)


PRIVILEGED = SafetyLayerConfig(blind=False, perceived=False)
"""The privileged safety layer: it sees the traffic's coming random draws (an upper reference)."""


__all__ = [
    "PRIVILEGED",
    "REFERENCE",
    "RESEARCH_KEYS",
    "SafetyLayerConfig",
]
