"""Torch-free runtime: load an exported ``.onnx`` and run it on raw radar frames.

Imports only numpy, onnxruntime and radaredge's own torch-free modules (cards, errors and this
package), so an embedded application needs neither torch nor the radaredge model code::

    from radaredge import runtime
    model = runtime.load("export/tdfanet.onnx")
    out = model.run([scan_t2, scan_t1, scan_t0])     # oldest first, each [N_k, 5] x,y,z,v_r,rcs
    out["descriptor_normalized"]                      # 256-d place descriptor

The package: :mod:`.model` (the exported-graph wrapper), :mod:`.session` (onnxruntime session
options), :mod:`.openvino` (OpenVINO's CPU plugin), :mod:`.runners` (either runtime behind one
callable), :mod:`.metadata` (the ``radaredge.*`` metadata contract), :mod:`.integrity` (each
graph's content hash, recomputed from the file whenever :func:`load` or :func:`inspect_export`
reads it), :mod:`.des4pos` and :mod:`.text_tokens` (the Des4Pos query path: tokens, map index,
locate).
"""

from __future__ import annotations

# The names below load on first use, so importing a light submodule (metadata, runners) or the
# command line does not import numpy and onnxruntime.
_MODEL_NAMES = ("RadarModel", "FrameFeeds", "load", "inspect_export", "max_points_per_frame", "DEFAULT_MAX_POINTS")
__all__ = list(_MODEL_NAMES)


def __getattr__(name):
    if name in _MODEL_NAMES:
        # lazy: radaredge.cli imports radaredge.runtime, and its light commands must not load numpy and onnxruntime
        from . import model

        return getattr(model, name)
    raise AttributeError(f"module 'radaredge.runtime' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_MODEL_NAMES))
