"""Model name -> builder. One line per model; the card's ``model`` field picks the entry."""

from __future__ import annotations

from typing import Callable

from .cards import ModelCard
from .errors import ConfigError


def _tdfanet():
    from .models.tdfanet_spec import TDFANET_SPEC
    return TDFANET_SPEC


def _maffnet():
    from .models.maffnet_spec import MAFFNET_SPEC
    return MAFFNET_SPEC


def _des4pos():
    from .models.des4pos_spec import DES4POS_SPEC
    return DES4POS_SPEC


MODELS: dict[str, Callable] = {
    "tdfanet": _tdfanet,
    "maffnet": _maffnet,
    "des4pos": _des4pos,       # a BundleSpec: three graphs (submap encoder, text encoder, fine stage)
}


def model_spec(card: ModelCard):
    """The :class:`radaredge.models.spec.ModelSpec` (one graph) or
    :class:`radaredge.models.spec.BundleSpec` (several graphs) of ``card``'s model."""
    try:
        return MODELS[card.model]()
    except KeyError:
        raise ConfigError(f"{card.where}: unknown model {card.model!r}; known: {sorted(MODELS)}") from None


def is_bundle(card: ModelCard) -> bool:
    """True when ``card``'s model exports as several graphs (a BundleSpec)."""
    from .models.spec import BundleSpec
    return isinstance(model_spec(card), BundleSpec)
