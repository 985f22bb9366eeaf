"""radaredge's version, written into every export's metadata."""

__version__ = "0.1.0"
