"""radaredge: export 4D-radar perception models to self-contained ONNX, prove parity, measure speed.

The verbs (:mod:`radaredge.api`)::

    import radaredge
    radaredge.export("tdfanet")                       # -> ExportResult
    report = radaredge.parity("tdfanet")              # bool(report) is the verdict
    radaredge.bench("tdfanet", threads=2)             # -> BenchReport
    radaredge.evaluate("tdfanet", onnx, database, queries)
    radaredge.quantize("maffnet-vod-edge", onnx, data="set", search=True)   # int8 judged by AP on val
    radaredge.train("tdfanet-edge", "train-towns")     # -> TrainReport; runs/tdfanet-edge/best.pth
    radaredge.card_from_openpcdet("MAFF-Net_vod.yaml", "models/my.yaml")   # `radaredge card from-openpcdet`

Importing the package imports neither torch nor onnxruntime (the verbs load them when called);
it registers the model families (:mod:`radaredge.models`, torch-free declarations), so every
card is parsed against its family's sections. ``radaredge.runtime`` needs only numpy and
onnxruntime.
"""

from . import models  # noqa: F401  (registers the model families; imports no torch)
from .version import __version__

__all__ = ["__version__", "export", "parity", "bench", "evaluate", "quantize", "train", "card_from_openpcdet"]

_VERBS = ("export", "parity", "bench", "evaluate", "quantize", "train", "card_from_openpcdet")


def __getattr__(name):
    if name in _VERBS:
        # lazy: the API imports torch, which importing radaredge must not
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'radaredge' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_VERBS))
