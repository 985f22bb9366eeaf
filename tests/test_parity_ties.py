"""Discrete decisions in parity: proposals compared as sets where they are taken, near ties named.

A proposal NMS over scores within float noise of each other can keep either box; the parity
check judges the graph's proposals against the reference proposal layer run on the graph's own
anchors (exact), and end to end accepts a difference only when the reference's NMS has a
decision within float noise, which the report names.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from radaredge.models.comparators import Proposals
from radaredge.ops.nms import NmsConfig, class_agnostic_nms_reference, describe_tie, near_ties


def _box(x, y, dx=4.0, dy=2.0, heading=0.0):
    return [x, y, 0.0, dx, dy, 1.5, heading]


def _outputs(boxes, logits, post_max=4):
    """Proposal-layer outputs of the reference NMS on ``boxes``/``logits`` [A, 1]."""
    boxes, logits = np.asarray(boxes, np.float32), np.asarray(logits, np.float32)
    cfg = NmsConfig(score_thresh=-math.inf, iou_thresh=0.7, pre_max=16, post_max=post_max)
    sel = class_agnostic_nms_reference(boxes, logits.max(-1), cfg)
    rois = np.zeros((post_max, 7), np.float32)
    rois[: len(sel)] = boxes[sel]
    labels = np.zeros(post_max, np.int64)
    labels[: len(sel)] = 1
    valid = np.arange(post_max) < len(sel)
    scores = np.linspace(0.9, 0.5, post_max).astype(np.float32)
    return {
        "rois": rois,
        "roi_labels": labels,
        "roi_valid": valid,
        "anchor_logits": logits,
        "anchor_boxes": boxes,
        "rcnn_scores": scores,
    }


def _comparator(**kw):
    return Proposals("rois", iou_thresh=0.7, pre_max=16, post_max=4, **kw)


def test_near_ties_name_an_order_flip_between_overlapping_boxes():
    boxes = [_box(0, 0), _box(0.1, 0), _box(20, 0)]
    scores = [2.0, 2.0 + 3e-6, 1.0]  # boxes 0 and 1 overlap (IoU 0.95), scores within noise
    ties = near_ties(
        np.array(boxes), np.array(scores, np.float32), NmsConfig(-math.inf, 0.7, 16, 4), (1e-4, 1e-3), 1e-3
    )
    assert [(t["decision"], sorted(t["anchors"])) for t in ties] == [("order", [0, 1])]
    assert "order of anchors 1 and 0" in describe_tie(ties[0])


def test_near_ties_name_an_overlap_at_the_threshold_and_nothing_when_clear():
    cfg = NmsConfig(-math.inf, 0.7, 16, 4)
    clear = near_ties(np.array([_box(0, 0), _box(30, 0)]), np.array([2.0, 1.0], np.float32), cfg, (1e-4, 1e-3), 1e-3)
    assert clear == []
    # two 4 x 2 m boxes shifted along x by d overlap (4 - d) / (4 + d): IoU 0.7 at d = 12 / 17 m
    d = 12 / 17
    ties = near_ties(np.array([_box(0, 0), _box(d, 0)]), np.array([2.0, 1.0], np.float32), cfg, (1e-4, 1e-3), 1e-3)
    assert [t["decision"] for t in ties] == ["overlap"] and abs(ties[0]["values"][0] - 0.7) < 1e-6


def test_near_ties_name_the_post_max_cut():
    boxes = [_box(10 * i, 0) for i in range(6)]
    scores = np.array([5, 4, 3, 2, 2 + 1e-6, 1], np.float32)[[0, 1, 2, 4, 3, 5]]
    ties = near_ties(np.array(boxes), scores, NmsConfig(-math.inf, 0.7, 16, 4), (1e-4, 1e-3), 1e-3)
    assert [t["decision"] for t in ties] == ["post_max cut"]


def test_proposals_swapped_slots_pass_as_a_set():
    boxes = [_box(0, 0), _box(10, 0), _box(20, 0)]
    ref = _outputs(boxes, [[3.0], [2.0], [1.0]])
    got = {k: v.copy() for k, v in ref.items()}
    got["rois"][[0, 1]] = got["rois"][[1, 0]]
    got["rcnn_scores"][[0, 1]] = got["rcnn_scores"][[1, 0]]
    c = _comparator().compare(got, ref, post=None)
    assert c and c.end_to_end["unmatched"] == 0 and c.end_to_end["rcnn_score_diff"] == 0.0


def test_proposals_judged_on_the_graphs_own_anchors():
    boxes = [_box(0, 0), _box(0.1, 0), _box(20, 0)]
    ref = _outputs(boxes, [[2.0], [2.0 + 3e-6], [1.0]])  # the reference keeps anchor 1
    got = _outputs(boxes, [[2.0 + 3e-6], [2.0], [1.0]])  # noise: the graph keeps anchor 0
    post = _outputs(boxes, got["anchor_logits"])  # the reference layer on the graph's anchors
    c = _comparator().compare(got, ref, post)
    assert c, c.reason  # a near tie explains the end-to-end flip
    assert c.end_to_end["unmatched"] == 2 and c.end_to_end["near_ties"][0]["decision"] == "order"
    bad = {k: v.copy() for k, v in got.items()}
    bad["rois"][0, 0] += 0.5  # the graph's NMS picked a box it should not
    c = _comparator().compare(bad, ref, post)
    assert not c and "differ from the reference proposal layer" in c.reason


def test_an_unexplained_end_to_end_difference_fails():
    boxes = [_box(0, 0), _box(10, 0), _box(20, 0)]
    ref = _outputs(boxes, [[3.0], [2.0], [1.0]])
    moved = [_box(0, 0), _box(10, 5), _box(20, 0)]  # a box 5 m away: no float noise does that
    got = _outputs(moved, [[3.0], [2.0], [1.0]])
    c = _comparator().compare(got, ref, post=_outputs(moved, got["anchor_logits"]))
    assert not c and "no decision of the reference's proposal NMS is within float noise" in c.reason
    assert _comparator().quantized().compare(got, ref, post=_outputs(moved, got["anchor_logits"]))  # int8: reported


@pytest.mark.parametrize("seed", range(5))
def test_near_ties_explain_every_flip_under_noise(seed):
    """Random overlapping proposals; the graph's logits and boxes differ from the reference's by
    noise below the tolerance: whenever the two NMS results differ, a near tie is named."""
    rng = np.random.default_rng(seed)
    n = 40
    centres = rng.uniform(0, 12, (n, 2))
    boxes = np.array([_box(x, y, 4, 2, h) for (x, y), h in zip(centres, rng.uniform(-np.pi, np.pi, n))], np.float32)
    logits = rng.choice([1.0, 1.5, 2.0], (n, 1)).astype(np.float32) + rng.normal(0, 1e-5, (n, 1)).astype(np.float32)
    ref = _outputs(boxes, logits, post_max=8)
    noisy = logits + rng.normal(0, 2e-5, logits.shape).astype(np.float32)
    got = _outputs(boxes + rng.normal(0, 1e-6, boxes.shape).astype(np.float32), noisy, post_max=8)
    c = Proposals("rois", iou_thresh=0.7, pre_max=16, post_max=8).compare(got, ref, post=None)
    assert c, c.reason
