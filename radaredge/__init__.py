"""radaredge: export 4D-radar perception models to self-contained ONNX, prove parity, measure speed.

Importing the package imports neither torch nor onnxruntime; ``radaredge.runtime`` needs only
numpy and onnxruntime.
"""

__version__ = "0.1.0"
