"""Model family name -> its declaration, filled by the model packages themselves.

Each package under :mod:`radaredge.models` calls :func:`register_family` when it is imported
(importing :mod:`radaredge.models`, which ``import radaredge`` does, discovers and imports them
all). A declaration is torch-free: the card sections the family reads, checked whenever a card
is parsed (:func:`radaredge.cards.parse_card`, also in the torch-free commands), and where its
spec lives, loaded when a verb first asks for it (:func:`model_spec`). The spec
(:class:`radaredge.models.spec.ModelSpec`) says everything else a verb needs: graphs,
comparators, int8 plan, bench tasks, evaluation and training recipe. This module imports no
model and no card, so it sits below both.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from .errors import ConfigError


@dataclass(frozen=True)
class ModelFamily:
    """A model family's declaration: ``name`` is the cards' ``model`` field; ``sections`` the
    top-level card sections its models read (besides the fields every card takes); ``spec`` where
    its spec function ``spec_for(card) -> ModelSpec`` lives, as ``"package.module:function"``
    (imported on first use: the spec's module imports torch)."""

    name: str
    sections: tuple[str, ...]
    spec: str

    def spec_for(self, card):
        """The :class:`radaredge.models.spec.ModelSpec` of ``card`` (a card may pick a variant,
        e.g. MAFF-Net's two-stage graph)."""
        module, _, function = self.spec.partition(":")
        return getattr(importlib.import_module(module), function)(card)


_FAMILIES: dict[str, ModelFamily] = {}


def register_family(family: ModelFamily) -> ModelFamily:
    """Registers ``family`` under its name; a name registers once (the same declaration again is
    a no-op, so a re-imported package is harmless)."""
    if family.name in _FAMILIES and _FAMILIES[family.name] != family:
        raise ValueError(f"model family {family.name!r} is registered twice")
    _FAMILIES[family.name] = family
    return family


def registered() -> list[str]:
    """The registered family names, sorted."""
    return sorted(_FAMILIES)


def card_sections(model: str) -> tuple[str, ...] | None:
    """The top-level sections a card of model family ``model`` may hold; None for a family that
    is not registered (the card is refused when a verb asks for its spec)."""
    family = _FAMILIES.get(model)
    return None if family is None else family.sections


def model_spec(card):
    """The :class:`radaredge.models.spec.ModelSpec` of ``card``'s model family."""
    try:
        family = _FAMILIES[card.model]
    except KeyError:
        raise ConfigError(f"{card.where}: unknown model {card.model!r}; known: {registered()}") from None
    return family.spec_for(card)
