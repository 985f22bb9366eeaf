"""MAFF-Net (stage one, and stage two where the card has one) trained with upstream's recipe on a
labelled KITTI-layout radar set.

Read in TRV-Lab/MAFF-Net (tools/cfgs/MAFF-Net/MAFF-Net_vod.yaml and _TJ4D.yaml, its
dataset configs, pcdet/datasets/augmentor, processor) and OpenPCDet (train_utils, the
AnchorHeadTemplate losses); nothing of either is copied.

Data. ``--data ROOT`` is a VoD or TJ4DRadSet layout (``radaredge make-benchmark --task
detection`` writes one): the ``train`` split trains, ``--validation`` names the split that picks
the best epoch (default ``val``). Each frame's points are what the card's graph takes
(``input.crop: camera_fov`` crops them to the camera's view, as upstream's FOV_POINTS_ONLY does
on loading); its boxes are every label of a card class (upstream trains on every annotated
object, seen by the radar or not).

Augmentation (upstream's DATA_AUGMENTOR, in its order, per scan): flip along x (y -> -y,
heading -> -heading) with probability 1/2, a world rotation about z uniform in +-45 deg, a world
scaling uniform in [0.95, 1.05]; headings then limited to [-pi, pi). ``translate_std_z`` (off by
default, as in MAFF-Net's configs) adds OpenPCDet's random_world_translation along z: one normal
offset of that standard deviation (metres) per scan, to every point and box. Point features
other than x, y, z stay as they are (radial speeds are invariant under all four). Upstream's gt_sampling
is disabled in its MAFF-Net configs, and so it is here. Then, as upstream's
mask_points_and_boxes_outside_range does, boxes with no corner inside the point-cloud range
are removed; a scan left without boxes is skipped (upstream draws another scan at random).

Targets and losses: :mod:`radaredge.training.anchor_targets` (the axis-aligned target assigner with
each class's matched / unmatched thresholds, focal loss, smooth-L1 on the residual coder with
the sine-difference heading, the direction classifier); a card with a ``stage_two`` adds, as
upstream's two-stage detector does, the training proposals, the proposal target layer, the point
head's and the ROI head's losses of :mod:`radaredge.training.roi_targets` (the CDA keypoints are
sampled around the sampled rois; no gradient flows through the proposals).

Optimiser (OpenPCDet's ``adam_onecycle``): Adam with betas (0.95 cycled to 0.85 and back, 0.99),
weight decay applied as decoupled decay to every parameter (fastai's true_wd, bn_wd), the
learning rate one-cycle from lr / 10 up to lr over the first 40 % of the steps, then cosine
down to lr / 10 / 1e4; gradients clipped to norm 10; one optimiser step per ``batch_size``
scans (the model runs one scan at a time; the scans' losses are averaged, as upstream's
per-sample normalisation averages over its batch). The VFE's batch norm takes the statistics of
the whole batch, as upstream's does (:func:`batch_norm_statistics`); the 2-D layers normalise
per scan, where upstream's normalise over the batch.

Initialisation: ``--checkpoint`` loads every tensor by name (the export's loader: nothing
missing, nothing unexpected, nothing re-initialised). Without one, the card's seeded network,
with the class bias set to upstream's prior ``head_prior`` (0.01; the cards' 0.1 exists so that
a random graph emits boxes for parity). ``freeze`` keeps matching parameters (and the batch-norm
statistics of modules whose parameters are all frozen) as they are. On a two-stage card,
``stage_one_weights`` starts stage one from a one-stage checkpoint of the same configuration (a
trained ``maffnet-vod`` for ``maffnet-vod-full``: every tensor outside pfe, point_head and
roi_head, key for key) and stage two from the seeded network, as OpenPCDet's
``--pretrained_model`` does with a partial checkpoint, except that here the split is named and
any other mismatch is an error.

Precision: ``precision: bf16`` runs the fuser, the 2D backbone and the anchor head under torch's
bfloat16 autocast (the CPU counterpart of upstream's ``--use_amp``, which is fp16 on CUDA; bf16
needs no loss scaling). The pillar and CFA stages (whose clustering is a discrete decision), the
losses, the optimiser's weights and validation stay fp32. On a CPU with bf16 instructions a
training scan takes about half of fp32's time (benchmarks/maffnet_train_step.py), with gradients
at cosine 0.998 to fp32's; on a CPU without them, bf16 is emulated and slower, hence fp32 by
default.

Quantisation-aware fine-tuning (``qat``, ``radaredge train --qat``; ours): the network runs with
the int8 graph's fake quantisation (:mod:`.qat`) from ``--checkpoint``'s weights; its first
activation ranges are observed on ``qat_scans`` training scans before the initial validation,
and best.pth keeps the learned ranges for the export.

Layout: the pillar stage runs in its training formulation (:func:`fused_map` with ``training``;
the export formulation's values and gradients, over the non-empty pillars only) and the network
is kept channels last, the layout oneDNN's convolutions prefer.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fnmatch
import functools
import math
import operator
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..cards import ModelCard
from ..config import Range, card_ranges, positive
from ..data.kitti_detection import DetectionSet, labels_to_radar_boxes
from ..errors import ConfigError, InputError
from ..eval.detection import as_labels, card_points, layout_for_card
from ..eval.kitti_ap import ap_table, evaluate_frames
from ..models.maffnet.model import decode_boxes
from ..models.maffnet.rcnn import STAGE_TWO_MODULES, run_stage_two, scan_points
from ..ops.input_flags import drop_implausible
from ..ops.nms import class_agnostic_nms_eager
from ..progress import no_progress
from .anchor_targets import anchor_classes, assign_targets, class_thresholds, head_loss
from .qat import resume_signature, start_qat
from .roi_targets import (
    RoiSampling,
    box_corners,
    point_head_loss,
    point_labels,
    roi_head_loss,
    sample_rois,
    training_proposals,
)
from .run import RunDir, Stopwatch, TrainingState, TrainReport, load_weights_outside, pick_device, recipe_from_options

TRAIN_SPLIT, VALIDATION_SPLIT = "train", "val"
TERMS = ("loss", "cls", "loc", "dir")  # logged per epoch as loss_<term>
STAGE_TWO_TERMS = ("point", "rcnn_cls", "rcnn_reg", "rcnn_corner")
PRECISIONS = {"fp32": None, "bf16": torch.bfloat16}  # recipe.precision -> autocast dtype


@card_ranges(
    epochs=(1, 10_000),
    batch_size=(1, 256),
    lr=positive(1.0),
    weight_decay=(0.0, 1.0),
    pct_start=Range(0.0, 1.0, True, True),
    div_factor=positive(1e6),
    grad_clip=positive(1e6),
    rotation=(0.0, math.pi),
    scale_min=positive(10.0),
    scale_max=positive(10.0),
    translate_std_z=(0.0, 10.0),
    val_every=(1, 10_000),
    val_frames=(0, 10**7),
    train_frames=(0, 10**7),
    head_prior=Range(0.0, 1.0, True, True),
    bn_scans=(0, 10**6),
    roi_per_image=(1, 2**16),
    train_proposals=(1, 2**16),
    train_proposals_pre=(1, 2**20),
    seed=(0, 2**32 - 1),
    qat_scans=(1, 10**6),
)
@dataclass(frozen=True)
class DetectionRecipe:
    """The options of MAFF-Net training (module docstring); defaults are upstream's
    (MAFF-Net_vod.yaml OPTIMIZATION and DATA_AUGMENTOR)."""

    epochs: int = 60  # NUM_EPOCHS (VoD; TJ4D 80)
    batch_size: int = 4  # BATCH_SIZE_PER_GPU
    lr: float = 0.01  # LR (the one-cycle peak)
    weight_decay: float = 0.01  # WEIGHT_DECAY
    pct_start: float = 0.4  # PCT_START
    div_factor: float = 10.0  # DIV_FACTOR
    grad_clip: float = 10.0  # GRAD_NORM_CLIP
    flip_x: bool = True  # random_world_flip ALONG_AXIS_LIST ['x']
    rotation: float = 0.78539816  # random_world_rotation WORLD_ROT_ANGLE +-
    scale_min: float = 0.95  # random_world_scaling WORLD_SCALE_RANGE
    scale_max: float = 1.05
    translate_std_z: float = 0.0  # random_world_translation NOISE_TRANSLATE_STD's z (m); 0: off, as upstream
    augment: bool = True  # false: no augmentation at all
    val_every: int = 1  # epochs between validations (the last epoch is always validated)
    val_frames: int = 0  # validation frames (evenly spaced over the split); 0: all
    train_frames: int = 0  # training frames (evenly spaced over the split); 0: all
    freeze: str = ""  # comma-separated parameter-name patterns kept fixed (fnmatch; "vfe" = "vfe.*")
    head_prior: float = 0.01  # without --checkpoint: the class bias's prior (upstream's init)
    stage_one_weights: str = ""  # two-stage cards: a one-stage checkpoint (a trained maffnet-vod's best.pth)
    # whose weights start stage one; stage two starts seeded
    bn_scans: int = 64  # ours: batch-norm statistics re-estimated on this many training scans
    # before each validation (0: upstream's running averages as they are)
    roi_per_image: int = 128  # two-stage cards: ROI_HEAD.TARGET_CONFIG.ROI_PER_IMAGE (rois sampled per scan)
    train_proposals: int = 512  # ROI_HEAD.NMS_CONFIG.TRAIN.NMS_POST_MAXSIZE
    train_proposals_pre: int = 9000  # ROI_HEAD.NMS_CONFIG.TRAIN.NMS_PRE_MAXSIZE
    seed: int = 0
    precision: str = "fp32"  # "bf16": mixed precision (module docstring); upstream trains in fp32
    qat: bool = False  # quantisation-aware fine-tuning of --checkpoint (radaredge.training.qat)
    qat_scans: int = 32  # ours: training scans a --qat run's first activation ranges are observed on

    def __post_init__(self):
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, not {self.precision!r}")
        if self.scale_min > self.scale_max:
            raise ValueError(f"scale_min ({self.scale_min}) must not exceed scale_max ({self.scale_max})")

    def roi_sampling(self) -> RoiSampling:
        """Stage two's training proposals and roi sampling (upstream's thresholds)."""
        return RoiSampling(
            pre_max=self.train_proposals_pre, post_max=self.train_proposals, roi_per_image=self.roi_per_image
        )

    @classmethod
    def from_options(cls, options: dict) -> "DetectionRecipe":
        """The recipe with ``options`` over the defaults (:func:`radaredge.training.run.recipe_from_options`)."""
        return recipe_from_options(cls, options, "MAFF-Net")


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class LabelledScan:
    """One training or validation frame: the card's points [N, F] (cropped as the graph takes
    them), boxes [M, 7] (radar frame) and their card class index [M]; ``frame`` keeps the labels,
    calibration and image size that AP needs."""

    points: np.ndarray
    boxes: np.ndarray
    classes: np.ndarray
    frame: object


def evenly(n: int, k: int) -> list[int]:
    """``k`` indices spread evenly over ``range(n)`` (all of them when k is 0 or >= n)."""
    if k <= 0 or k >= n:
        return list(range(n))
    return sorted({int(i) for i in np.linspace(0, n - 1, k).round()})


def load_split(card: ModelCard, root, split: str, data_format: str | None, limit: int = 0) -> list[LabelledScan]:
    """The frames of ``split`` under ``root`` (at most ``limit``, evenly spaced) as LabelledScans."""
    layout = layout_for_card(card, data_format)
    the_set = DetectionSet(root, split, layout, int(card.get("input.scans_accumulated", 1)))
    index = {name: i for i, name in enumerate(card.get("classes"))}
    out = []
    for i in evenly(len(the_set), limit):
        frame = the_set.frame(i, card.features)
        points = card_points(frame, card)
        if not np.isfinite(points).all():
            point, column = (int(x[0]) for x in np.nonzero(~np.isfinite(points)))
            raise InputError(
                f"{the_set.training / 'velodyne' / (frame.frame_id + '.bin')}: non-finite value at point "
                f"{point}, column {card.features[column]!r}"
            )
        keep = np.array([n in index for n in frame.labels.name], bool)
        boxes = labels_to_radar_boxes(frame.labels.select(keep), frame.calib).astype(np.float32)
        classes = np.array([index[n] for n in frame.labels.name[keep]], np.int64)
        out.append(LabelledScan(points.astype(np.float32), boxes, classes, frame))
    return out


def augment(
    points: np.ndarray, boxes: np.ndarray, xyz: list[int], recipe: DetectionRecipe, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Upstream's world augmentation (module docstring) of one scan: (points, boxes) copies."""
    points, boxes = points.copy(), boxes.astype(np.float64).copy()
    ix, iy, iz = xyz
    if recipe.flip_x and rng.random() < 0.5:
        points[:, iy] = -points[:, iy]
        boxes[:, 1], boxes[:, 6] = -boxes[:, 1], -boxes[:, 6]
    if recipe.rotation > 0:
        a = rng.uniform(-recipe.rotation, recipe.rotation)
        c, s = math.cos(a), math.sin(a)
        x, y = points[:, ix].copy(), points[:, iy].copy()
        points[:, ix], points[:, iy] = c * x - s * y, s * x + c * y
        bx, by = boxes[:, 0].copy(), boxes[:, 1].copy()
        boxes[:, 0], boxes[:, 1] = c * bx - s * by, s * bx + c * by
        boxes[:, 6] += a
    scale = rng.uniform(recipe.scale_min, recipe.scale_max)
    points[:, [ix, iy, iz]] *= scale
    boxes[:, :6] *= scale
    if recipe.translate_std_z > 0:
        dz = rng.normal(0.0, recipe.translate_std_z)
        points[:, iz] += dz
        boxes[:, 2] += dz
    boxes[:, 6] = boxes[:, 6] - np.floor(boxes[:, 6] / (2 * np.pi) + 0.5) * 2 * np.pi
    return points, boxes.astype(np.float32)


