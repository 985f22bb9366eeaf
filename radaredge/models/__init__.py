"""The models: one package per model family (:mod:`.tdfanet`, :mod:`.maffnet`, :mod:`.des4pos`),
each holding its network (reference and export formulations on one set of weights), its spec
(:mod:`.spec`: graphs, comparators, synthetic cases, stages, int8 plan, bench tasks, evaluation
and recipe names) and its upstream key maps.

Importing this package imports no torch: it discovers the family packages and imports each,
which registers its torch-free declaration (:class:`radaredge.registry.ModelFamily`: card
sections, where its spec lives). Adding a family is adding a package here (docs/layout.md, "Add
a model"). :func:`create_model` and the checkpoint helpers of :mod:`.factory` import torch, so
they are loaded on first use (module ``__getattr__``); this is the models' one lazy boundary.

The verbs (export, parity, bench, eval, train) read the models' specs; the models import no verb.
"""

import importlib
import pkgutil

from ..registry import model_spec, registered

for _family in pkgutil.iter_modules(__path__):
    if _family.ispkg:
        importlib.import_module(f"{__name__}.{_family.name}")

_FACTORY = ("create_model", "load_checkpoint", "save_checkpoint", "weights_hash", "LoadReport")

__all__ = ["model_spec", "registered", *_FACTORY]


def __getattr__(name):
    if name in _FACTORY:
        factory = importlib.import_module(f"{__name__}.factory")  # torch: loaded when first used
        return getattr(factory, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
