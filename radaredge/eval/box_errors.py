"""Box errors of matched detections: where a detector's boxes go wrong, beside its AP.

AP at a 3D IoU threshold folds every error into one number; a detector that finds the objects
in bird's-eye view but places them at the wrong height scores a high BEV AP and a low 3D AP,
and only the errors tell why. Matching follows nuScenes' true-positive metrics: the detections
of a class, over all frames in descending score, each take the nearest still unmatched
ground-truth box of that class whose centre lies within ``MATCH_DISTANCE`` m in bird's-eye view.
Over the matched pairs, radar frame (x forward, z up), metres and degrees:

* ``xy``: the mean BEV distance between the centres;
* ``dz``: the mean signed error of the centre's height (detection minus ground truth), a bias;
  ``abs_dz`` its mean absolute value;
* ``abs_dl``, ``abs_dw``, ``abs_dh``: the mean absolute errors of length, width and height;
* ``heading_deg``: the mean absolute heading error, wrapped to [0, 180].
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

MATCH_DISTANCE = 2.0  # m, nuScenes' centre distance for its true-positive metrics


@dataclass(frozen=True)
class BoxErrors:
    """One class's matched pairs (module docstring); errors are NaN without a match."""

    ground_truth: int
    matched: int
    xy: float
    dz: float
    abs_dz: float
    abs_dl: float
    abs_dw: float
    abs_dh: float
    heading_deg: float

    def to_dict(self) -> dict:
        """The fields, None for an error without a match (JSON has no NaN)."""
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in asdict(self).items()}


def match_frame(dt: np.ndarray, gt: np.ndarray) -> list[tuple[int, int]]:
    """(detection, ground truth) index pairs of one frame and class: detections ``dt`` [D, 7]
    in the order given (descending score) each take the nearest unmatched box of ``gt`` [G, 7]
    within ``MATCH_DISTANCE`` m in bird's-eye view."""
    free = np.ones(len(gt), bool)
    pairs = []
    for i, box in enumerate(dt):
        if not free.any():
            break
        dist = np.where(free, np.hypot(gt[:, 0] - box[0], gt[:, 1] - box[1]), np.inf)
        j = int(np.argmin(dist))
        if dist[j] <= MATCH_DISTANCE:
            free[j] = False
            pairs.append((i, j))
    return pairs


def class_box_errors(frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> BoxErrors:
    """The errors (module docstring) of one class over ``frames``: per frame (detections [D, 7],
    their scores [D], ground truth [G, 7]), radar-frame boxes (x, y, z centre, l, w, h, heading).
    A frame's detections are matched in descending score, as over all frames together: a
    detection only competes for the boxes of its own frame."""
    found, truth = [], []
    for boxes, scores, gt in frames:
        order = np.argsort(-np.asarray(scores), kind="stable")
        for i, j in match_frame(np.asarray(boxes, np.float64).reshape(-1, 7)[order], gt):
            found.append(boxes[order[i]])
            truth.append(gt[j])
    total = sum(len(gt) for _, _, gt in frames)
    if not found:
        return BoxErrors(total, 0, *([float("nan")] * 7))
    d, g = np.asarray(found, np.float64), np.asarray(truth, np.float64)
    err = d - g
    heading = np.abs((err[:, 6] + np.pi) % (2 * np.pi) - np.pi)
    return BoxErrors(
        total,
        len(d),
        float(np.hypot(err[:, 0], err[:, 1]).mean()),
        float(err[:, 2].mean()),
        float(np.abs(err[:, 2]).mean()),
        float(np.abs(err[:, 3]).mean()),
        float(np.abs(err[:, 4]).mean()),
        float(np.abs(err[:, 5]).mean()),
        float(np.degrees(heading).mean()),
    )


def box_error_lines(errors: dict[str, dict[str, BoxErrors]]) -> list[str]:
    """Text: a row per backend and class (``errors[backend][class]``)."""
    head = (
        f"{'box errors':<18}{'class':<12}{'matched':>12}{'xy m':>8}{'dz m':>8}{'|dz| m':>8}{'|dl| m':>8}"
        f"{'|dw| m':>8}{'|dh| m':>8}{'heading':>9}"
    )
    lines = [head]
    for backend, per_class in errors.items():
        for cls, e in per_class.items():
            lines.append(
                f"{backend:<18}{cls:<12}{f'{e.matched}/{e.ground_truth}':>12}{e.xy:>8.2f}{e.dz:>+8.2f}"
                f"{e.abs_dz:>8.2f}{e.abs_dl:>8.2f}{e.abs_dw:>8.2f}{e.abs_dh:>8.2f}{e.heading_deg:>8.1f}°"
            )
    return lines
