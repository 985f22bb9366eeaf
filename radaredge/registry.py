"""Model family name -> its spec, filled by the model packages themselves.

Each package under :mod:`radaredge.models` decorates its spec function with
:func:`register_model`; importing :mod:`radaredge.models` imports them all. This module imports
nothing from the models, so the registry sits below them (the card's ``model`` field is the key;
its top-level sections are :data:`radaredge.cards.CARD_SECTIONS`).
"""

from __future__ import annotations

from typing import Callable

from .cards import ModelCard
from .errors import ConfigError

_SPECS: dict[str, Callable] = {}


def register_model(name: str) -> Callable[[Callable], Callable]:
    """Decorator: ``spec_for(card) -> ModelSpec`` is the spec of family ``name`` (a card may pick
    a variant, e.g. MAFF-Net's two-stage graph). A name registers once."""
    def add(spec_for: Callable) -> Callable:
        if name in _SPECS and _SPECS[name] is not spec_for:
            raise ValueError(f"model {name!r} is registered twice")
        _SPECS[name] = spec_for
        return spec_for
    return add


def registered() -> list[str]:
    """The registered family names, sorted."""
    return sorted(_SPECS)


def model_spec(card: ModelCard):
    """The :class:`radaredge.models.spec.ModelSpec` of ``card``'s model (its graphs);
    the models register on ``import radaredge.models``, which every verb does."""
    try:
        spec_for = _SPECS[card.model]
    except KeyError:
        raise ConfigError(f"{card.where}: unknown model {card.model!r}; known: {registered()}") from None
    return spec_for(card)
