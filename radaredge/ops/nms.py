"""Class-agnostic rotated-box NMS, as OpenPCDet's ``class_agnostic_nms`` with ``nms_gpu`` runs it.

What it computes for per-anchor boxes [A, 7] (OpenPCDet layout, metres / radians) and scores [A]:
1. keep the boxes with score >= ``score_thresh``;
2. of those, the ``pre_max`` highest scores, in descending score order (equal scores: lower
   anchor index first);
3. greedy NMS: walk that list; a box is kept unless a box kept before it overlaps it with
   rotated BEV IoU > ``iou_thresh`` (:mod:`radaredge.ops.box_iou`);
4. the first ``post_max`` kept boxes.
Returns the selected anchor indices in that order.

Export formulation (:func:`class_agnostic_nms`): fixed-shape top-k, then only the candidates
above the threshold (a prefix of the top-k list, taken with NonZero, plus 8 invalid padding
rows so no size is ever 0 or 1), so the pairwise work follows the number of boxes that pass the
threshold, not ``pre_max``; IoU only for the pairs whose axis-aligned bounding rectangles
overlap and whose IoU bound from those rectangles exceeds the threshold (no other pair can
suppress), gathered with NonZero; the greedy walk as its fixed point: keep[j] = valid[j] and no
kept i < j suppresses j. Iterating that map
from "all valid" settles index j after at most j + 1 rounds and stops at the first round that
changes nothing, which is exactly the greedy result (entry j depends only on entries before
it, so the fixed point is unique). The loop is a ``torch.while_loop`` (an ONNX ``Loop``); its
round count is the length of the longest suppression chain, a handful in practice.

Reference formulation (:func:`class_agnostic_nms_reference`): the same steps written plainly
in Python with :func:`radaredge.ops.box_iou.bev_iou_reference`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..config import card_ranges
from .box_iou import bev_half_extents, bev_iou_paired, bev_iou_reference, bev_iou_upper_bound
from .loops import fixed_point_loop
from .topk import topk_indices


@card_ranges(score_thresh=(0.0, 1.0), iou_thresh=(0.0, 1.0), pre_max=(1, 2**20), post_max=(1, 2**20))
@dataclass(frozen=True)
class NmsConfig:
    """OpenPCDet POST_PROCESSING values (SCORE_THRESH, NMS_CONFIG)."""

    score_thresh: float = 0.1
    iou_thresh: float = 0.1  # NMS_THRESH
    pre_max: int = 4096  # NMS_PRE_MAXSIZE
    post_max: int = 500  # NMS_POST_MAXSIZE

    def __post_init__(self):
        if self.pre_max < 1 or self.post_max < 1:
            raise ValueError("pre_max and post_max must be >= 1")
        if not 0.0 <= self.iou_thresh <= 1.0:
            raise ValueError("iou_thresh must be in [0, 1]")


def suppression_matrix(boxes: torch.Tensor, valid: torch.Tensor, iou_thresh: float) -> torch.Tensor:
    """S [K, K] float: S[i, j] = 1 when i < j, both valid and IoU(i, j) > iou_thresh.

    Two filters before the polygon clipping, each exact: only pairs whose axis-aligned bounding
    rectangles overlap (half extents grown by 1 mm, so float32 rounding cannot drop a touching
    pair) are gathered, since a rotated box lies inside its bounding rectangle; of those, only
    pairs whose IoU bound (:func:`radaredge.ops.box_iou.bev_iou_upper_bound`) exceeds
    ``iou_thresh`` less 1e-6 (far above float64 rounding) get an IoU. Every other pair has IoU at
    most ``iou_thresh`` and suppresses nothing. On upstream's worst case (4,096 candidates from
    a seeded maffnet-vod) the bound leaves 76 k of 232 k overlapping pairs, 64 k of them above
    the threshold.
    """
    k = boxes.shape[0]
    ex, ey = bev_half_extents(boxes)
    ex, ey = ex + 1e-3, ey + 1e-3  # m
    x, y = boxes[:, 0], boxes[:, 1]
    dev = boxes.device
    idx = torch.arange(k, device=dev)
    candidate = (x.unsqueeze(1) - x.unsqueeze(0)).abs() <= ex.unsqueeze(1) + ex.unsqueeze(0)
    candidate &= (y.unsqueeze(1) - y.unsqueeze(0)).abs() <= ey.unsqueeze(1) + ey.unsqueeze(0)
    candidate &= (idx.unsqueeze(1) < idx.unsqueeze(0)) & valid.unsqueeze(1) & valid.unsqueeze(0)
    # P candidate pairs (data-dependent) plus 8 dummy pairs (0, 0) written to a spare slot and
    # never filtered out: the exported graph never sees fewer than 8 pairs (torch.export assumes
    # a data-dependent size is not 0 or 1 when it decides broadcasts, which broke scans with
    # almost no candidates). float64: the reference computes IoU in float64, and a float32 IoU
    # can sit on the other side of iou_thresh when the true value is within ~3e-5 of it.
    found = torch.nonzero(candidate)  # [P, 2]
    dummy = torch.cat(
        [torch.zeros(found.shape[0], dtype=torch.bool, device=dev), torch.ones(8, dtype=torch.bool, device=dev)]
    )
    pairs = torch.cat([found, torch.zeros(8, 2, dtype=torch.int64, device=dev)])
    target = torch.cat([found[:, 0] * k + found[:, 1], torch.full((8,), k * k, dtype=torch.int64, device=dev)])
    both = boxes.to(torch.float64).index_select(0, pairs.reshape(-1)).reshape(-1, 2, 7)  # one pair count
    near = torch.nonzero((bev_iou_upper_bound(both[:, 0], both[:, 1]) > iou_thresh - 1e-6) | dummy).squeeze(1)
    both, target = both.index_select(0, near), target.index_select(0, near)
    iou = bev_iou_paired(both[:, 0], both[:, 1])
    flat = torch.zeros(k * k + 1, dtype=boxes.dtype, device=dev)
    flat = flat.scatter(0, target, (iou > iou_thresh).to(boxes.dtype))
    return flat[: k * k].reshape(k, k)


def greedy_keep(suppress: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Greedy NMS over a score-sorted list as a fixed point: keep [K] bool (see module docstring).

    The rounds run in :func:`radaredge.ops.loops.fixed_point_loop` (an ONNX ``Loop`` once exported)."""

    def not_done(keep, changed):
        return changed.clone()

    def step(keep, changed):
        hit = (keep.to(suppress.dtype).unsqueeze(0) @ suppress).squeeze(0) > 0
        new = valid & ~hit
        return new, (new != keep).any()

    return fixed_point_loop(not_done, step, (valid.clone(), torch.ones((), dtype=torch.bool, device=valid.device)))[0]


