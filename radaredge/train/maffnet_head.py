"""Fit MAFF-Net's anchor head on synthetic VoD scans: a test article for int8.

Why. With the seeded weights, maffnet-vod scores nearly all of its anchors just above the 0.10
score threshold, so the greedy NMS chooses between near-ties and int8 noise re-decides them:
`parity-check --quantized` then measures tie-breaking, not whether int8 keeps the detections.
A trained upstream checkpoint settles that where one can be had; this script makes a stand-in
anywhere. docs/quantization.md describes what int8 does to the seeded and the fitted checkpoints.

What it does. It keeps the seeded network up to the anchor head frozen (VFE, SPA, CFA, CAF,
BaseBEVBackbone) and fits only the head's three 1x1 convolutions (class scores, box residuals,
direction bins) on synthetic VoD scans with ground-truth boxes, with OpenPCDet's training
recipe for this head: AxisAlignedTargetAssigner (axis-aligned BEV IoU of the anchors and boxes
rotated to the nearest axis; upstream VoD thresholds), sigmoid focal loss, smooth-L1 on
ResidualCoder residuals with the sin-difference heading, and direction-bin cross entropy. It
writes a checkpoint (seeded backbone + fitted head) and prints the fitted detector's recall of
ground-truth boxes on held-out scans. ``--set train_backbone=true`` fits BaseBEVBackbone with the head
(the layers before it, VFE, SPA, CFA and CAF, stay seeded); every step then runs the backbone,
so it takes far longer than the head alone. Either checkpoint is a test article for int8
(scores that separate), not a trained MAFF-Net: the layers it does not fit stay random.

    radaredge train --model maffnet-vod --data synthetic --output runs/maffnet-vod-fitted-head
    radaredge export --model maffnet-vod --checkpoint runs/maffnet-vod-fitted-head/best.pth --quantize int8
    radaredge parity-check --model maffnet-vod --checkpoint runs/maffnet-vod-fitted-head/best.pth --quantized
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..config import card_ranges, positive
from ..data.synthetic import CLASS_NAMES, generate_scan
from ..errors import ConfigError
from ..models.maffnet.spec import synthetic_points
from ..parity.comparators import match_boxes
from .run import RunDir, Stopwatch, TrainReport, recipe_from_options

# OpenPCDet's VoD configuration (MAFF-Net_vod.yaml, ANCHOR_GENERATOR_CONFIG): matched / unmatched
# IoU thresholds of the axis-aligned target assigner, per class.
THRESHOLDS = {"Car": (0.6, 0.45), "Pedestrian": (0.5, 0.35), "Cyclist": (0.5, 0.35)}
# OpenPCDet LOSS_CONFIG: cls 1.0, loc 2.0, dir 0.2; focal alpha 0.25, gamma 2; smooth-L1 beta 1/9.
LOSS_WEIGHTS = {"cls": 1.0, "loc": 2.0, "dir": 0.2}
SCENES = ({}, {"num_cars": 10, "num_pedestrians": 8, "num_cyclists": 6, "static_points": 600},
          {"dynamic_fraction": 0.4})


def synthetic_examples(card, seeds) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(points [N, F] in the card's columns, boxes [M, 7], labels [M] card class index) per seed:
    synthetic VoD scans in rotation through plain drives, dense traffic and 40 % dynamic points.
    Ground truth keeps the objects with at least one radar point whose centre lies in the range."""
    r = card.get("pillars.point_cloud_range")
    index = {name.lower(): i for i, name in enumerate(card.get("classes"))}
    out = []
    for k, seed in enumerate(seeds):
        scan = generate_scan(seed=seed, **SCENES[k % len(SCENES)])
        pts = synthetic_points(scan, card)
        b = scan.boxes
        keep = ((scan.box_num_points > 0) & (b[:, 0] >= r[0]) & (b[:, 0] < r[3]) & (b[:, 1] >= r[1])
                & (b[:, 1] < r[4]))
        labels = np.array([index[CLASS_NAMES[c]] for c in scan.box_labels[keep]], np.int64)
        out.append((pts, b[keep].astype(np.float32), labels))
    return out