def boxes_in_range(boxes: np.ndarray, point_cloud_range) -> np.ndarray:
    """Boxes with at least one corner inside the range (OpenPCDet mask_boxes_outside_range_numpy)."""
    if not len(boxes):
        return np.zeros(0, bool)
    r = np.asarray(point_cloud_range, np.float64)
    corners = box_corners(torch.from_numpy(boxes.astype(np.float64))).numpy()
    return ((corners >= r[:3]) & (corners <= r[3:])).all(2).any(1)


# ----------------------------------------------------------------------------- model plumbing


def mixed_precision(device: torch.device, dtype: torch.dtype | None):
    """torch's autocast to ``dtype`` on ``device`` (recipe.precision); a no-op for None (fp32)."""
    return torch.autocast(device.type, dtype=dtype or torch.bfloat16, enabled=dtype is not None)


def fused_map(
    model, points: torch.Tensor, dtype: torch.dtype | None = None, training: bool = False
) -> dict[str, torch.Tensor]:
    """One scan through VFE + SPA, CFA and the fusion, export formulation (``training``: the
    pillars' training formulation, the same values with a cheaper backward,
    :meth:`~radaredge.models.maffnet.model.MAFFNet.pillar_stage_training`): ``points`` [N, F]
    (rows with an implausible value turned to NaN, as the graph does), ``fused`` [1, C, H, W]
    (the fuser's BEV map; the fuser under autocast to ``dtype`` when given, the point stages in
    fp32), ``cluster`` [N] bool (the CFA's cluster points), ``overflow`` [] bool (SPA)."""
    points, _ = drop_implausible(points, *model.point_bounds)
    pillar, _, overflow = model.pillar_stage_training(points) if training else model.pillar_stage(points, False)
    cfa, _, _, cluster = model.cfa_stage(points, False)
    with mixed_precision(points.device, dtype):
        fused = model.fuser(pillar.unsqueeze(0), cfa)
    return {"points": points, "fused": fused, "cluster": cluster, "overflow": overflow}


