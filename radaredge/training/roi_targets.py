"""OpenPCDet's second-stage training targets and losses, as MAFF-Net's two-stage model trains
them (read in TRV-Lab/MAFF-Net: detectors/MAFF_Net.py, VoxelSetAbstraction_cda and the configs;
OpenPCDet: ProposalTargetLayer, RoIHeadTemplate, PointHeadSimple and PointHeadTemplate,
loss_utils; nothing of either is copied). Boxes are [x, y, z, dx, dy, dz, heading] in the radar
frame (x forward, metres, z at the box centre, heading in radians about z), labels 1-based.

Per scan, in upstream's order (its detector is PV-RCNN++'s: targets before keypoints):

1. training proposals (NMS_CONFIG.TRAIN, :func:`training_proposals`): per anchor the best class
   logit, the 9,000 best, rotated BEV NMS at IoU 0.8, the first 512; zero rows (label 1) fill
   the slots NMS leaves empty. No gradient flows through them;
2. the proposal target layer (:func:`sample_rois`): each roi's 3-D IoU with the boxes of its own
   class (0 without one), then 128 rois: up to 64 foreground (IoU >= 0.55) drawn without
   replacement, the rest background drawn with replacement, 80 % of it hard (0.1 <= IoU < 0.55)
   when both kinds exist; only foreground (no background at all): 128 foreground draws with
   replacement. Regression on rois with IoU > 0.55; the class target is the IoU mapped linearly
   from [0.25, 0.75] onto [0, 1] (CLS_SCORE_TYPE roi_iou);
3. the CDA keypoints are sampled around these 128 rois (not the test-time proposals), and the
   point head learns which keypoints are foreground (:func:`point_labels`): inside a box 1, in
   the shell of the box enlarged by 0.2 m per dimension -1 (ignored), elsewhere 0; sigmoid
   focal loss (alpha 0.25, gamma 2) over the cared keypoints / the foreground count;
4. the ROI head (:func:`roi_head_loss`): binary cross entropy of its class logit with the soft
   target, mean over the 128 rois; smooth-L1 (beta 1/9) of its residuals against the box in the
   roi's canonical frame (:func:`canonical_boxes`) encoded by the ResidualCoder against the roi's
   size, summed over the foreground rois / their count; the corner loss: the 8 corners of the
   decoded box against the box's, each corner against the nearer of the box and the box turned
   by pi, smooth-L1 (beta 1), mean.

All weights 1.0 (LOSS_WEIGHTS). Upstream normalises the point and regression terms by the
foreground count of the whole batch and the class term by batch x 128; radaredge runs one scan
at a time, normalises each scan by its own counts and averages the scans (as stage one does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..config import card_ranges
from ..models.maffnet.rcnn import decode_roi_residuals
from ..ops.box_iou import boxes_iou3d
from ..ops.nms import NmsConfig, class_agnostic_nms_eager
from .anchor_targets import encode_boxes, sigmoid_focal, smooth_l1

GT_EXTRA_WIDTH = 0.2  # POINT_HEAD.TARGET_CONFIG.GT_EXTRA_WIDTH, m added to dx, dy and dz
POINT_IN_BOX_TOL = 1e-5  # m, OpenPCDet's points_in_boxes: |local x| < dx / 2 + tol
LOSS_WEIGHTS = {"point": 1.0, "rcnn_cls": 1.0, "rcnn_reg": 1.0, "rcnn_corner": 1.0}


@card_ranges(
    pre_max=(1, 2**20),
    post_max=(1, 2**16),
    nms_iou=(0.0, 1.0),
    roi_per_image=(1, 2**16),
    fg_ratio=(0.0, 1.0),
    reg_fg_thresh=(0.0, 1.0),
    cls_fg_thresh=(0.0, 1.0),
    cls_bg_thresh=(0.0, 1.0),
    cls_bg_thresh_lo=(0.0, 1.0),
    hard_bg_ratio=(0.0, 1.0),
)
@dataclass(frozen=True)
class RoiSampling:
    """ROI_HEAD.NMS_CONFIG.TRAIN and TARGET_CONFIG; defaults are upstream's (MAFF-Net_vod.yaml and
    _TJ4D.yaml, the same as OpenPCDet's pv_rcnn.yaml)."""

    pre_max: int = 9000  # NMS_PRE_MAXSIZE (TRAIN)
    post_max: int = 512  # NMS_POST_MAXSIZE (TRAIN)
    nms_iou: float = 0.8  # NMS_THRESH (TRAIN)
    roi_per_image: int = 128  # ROI_PER_IMAGE
    fg_ratio: float = 0.5  # FG_RATIO
    reg_fg_thresh: float = 0.55  # REG_FG_THRESH
    cls_fg_thresh: float = 0.75  # CLS_FG_THRESH
    cls_bg_thresh: float = 0.25  # CLS_BG_THRESH
    cls_bg_thresh_lo: float = 0.1  # CLS_BG_THRESH_LO (easy / hard background)
    hard_bg_ratio: float = 0.8  # HARD_BG_RATIO

    def __post_init__(self):
        if not self.cls_bg_thresh < self.cls_fg_thresh:
            raise ValueError(f"cls_bg_thresh ({self.cls_bg_thresh}) must be below cls_fg_thresh ({self.cls_fg_thresh})")


