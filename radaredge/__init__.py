"""radaredge: export 4D-radar perception models to self-contained ONNX, prove parity, measure speed.

The verbs (:mod:`radaredge.api`)::

    import radaredge
    radaredge.export("tdfanet")                       # -> ExportResult
    report = radaredge.parity("tdfanet")              # bool(report) is the verdict
    radaredge.bench("tdfanet", threads=2)             # -> BenchReport
    radaredge.evaluate("tdfanet", onnx, database, queries)
    radaredge.train("tdfanet-edge", "train-towns")     # -> TrainReport; runs/tdfanet-edge/best.pth
    radaredge.card_from_openpcdet("MAFF-Net_vod.yaml", "models/my.yaml")   # `radaredge card from-openpcdet`

Importing the package imports neither torch nor onnxruntime (the verbs load them when called);
it registers the model families (:mod:`radaredge.models`, torch-free declarations), so every
card is parsed against its family's sections. ``radaredge.runtime`` needs only numpy and
onnxruntime.
"""

import importlib
import sys
import types

from . import models  # noqa: F401  (registers the model families; imports no torch)
from .version import __version__

__all__ = ["__version__", "export", "parity", "bench", "evaluate", "train", "card_from_openpcdet"]

_VERBS = ("export", "parity", "bench", "evaluate", "train", "card_from_openpcdet")
_VERB_PACKAGES = ("export", "parity", "bench", "train")     # verbs whose machinery is a subpackage of that name


class _VerbPackage(types.ModuleType):
    """A verb's subpackage (``radaredge.export``, ...) that is also the verb: calling it calls
    :mod:`radaredge.api`'s function of that name, so ``radaredge.export("tdfanet")`` and
    ``from radaredge.export import graphs`` both work."""

    def __call__(self, *args, **kwargs):
        # lazy: the API imports torch, which importing radaredge must not
        from . import api
        return getattr(api, self.__name__.rsplit(".", 1)[1])(*args, **kwargs)


class _Package(types.ModuleType):
    """The package module: binding a verb's subpackage as its attribute makes that package callable."""

    def __setattr__(self, name, value):
        if name in _VERB_PACKAGES and isinstance(value, types.ModuleType):
            value.__class__ = _VerbPackage
        super().__setattr__(name, value)


def __getattr__(name):
    if name in _VERB_PACKAGES:                      # importing binds it (callable) through _Package
        return importlib.import_module(f"{__name__}.{name}")
    if name in ("evaluate", "card_from_openpcdet"):
        # lazy: the API imports torch, which importing radaredge must not
        from . import api
        return getattr(api, name)
    raise AttributeError(f"module 'radaredge' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_VERBS))


sys.modules[__name__].__class__ = _Package
