"""Errors a user can act on.

Every failure caused by the caller's data or configuration is raised as one of these, with a
message that names the frame, the column or the field and says what was expected. Nothing in
radaredge should let a bad input surface as a traceback from deep inside torch or onnxruntime.
"""


class RadarEdgeError(Exception):
    """Base class of every radaredge error."""


class InputError(RadarEdgeError, ValueError):
    """Raw radar input does not match what the model card declares (shape, dtype, finite values)."""


class ConfigError(RadarEdgeError, ValueError):
    """A model card or a command-line option is missing a field or holds an invalid value."""


class CapacityError(RadarEdgeError, ValueError):
    """A fixed-capacity export buffer (pillars, points per pillar, boxes) would be exceeded."""


class ExportError(RadarEdgeError, RuntimeError):
    """Exporting a model to ONNX, or checking the exported graph, failed."""
