"""Which comparator judges each output of each model's graphs, keyed by model family name: the
parity verb's knowledge of the models (the models declare their outputs, not how they are judged)."""

from __future__ import annotations

import math
from typing import Callable

from ..cards import ModelCard
from ..errors import ConfigError
from ..models.maffnet import rcnn as maffnet_stage_two
from ..models.maffnet.model import output_names as maffnet_outputs
from .comparators import Boxes, Comparator, Dense, Descriptor, Exact, Proposals

TDFANET = (
    Dense("descriptor", atol=1e-4, rtol=1e-3, quantized_info=True),
    Descriptor("descriptor_normalized", min_cosine=0.9999),
    Dense("ego_velocity", unit="m/s", atol=1e-4, rtol=0.0),
    Exact("ego_valid"),
    Exact("input_flags"),
)

DES4POS = {
    "submap_encoder": (Descriptor("descriptor", min_cosine=0.9999), Dense("object_features", atol=1e-4, rtol=1e-3)),
    # int8 (the dynamically quantised copy): the sentence descriptor holds the descriptor budget;
    # the per-hint features the fine stage reads are reported, not judged
    "text_encoder": (Descriptor("descriptor", min_cosine=0.9999),
                     Dense("hint_features", atol=1e-4, rtol=1e-3, quantized_info=True)),
    "fine_stage": (Dense("offset", atol=1e-5, rtol=1e-4), Dense("position", unit="m", atol=1e-3, rtol=0.0)),
}


def maffnet(card: ModelCard, graph: str) -> tuple[Comparator, ...]:
    """How parity judges each output of MAFF-Net's one- or two-stage graph (graph order). Stage
    two's outputs follow the proposal NMS and the keypoint sampling, so they are judged on the
    graph's own rois and keypoints (``conditioned``; see the spec's ``postprocess_reference``)."""
    stage_two = card.get("stage_two") is not None
    angle = dict(angle_column=6, angle_period=math.pi)
    proposals = (maffnet_stage_two.read_stage_two(card).proposals if stage_two
                 else maffnet_stage_two.ProposalConfig())
    judges = {
        "boxes": Boxes("boxes", unit="m, rad"),               # with its scores and labels outputs
        "anchor_scores": Dense("anchor_scores", atol=1e-4, rtol=1e-3, quantized_info=True),
        # heading compared modulo pi: a direction-bin logit pair within float noise may pick the other bin
        "anchor_boxes": Dense("anchor_boxes", unit="m, rad", atol=1e-3, rtol=1e-3, quantized_info=True, **angle),
        "num_pillars": Exact("num_pillars"),
        "spa_overflow": Exact("spa_overflow"),
        "cfa_converged": Exact("cfa_converged"),
        "input_flags": Exact("input_flags"),
        # stage two (cards with ``stage_two``): the logits the proposal layer ranks, then the
        # proposals with their labels and slots (one comparator) and what follows them
        "anchor_logits": Dense("anchor_logits", atol=1e-4, rtol=1e-3, quantized_info=True),
        "rois": Proposals("rois", unit="m, rad", iou_thresh=proposals.iou_thresh, pre_max=proposals.pre_max,
                          post_max=proposals.post_max, score_tol=(1e-4, 1e-3)),
        "keypoints": Dense("keypoints", unit="m", atol=1e-6, rtol=0.0, conditioned=True),
        "keypoint_valid": Exact("keypoint_valid", conditioned=True),
        # a probability after the ROI head's 27,648-wide FC stack: its logit carries float32 noise
        # of a few 1e-4 relative, which moves the probability by up to a quarter of that times
        # |logit| (9e-4 seen with trained-scale weights); judged absolutely, as a probability
        "rcnn_scores": Dense("rcnn_scores", atol=2e-3, rtol=0.0, quantized_info=True, conditioned=True),
        "rcnn_boxes": Dense("rcnn_boxes", unit="m, rad", atol=1e-3, rtol=1e-3, quantized_info=True, conditioned=True,
                            **angle),
    }
    return tuple(judges[n] for n in maffnet_outputs(stage_two) if n in judges)


JUDGES: dict[str, Callable[[ModelCard, str], tuple[Comparator, ...]]] = {
    "tdfanet": lambda card, graph: TDFANET,
    "maffnet": maffnet,
    "des4pos": lambda card, graph: DES4POS[graph],
}


def comparators(card: ModelCard, graph: str) -> tuple[Comparator, ...]:
    """The comparators of graph ``graph`` of ``card``'s model, one per judged output."""
    try:
        judge = JUDGES[card.model]
    except KeyError:
        raise ConfigError(f"{card.name}: parity has no comparators for model {card.model!r}; known: "
                          f"{sorted(JUDGES)}") from None
    return judge(card, graph)
