"""Average precision of 3D detections as View-of-Delft's devkit computes it (and TRV-Lab/MAFF-Net's
TJ4DRadSet evaluation, the same code with other classes).

The protocol (tudelft-iv/view-of-delft-dataset, ``vod/evaluation``; a KITTI evaluation with
VoD's cleaning), in the camera frame of the labels:

* **Per class**, ground truth of the class counts; its neighbouring class (Van for Car,
  Person_sitting for Pedestrian) and ground truth whose 2D box is at most 40 px high (or
  occlusion above 4) is *ignored*: matching it is neither a hit nor a false positive. Other
  classes and DontCare play no part, except that in the 2D-box metric a detection inside a
  DontCare region is no false positive. Detections of the class count; a detection whose 2D
  box (the projected 3D box clipped to the image) is under 40 px high is ignored, whatever its
  class.
* **Areas**: the entire annotated area, and the *driving corridor*: ground truth and
  detections whose camera-frame centre lies outside x in [-4, 4] m or beyond z = 25 m are ignored.
* **Matching**: each ground-truth box, in label order, takes the unassigned detection above the
  score threshold with the largest IoU above the class's minimum (strictly greater); 3D IoU =
  BEV overlap (rotated, x-z plane) x height overlap / union volume; BEV IoU; 2D-box IoU.
* **Thresholds**: the scores of the true positives found with the best-scoring match, thinned
  to 41 recall positions (recall 0, 1/40, ..., 1). Precision at each threshold, then the
  running maximum from the right.
* **AP**: VoD reports the **11-point** AP, the mean precision at recall 0, 0.1, ..., 1.0 (every
  4th of the 41 positions; ``get_m_ap``), and so do MAFF-Net's published VoD and TJ4D figures,
  which come from that code. The 40-point AP (positions 1/40 ... 1, KITTI's since 2019) is
  reported beside it. AOS is the 2D-box metric's orientation similarity, weighted like AP.
* Minimum IoU: 3D and BEV Car 0.5, Pedestrian 0.25, Cyclist 0.25 (TJ4D Truck 0.5); 2D box (and
  AOS) Car 0.7, Pedestrian 0.5, Cyclist 0.5 (TJ4D Truck 0.7).

**Intervals** (radaredge's, not the devkit's): the 95 % percentile bootstrap over frames. Each
resample draws the frames with replacement and recomputes the devkit's AP on it, thresholds
included (:func:`resampled_ap`, from a per-frame table of each frame's counts at each of its own
detection scores, :class:`FrameTable`); two detectors are resampled on the same frames, so their
difference gets a paired interval. Frames of one drive are not independent, so the interval is on
the narrow side.

Two deviations from the devkit's code, neither of which changes a figure except at exact ties:
IoU is computed in float64 (the devkit rounds boxes to float32), and the rotated overlap is
:func:`radaredge.ops.box_iou.bev_overlap_paired` (edge clipping) rather than the devkit's
vertex sorting. TRV-Lab/MAFF-Net's copy of the evaluation, like the devkit's 1.0.3 release on
PyPI, adds 0.01 to each detection's rotation and 2D box before the IoU; the devkit's current
source does not, nor does radaredge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..data.kitti_detection import DONT_CARE, EvalClass, Labels
from ..ops.box_iou import bev_overlap_paired

N_SAMPLE_PTS = 41
MIN_HEIGHT_PX = 40.0  # clean_data: min_instance_height
MAX_OCCLUSION = 4  # clean_data: max_instance_occlusion
CORRIDOR_X = (-4.0, 4.0)  # m, camera x (lateral)
CORRIDOR_Z = 25.0  # m, camera z (forward)
METRICS = ("bbox", "bev", "3d")
AREAS = ("entire_area", "corridor")
_NO_DETECTION = -10_000_000.0


# ----------------------------------------------------------------------------- overlaps


def _bev_boxes(labels: Labels) -> torch.Tensor:
    """Camera-frame BEV footprints as OpenPCDet 7-vectors: (x, z) centre, (l, w), heading -ry."""
    zero = np.zeros(len(labels))
    loc, dims = labels.location, labels.dimensions
    return torch.from_numpy(
        np.column_stack([loc[:, 0], loc[:, 2], zero, dims[:, 0], dims[:, 2], zero, -labels.rotation_y]).astype(
            np.float64
        )
    )


def _pairwise_bev_overlap(dt: Labels, gt: Labels) -> np.ndarray:
    """Rotated BEV intersection area [n_dt, n_gt] (m^2) in the camera's x-z plane."""
    n, m = len(dt), len(gt)
    if n == 0 or m == 0:
        return np.zeros((n, m))
    a, b = _bev_boxes(dt), _bev_boxes(gt)
    area = bev_overlap_paired(a.repeat_interleave(m, 0), b.repeat(n, 1)).numpy().reshape(n, m)
    return np.nan_to_num(area)