def class_agnostic_nms(boxes: torch.Tensor, scores: torch.Tensor, config: NmsConfig) -> torch.Tensor:
    """Export formulation: selected anchor indices [M] (int64, M <= post_max), best first."""
    a = scores.shape[0]
    above = scores >= config.score_thresh
    # Equal scores: lower anchor index first. A float64 key with a per-index step smaller than
    # any float32 spacing at or above the threshold gives that order through one TopK.
    step = 2.0**-26 * max(config.score_thresh, 1e-3) / max(a, 1)
    key = torch.where(above, scores.to(torch.float64), torch.full_like(scores, -1.0, dtype=torch.float64))
    key = key - torch.arange(a, dtype=torch.float64, device=scores.device) * step
    order = topk_indices(key, min(config.pre_max, a))
    # The boxes above the threshold come first in ``order``; keep only them (n, data-dependent)
    # plus 8 invalid padding rows, so the K x K work is (n + 8)^2 rather than pre_max^2.
    order = order.index_select(0, torch.nonzero(above.index_select(0, order)).squeeze(1))  # [n]
    cand = torch.cat([boxes.index_select(0, order), torch.zeros(8, 7, dtype=boxes.dtype, device=boxes.device)])
    valid = torch.cat([torch.ones_like(order, dtype=torch.bool), torch.zeros(8, dtype=torch.bool, device=order.device)])
    keep = greedy_keep(suppression_matrix(cand, valid, config.iou_thresh), valid)
    rank = torch.nonzero(keep).squeeze(1)[: config.post_max]
    return order.index_select(0, rank)


