"""Model name -> builder. One line per model; the card's ``model`` field picks the entry (its
top-level sections are :data:`radaredge.cards.CARD_SECTIONS`)."""

from __future__ import annotations

from typing import Callable

from .cards import ModelCard
from .errors import ConfigError


def _tdfanet(card=None):
    from .models.tdfanet_spec import TDFANET_SPEC
    return TDFANET_SPEC


def _maffnet(card=None):
    from .models.maffnet_spec import spec_for
    return spec_for(card)          # a card with stage_two gets the two-stage graph's spec


def _des4pos(card=None):
    from .models.des4pos_spec import DES4POS_SPEC
    return DES4POS_SPEC


MODELS: dict[str, Callable] = {
    "tdfanet": _tdfanet,
    "maffnet": _maffnet,
    "des4pos": _des4pos,       # three graphs: submap encoder, text encoder, fine stage
}


def model_spec(card: ModelCard):
    """The :class:`radaredge.models.spec.ModelSpec` of ``card``'s model (its graphs and hooks)."""
    try:
        entry = MODELS[card.model]
    except KeyError:
        raise ConfigError(f"{card.where}: unknown model {card.model!r}; known: {sorted(MODELS)}") from None
    return entry(card)
