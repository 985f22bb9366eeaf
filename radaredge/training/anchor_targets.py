"""OpenPCDet's anchor-head training targets and loss, as MAFF-Net's AnchorHeadSingle uses them
(read in open-mmlab/OpenPCDet and TRV-Lab/MAFF-Net: AxisAlignedTargetAssigner, ResidualCoder,
AnchorHeadTemplate.get_loss). Boxes are OpenPCDet's [x, y, z, dx, dy, dz, heading] in the radar
frame (x forward, metres, z at the box centre, heading in radians about z).

- targets: per class, an anchor is positive when the axis-aligned BEV IoU of the anchor and a
  box of that class (both rotated to the nearest axis) reaches the class's matched threshold,
  or when it is that box's best anchor; negative below the unmatched threshold; ignored between;
- classification: sigmoid focal loss (alpha 0.25, gamma 2) over the cared anchors;
- regression: smooth-L1 (beta 1/9) on ResidualCoder residuals, the heading as sin(a - b);
- direction: cross entropy over the heading's bins (dir_offset, num_dir_bins);
all normalised by the scan's positive anchors, weighted cls 1.0, loc 2.0, dir 0.2.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..errors import ConfigError

# Upstream's matched / unmatched IoU thresholds per class (MAFF-Net_vod.yaml, MAFF-Net_TJ4D.yaml
# ANCHOR_GENERATOR_CONFIG), used when a card's anchor entry does not set its own.
THRESHOLDS = {"Car": (0.6, 0.45), "Pedestrian": (0.5, 0.35), "Cyclist": (0.5, 0.35), "Truck": (0.6, 0.45)}
# OpenPCDet LOSS_CONFIG: cls 1.0, loc 2.0, dir 0.2; focal alpha 0.25, gamma 2; smooth-L1 beta 1/9.
LOSS_WEIGHTS = {"cls": 1.0, "loc": 2.0, "dir": 0.2}


def class_thresholds(card) -> list[tuple[float, float]]:
    """(matched, unmatched) IoU threshold of every anchor class, in card order: the anchor entry's
    ``matched_threshold`` / ``unmatched_threshold`` when set, else upstream's for that class."""
    out = []
    for i, entry in enumerate(card.get("dense_head.anchors")):
        name = entry["class_name"]
        default = THRESHOLDS.get(name)
        hi = entry.get("matched_threshold", default[0] if default else None)
        lo = entry.get("unmatched_threshold", default[1] if default else None)
        if hi is None or lo is None:
            raise ConfigError(
                f"{card.where}: dense_head.anchors[{i}] ({name}) needs matched_threshold and "
                f"unmatched_threshold for training (upstream knows {sorted(THRESHOLDS)} only)"
            )
        if not 0.0 <= lo <= hi <= 1.0:
            raise ConfigError(
                f"{card.where}: dense_head.anchors[{i}] ({name}): expected 0 <= unmatched_threshold "
                f"<= matched_threshold <= 1, got {lo} and {hi}"
            )
        out.append((float(hi), float(lo)))
    return out


