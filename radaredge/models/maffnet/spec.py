"""MAFF-Net's graph signature, parity cases, conditioned reference stages and runtime checks (see
radaredge.models.spec)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from ...cards import ModelCard
from ...data.synthetic import generate_scan, generate_sequence, tj4d_table, vod_accumulated_table, vod_table
from ...errors import ConfigError
from ...runtime.metadata import OutputCheck
from ..comparators import Boxes, Comparator, Dense, Exact, Proposals
from ..spec import GraphSpec, ModelSpec
from . import rcnn as two
from .model import MAFFNet, build_maffnet, output_names, stage_times


def input_names(card: ModelCard) -> list[str]:
    """One scan: points [N, F], columns as the card's ``features``."""
    return ["points"]


def dynamic_axes(card: ModelCard) -> dict:
    return {"points": {0: "num_points"}}


VOD_FEATURES = ("x", "y", "z", "rcs", "v_r", "v_r_comp", "time")  # upstream's names of the VoD columns


def synthetic_columns(scan) -> dict[str, np.ndarray]:
    """Every feature name a MAFF-Net card may use, from a synthetic scan: the VoD columns under
    upstream's names (:data:`VOD_FEATURES`) and TJ4D's SNR (the Power column) and range."""
    vod, tj4d = vod_table(scan), tj4d_table(scan)
    cols = dict(zip(VOD_FEATURES, vod.T))
    cols.update(snr=tj4d[:, 5], range=tj4d[:, 4])
    return cols


def synthetic_points(scan, card: ModelCard) -> np.ndarray:
    """A synthetic scan's points [N, F] float32 in the card's feature columns, in card order."""
    return _card_columns(synthetic_columns(scan), card)


def _card_columns(cols: dict[str, np.ndarray], card: ModelCard) -> np.ndarray:
    """The card's feature columns of ``cols`` [N, F] float32, in card order."""
    missing = [f for f in card.features if f not in cols]
    if missing:
        raise ConfigError(
            f"{card.where}: synthetic scans provide {sorted(cols)}; card features {missing} are not among them"
        )
    return np.ascontiguousarray(np.stack([cols[f] for f in card.features], 1), np.float32)


def _out_of_range(rng: np.random.Generator, card: ModelCard, width: int, n: int = 30) -> np.ndarray:
    """Points beyond the faces of the pillar range (dropped by the pillars, x/y outside the CFA grid too)."""
    r = card.get("pillars.point_cloud_range")
    pts = rng.normal(0, 1, (n, width)).astype(np.float32)
    pts[:, 0] = rng.choice([r[0] - 2.0, r[3] + 3.0, (r[0] + r[3]) / 2], n)
    pts[:, 1] = rng.choice([r[1] - 3.0, r[4] + 3.0], n)
    pts[:, 2] = rng.choice([r[2] - 2.0, r[5] + 2.0, 0.0], n)
    return pts


DENSE_TRAFFIC = {"num_cars": 10, "num_pedestrians": 8, "num_cyclists": 6, "static_points": 600}
VOD_CAMERA_FOV_DEG = 32.9  # half the horizontal field of view of VoD's camera (FOV_POINTS_ONLY)


def five_frame_points(seed: int, card: ModelCard, dense: bool = True) -> np.ndarray:
    """A VoD ``radar_5frames``-style cloud: 5 consecutive synthetic scans moved into the newest
    scan's frame, ``time`` <= 0 s, cropped to the camera's field of view, in the card's columns."""
    seq = generate_sequence(5, seed=seed, **(DENSE_TRAFFIC if dense else {}))
    return _card_columns(dict(zip(VOD_FEATURES, vod_accumulated_table(seq, VOD_CAMERA_FOV_DEG).T)), card)


def make_cases(card: ModelCard, n: int, seed: int) -> list[tuple[str, dict[str, np.ndarray]]]:
    """``n`` synthetic scans in rotation: urban drives, 40 % dynamic points, dense traffic (more
    clusters for the CFA), drives with points outside the range and, for cards with VoD's
    ``time`` column, dense 5-frame accumulated clouds (upstream's radar_5frames input); one in ten
    has 3 points."""
    kinds = ("drive", "dynamic-40%", "dense-traffic", "out-of-range")
    if "time" in card.features and set(card.features) <= set(VOD_FEATURES):
        kinds += ("5-frame",)
    cases = []
    for i in range(n):
        kind = kinds[i % len(kinds)]
        s = seed * 1000 + i
        overrides = {"dynamic_fraction": 0.4} if kind == "dynamic-40%" else {}
        if kind == "dense-traffic":
            overrides = dict(DENSE_TRAFFIC)
        if kind == "5-frame":
            pts = five_frame_points(s, card)
        else:
            pts = synthetic_points(generate_scan(seed=s, **overrides), card)
        rng = np.random.default_rng(s)
        if kind == "out-of-range":
            pts = np.concatenate([pts, _out_of_range(rng, card, pts.shape[1])])
            pts = pts[rng.permutation(len(pts))]
        if i % 10 == 9:
            pts, kind = pts[:3], "3-points"
        cases.append((f"{i:02d}-{kind}", {"points": pts}))
    return cases


