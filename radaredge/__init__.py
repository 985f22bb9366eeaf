"""radaredge: export 4D-radar perception models to self-contained ONNX, prove parity, measure speed.

The verbs (:mod:`radaredge.api`)::

    import radaredge
    radaredge.export("tdfanet")                       # -> ExportResult
    report = radaredge.parity("tdfanet")              # bool(report) is the verdict
    radaredge.bench("tdfanet", threads=2)             # -> BenchReport
    radaredge.evaluate("tdfanet", onnx, database, queries)
    radaredge.train("tdfanet-edge", "train-towns")     # -> TrainReport; runs/tdfanet-edge/best.pth

Importing the package imports neither torch nor onnxruntime (the verbs load them when called);
``radaredge.runtime`` needs only numpy and onnxruntime.
"""

__version__ = "0.1.0"

_VERBS = ("export", "parity", "bench", "evaluate", "train")


def __getattr__(name):
    if name in _VERBS:
        from . import api
        return getattr(api, name)
    raise AttributeError(f"module 'radaredge' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_VERBS))