@dataclass
class LossSetup:
    """What the loss of a scan needs beyond the scan: the anchors' classes [A], the assigner's
    thresholds, stage two's sampling (None for a stage-one card; it draws from torch's global
    generator), the autocast dtype of the dense stages (None: fp32) and the pillar stage's
    formulation."""

    anchor_classes: torch.Tensor
    thresholds: list
    sampling: RoiSampling | None
    dtype: torch.dtype | None = None
    export_pillars: bool = False  # the pillar stage's export formulation (the same values, a slower
    # backward; benchmarks/maffnet_train_step.py times both)


def stage_two_terms(model, scan: dict, cls, box, direction, gt, gt_labels, setup: LossSetup) -> dict:
    """Stage two's loss terms of one scan (radaredge.training.roi_targets, in upstream's order): the
    training proposals from the detached anchor outputs, the sampled rois, CDA keypoints around
    them, VSA, the point head and the ROI head; ``gt_labels`` 1-based."""
    with torch.no_grad():
        decoded = decode_boxes(box, model.anchors, direction, model.head_config)
    rois, roi_labels = training_proposals(cls.detach(), decoded, setup.sampling)
    t = sample_rois(rois, roi_labels, gt, gt_labels, setup.sampling)
    xyz, feats, in_scan = scan_points(scan["points"], model.vfe.config.point_cloud_range)
    cluster = scan["cluster"] & in_scan
    every = torch.ones(len(t["rois"]), dtype=torch.bool, device=rois.device)
    keypoints, valid = model.keypoint_sampler(xyz, cluster, in_scan, t["rois"], every)
    before, point_features = model.pfe(scan["fused"][0], keypoints, xyz, feats, in_scan)
    logits = model.point_head.logits(before)
    rcnn_cls, rcnn_reg = model.roi_head(t["rois"], keypoints, valid, point_features * torch.sigmoid(logits)[:, None])
    return {
        "point": point_head_loss(logits, point_labels(keypoints, valid, gt)),
        **roi_head_loss(rcnn_cls, rcnn_reg, t),
    }