# ----------------------------------------------------------------------------- proposals and sampling


def training_proposals(cls_logits: torch.Tensor, boxes: torch.Tensor, cfg: RoiSampling):
    """NMS_CONFIG.TRAIN proposals of one scan, without gradient: (rois [post_max, 7], labels
    [post_max] 1-based). Per anchor the best class logit (no threshold); zero rows with label 1
    fill the empty slots, as upstream's zero-initialised roi tensor does."""
    with torch.no_grad():
        score, label = cls_logits.max(-1)
        sel = class_agnostic_nms_eager(
            boxes,
            score,
            NmsConfig(score_thresh=-math.inf, iou_thresh=cfg.nms_iou, pre_max=cfg.pre_max, post_max=cfg.post_max),
        )
        sel = sel.to(boxes.device)
        rois = boxes.new_zeros((cfg.post_max, 7))
        labels = torch.ones(cfg.post_max, dtype=torch.int64, device=boxes.device)
        rois[: len(sel)] = boxes[sel].detach()
        labels[: len(sel)] = label[sel] + 1
    return rois, labels


def max_iou_same_class(rois, roi_labels, gt, gt_labels):
    """Per roi the highest 3-D IoU with a box of its own class and that box's index: (iou [R],
    index [R]); 0 and 0 for a roi whose class has no box."""
    iou = rois.new_zeros(len(rois))
    index = torch.zeros(len(rois), dtype=torch.int64, device=rois.device)
    for k in torch.unique(gt_labels).tolist():
        on_r, on_g = roi_labels == k, gt_labels == k
        if on_r.any():
            best, at = boxes_iou3d(rois[on_r], gt[on_g]).max(1)
            iou[on_r] = best
            index[on_r] = torch.nonzero(on_g).squeeze(1)[at]
    return iou, index


def _draw_device(gen: torch.Generator | None) -> torch.device:
    """Where draws from ``gen`` are made (None: torch's global CPU generator), whatever the rois' device."""
    return gen.device if gen is not None else torch.device("cpu")


def _draw(indices: torch.Tensor, n: int, gen: torch.Generator | None = None) -> torch.Tensor:
    """``n`` of ``indices`` drawn uniformly with replacement."""
    return indices[torch.randint(len(indices), (n,), generator=gen, device=_draw_device(gen)).to(indices.device)]


def _background(
    hard: torch.Tensor, easy: torch.Tensor, n: int, ratio: float, gen: torch.Generator | None = None
) -> torch.Tensor:
    """OpenPCDet sample_bg_inds: ``n`` background rois with replacement, int(n * ratio) of them hard
    (at most as many as there are) when both kinds exist, else all of the kind there is."""
    if len(hard) and len(easy):
        n_hard = min(int(n * ratio), len(hard))
        return torch.cat([_draw(hard, n_hard, gen), _draw(easy, n - n_hard, gen)])
    return _draw(hard if len(hard) else easy, n, gen)