def class_agnostic_nms_eager(boxes: torch.Tensor, scores: torch.Tensor, config: NmsConfig) -> torch.Tensor:
    """Training-time formulation of :func:`class_agnostic_nms` (same indices): the greedy walk as
    a Python loop over the *kept* boxes, each suppressing the later candidates it overlaps (IoU in
    float64 only for those within reach of its bounding rectangle and of its IoU bound). Eager
    torch, never exported: validation during training runs it because a half-trained head can put thousands of anchors
    above the threshold, and the export formulation's pairwise work then takes seconds a frame."""
    device = boxes.device
    boxes, scores = boxes.detach().cpu(), scores.detach().cpu()
    above = torch.nonzero(scores >= config.score_thresh).squeeze(1)
    # descending score, equal scores lower anchor index first (a stable sort of the index order)
    order = above[torch.sort(scores[above], descending=True, stable=True).indices][: config.pre_max]
    cand = boxes[order].to(torch.float64)
    ex, ey = bev_half_extents(cand)
    ex, ey = ex + 1e-3, ey + 1e-3
    alive = torch.ones(len(order), dtype=torch.bool, device=order.device)
    kept: list[int] = []
    for i in range(len(order)):
        if not alive[i]:
            continue
        kept.append(i)
        if len(kept) == config.post_max:
            break
        later = torch.arange(i + 1, len(order), device=order.device)
        later = later[
            alive[later]
            & ((cand[later, 0] - cand[i, 0]).abs() <= ex[later] + ex[i])
            & ((cand[later, 1] - cand[i, 1]).abs() <= ey[later] + ey[i])
        ]
        later = later[bev_iou_upper_bound(cand[i].expand(len(later), 7), cand[later]) > config.iou_thresh - 1e-6]
        if len(later):
            iou = bev_iou_paired(cand[i].expand(len(later), 7), cand[later])
            alive[later[iou > config.iou_thresh]] = False
    return order[torch.tensor(kept, dtype=torch.int64, device=order.device)].to(device)


# ----------------------------------------------------------------------------- reference


def greedy_nms_reference(boxes: np.ndarray, iou_thresh: float) -> list[int]:
    """Plain greedy NMS over boxes [K, 7] already in score order: indices of the kept boxes.

    A kept box whose circumscribed circle misses box j's cannot overlap it, so only the kept
    boxes within reach are clipped polygon by polygon.
    """
    boxes = np.asarray(boxes, np.float64)
    centre, radius = boxes[:, :2], 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    kept = np.empty(len(boxes), np.int64)
    n = 0
    for j in range(len(boxes)):
        mine = kept[:n]
        near = mine[((centre[mine] - centre[j]) ** 2).sum(1) <= (radius[mine] + radius[j]) ** 2]
        if all(bev_iou_reference(boxes[i], boxes[j]) <= iou_thresh for i in near):
            kept[n] = j
            n += 1
    return kept[:n].tolist()


def class_agnostic_nms_reference(boxes: np.ndarray, scores: np.ndarray, config: NmsConfig) -> np.ndarray:
    """Reference formulation of :func:`class_agnostic_nms` (numpy in, int64 indices out)."""
    boxes = np.asarray(boxes, np.float64)
    scores = np.asarray(scores, np.float32)
    above = [i for i in range(len(scores)) if scores[i] >= np.float32(config.score_thresh)]
    above.sort(key=lambda i: (-float(scores[i]), i))
    order = above[: config.pre_max]
    kept = greedy_nms_reference(boxes[order], config.iou_thresh) if order else []
    return np.array([order[j] for j in kept[: config.post_max]], np.int64)


# ----------------------------------------------------------------------------- near ties