def scan_terms(model, points: torch.Tensor, gt: torch.Tensor, gt_classes: torch.Tensor, setup: LossSetup) -> dict:
    """The loss terms of one scan (``gt`` [M, 7] radar frame, ``gt_classes`` [M] 0-based card
    classes): stage one's (loss, cls, loc, dir), stage two's when the card has one (their sum is
    ``loss``), and ``overflow`` (SPA) as a tensor. With ``setup.dtype`` the fuser, backbone and
    head run under autocast; their outputs return to fp32 before the losses and stage two."""
    scan = fused_map(model, points, setup.dtype, training=not setup.export_pillars)
    with mixed_precision(points.device, setup.dtype):
        outputs = model.dense_head(model.backbone_2d(scan["fused"]))
    cls, box, direction = (t.float() for t in outputs)
    scan["fused"] = scan["fused"].float()
    targets = assign_targets(model.anchors, setup.anchor_classes, gt, gt_classes, setup.thresholds)
    terms = head_loss(cls, box, direction, targets, model.head_config, model.dense_head.num_classes)
    if setup.sampling is not None:
        two = stage_two_terms(model, scan, cls, box, direction, gt, gt_classes + 1, setup)
        terms.update(two)
        terms["loss"] = terms["loss"] + sum(two.values())
    return {**terms, "overflow": scan["overflow"]}