def subsample_rois(iou: torch.Tensor, cfg: RoiSampling, gen: torch.Generator | None = None) -> torch.Tensor:
    """OpenPCDet subsample_rois: the indices [roi_per_image] of the sampled rois (foreground first,
    then hard, then easy background); module docstring, step 2."""
    per_image = cfg.roi_per_image
    fg_per_image = int(np.round(cfg.fg_ratio * per_image))
    fg = torch.nonzero(iou >= min(cfg.reg_fg_thresh, cfg.cls_fg_thresh)).squeeze(1)
    easy = torch.nonzero(iou < cfg.cls_bg_thresh_lo).squeeze(1)
    hard = torch.nonzero((iou < cfg.reg_fg_thresh) & (iou >= cfg.cls_bg_thresh_lo)).squeeze(1)
    if len(fg) and (len(hard) or len(easy)):
        n_fg = min(fg_per_image, len(fg))
        picked = fg[torch.randperm(len(fg), generator=gen, device=_draw_device(gen))[:n_fg].to(fg.device)]
        return torch.cat([picked, _background(hard, easy, per_image - n_fg, cfg.hard_bg_ratio, gen)])
    if len(fg):
        return _draw(fg, per_image, gen)
    if len(hard) or len(easy):
        return _background(hard, easy, per_image, cfg.hard_bg_ratio, gen)
    raise ValueError(f"no roi has a finite IoU with the boxes (IoUs {iou[:8].tolist()} ...)")


def sample_rois(
    rois, roi_labels, gt, gt_labels, cfg: RoiSampling, gen: torch.Generator | None = None
) -> dict[str, torch.Tensor]:
    """The proposal target layer for one scan (module docstring, step 2): rois [S, 7], roi_labels
    [S], iou [S], gt_of_rois [S, 7] (the matched box, in the radar frame), reg_valid [S] bool,
    cls_labels [S] float in [0, 1]; S = roi_per_image. Draws from ``gen`` (default: torch's global
    CPU generator, which training seeds and ``--resume`` restores). No gradient."""
    with torch.no_grad():
        iou, index = max_iou_same_class(rois, roi_labels, gt, gt_labels)
        keep = subsample_rois(iou, cfg, gen)
        iou = iou[keep]
        soft = (iou - cfg.cls_bg_thresh) / (cfg.cls_fg_thresh - cfg.cls_bg_thresh)
        cls_labels = torch.where(
            iou > cfg.cls_fg_thresh,
            torch.ones_like(iou),
            torch.where(iou < cfg.cls_bg_thresh, torch.zeros_like(iou), soft),
        )
        padded = gt if len(gt) else gt.new_zeros((1, 7))  # no box: upstream's one zero row
        return {
            "rois": rois[keep],
            "roi_labels": roi_labels[keep],
            "iou": iou,
            "gt_of_rois": padded[index[keep]],
            "reg_valid": iou > cfg.reg_fg_thresh,
            "cls_labels": cls_labels,
        }


# ----------------------------------------------------------------------------- geometry


def box_corners(boxes: torch.Tensor) -> torch.Tensor:
    """The 8 corners [N, 8, 3] (m) of boxes [N, 7]."""
    signs = (
        torch.tensor(
            [[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)], dtype=boxes.dtype, device=boxes.device
        )
        / 2
    )
    local = boxes[:, None, 3:6] * signs[None]
    c, s = torch.cos(boxes[:, 6])[:, None], torch.sin(boxes[:, 6])[:, None]
    return torch.stack(
        [
            local[..., 0] * c - local[..., 1] * s + boxes[:, None, 0],
            local[..., 0] * s + local[..., 1] * c + boxes[:, None, 1],
            local[..., 2] + boxes[:, None, 2],
        ],
        -1,
    )