def anchor_classes(card, num_anchors: int) -> torch.Tensor:
    """Class index of every anchor [A], in the order of ``model.anchors`` and the head's outputs
    (per location: each class's sizes x rotations, classes in card order)."""
    per_loc = [len(a["anchor_sizes"]) * len(a["anchor_rotations"]) for a in card.get("dense_head.anchors")]
    loc = torch.cat([torch.full((n,), c, dtype=torch.int64) for c, n in enumerate(per_loc)])
    return loc.repeat(num_anchors // len(loc))


def nearest_bev(boxes: torch.Tensor) -> torch.Tensor:
    """Axis-aligned BEV rectangles (x1, y1, x2, y2) of boxes [N, 7] rotated to the nearest axis
    (OpenPCDet boxes3d_nearest_bev_iou): a heading within 45 degrees of the y axis swaps length
    and width."""
    yaw = boxes[:, 6] - torch.floor(boxes[:, 6] / math.pi + 0.5) * math.pi  # limit to [-pi/2, pi/2)
    swap = yaw.abs() > math.pi / 4
    dx = torch.where(swap, boxes[:, 4], boxes[:, 3])
    dy = torch.where(swap, boxes[:, 3], boxes[:, 4])
    return torch.stack([boxes[:, 0] - dx / 2, boxes[:, 1] - dy / 2, boxes[:, 0] + dx / 2, boxes[:, 1] + dy / 2], 1)


def axis_aligned_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU [N, M] of rectangles a [N, 4] and b [M, 4] (x1, y1, x2, y2)."""
    w = (torch.minimum(a[:, None, 2], b[None, :, 2]) - torch.maximum(a[:, None, 0], b[None, :, 0])).clamp(min=0)
    h = (torch.minimum(a[:, None, 3], b[None, :, 3]) - torch.maximum(a[:, None, 1], b[None, :, 1])).clamp(min=0)
    inter = w * h
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / (area_a[:, None] + area_b[None, :] - inter).clamp(min=1e-6)


def encode_boxes(gt: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """OpenPCDet ResidualCoder.encode_torch: residuals [A, 7] of gt [A, 7] w.r.t. anchors [A, 7],
    the inverse of :func:`radaredge.models.maffnet.model.decode_boxes` before its direction fix."""
    anchors = torch.cat([anchors[:, :3], anchors[:, 3:6].clamp(min=1e-5), anchors[:, 6:]], 1)
    gt = torch.cat([gt[:, :3], gt[:, 3:6].clamp(min=1e-5), gt[:, 6:]], 1)  # as upstream: no log(0)
    xa, ya, za, dxa, dya, dza, ra = anchors.unbind(-1)
    xg, yg, zg, dxg, dyg, dzg, rg = gt.unbind(-1)
    diagonal = torch.sqrt(dxa**2 + dya**2)
    return torch.stack(
        [
            (xg - xa) / diagonal,
            (yg - ya) / diagonal,
            (zg - za) / dza,
            torch.log(dxg / dxa),
            torch.log(dyg / dya),
            torch.log(dzg / dza),
            rg - ra,
        ],
        -1,
    )


def assign_targets(
    anchors: torch.Tensor,
    classes: torch.Tensor,
    gt: torch.Tensor,
    gt_labels: torch.Tensor,
    thresholds: list[tuple[float, float]],
) -> dict[str, torch.Tensor]:
    """OpenPCDet's AxisAlignedTargetAssigner for one scan. Per class, an anchor is positive when its
    axis-aligned BEV IoU with a box of that class reaches the matched threshold, or when it is a
    box's best anchor (IoU > 0), and is matched to the box it overlaps most; negative below the
    unmatched threshold; otherwise ignored.
    Returns labels [A] (-1 ignored, 0 background, c + 1 class c), box residual targets [A, 7]
    (zero off the positives) and the matched box [A, 7] (zero off the positives)."""
    labels = torch.zeros(len(anchors), dtype=torch.int64, device=anchors.device)
    matched = torch.zeros(len(anchors), 7, device=anchors.device)
    rect = nearest_bev(anchors)
    for c, (hi, lo) in enumerate(thresholds):
        on_a, on_g = classes == c, gt_labels == c
        if not on_g.any():
            continue
        idx_a = torch.nonzero(on_a).squeeze(1)
        boxes = gt[on_g]
        iou = axis_aligned_iou(rect[idx_a], nearest_bev(boxes))  # [Ac, Gc]
        best_iou, best_gt = iou.max(1)
        pos = best_iou >= hi
        per_gt = iou.max(0).values
        forced = ((iou == per_gt[None]) & (per_gt[None] > 0)).any(1)  # each box's best anchor(s)
        pos = pos | forced  # matched to their own best box
        sub = torch.where(best_iou < lo, 0, -1)
        sub[pos] = c + 1
        labels[idx_a] = sub
        matched[idx_a[pos]] = boxes[best_gt[pos]]
    targets = torch.zeros(len(anchors), 7, device=anchors.device)
    pos = labels > 0
    targets[pos] = encode_boxes(matched[pos], anchors[pos])
    return {"labels": labels, "box_targets": targets, "matched": matched}


def direction_targets(matched: torch.Tensor, cfg) -> torch.Tensor:
    """OpenPCDet get_direction_target: the direction bin of each matched box's heading [A]."""
    period = 2 * math.pi / cfg.num_dir_bins
    rot = matched[:, 6] - cfg.dir_offset
    rot = rot - torch.floor(rot / (2 * math.pi)) * 2 * math.pi
    return torch.clamp(torch.floor(rot / period).long(), 0, cfg.num_dir_bins - 1)


def sigmoid_focal(logits: torch.Tensor, targets: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0) -> torch.Tensor:
    """OpenPCDet SigmoidFocalClassificationLoss per element (unweighted): alpha_t (1 - p_t)^gamma
    times the binary cross entropy of ``logits`` with ``targets`` (0 / 1, same shape)."""
    p = torch.sigmoid(logits)
    alpha_t = targets * alpha + (1 - targets) * (1 - alpha)
    pt = targets * (1 - p) + (1 - targets) * p
    return alpha_t * pt.pow(gamma) * F.binary_cross_entropy_with_logits(logits, targets, reduction="none")


def smooth_l1(diff: torch.Tensor, beta: float) -> torch.Tensor:
    """Smooth-L1 per element of ``diff``: 0.5 d^2 / beta below beta, |d| - beta / 2 above."""
    d = diff.abs()
    return torch.where(d < beta, 0.5 * d**2 / beta, d - 0.5 * beta)


def head_loss(cls_logits, box_pred, dir_logits, targets: dict, cfg, num_classes: int) -> dict[str, torch.Tensor]:
    """OpenPCDet AnchorHeadTemplate loss for one scan, normalised by the number of positives:
    {"loss": the weighted sum, "cls", "loc", "dir": the weighted terms}."""
    labels = targets["labels"]
    pos = labels > 0
    cared = (labels >= 0).float()
    norm = max(int(pos.sum()), 1)
    one_hot = F.one_hot(labels.clamp(min=0), num_classes + 1)[:, 1:].float()
    cls = sigmoid_focal(cls_logits, one_hot).sum(1) * cared
    terms = {"cls": LOSS_WEIGHTS["cls"] * cls.sum() / norm}
    zero = cls_logits.sum() * 0.0
    terms["loc"] = terms["dir"] = zero
    if pos.any():
        pred, tgt = box_pred[pos], targets["box_targets"][pos]
        sin_pred = torch.sin(pred[:, 6:7]) * torch.cos(tgt[:, 6:7])  # sin(a - b) split between the two
        sin_tgt = torch.cos(pred[:, 6:7]) * torch.sin(tgt[:, 6:7])
        diff = torch.cat([pred[:, :6] - tgt[:, :6], sin_pred - sin_tgt], 1)
        terms["loc"] = LOSS_WEIGHTS["loc"] * smooth_l1(diff, 1.0 / 9.0).sum() / norm
        dirs = direction_targets(targets["matched"][pos], cfg)
        terms["dir"] = LOSS_WEIGHTS["dir"] * F.cross_entropy(dir_logits[pos], dirs, reduction="sum") / norm
    return {"loss": terms["cls"] + terms["loc"] + terms["dir"], **terms}