def detect(model, points: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The graph's detections of one scan (boxes [M, 7], scores [M], labels [M] 1-based), with the
    greedy NMS of :func:`radaredge.ops.nms.class_agnostic_nms_eager` (the same selection as the
    graph's; fast when a half-trained head leaves thousands of candidates); a two-stage card's are
    the refined boxes of its second stage."""
    scan = fused_map(model, points)
    logits, boxes = model.head_stage(scan["fused"])
    if model.stage_two_config is not None:
        out = run_stage_two(
            model, scan["points"], scan["fused"][0], scan["cluster"], logits, boxes, False, eager_nms=True
        )
        boxes, best, label = out["boxes"], out["scores"], out["labels"]
    else:
        best, label = torch.sigmoid(logits).max(-1)
        sel = class_agnostic_nms_eager(boxes, best, model.nms_config)
        boxes, best, label = boxes[sel], best[sel], label[sel] + 1
    return (boxes.cpu().numpy().astype(np.float64), best.cpu().numpy().astype(np.float64), label.cpu().numpy())


def frozen_parameters(model, patterns: str) -> list[str]:
    """Names of the parameters matched by the comma-separated ``patterns`` (fnmatch on the
    parameter name; a bare module name matches everything under it). ConfigError for a pattern
    that matches nothing, or when nothing would be left to train."""
    names = [n for n, _ in model.named_parameters()]
    out: set[str] = set()
    for pat in (p.strip() for p in patterns.split(",") if p.strip()):
        hit = [n for n in names if fnmatch.fnmatchcase(n, pat) or n.startswith(pat.rstrip(".") + ".")]
        if not hit:
            tops = sorted({n.split(".")[0] for n in names})
            raise ConfigError(
                f"--freeze {pat!r} matches no parameter; the modules are {tops} "
                f"(patterns match parameter names, e.g. 'backbone_2d.blocks.0.*')"
            )
        out.update(hit)
    if out and len(out) == len(names):
        raise ConfigError(f"--freeze {patterns!r} freezes every parameter; nothing would train")
    return [n for n in names if n in out]


def set_train_mode(model, frozen: set[str]) -> None:
    """Training mode, except modules whose parameters are all frozen (their batch-norm statistics
    stay as loaded)."""
    model.train()
    for name, module in model.named_modules():
        params = [f"{name}.{p}" if name else p for p, _ in module.named_parameters()]
        if params and all(p in frozen for p in params):
            module.eval()


def _adam_onecycle(model, recipe: DetectionRecipe, steps: int):
    """OpenPCDet's adam_onecycle (module docstring) as torch AdamW + OneCycleLR."""
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(
        params, lr=recipe.lr / recipe.div_factor, betas=(0.95, 0.99), weight_decay=recipe.weight_decay
    )
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt,
        max_lr=recipe.lr,
        total_steps=max(steps, 1),
        pct_start=recipe.pct_start,
        anneal_strategy="cos",
        cycle_momentum=True,
        base_momentum=0.85,
        max_momentum=0.95,
        div_factor=recipe.div_factor,
        final_div_factor=1e4,
    )
    return params, opt, sched


# ----------------------------------------------------------------------------- validation


def batch_norm_statistics(model, scans: list[torch.Tensor]):
    """A context in which the VFE's train-mode norm uses the statistics of the batch ``scans``
    (points [N, F] each) while the scans run one at a time: upstream's BatchNorm1d normalises
    over every pillar slot of every scan of a batch, so an offset common to one scan's points
    (a height offset from the road's grade) reaches the layers after it, where each scan's own
    statistics would remove it exactly (the layer before the norm is linear). The 2-D layers
    after the scatter still normalise per scan."""
    if not scans:
        return contextlib.nullcontext()
    moments = [model.pillar_input_moments(drop_implausible(p, *model.point_bounds)[0]) for p in scans]
    return model.vfe.pfn_layers[0].batch_statistics(functools.reduce(operator.add, moments))


def reestimate_norm_statistics(
    model, scans: list[LabelledScan], frozen: set[str], setup: LossSetup, pc_range, device, batch_size: int
) -> None:
    """Batch-norm running statistics of the trainable modules recomputed with the current weights:
    the cumulative average over ``scans`` (no augmentation) in batches of ``batch_size``
    consecutive scans (:func:`batch_norm_statistics`), run as in training (a two-stage card's second stage on its
    sampled rois, as its running averages see it).
    Upstream's running averages (momentum 0.01) trail the weights by about a hundred scans; on a
    schedule of a few epochs at a 0.01 peak learning rate that lag compounds through the 20
    normalised layers, and an eval-mode network scores every anchor 1.0 (measured on maffnet-vod
    after one epoch: batch variances 1.3-1.8 x the running ones, layer after layer)."""
    set_train_mode(model, frozen)
    norms = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm) and m.training]
    saved = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None
    with torch.no_grad():
        for first in range(0, len(scans), batch_size):
            batch = scans[first : first + batch_size]
            with batch_norm_statistics(model, [torch.from_numpy(s.points).to(device) for s in batch]):
                for scan in batch:
                    keep = boxes_in_range(scan.boxes, pc_range)
                    scan_terms(
                        model,
                        torch.from_numpy(scan.points).to(device),
                        torch.from_numpy(scan.boxes[keep]).to(device),
                        torch.from_numpy(scan.classes[keep]).to(device),
                        setup,
                    )
    for m, momentum in zip(norms, saved):
        m.momentum = momentum
    model.eval()


