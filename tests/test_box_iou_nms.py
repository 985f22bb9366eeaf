"""Rotated BEV IoU and class-agnostic NMS: export formulation == reference, in torch and onnxruntime."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radaredge.ops.box_iou import bev_iou_matrix_reference, bev_iou_paired, bev_iou_reference, bev_iou_upper_bound
from radaredge.ops.nms import (
    NmsConfig,
    class_agnostic_nms,
    class_agnostic_nms_eager,
    class_agnostic_nms_reference,
    greedy_nms_reference,
)


def random_boxes(rng, n, spread=4.0):
    b = np.zeros((n, 7), np.float32)
    b[:, :2] = rng.uniform(-spread, spread, (n, 2))
    b[:, 2] = rng.normal(0, 1, n)
    b[:, 3:6] = rng.uniform(0.3, 5.0, (n, 3))
    b[:, 6] = rng.uniform(-math.pi, math.pi, n)
    return b


def special_pairs(rng):
    """Identical, rotated by 90 deg, contained, flipped by pi, edge-touching, far apart."""
    a = random_boxes(rng, 60)
    b = a.copy()
    b[10:20, 6] += math.pi / 2
    b[20:30, 3:5] *= 0.5
    b[30:40, 6] += math.pi
    b[40:50, 0] += np.cos(a[40:50, 6]) * a[40:50, 3]  # shifted by its length along its heading
    b[40:50, 1] += np.sin(a[40:50, 6]) * a[40:50, 3]
    b[50:60, :2] += 50.0
    return a, b


def test_iou_known_values():
    unit = np.array([0, 0, 0, 1, 1, 1, 0], np.float32)
    half = unit.copy()
    half[0] = 0.5
    diamond = unit.copy()
    diamond[6] = math.pi / 4
    assert bev_iou_reference(unit, half) == pytest.approx(1 / 3)
    # unit square vs the same square rotated 45 deg: overlap = regular octagon of area 2(sqrt(2)-1)
    octagon = 2 * (math.sqrt(2) - 1)
    assert bev_iou_reference(unit, diamond) == pytest.approx(octagon / (2 - octagon))
    got = bev_iou_paired(torch.from_numpy(np.stack([unit, unit])), torch.from_numpy(np.stack([half, diamond]))).numpy()
    np.testing.assert_allclose(got, [1 / 3, octagon / (2 - octagon)], atol=1e-4)  # float32: tol x perimeter


@pytest.mark.parametrize("dtype,atol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_iou_matches_reference(dtype, atol):
    rng = np.random.default_rng(0)
    a, b = special_pairs(rng)
    ra, rb = random_boxes(rng, 2000), random_boxes(rng, 2000)
    a, b = np.concatenate([a, ra]), np.concatenate([b, rb])
    got = bev_iou_paired(torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype)).numpy()
    ref = np.array([bev_iou_reference(x, y) for x, y in zip(a.astype(np.float64), b.astype(np.float64))])
    assert np.abs(got - ref).max() <= atol
    # the special pairs are built in float32, so "identical" and "touching" hold to ~1e-6
    np.testing.assert_allclose(got[:10], 1.0, atol=1e-5)  # identical boxes
    np.testing.assert_allclose(got[30:40], 1.0, atol=1e-5)  # same footprint, flipped
    np.testing.assert_allclose(got[40:60], 0.0, atol=1e-5)  # touching or far apart


def test_iou_upper_bound_never_falls_below_the_iou():
    """The bound the NMS filters pairs with: >= the reference IoU on every pair (special, random,
    close), equal to it for axis-aligned boxes, 0 for disjoint rectangles."""
    rng = np.random.default_rng(4)
    a, b = special_pairs(rng)
    close = random_boxes(rng, 3000, spread=1.0)
    a, b = np.concatenate([a, random_boxes(rng, 3000, 1.0)]), np.concatenate([b, close])
    square = random_boxes(rng, 500, 2.0)
    square[:, 6] = rng.choice([0.0, math.pi / 2, -math.pi, math.pi], 500)
    square_b = random_boxes(rng, 500, 2.0)
    square_b[:, 6] = rng.choice([0.0, math.pi / 2], 500)
    a, b = np.concatenate([a, square]).astype(np.float64), np.concatenate([b, square_b]).astype(np.float64)
    bound = bev_iou_upper_bound(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    ref = np.array([bev_iou_reference(x, y) for x, y in zip(a, b)])
    assert (bound >= ref - 1e-12).all() and (bound <= 1 + 1e-12).all()
    assert (bound > ref + 0.05).sum() > 100  # a bound, not the IoU itself
    np.testing.assert_allclose(bound[-500:], ref[-500:], atol=1e-6)  # axis-aligned (to float32 headings)
    assert (bound[50:60] == 0).all()  # far apart


def test_iou_matrix_reference_is_symmetric():
    rng = np.random.default_rng(1)
    b = random_boxes(rng, 30, spread=2.0)
    m = bev_iou_matrix_reference(b, b)
    np.testing.assert_allclose(m, m.T, atol=1e-12)
    np.testing.assert_allclose(np.diag(m), 1.0, atol=1e-12)


def test_greedy_reference_by_hand():
    boxes = np.array(
        [
            [0, 0, 0, 2, 2, 1, 0],  # kept
            [0.2, 0, 0, 2, 2, 1, 0],  # IoU 0.82 with 0: suppressed
            [5, 0, 0, 2, 2, 1, 0],  # far: kept
            [1.9, 0, 0, 2, 2, 1, 0],
        ],  # IoU 0.026 with 0: kept at 0.1
        np.float64,
    )
    assert greedy_nms_reference(boxes, 0.1) == [0, 2, 3]
    assert greedy_nms_reference(boxes, 0.9) == [0, 1, 2, 3]


def _nms_cases(rng):
    for i in range(6):
        boxes = random_boxes(rng, 1500, spread=15.0)
        scores = rng.random(1500).astype(np.float32)
        if i % 2:
            scores[:400] = 0.5  # a block of equal scores: lower index first
        yield boxes, scores


@pytest.mark.parametrize("config", [NmsConfig(0.1, 0.1, 400, 100), NmsConfig(0.3, 0.5, 4096, 500)])
def test_nms_matches_reference_in_torch(config):
    rng = np.random.default_rng(2)
    for boxes, scores in _nms_cases(rng):
        got = class_agnostic_nms(torch.tensor(boxes), torch.tensor(scores), config).numpy()
        ref = class_agnostic_nms_reference(boxes, scores, config)
        assert got.tolist() == ref.tolist()
        eager = class_agnostic_nms_eager(torch.tensor(boxes), torch.tensor(scores), config).numpy()
        assert eager.tolist() == ref.tolist()  # training's validation NMS: the same indices


class _Nms(torch.nn.Module):
    def __init__(self, config):
        super().__init__()
        self.config = config

    def forward(self, boxes, scores):
        return class_agnostic_nms(boxes, scores, self.config)


def test_nms_onnx_matches_reference(onnx_roundtrip):
    config = NmsConfig(0.1, 0.1, 500, 120)
    rng = np.random.default_rng(3)
    boxes, scores = next(_nms_cases(rng))
    rt = onnx_roundtrip(
        _Nms(config),
        {"boxes": torch.tensor(boxes), "scores": torch.tensor(scores)},
        ["selected"],
        {"boxes": {0: "anchors"}, "scores": {0: "anchors"}},
    )
    few = []  # 0, 1 and 2 boxes above the threshold: the data-dependent
    for n_above in (0, 1, 2):  # candidate count may not break the graph's shapes
        sc = np.full(60, 0.05, np.float32)
        sc[rng.choice(60, n_above, replace=False)] = 0.9
        few.append((random_boxes(rng, 60), sc))
    cluster = random_boxes(rng, 300, spread=1.0)  # a dense head: hundreds of overlapping boxes
    few.append((cluster, rng.random(300).astype(np.float32)))
    for boxes, scores in list(_nms_cases(rng)) + few:
        _, got = rt({"boxes": torch.tensor(boxes), "scores": torch.tensor(scores)})
        assert got["selected"].tolist() == class_agnostic_nms_reference(boxes, scores, config).tolist()
