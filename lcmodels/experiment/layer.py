"""The safety layer as the experiment uses it, in one place: which recipe a layer follows, and the settings of a
recipe's ``[safety]`` table or of a zoo card's layer as the stage records hold them."""

from __future__ import annotations

from typing import Any

from lcmodels.recipe import Recipe


def has_layer(recipe: Recipe) -> bool:
    """``recipe`` is evaluated behind the safety layer too (it has a ``[safety]`` table)."""
    return recipe.safety is not None


def follows(recipe: Recipe) -> str | None:
    """The recipe whose final policy (same training seed) the layer's imagined futures follow; None when the
    recipe has no layer or its layer follows the policy itself."""
    return recipe.safety.follow or None if recipe.safety is not None else None


def lookahead_settings(s: Any) -> dict[str, Any]:
    """The settings of a recipe's safety layer (a :class:`lcsim.planning.SafetyLayerConfig`, blind) as its stages
    record them, so that stages measured before stay complete."""
    return {"horizon_decisions": s.horizon_decisions, "samples": s.samples, "perceived": s.perceived}


def recipe_lookahead(recipe: Recipe) -> dict[str, Any]:
    """The lookahead settings of ``recipe``'s layer (it must have one)."""
    assert recipe.safety is not None
    return lookahead_settings(recipe.safety)


def card_lookahead(card: dict[str, Any]) -> dict[str, Any] | None:
    """The lookahead settings a zoo card's safety layer was measured with (None: the card has no layer)."""
    look = ((card.get("safety_layer") or {}).get("config") or {}).get("lookahead")
    return dict(look) if look else None