def trace_order(card: ModelCard) -> tuple[str, ...]:
    stage_one = ("pillar_bev", "cfa_map", "cfa_features", "fused")
    return stage_one + ("point_features", "point_cls_scores") if card.get("stage_two") else stage_one


def run_reference(model: MAFFNet, feeds, trace=None):
    return model.run(torch.as_tensor(feeds["points"]), reference=True, trace=trace)


def run_export(model: MAFFNet, feeds, trace=None):
    return model.run(torch.as_tensor(feeds["points"]), reference=False, trace=trace)


def postprocess_reference(model: MAFFNet, feeds, got: dict, ref: dict, trace: dict) -> dict:
    """The reference NMS on the graph's own per-anchor scores and boxes."""
    boxes, scores, labels = model.postprocess(
        torch.as_tensor(got["anchor_scores"]), torch.as_tensor(got["anchor_boxes"]), reference=True
    )
    return {"boxes": boxes, "scores": scores, "labels": labels}


_ROI_STAGE = ("rois", "roi_labels", "roi_valid", "keypoints", "keypoint_valid")


def postprocess_reference_two(model: MAFFNet, feeds, got: dict, ref: dict, trace: dict) -> dict:
    """Stage two's reference, each step on the graph's own inputs to it: the proposal layer on the
    graph's anchor logits and boxes; the CDA keypoints on the graph's rois (with the reference's
    cluster points); VSA, point head and ROI head on the graph's rois and keypoints (with the
    reference's fused BEV map); the final NMS on the graph's refined boxes and scores. Where the
    graph's rois and keypoints equal the reference's, its ROI-head outputs are reused."""
    g = {
        k: torch.as_tensor(got[k]) for k in ("anchor_logits", "anchor_boxes", *_ROI_STAGE, "rcnn_boxes", "rcnn_scores")
    }
    rois, roi_labels, roi_valid = model.proposal_layer.reference(g["anchor_logits"], g["anchor_boxes"])
    xyz, feats, scan = two.scan_points(torch.as_tensor(feeds["points"]), model.vfe.config.point_cloud_range)
    cluster = trace["cluster_points"] & scan
    keypoints, keypoint_valid = model.keypoint_sampler.reference(
        xyz.numpy(), cluster.numpy(), scan.numpy(), got["rois"], got["roi_valid"]
    )
    if all(np.array_equal(got[k], ref[k]) for k in _ROI_STAGE):
        rcnn_scores, rcnn_boxes = torch.as_tensor(ref["rcnn_scores"]), torch.as_tensor(ref["rcnn_boxes"])
    else:
        s = {k: g[k] for k in _ROI_STAGE}
        features, point_scores = two.keypoint_features(model, trace["fused"][0], s, xyz, feats, scan, reference=True)
        rcnn_scores, rcnn_boxes = two.refine(model, s, features, point_scores, reference=True)
    boxes, scores, labels = two.final_nms(
        model, g["rcnn_boxes"], g["rcnn_scores"], g["roi_labels"], g["roi_valid"], reference=True
    )
    return {
        "rois": rois,
        "roi_labels": roi_labels,
        "roi_valid": roi_valid,
        "keypoints": keypoints,
        "keypoint_valid": keypoint_valid,
        "rcnn_scores": rcnn_scores,
        "rcnn_boxes": rcnn_boxes,
        "boxes": boxes,
        "scores": scores,
        "labels": labels,
    }


def runtime_checks(card: ModelCard) -> list[OutputCheck]:
    """The capacity flags the runtime acts on: ``spa_overflow`` (more non-empty pillars than the
    sparse pillar attention holds: always an error) and ``cfa_converged`` (the clustering map is
    not the one its method defines; the card's ``cfa.not_converged`` says error or warning,
    default error for DBSCAN, whose points beyond its capacity were left out, and warning for
    GridDensityBEV, whose max-pool components stopped short)."""
    spa = OutputCheck(
        "spa_overflow",
        True,
        "error",
        f"the scan has {{num_pillars}} non-empty pillars but {card.name}'s sparse pillar attention "
        f"holds spa.capacity = {card.get('spa.capacity')}; export with a larger spa.capacity "
        f"(--config) or crop the scan",
    )
    cfa = card.get("cfa", {}) or {}
    method = cfa.get("method", "grid_density")
    policy = cfa.get("not_converged") or ("error" if method == "dbscan" else "warn")
    if method == "dbscan":
        msg = (
            f"the scan has {{points_in_range}} points inside the range (x, y within pillars.point_cloud_range) "
            f"but {card.name}'s DBSCAN clusters cfa.dbscan.capacity = {card.get('cfa.dbscan.capacity')}; the "
            "points beyond it were left out of the clustering map; export with a larger capacity (--config) or "
            "crop the scan"
        )
    else:
        msg = (
            f"{card.name}'s GridDensityBEV components did not converge in cfa.grid.cc_iterations = "
            f"{card.get('cfa.grid.cc_iterations')} max-pool steps (the fork's partial labels); "
            "cc_mode: exact gives true components"
        )
    return [spa, OutputCheck("cfa_converged", False, policy, msg)]


