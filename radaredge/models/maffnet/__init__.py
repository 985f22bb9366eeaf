"""MAFF-Net (4D-radar 3D detection, an OpenPCDet fork): stage one (:mod:`.model`, with the
fuser of :mod:`.fuser`), stage two (:mod:`.rcnn`) and the spec (:mod:`.spec`), registered as
``maffnet``."""

from ...registry import ModelFamily, register_family

register_family(
    ModelFamily(
        "maffnet",
        sections=(
            "pillars",
            "spa",
            "cfa",
            "caf",
            "backbone_2d",
            "dense_head",
            "post_processing",
            "stage_two",
            "input",
            "init",
            "vfe_features",
        ),
        spec=f"{__name__}.spec:spec_for",
    )
)
