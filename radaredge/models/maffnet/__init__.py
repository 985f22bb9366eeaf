"""MAFF-Net (4D-radar 3D detection, an OpenPCDet fork): stage one (:mod:`.model`, with the
fuser of :mod:`.fuser`), stage two (:mod:`.rcnn`) and the spec (:mod:`.spec`), registered as
``maffnet``."""

from . import spec  # noqa: F401  (registers the spec)