def judges(card: ModelCard) -> tuple[Comparator, ...]:
    """How parity judges each output of MAFF-Net's one- or two-stage graph (graph order). Stage
    two's outputs follow the proposal NMS and the keypoint sampling, so they are judged on the
    graph's own rois and keypoints (``conditioned``; see the spec's ``postprocess_reference``)."""
    stage_two = card.get("stage_two") is not None
    angle = dict(angle_column=6, angle_period=math.pi)
    proposals = two.read_stage_two(card).proposals if stage_two else two.ProposalConfig()
    judges = {
        "boxes": Boxes("boxes", unit="m, rad"),  # with its scores and labels outputs
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
        "rois": Proposals(
            "rois",
            unit="m, rad",
            iou_thresh=proposals.iou_thresh,
            pre_max=proposals.pre_max,
            post_max=proposals.post_max,
            score_tol=(1e-4, 1e-3),
        ),
        "keypoints": Dense("keypoints", unit="m", atol=1e-6, rtol=0.0, conditioned=True),
        "keypoint_valid": Exact("keypoint_valid", conditioned=True),
        # a probability after the ROI head's 27,648-wide FC stack: its logit carries float32 noise
        # of a few 1e-4 relative, which moves the probability by up to a quarter of that times
        # |logit| (9e-4 seen with trained-scale weights); judged absolutely, as a probability
        "rcnn_scores": Dense("rcnn_scores", atol=2e-3, rtol=0.0, quantized_info=True, conditioned=True),
        "rcnn_boxes": Dense(
            "rcnn_boxes", unit="m, rad", atol=1e-3, rtol=1e-3, quantized_info=True, conditioned=True, **angle
        ),
    }
    return tuple(judges[n] for n in output_names(stage_two) if n in judges)


STAGE_ONE_GRAPH = GraphSpec(
    name="maffnet",
    input_names=input_names,
    dynamic_axes=dynamic_axes,
    frame_inputs=input_names,
    output_names=lambda card: list(output_names(False)),
    make_cases=make_cases,
    run_reference=run_reference,
    run_export=run_export,
    trace_order=trace_order,
    judges=judges,
    postprocess_reference=postprocess_reference,
    stage_times=lambda model, feeds, reference: stage_times(model, torch.as_tensor(feeds["points"]), reference),
    onnx_stages=(
        ("VFE+SPA", ("vfe", "map_to_bev_module")),
        ("CFA", ("image_backbone",)),
        ("CAF", ("fuser",)),
        ("backbone+head", ("backbone_2d", "dense_head")),
        ("NMS", ()),
    ),
    onnx_post_outputs=("anchor_scores", "anchor_boxes"),
)

# Cards with ``stage_two``: the stage-one NMS is replaced by the proposal layer, and the graph
# continues with CDA keypoints, VSA, point head, ROI head and the final NMS.
TWO_STAGE_GRAPH = replace(
    STAGE_ONE_GRAPH,
    output_names=lambda card: list(output_names(True)),
    postprocess_reference=postprocess_reference_two,
    onnx_stages=(
        *STAGE_ONE_GRAPH.onnx_stages[:4],
        ("proposals+CDA", ("proposal_layer", "keypoint_sampler")),
        ("VSA+point head", ("pfe", "point_head")),
        ("ROI head", ("roi_head",)),
        ("final NMS", ()),
    ),
    onnx_post_outputs=("rcnn_scores", "rcnn_boxes"),
)

MAFFNET_SPEC = ModelSpec(
    build=build_maffnet,
    graphs=(STAGE_ONE_GRAPH,),
    runtime_checks=runtime_checks,
    evaluation="detection",
    recipe="openpcdet-detection",
)
MAFFNET_FULL_SPEC = replace(MAFFNET_SPEC, graphs=(TWO_STAGE_GRAPH,))


def spec_for(card: ModelCard | None = None) -> ModelSpec:
    """MAFFNET_FULL_SPEC for a card with ``stage_two``, else MAFFNET_SPEC."""
    return MAFFNET_FULL_SPEC if card is not None and card.get("stage_two") is not None else MAFFNET_SPEC