def validation_ap(
    model,
    scans: list[LabelledScan],
    card: ModelCard,
    data_format: str | None,
    device: torch.device,
    progress=no_progress,
) -> dict[str, float]:
    """3D AP (%, entire area, 11 recall positions, the dataset's IoU thresholds) per evaluated
    class of the model's detections (:func:`detect`) on ``scans``, and their mean
    ``mAP``; also each class's BEV AP."""
    layout = layout_for_card(card, data_format)
    eval_classes = tuple(
        layout.eval_class(c) for c in card.get("classes") if c in {e.name for e in layout.eval_classes}
    )
    model.eval()
    dts = []
    bar = progress("validation AP", len(scans))
    with torch.no_grad():
        for scan in scans:
            dts.append(
                as_labels(detect(model, torch.from_numpy(scan.points).to(device)), scan.frame, card.get("classes"))
            )
            bar.update()
    bar.close()
    table = ap_table(evaluate_frames([s.frame.labels for s in scans], dts, eval_classes, ("entire_area",)))
    rows = table["entire_area"]
    metrics = {f"AP3d_{c}": float(r["3d"]) for c, r in rows.items()}
    metrics.update({f"APbev_{c}": float(r["bev"]) for c, r in rows.items()})
    metrics["mAP3d"] = float(np.mean([r["3d"] for r in rows.values()]))
    return metrics


# ----------------------------------------------------------------------------- training


def require_labelled_objects(card: ModelCard, root, data_format: str | None, train: list[LabelledScan]) -> None:
    """InputError naming the training split and the card's classes when no frame of ``train``
    holds a labelled object of those classes: every scan would be skipped and the run would
    "succeed" with a best.pth that learnt nothing."""
    if any(len(scan.classes) for scan in train):
        return
    the_set = DetectionSet(
        root, TRAIN_SPLIT, layout_for_card(card, data_format), int(card.get("input.scans_accumulated", 1))
    )
    others = sorted({str(n) for scan in train for n in scan.frame.labels.name} - {"DontCare"})
    found = f"their labels name only {others}" if others else "their label files hold no object"
    raise InputError(
        f"{the_set.split_file}: none of the {len(train)} training frames read has a labelled object of "
        f"the card's classes {list(card.get('classes'))} ({found}); training would learn nothing. "
        f"Train on a split with labelled objects of these classes, or a card whose classes the labels use"
    )


def _signature(card: ModelCard, root, recipe: DetectionRecipe, validation: str, train: list, val: list) -> dict:
    """What a resumed run must share with the one that wrote ``last.pth``."""
    keep = resume_signature({k: v for k, v in dataclasses.asdict(recipe).items() if k not in ("epochs", "val_every")})
    return {
        "card": card.data,
        "data": str(Path(root).resolve()),
        "validation": validation,
        "train_frames": [s.frame.frame_id for s in train],
        "val_frames": [s.frame.frame_id for s in val],
        "recipe": keep,
    }