def cached_input(model, points: np.ndarray, train_backbone: bool = False) -> torch.Tensor:
    """What training reads from the frozen part of the network: the anchor head's input (the
    backbone's output), or with ``train_backbone`` the fusion's BEV map that BaseBEVBackbone reads,
    [1, C, H, W] (export formulation)."""
    pts = torch.from_numpy(points)
    with torch.no_grad():
        pillar, _, _ = model.pillar_stage(pts, False)
        cfa = model.cfa_stage(pts, False)[0]
        fused = model.fuser(pillar.unsqueeze(0), cfa)
        return fused if train_backbone else model.backbone_2d(fused)


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
    yaw = boxes[:, 6] - torch.floor(boxes[:, 6] / math.pi + 0.5) * math.pi        # limit to [-pi/2, pi/2)
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
    xa, ya, za, dxa, dya, dza, ra = anchors.unbind(-1)
    xg, yg, zg, dxg, dyg, dzg, rg = gt.unbind(-1)
    diagonal = torch.sqrt(dxa ** 2 + dya ** 2)
    return torch.stack([(xg - xa) / diagonal, (yg - ya) / diagonal, (zg - za) / dza, torch.log(dxg / dxa),
                        torch.log(dyg / dya), torch.log(dzg / dza), rg - ra], -1)


def assign_targets(anchors: torch.Tensor, classes: torch.Tensor, gt: torch.Tensor, gt_labels: torch.Tensor,
                   class_names: list[str]) -> dict[str, torch.Tensor]:
    """OpenPCDet's AxisAlignedTargetAssigner for one scan. Per class, an anchor is positive when its
    axis-aligned BEV IoU with a box of that class reaches the matched threshold, or when it is a
    box's best anchor (IoU > 0), and is matched to the box it overlaps most; negative below the
    unmatched threshold; otherwise ignored.
    Returns labels [A] (-1 ignored, 0 background, c + 1 class c), box residual targets [A, 7]
    (zero off the positives) and the matched box [A, 7] (zero off the positives)."""
    labels = torch.zeros(len(anchors), dtype=torch.int64)
    matched = torch.zeros(len(anchors), 7)
    rect = nearest_bev(anchors)
    for c, name in enumerate(class_names):
        on_a, on_g = classes == c, gt_labels == c
        if not on_g.any():
            continue
        idx_a = torch.nonzero(on_a).squeeze(1)
        boxes = gt[on_g]
        iou = axis_aligned_iou(rect[idx_a], nearest_bev(boxes))                 # [Ac, Gc]
        best_iou, best_gt = iou.max(1)
        hi, lo = THRESHOLDS[name]
        pos = best_iou >= hi
        per_gt = iou.max(0).values
        forced = ((iou == per_gt[None]) & (per_gt[None] > 0)).any(1)           # each box's best anchor(s)
        pos = pos | forced                                                      # matched to their own best box
        sub = torch.where(best_iou < lo, 0, -1)
        sub[pos] = c + 1
        labels[idx_a] = sub
        matched[idx_a[pos]] = boxes[best_gt[pos]]
    targets = torch.zeros(len(anchors), 7)
    pos = labels > 0
    targets[pos] = encode_boxes(matched[pos], anchors[pos])
    return {"labels": labels, "box_targets": targets, "matched": matched}


def direction_targets(matched: torch.Tensor, cfg) -> torch.Tensor:
    """OpenPCDet get_direction_target: the direction bin of each matched box's heading [A]."""
    period = 2 * math.pi / cfg.num_dir_bins
    rot = matched[:, 6] - cfg.dir_offset
    rot = rot - torch.floor(rot / (2 * math.pi)) * 2 * math.pi
    return torch.clamp(torch.floor(rot / period).long(), 0, cfg.num_dir_bins - 1)


