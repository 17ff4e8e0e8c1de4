"""The safety layer as the experiment's stage records hold it, in one place: the settings of a recipe's
``[safety]`` table or of a zoo card's layer. (Which recipe a layer follows: :attr:`Recipe.follows
<lcmodels.experiment.recipe.Recipe.follows>`.)"""

from __future__ import annotations

from typing import Any


def lookahead_settings(s: Any) -> dict[str, Any]:
    """The settings of a recipe's safety layer (a :class:`lcsim.planning.SafetyLayerConfig`, blind) as its stages
    record them, so that stages measured before stay complete."""
    return {"horizon_decisions": s.horizon_decisions, "samples": s.samples, "perceived": s.perceived}


def card_lookahead(card: dict[str, Any]) -> dict[str, Any] | None:
    """The lookahead settings a zoo card's safety layer was measured with (None: the card has no layer)."""
    look = ((card.get("safety_layer") or {}).get("config") or {}).get("lookahead")
    return dict(look) if look else None