def _epoch_line(e: dict, classes: list[str]) -> str:
    ap = " / ".join(f"{e.get(f'AP3d_{c}', float('nan')):.1f}" for c in classes if f"AP3d_{c}" in e)
    val = f", validation 3D AP {ap} (mAP {e['mAP3d']:.1f})" if "mAP3d" in e else ""
    loss = "-" if not math.isfinite(e["loss"]) else f"{e['loss']:.4f}"
    return f"epoch {e['epoch']:>3}: loss {loss}{val}, {e['seconds'] / 60:.1f} min"


def train_detector(
    card: ModelCard,
    model,
    data_root,
    output,
    recipe: DetectionRecipe,
    device: str = "cpu",
    resume: bool = False,
    validation: str = VALIDATION_SPLIT,
    data_format: str | None = None,
    checkpoint=None,
    progress=no_progress,
    log: Callable[[str], None] = lambda line: None,
) -> TrainReport:
    """Train ``model`` (a MAFF-Net of ``card``, one stage or two) on the ``train`` split under ``data_root``
    with ``recipe``, validate on the ``validation`` split, and write the run directory ``output``
    (:mod:`.run`: best.pth by validation mAP, last.pth for ``resume``, train-log.json)."""
    dev = pick_device(device)
    run = RunDir(output, card)
    if resume:
        run.require_last()
    frozen = frozen_parameters(model, recipe.freeze)
    train = load_split(card, data_root, TRAIN_SPLIT, data_format, recipe.train_frames)
    require_labelled_objects(card, data_root, data_format, train)
    val = load_split(card, data_root, validation, data_format, recipe.val_frames)
    thresholds = class_thresholds(card)
    xyz = [card.features.index(c) for c in ("x", "y", "z")]
    pc_range = card.get("pillars.point_cloud_range")
    n_boxes = {c: int(sum((s.classes == i).sum() for s in train)) for i, c in enumerate(card.get("classes"))}
    summary = {
        "root": str(data_root),
        "train_frames": len(train),
        "validation_split": validation,
        "validation_frames": len(val),
        "train_boxes": n_boxes,
        "initial_weights": (
            str(checkpoint)
            if checkpoint
            else f"stage one {recipe.stage_one_weights}, stage two seeded"
            if recipe.stage_one_weights
            else f"seeded (card seed {card.get('seed', 0)})"
        ),
        "frozen_parameters": len(frozen),
    }
    log(
        f"data: {len(train)} training frames ({', '.join(f'{v} {k}' for k, v in n_boxes.items())}), "
        f"{len(val)} validation frames ({validation}); weights: {summary['initial_weights']}"
        + (f"; {len(frozen)} parameter tensors frozen" if frozen else "")
    )
    if recipe.stage_one_weights and not resume:
        if model.stage_two_config is None:
            raise ConfigError(
                f"stage_one_weights is for a card with a second stage; {card.name} has none "
                f"(a checkpoint of the whole network loads with --checkpoint)"
            )
        if checkpoint:
            raise ConfigError("--checkpoint and stage_one_weights both give initial weights; give one")
        log(load_weights_outside(model, recipe.stage_one_weights, STAGE_TWO_MODULES, "stage two", "stage_one_weights"))
    elif not checkpoint:
        with torch.no_grad():
            model.dense_head.conv_cls.bias.fill_(-math.log((1 - recipe.head_prior) / recipe.head_prior))
    frozen_set = set(frozen)
    for name, p in model.named_parameters():
        p.requires_grad_(name not in frozen_set)
    # channels last: the training canvas comes that way (pillar_stage_training), and oneDNN's
    # convolutions then run without converting layouts back and forth (measured on maffnet-vod,
    # bf16: 0.70 against 1.0 s a training scan)
    model.to(dev, memory_format=torch.channels_last)
    fake_quant = start_qat(model, card, recipe.precision, bool(checkpoint) or resume) if recipe.qat else None
    setup = LossSetup(
        anchor_classes(card, len(model.anchors)).to(dev),
        thresholds,
        recipe.roi_sampling() if model.stage_two_config is not None else None,
        PRECISIONS[recipe.precision],
    )
    steps_per_epoch = math.ceil(len(train) / recipe.batch_size)
    params, opt, sched = _adam_onecycle(model, recipe, steps_per_epoch * recipe.epochs)
    rng = np.random.default_rng(recipe.seed)
    torch.manual_seed(recipe.seed)
    signature = _signature(card, data_root, recipe, validation, train, val)
    report = TrainReport(
        card.name, run.path, "mAP3d", data=summary, options={**dataclasses.asdict(recipe), "device": device}
    )
    start, best = 1, None
    saved = TrainingState(run, signature, model, rng, report, opt, sched)
    if resume:
        state, clock = saved.resume(recipe.epochs, schedule=True)
        best = report.best["mAP3d"] if report.best is not None else None
        start = state["epoch"] + 1
        if fake_quant is not None:
            fake_quant.load_state_dict(state["qat"])
        log(f"resuming after epoch {state['epoch']} from {run.last}")
    else:
        clock = Stopwatch()
        if fake_quant is not None:  # the first activation ranges, on training scans
            with fake_quant.observing():
                validation_ap(model, [train[i] for i in evenly(len(train), recipe.qat_scans)], card, data_format, dev)
        metrics = validation_ap(model, val, card, data_format, dev, progress)
        report.epochs.append({"epoch": 0, "loss": float("nan"), **metrics, "seconds": round(clock(), 1)})
        log(_epoch_line(report.epochs[-1], card.get("classes")) + "  (initial weights)")
    for epoch in range(start, recipe.epochs + 1):
        set_train_mode(model, frozen_set)
        order = rng.permutation(len(train))
        bar = progress(f"epoch {epoch}/{recipe.epochs}", len(order))
        sums = dict.fromkeys(TERMS + (STAGE_TWO_TERMS if setup.sampling else ()), 0.0)
        counted = skipped = overflows = 0
        for first in range(0, len(order), recipe.batch_size):
            batch = order[first : first + recipe.batch_size]
            opt.zero_grad()
            inputs = []
            for i in batch:
                scan = train[int(i)]
                points, boxes = (
                    (augment(scan.points, scan.boxes, xyz, recipe, rng))
                    if recipe.augment
                    else (scan.points, scan.boxes)
                )
                keep = boxes_in_range(boxes, pc_range)
                bar.update()
                if not keep.any():
                    skipped += 1
                    continue
                inputs.append(
                    (
                        torch.from_numpy(points).to(dev),
                        torch.from_numpy(boxes[keep]).to(dev),
                        torch.from_numpy(scan.classes[keep]).to(dev),
                    )
                )
            with batch_norm_statistics(model, [points for points, _, _ in inputs]):
                for points, boxes, classes in inputs:
                    terms = scan_terms(model, points, boxes, classes, setup)
                    overflows += int(terms["overflow"])
                    (terms["loss"] / len(batch)).backward()
                    for k in sums:
                        sums[k] += float(terms[k].detach())
            counted += len(inputs)
            if inputs:
                torch.nn.utils.clip_grad_norm_(params, recipe.grad_clip)
                opt.step()
            sched.step()
            bar.set_postfix(loss=f"{sums['loss'] / max(counted, 1):.4f}")
        bar.close()
        means = {k: v / max(counted, 1) for k, v in sums.items()}
        if not math.isfinite(means["loss"]):
            raise ConfigError(
                f"training diverged in epoch {epoch} (loss {means['loss']}); lower --lr (now {recipe.lr:g})"
            )
        row = {
            "epoch": epoch,
            "loss": means.pop("loss"),
            **{f"loss_{k}": v for k, v in means.items()},
            "lr": float(opt.param_groups[0]["lr"]),
            "skipped_scans": skipped,
            "spa_overflows": overflows,
        }
        if epoch % recipe.val_every == 0 or epoch == recipe.epochs:
            if recipe.bn_scans:
                reestimate_norm_statistics(
                    model,
                    [train[i] for i in evenly(len(train), recipe.bn_scans)],
                    frozen_set,
                    dataclasses.replace(setup, dtype=None),
                    pc_range,
                    dev,
                    recipe.batch_size,
                )
            row.update(validation_ap(model, val, card, data_format, dev, progress))
            if best is None or row["mAP3d"] > best:
                best, report.best_epoch = row["mAP3d"], epoch
                run.save_best(
                    model,
                    epoch,
                    {k: v for k, v in row.items() if k.startswith(("AP", "mAP"))},
                    **({"qat": fake_quant.checkpoint_entry()} if fake_quant else {}),
                )
        row["seconds"] = round(clock(), 1)
        report.epochs.append(row)
        report.seconds = clock()
        saved.save(epoch, clock, epochs=recipe.epochs, **({"qat": fake_quant.state_dict()} if fake_quant else {}))
        run.write_log(report.to_dict())
        log(_epoch_line(row, card.get("classes")) + ("  (best)" if report.best_epoch == epoch else ""))
    report.seconds = clock()
    run.write_log(report.to_dict())
    if fake_quant is not None:
        fake_quant.remove()
    model.eval()
    return report