def head_loss(cls_logits, box_pred, dir_logits, targets: dict, cfg, num_classes: int) -> torch.Tensor:
    """OpenPCDet AnchorHeadTemplate loss for one scan, normalised by the number of positives."""
    labels = targets["labels"]
    pos = labels > 0
    cared = (labels >= 0).float()
    norm = max(int(pos.sum()), 1)
    one_hot = F.one_hot(labels.clamp(min=0), num_classes + 1)[:, 1:].float()
    p = torch.sigmoid(cls_logits)
    alpha = one_hot * 0.25 + (1 - one_hot) * 0.75
    pt = one_hot * (1 - p) + (1 - one_hot) * p
    ce = F.binary_cross_entropy_with_logits(cls_logits, one_hot, reduction="none")
    cls = (alpha * pt.pow(2.0) * ce).sum(1) * cared
    loss = LOSS_WEIGHTS["cls"] * cls.sum() / norm
    if pos.any():
        pred, tgt = box_pred[pos], targets["box_targets"][pos]
        sin_pred = torch.sin(pred[:, 6:7]) * torch.cos(tgt[:, 6:7])          # sin(a - b) split between the two
        sin_tgt = torch.cos(pred[:, 6:7]) * torch.sin(tgt[:, 6:7])
        diff = torch.cat([pred[:, :6] - tgt[:, :6], sin_pred - sin_tgt], 1).abs()
        beta = 1.0 / 9.0
        loc = torch.where(diff < beta, 0.5 * diff ** 2 / beta, diff - 0.5 * beta)
        loss = loss + LOSS_WEIGHTS["loc"] * loc.sum() / norm
        dirs = direction_targets(targets["matched"][pos], cfg)
        loss = loss + LOSS_WEIGHTS["dir"] * F.cross_entropy(dir_logits[pos], dirs, reduction="sum") / norm
    return loss


def reset_head(head, prior: float = 0.01) -> None:
    """OpenPCDet's AnchorHeadSingle initialisation: class bias at the prior, small box weights."""
    for conv in (head.conv_cls, head.conv_box, head.conv_dir_cls):
        torch.nn.init.normal_(conv.weight, std=0.01)
        torch.nn.init.zeros_(conv.bias)
    torch.nn.init.constant_(head.conv_cls.bias, -math.log((1 - prior) / prior))
    torch.nn.init.normal_(head.conv_box.weight, std=0.001)


def fit(model, features: list[torch.Tensor], targets: list[dict], epochs: int, lr: float,
        train_backbone: bool = False, log=print) -> None:
    """Adam, one scan per step, scans shuffled every epoch, from a freshly initialised head.

    Head only (``features`` from :func:`cached_input` without ``train_backbone``): the head's
    parameters, learning rate cosine-annealed from ``lr``. With ``train_backbone`` (features are
    the fusion's maps): BaseBEVBackbone and the head together, the backbone's batch norms in
    training mode, a one-cycle schedule peaking at ``lr`` after 30 % of the steps, and gradients
    clipped to norm 10. The model is left in eval mode."""
    head = model.dense_head
    reset_head(head)
    params = list(head.parameters()) + (list(model.backbone_2d.parameters()) if train_backbone else [])
    opt = torch.optim.Adam(params, lr=lr)
    steps = epochs * len(features)
    sched = (torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps, pct_start=0.3) if train_backbone
             else torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps))
    model.backbone_2d.train(train_backbone)
    gen = torch.Generator().manual_seed(0)
    for epoch in range(epochs):
        total = 0.0
        for i in torch.randperm(len(features), generator=gen).tolist():
            x = features[i].float()
            cls, box, direction = head(model.backbone_2d(x) if train_backbone else x)
            loss = head_loss(cls, box, direction, targets[i], model.head_config, head.num_classes)
            opt.zero_grad()
            loss.backward()
            if train_backbone:
                torch.nn.utils.clip_grad_norm_(params, 10.0)
            opt.step()
            sched.step()
            total += loss.item()
        if train_backbone or epoch % 5 == 0 or epoch == epochs - 1:
            log(f"  epoch {epoch:3d}  loss {total / len(features):.4f}")
    model.eval()


def detection_recall(model, examples, min_iou: float = 0.5) -> tuple[float, float]:
    """(share of ground-truth boxes detected with the right class at rotated BEV IoU >= min_iou,
    mean detections per scan) of the model's export formulation on ``examples``."""
    found = total = dets = 0
    for pts, gt, labels in examples:
        with torch.no_grad():
            out = model.run(torch.from_numpy(pts))
        pairs, _, _ = match_boxes(out["boxes"].numpy(), out["labels"].numpy() - 1, gt, labels, min_iou)
        found += len(pairs)
        total += len(gt)
        dets += len(out["boxes"])
    return found / max(total, 1), dets / max(len(examples), 1)


SYNTHETIC = "synthetic"     # --data: the recipe's scans are generated (synthetic VoD scenes)