def near_ties(
    boxes: np.ndarray,
    scores: np.ndarray,
    config: NmsConfig,
    score_tol: tuple[float, float],
    iou_tol: float,
    limit: int = 20,
) -> list[dict]:
    """The decisions of :func:`class_agnostic_nms_reference` on ``boxes`` [A, 7] and ``scores``
    [A] that inputs perturbed by float noise could take the other way: the evidence a parity
    report needs before it calls an end-to-end difference a near tie.

    Noise of a score s is ``score_tol`` = (atol, rtol): atol + rtol * |s|; two scores can swap
    when they are within twice that of each other. An IoU can cross ``iou_thresh`` when it is
    within ``iou_tol`` of it. Decisions (at most ``limit``, each a dict with ``decision``,
    ``anchors``, ``values`` and ``threshold``):

    - ``score threshold``: a score within noise of ``score_thresh``;
    - ``pre_max cut``: the last score kept by the top-``pre_max`` and the first one left out;
    - ``order``: two candidates within noise of each other whose boxes overlap beyond
      ``iou_thresh`` (minus ``iou_tol``): whichever ranks first suppresses the other;
    - ``overlap``: a kept box and a later candidate whose IoU is within ``iou_tol`` of ``iou_thresh``;
    - ``post_max cut``: the last kept box within ``post_max`` and the next one kept after it.
    """
    boxes = np.asarray(boxes, np.float64)
    scores = np.asarray(scores, np.float32)
    atol, rtol = score_tol

    def swap(a: float, b: float) -> bool:
        return abs(a - b) <= 2 * (atol + rtol * max(abs(a), abs(b)))

    ties: list[dict] = []

    def add(decision, anchors, values, threshold):
        if len(ties) < limit:
            ties.append(
                {
                    "decision": decision,
                    "anchors": [int(a) for a in anchors],
                    "values": [float(v) for v in values],
                    "threshold": float(threshold),
                }
            )

    thresh = np.float32(config.score_thresh)
    order = sorted((i for i in range(len(scores)) if scores[i] >= thresh), key=lambda i: (-float(scores[i]), i))
    if math.isfinite(float(thresh)):
        for i in range(len(scores)):
            if abs(float(scores[i]) - float(thresh)) <= atol + rtol * abs(float(thresh)):
                add("score threshold", [i], [scores[i]], thresh)
    k = min(config.pre_max, len(order))
    if len(order) > k and swap(float(scores[order[k - 1]]), float(scores[order[k]])):
        add("pre_max cut", [order[k - 1], order[k]], [scores[order[k - 1]], scores[order[k]]], config.pre_max)
    cand = order[: k + 1]
    centre, radius = boxes[:, :2], 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])

    def reach(i, j) -> bool:
        return float(((centre[i] - centre[j]) ** 2).sum()) <= float(radius[i] + radius[j]) ** 2

    for p, a in enumerate(cand):
        for b in cand[p + 1 :]:
            if not swap(float(scores[a]), float(scores[b])):
                break
            if reach(a, b) and bev_iou_reference(boxes[a], boxes[b]) > config.iou_thresh - iou_tol:
                add("order", [a, b], [scores[a], scores[b]], config.iou_thresh)
    kept: list[int] = []
    for j in order[:k]:
        suppressed = False
        for i in kept:
            if not reach(i, j):
                continue
            iou = bev_iou_reference(boxes[i], boxes[j])
            if abs(iou - config.iou_thresh) <= iou_tol:
                add("overlap", [i, j], [iou], config.iou_thresh)
            suppressed |= iou > config.iou_thresh
        if not suppressed:
            kept.append(j)
    if len(kept) > config.post_max and swap(
        float(scores[kept[config.post_max - 1]]), float(scores[kept[config.post_max]])
    ):
        a, b = kept[config.post_max - 1], kept[config.post_max]
        add("post_max cut", [a, b], [scores[a], scores[b]], config.post_max)
    return ties


def describe_tie(tie: dict) -> str:
    """One line for a :func:`near_ties` decision."""
    a = tie["anchors"]
    v = ", ".join(f"{x:.7g}" for x in tie["values"])
    if tie["decision"] == "overlap":
        return f"overlap of anchors {a[0]} and {a[1]}: IoU {v} vs iou_thresh {tie['threshold']:g}"
    if tie["decision"] == "order":
        return f"order of anchors {a[0]} and {a[1]}: scores {v}, overlapping beyond iou_thresh {tie['threshold']:g}"
    if tie["decision"] == "score threshold":
        return f"anchor {a[0]}: score {v} vs score_thresh {tie['threshold']:g}"
    return f"{tie['decision']} {int(tie['threshold'])}: anchors {a[0]} and {a[1]}, scores {v}"
