"""Model name -> builder. One line per model; the card's ``model`` field picks the entry."""

from __future__ import annotations

from typing import Callable

from .cards import ModelCard
from .errors import ConfigError


def _tdfanet():
    from .models.tdfanet_spec import TDFANET_SPEC
    return TDFANET_SPEC


MODELS: dict[str, Callable] = {
    "tdfanet": _tdfanet,
}


def model_spec(card: ModelCard):
    """The :class:`radaredge.models.spec.ModelSpec` that builds, feeds and compares ``card``'s model."""
    try:
        return MODELS[card.model]()
    except KeyError:
        raise ConfigError(f"{card.where}: unknown model {card.model!r}; known: {sorted(MODELS)}") from None