@card_ranges(train_scans=(1, 100_000), test_scans=(1, 100_000), epochs=(1, 10_000), lr=positive(1.0),
             seed=(0, 2**32 - 1))
@dataclass(frozen=True)
class HeadRecipe:
    """The options of the head fit: ``train_scans`` / ``test_scans`` synthetic scans (seeds from
    7000 / 8000), ``train_backbone`` (fit BaseBEVBackbone too), ``epochs`` and ``lr`` (default 40
    and 3e-3 for the head alone, 12 and a 1e-3 one-cycle peak with the backbone), ``seed``."""

    train_scans: int = 40
    test_scans: int = 8
    train_backbone: bool = False
    epochs: int | None = None
    lr: float | None = None
    seed: int = 0

    @classmethod
    def from_options(cls, options: dict) -> "HeadRecipe":
        """The recipe with ``options`` over the defaults (:func:`radaredge.train.run.recipe_from_options`)."""
        return recipe_from_options(cls, options, "MAFF-Net head fit")


def train_head(card, model, data, inputs) -> TrainReport:
    """``radaredge train --model maffnet-vod --data synthetic``: fit the anchor head (module
    docstring) on synthetic VoD scans and write the run directory (``best.pth``, the fitted
    checkpoint, and ``train-log.json``); the report's one row is the held-out recall."""
    if str(data) != SYNTHETIC:
        raise ConfigError(f"--data {data}: {card.name}'s recipe in radaredge fits the anchor head on synthetic VoD "
                          f"scans (--data {SYNTHETIC}); it reads no recorded data")
    given = [name for name, value in (("--validation", inputs.validation), ("--format", inputs.data_format),
                                      ("--resume", inputs.resume or None)) if value]
    given += [f"--{k.replace('_', '-')}" for k, v in (inputs.bag or {}).items() if v is not None]
    if given:
        raise ConfigError(f"{', '.join(given)}: not used by {card.name}'s head fit on synthetic scans")
    if inputs.device != "cpu":
        raise ConfigError(f"--device {inputs.device}: {card.name}'s head fit runs on the CPU (a few minutes); "
                          f"drop --device")
    if card.get("stage_two") is not None:
        raise ConfigError(f"{card.name}: the head fit covers stage one's anchor head; use a one-stage card "
                          f"(maffnet-vod)")
    recipe = HeadRecipe.from_options(inputs.options or {})
    log = inputs.log or (lambda line: None)
    run = RunDir(inputs.output, card)
    deep = recipe.train_backbone
    epochs = recipe.epochs or (12 if deep else 40)
    lr = recipe.lr or (1e-3 if deep else 3e-3)
    torch.manual_seed(recipe.seed)
    clock = Stopwatch()
    train = synthetic_examples(card, range(7000, 7000 + recipe.train_scans))
    test = synthetic_examples(card, range(8000, 8000 + recipe.test_scans))
    classes = anchor_classes(card, len(model.anchors))
    features, targets = [], []
    for pts, gt, labels in train:
        features.append(cached_input(model, pts, deep).half())
        targets.append(assign_targets(model.anchors, classes, torch.from_numpy(gt), torch.from_numpy(labels),
                                      card.get("classes")))
    n_pos = sum(int((t["labels"] > 0).sum()) for t in targets)
    n_gt = sum(len(g) for _, g, _ in train)
    log(f"{len(train)} training scans: {n_gt} boxes, {n_pos} positive anchors ({clock():.0f} s for the frozen network)")
    fit(model, features, targets, epochs, lr, deep, log=log)
    recall, per_scan = detection_recall(model, test)
    metrics = {"recall_bev_iou_0.5": recall, "detections_per_scan": per_scan}
    run.save_best(model, epochs, metrics)
    report = TrainReport(card.name, run.path, "recall_bev_iou_0.5", best_epoch=epochs, seconds=clock(),
                         data={"scans": SYNTHETIC, "train_scans": len(train), "test_scans": len(test),
                               "boxes": n_gt, "positive_anchors": n_pos},
                         options={**dataclasses.asdict(recipe), "epochs": epochs, "lr": lr})
    report.epochs.append({"epoch": epochs, **metrics, "seconds": round(report.seconds, 1)})
    run.write_log(report.to_dict())
    return report
