"""The models: one package per model family (:mod:`.tdfanet`, :mod:`.maffnet`, :mod:`.des4pos`),
each holding its network (reference and export formulations on one set of weights), its spec
(:mod:`.spec`: graphs, synthetic cases, stages) and its upstream key maps, and registering
itself in :mod:`radaredge.registry` on import. :func:`create_model` builds a card's model.

The verbs (export, parity, bench, eval, train) know the models; the models know no verb.
"""

from . import des4pos, maffnet, tdfanet  # noqa: F401  (each package registers its spec on import)
from ..registry import model_spec, registered
from .factory import LoadReport, create_model, load_checkpoint, save_checkpoint, weights_hash

__all__ = ["create_model", "model_spec", "registered", "load_checkpoint", "save_checkpoint", "weights_hash",
           "LoadReport"]