def canonical_boxes(rois: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Boxes [S, 7] in their rois' canonical frames (OpenPCDet RoIHeadTemplate.assign_targets):
    centre relative to the roi's, rotated by minus the roi heading; heading relative to the roi's,
    turned by pi when it points backwards, in [-pi/2, pi/2]; sizes as they are."""
    ry = torch.remainder(rois[:, 6], 2 * math.pi)
    d = boxes[:, :3] - rois[:, :3]
    c, s = torch.cos(ry), torch.sin(ry)
    x, y = d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c
    h = torch.remainder(boxes[:, 6] - ry, 2 * math.pi)
    backwards = (h > math.pi / 2) & (h < 1.5 * math.pi)
    h = torch.where(backwards, torch.remainder(h + math.pi, 2 * math.pi), h)
    h = torch.where(h > math.pi, h - 2 * math.pi, h).clamp(-math.pi / 2, math.pi / 2)
    return torch.stack([x, y, d[:, 2], boxes[:, 3], boxes[:, 4], boxes[:, 5], h], -1)


def points_in_boxes(points: torch.Tensor, boxes: torch.Tensor, extra: float = 0.0) -> torch.Tensor:
    """[K, M] bool: point k inside box m enlarged by ``extra`` m in each of dx, dy, dz (OpenPCDet
    points_in_boxes: |z - cz| <= dz / 2, |local x| < dx / 2 + 1e-5, |local y| < dy / 2 + 1e-5)."""
    d = points[:, None, :3] - boxes[None, :, :3]
    c, s = torch.cos(boxes[:, 6])[None], torch.sin(boxes[:, 6])[None]
    lx, ly = d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c
    half = (boxes[None, :, 3:6] + extra) / 2
    return (
        (d[..., 2].abs() <= half[..., 2])
        & (lx.abs() < half[..., 0] + POINT_IN_BOX_TOL)
        & (ly.abs() < half[..., 1] + POINT_IN_BOX_TOL)
    )


# ----------------------------------------------------------------------------- losses


def point_labels(keypoints: torch.Tensor, keypoint_valid: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """PointHeadSimple targets [K]: 1 inside a box, -1 (ignored) in the shell of the box enlarged by
    GT_EXTRA_WIDTH and for invalid keypoints, 0 elsewhere."""
    inside = points_in_boxes(keypoints, gt).any(1)
    near = points_in_boxes(keypoints, gt, GT_EXTRA_WIDTH).any(1)
    labels = inside.to(torch.int64)
    return torch.where((inside ^ near) | ~keypoint_valid, -1, labels)


def point_head_loss(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Sigmoid focal loss of the keypoint logits [K] over labels >= 0, / max(foreground, 1)."""
    cared = (labels >= 0).to(logits.dtype)
    per_point = sigmoid_focal(logits, (labels == 1).to(logits.dtype)) * cared
    return LOSS_WEIGHTS["point"] * per_point.sum() / max(int((labels == 1).sum()), 1)


def corner_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """OpenPCDet get_corner_loss_lidar: per box the mean over its 8 corners of smooth-L1 (beta 1) of
    the corner distance to the nearer of gt's corner and the corner of gt turned by pi; [N]."""
    flipped = torch.cat([gt[:, :6], gt[:, 6:] + math.pi], 1)
    pc = box_corners(pred)
    dist = torch.minimum(
        torch.linalg.vector_norm(pc - box_corners(gt), dim=2),
        torch.linalg.vector_norm(pc - box_corners(flipped), dim=2),
    )
    return smooth_l1(dist, 1.0).mean(1)


def roi_head_loss(cls_logit: torch.Tensor, residuals: torch.Tensor, t: dict) -> dict[str, torch.Tensor]:
    """The ROI head's loss on the sampled rois of :func:`sample_rois` (module docstring, step 4):
    {"rcnn_cls", "rcnn_reg", "rcnn_corner"}, weighted."""
    terms = {"rcnn_cls": LOSS_WEIGHTS["rcnn_cls"] * F.binary_cross_entropy_with_logits(cls_logit, t["cls_labels"])}
    fg = t["reg_valid"]
    zero = residuals.sum() * 0.0
    terms["rcnn_reg"] = terms["rcnn_corner"] = zero
    if fg.any():
        rois = t["rois"][fg]
        centred = torch.cat([torch.zeros_like(rois[:, :3]), rois[:, 3:6], torch.zeros_like(rois[:, 6:])], 1)
        target = encode_boxes(canonical_boxes(rois, t["gt_of_rois"][fg]), centred)
        terms["rcnn_reg"] = (
            LOSS_WEIGHTS["rcnn_reg"] * smooth_l1(residuals[fg] - target, 1.0 / 9.0).sum() / int(fg.sum())
        )
        decoded = decode_roi_residuals(residuals[fg], rois)
        terms["rcnn_corner"] = LOSS_WEIGHTS["rcnn_corner"] * corner_loss(decoded, t["gt_of_rois"][fg]).mean()
    return terms