def overlaps(metric: str, dt: Labels, gt: Labels) -> np.ndarray:
    """IoU [n_dt, n_gt] of every detection with every label under ``metric`` (bbox, bev, 3d)."""
    n, m = len(dt), len(gt)
    if n == 0 or m == 0:
        return np.zeros((n, m))
    if metric == "bbox":
        return image_box_overlap(dt.bbox, gt.bbox)
    inter = _pairwise_bev_overlap(dt, gt)
    if metric == "bev":
        area_dt = dt.dimensions[:, 0] * dt.dimensions[:, 2]
        area_gt = gt.dimensions[:, 0] * gt.dimensions[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            iou = inter / (area_dt[:, None] + area_gt[None, :] - inter)
    else:
        y_dt, h_dt = dt.location[:, 1][:, None], dt.dimensions[:, 1][:, None]
        y_gt, h_gt = gt.location[:, 1][None, :], gt.dimensions[:, 1][None, :]
        height = np.minimum(y_dt, y_gt) - np.maximum(y_dt - h_dt, y_gt - h_gt)  # y points down: box is [y - h, y]
        inc = np.where((inter > 0) & (height > 0), inter * height, 0.0)
        vol_dt = np.prod(dt.dimensions, 1)[:, None]
        vol_gt = np.prod(gt.dimensions, 1)[None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            iou = np.where(inc > 0, inc / (vol_dt + vol_gt - inc), 0.0)
    return np.nan_to_num(iou)


def image_box_overlap(boxes: np.ndarray, query: np.ndarray, criterion: int = -1) -> np.ndarray:
    """2D-box overlap [N, K] (left, top, right, bottom px): IoU (criterion -1) or intersection over
    the area of ``boxes`` (0; DontCare regions)."""
    boxes, query = np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(query, np.float64).reshape(-1, 4)
    iw = np.minimum(boxes[:, None, 2], query[None, :, 2]) - np.maximum(boxes[:, None, 0], query[None, :, 0])
    ih = np.minimum(boxes[:, None, 3], query[None, :, 3]) - np.maximum(boxes[:, None, 1], query[None, :, 1])
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    if criterion == 0:
        union = np.broadcast_to(area[:, None], inter.shape)
    else:
        area_q = (query[:, 2] - query[:, 0]) * (query[:, 3] - query[:, 1])
        union = area[:, None] + area_q[None, :] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / union, 0.0)


# ----------------------------------------------------------------------------- cleaning


@dataclass(frozen=True)
class _Cleaned:
    """One frame for one class and area: ignore flags (0 counts, 1 ignored, -1 not this class)."""

    num_valid_gt: int
    ignored_gt: np.ndarray
    ignored_dt: np.ndarray
    dont_care: np.ndarray  # [D, 4] 2D boxes


def _outside_corridor(location: np.ndarray) -> np.ndarray:
    x, z = location[:, 0], location[:, 2]
    return (x < CORRIDOR_X[0]) | (x > CORRIDOR_X[1]) | (z > CORRIDOR_Z)


def clean(gt: Labels, dt: Labels, cls: EvalClass, corridor: bool) -> _Cleaned:
    """The devkit's ``clean_data`` for one frame."""
    name = cls.name.lower()
    gt_names = np.array([str(n).lower() for n in gt.name])
    valid = np.where(gt_names == name, 1, np.where(np.isin(gt_names, [n.lower() for n in cls.neighbours]), 0, -1))
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    ignore = (gt.occluded > MAX_OCCLUSION) | (height <= MIN_HEIGHT_PX)
    if corridor:
        ignore |= _outside_corridor(gt.location)
    ignored_gt = np.where((valid == 1) & ~ignore, 0, np.where((valid == 0) | ((valid == 1) & ignore), 1, -1))
    dont_care = gt.bbox[np.array([str(n) == DONT_CARE for n in gt.name], bool)].reshape(-1, 4)
    dt_height = np.abs(dt.bbox[:, 3] - dt.bbox[:, 1])
    small = dt_height < MIN_HEIGHT_PX
    outside = _outside_corridor(dt.location) if corridor else np.zeros(len(dt), bool)
    same = np.array([str(n).lower() == name for n in dt.name], bool)
    ignored_dt = np.where(small | outside, 1, np.where(same, 0, -1))
    return _Cleaned(int(np.sum(ignored_gt == 0)), ignored_gt.astype(np.int64), ignored_dt.astype(np.int64), dont_care)


# ----------------------------------------------------------------------------- statistics


@dataclass
class _Stats:
    tp: int = 0
    fp: int = 0
    fn: int = 0
    similarity: float = 0.0
    thresholds: tuple = ()


def statistics(
    overlap: np.ndarray,
    gt_alpha: np.ndarray,
    dt_alpha: np.ndarray,
    dt_score: np.ndarray,
    dt_bbox: np.ndarray,
    c: _Cleaned,
    metric: str,
    min_overlap: float,
    thresh: float = 0.0,
    compute_fp: bool = False,
    compute_aos: bool = False,
) -> _Stats:
    """The devkit's ``compute_statistics_jit`` for one frame: greedy matching of each ground-truth
    box, in order, to an unassigned detection (``overlap`` [n_dt, n_gt])."""
    n_dt = len(dt_score)
    assigned = np.zeros(n_dt, bool)
    below = (dt_score < thresh) if compute_fp else np.zeros(n_dt, bool)
    usable_base = (c.ignored_dt != -1) & ~below
    tp = fp = fn = 0
    scores, deltas = [], []
    for i in np.flatnonzero(c.ignored_gt != -1):
        cand = usable_base & ~assigned & (overlap[:, i] > min_overlap)
        det = -1
        if cand.any():
            if not compute_fp:
                idx = np.flatnonzero(cand)
                det = int(idx[np.argmax(dt_score[idx])])  # first of the best scores
            else:
                counted = cand & (c.ignored_dt == 0)
                if counted.any():
                    idx = np.flatnonzero(counted)
                    det = int(idx[np.argmax(overlap[idx, i])])  # first of the largest overlaps
                else:
                    det = int(np.flatnonzero(cand)[0])  # the first ignored detection
        if det < 0:
            if c.ignored_gt[i] == 0:
                fn += 1
        elif c.ignored_gt[i] == 1 or c.ignored_dt[det] == 1:
            assigned[det] = True
        else:
            tp += 1
            scores.append(dt_score[det])
            if compute_aos:
                deltas.append(gt_alpha[i] - dt_alpha[det])
            assigned[det] = True
    similarity = 0.0
    if compute_fp:
        fp = int(np.sum(~(assigned | (c.ignored_dt == -1) | (c.ignored_dt == 1) | below)))
        if metric == "bbox" and len(c.dont_care):
            in_dc = image_box_overlap(dt_bbox, c.dont_care, 0)
            stuff = 0
            for k in range(len(c.dont_care)):
                hit = ~assigned & (c.ignored_dt == 0) & ~below & (in_dc[:, k] > min_overlap)
                assigned |= hit
                stuff += int(hit.sum())
            fp -= stuff
        if compute_aos:
            similarity = float(np.sum((1.0 + np.cos(deltas)) / 2.0)) if (tp > 0 or fp > 0) else -1.0
    return _Stats(tp, fp, fn, similarity, tuple(scores))


def recall_thresholds(scores: np.ndarray, num_gt: int, num_sample_pts: int = N_SAMPLE_PTS) -> np.ndarray:
    """The devkit's ``get_thresholds``: the true-positive scores, highest first, kept where recall
    passes the next of ``num_sample_pts`` evenly spaced positions. The devkit walks every score;
    this finds each kept one at once (the skip test is monotone in the rank), with the devkit's
    own float operations, so the result is the same."""
    scores = np.sort(np.asarray(scores, np.float64))[::-1]
    n = len(scores)
    if n == 0:
        return np.zeros(0, np.float64)
    rank = np.arange(n)
    left = (rank + 1) / num_gt
    right = np.where(rank < n - 1, (rank + 2) / num_gt, left)
    kept, current, last = [], 0.0, -1
    while last < n - 1:
        keep = ~((right - current) < (current - left))
        keep[n - 1] = True  # the last score is always kept
        keep[: last + 1] = False
        last = int(np.argmax(keep))
        kept.append(last)
        current += 1.0 / (num_sample_pts - 1.0)
    return scores[kept]


@dataclass(frozen=True)
class ClassCurve:
    """One class, area and metric: precision, recall and orientation similarity at the 41
    positions (after the running maximum; the first ``filled`` hold thresholds, the rest 0), and
    the number of counted ground-truth boxes."""

    precision: np.ndarray
    recall: np.ndarray
    orientation: np.ndarray | None
    num_gt: int
    filled: int = 0
    frames: "FrameTable | None" = None  # per frame, for the bootstrap (:func:`resampled_ap`)

    @property
    def ap11(self) -> float:
        """11-point AP (VoD's reported figure), %."""
        return float(np.sum(self.precision[0::4]) / 11 * 100)

    @property
    def ap40(self) -> float:
        """40-point AP, %."""
        return float(np.sum(self.precision[1:]) / 40 * 100)

    @property
    def aos11(self) -> float | None:
        return None if self.orientation is None else float(np.sum(self.orientation[0::4]) / 11 * 100)

    @property
    def aos40(self) -> float | None:
        return None if self.orientation is None else float(np.sum(self.orientation[1:]) / 40 * 100)


def class_curve(
    gts: list[Labels],
    dts: list[Labels],
    cls: EvalClass,
    metric: str,
    corridor: bool,
    frame_overlaps: list[np.ndarray] | None = None,
    table: bool = False,
) -> ClassCurve:
    """The devkit's ``eval_class`` for one class, metric and area over all frames; ``table``
    keeps the per-frame :class:`FrameTable` the bootstrap resamples."""
    if len(gts) != len(dts):
        raise ValueError(f"{len(gts)} ground-truth frames but {len(dts)} detection frames")
    min_overlap = cls.min_iou_image if metric == "bbox" else cls.min_iou
    aos = metric == "bbox"
    ovs = frame_overlaps if frame_overlaps is not None else [overlaps(metric, d, g) for g, d in zip(gts, dts)]
    cleaned = [clean(g, d, cls, corridor) for g, d in zip(gts, dts)]
    num_gt = sum(c.num_valid_gt for c in cleaned)
    found = [
        np.asarray(statistics(ov, g.alpha, d.alpha, d.score, d.bbox, c, metric, min_overlap).thresholds, np.float64)
        for g, d, c, ov in zip(gts, dts, cleaned, ovs)
    ]
    thresholds = recall_thresholds(np.concatenate(found or [np.zeros(0)]), num_gt) if num_gt else np.zeros(0)
    pr = np.zeros((len(thresholds), 4))
    for g, d, c, ov in zip(gts, dts, cleaned, ovs):
        for t, thresh in enumerate(thresholds):
            s = statistics(ov, g.alpha, d.alpha, d.score, d.bbox, c, metric, min_overlap, thresh, True, aos)
            pr[t] += (s.tp, s.fp, s.fn, s.similarity if s.similarity != -1 else 0.0)
    precision, recall, orientation = _curve(pr, aos)
    frames = None
    if table:
        cuts = [np.unique(np.asarray(d.score, np.float64)) for d in dts]
        counts = [
            np.array(
                [
                    _counts(statistics(ov, g.alpha, d.alpha, d.score, d.bbox, c, metric, min_overlap, t, True))
                    for t in (*cut, np.inf)
                ],
                np.float64,
            ).reshape(-1, 3)
            for g, d, c, ov, cut in zip(gts, dts, cleaned, ovs, cuts)
        ]
        frames = FrameTable(
            tuple(found), np.array([c.num_valid_gt for c in cleaned], np.int64), tuple(cuts), tuple(counts)
        )
    return ClassCurve(precision, recall, orientation, num_gt, len(thresholds), frames)


def _counts(s: _Stats) -> tuple[int, int, int]:
    return s.tp, s.fp, s.fn


def _curve(pr: np.ndarray, aos: bool = False):
    """Precision, recall (and orientation similarity) at the 41 positions from the summed
    (tp, fp, fn[, similarity]) at each threshold [T, 3 or 4], each a running maximum from the right."""
    precision, recall = np.zeros(N_SAMPLE_PTS), np.zeros(N_SAMPLE_PTS)
    orientation = np.zeros(N_SAMPLE_PTS) if aos else None
    n = len(pr)
    with np.errstate(divide="ignore", invalid="ignore"):
        recall[:n] = pr[:, 0] / (pr[:, 0] + pr[:, 2])
        precision[:n] = pr[:, 0] / (pr[:, 0] + pr[:, 1])
        if aos:
            orientation[:n] = pr[:, 3] / (pr[:, 0] + pr[:, 1])
    for i in range(n):
        precision[i] = np.max(precision[i:])
        recall[i] = np.max(recall[i:])
        if aos:
            orientation[i] = np.max(orientation[i:])
    return precision, recall, orientation


@dataclass(frozen=True)
class FrameTable:
    """One class, metric and area, frame by frame: what the devkit's AP of any resample of the
    frames needs. ``found[f]``: the scores of frame f's true positives in the threshold pass;
    ``num_gt[f]``: its counted ground truth; ``cuts[f]``: its detections' distinct scores,
    ascending; ``counts[f]`` [len(cuts[f]) + 1, 3]: its (tp, fp, fn) when the detections scoring
    at least ``cuts[f][k]`` take part, the last row with none (a threshold above every score)."""

    found: tuple
    num_gt: np.ndarray
    cuts: tuple
    counts: tuple

    def __len__(self) -> int:
        return len(self.num_gt)


def bootstrap_rows(frames: int, samples: int = 1000, seed: int = 0) -> np.ndarray:
    """int64 [samples, frames]: frame indices drawn with replacement, one resample a row."""
    if frames == 0:
        return np.zeros((samples, 0), np.int64)
    return np.random.default_rng(seed).integers(0, frames, (samples, frames))


def resampled_ap(table: FrameTable, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(11-point AP, 40-point AP) in % [S] of each resample ``rows`` [S, F] of the frames: the
    devkit's AP on the frames of the row, thresholds recomputed on them (module docstring). Every
    threshold of a resample is one of the set's true-positive scores, so each frame's counts are
    looked up once for each of those scores, and a resample sums them with its frame weights."""
    ap11, ap40 = np.zeros(len(rows)), np.zeros(len(rows))
    found_frame = np.concatenate(
        [np.full(len(f), i, np.int64) for i, f in enumerate(table.found)] or [np.zeros(0, np.int64)]
    )
    found = np.concatenate(list(table.found) or [np.zeros(0)])
    candidates = np.unique(found)
    at = (
        np.stack([c[np.searchsorted(cut, candidates, side="left")] for cut, c in zip(table.cuts, table.counts)])
        if len(table)
        else np.zeros((0, len(candidates), 3))
    )  # [F, U, 3]
    for s, row in enumerate(rows):
        weight = np.bincount(row, minlength=len(table))
        num_gt = int(weight @ table.num_gt)
        if num_gt == 0:
            continue
        thresholds = recall_thresholds(np.repeat(found, weight[found_frame]), num_gt)
        pr = np.einsum("f,ftk->tk", weight.astype(np.float64), at[:, np.searchsorted(candidates, thresholds)])
        precision = _curve(pr)[0]
        ap11[s], ap40[s] = np.sum(precision[0::4]) / 11 * 100, np.sum(precision[1:]) / 40 * 100
    return ap11, ap40


def evaluate_frames(
    gts: list[Labels],
    dts: list[Labels],
    classes: tuple[EvalClass, ...],
    areas: tuple[str, ...] = AREAS,
    tables: tuple[str, ...] = (),
) -> dict[str, dict[str, dict[str, ClassCurve]]]:
    """area -> class name -> metric -> :class:`ClassCurve` over paired frames of ground truth
    and detections (camera-frame KITTI labels; detections carry scores); the metrics in
    ``tables`` keep their per-frame tables for the bootstrap."""
    ovs = {m: [overlaps(m, d, g) for g, d in zip(gts, dts)] for m in METRICS}
    return {
        area: {
            c.name: {m: class_curve(gts, dts, c, m, area == "corridor", ovs[m], m in tables) for m in METRICS}
            for c in classes
        }
        for area in areas
    }


def ap_table(curves: dict[str, dict[str, dict[str, ClassCurve]]]) -> dict[str, dict[str, dict[str, float]]]:
    """area -> class -> {3d, bev, aos, bbox} 11-point AP (%) and the same with ``_r40``."""
    out = {}
    for area, per_class in curves.items():
        out[area] = {}
        for cls, per_metric in per_class.items():
            row = {
                "3d": per_metric["3d"].ap11,
                "bev": per_metric["bev"].ap11,
                "aos": per_metric["bbox"].aos11,
                "bbox": per_metric["bbox"].ap11,
                "3d_r40": per_metric["3d"].ap40,
                "bev_r40": per_metric["bev"].ap40,
                "aos_r40": per_metric["bbox"].aos40,
                "bbox_r40": per_metric["bbox"].ap40,
                "num_gt": per_metric["3d"].num_gt,
            }
            out[area][cls] = row
    return out
