"""MAFF-Net's second stage trains as upstream's two-stage detector does (radaredge.training.roi_targets):
3-D IoU, the proposal target layer's sampling and soft labels, the canonical frame and its
residuals, the corner loss, the point head's labels, and a tiny two-stage card that learns."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import MAFFNET_TINY_FULL_CARD, invoke

from radaredge.models.maffnet.rcnn import decode_roi_residuals
from radaredge.ops.box_iou import bev_iou_reference, boxes_iou3d
from radaredge.training import roi_targets as rt
from radaredge.training.anchor_targets import encode_boxes


def _random_boxes(rng, n):
    centre = rng.uniform([-4, -4, -1], [4, 4, 1], (n, 3))
    size = rng.uniform([0.5, 0.5, 0.5], [4.5, 2.0, 2.0], (n, 3))
    return np.column_stack([centre, size, rng.uniform(-math.pi, math.pi, n)])


def _iou3d_reference(a, b):
    """Rotated BEV overlap (from the reference BEV IoU) times the z overlap, over the union volume."""
    iou_bev = bev_iou_reference(a, b)
    overlap = iou_bev * (a[3] * a[4] + b[3] * b[4]) / (1 + iou_bev)
    dz = max(min(a[2] + a[5] / 2, b[2] + b[5] / 2) - max(a[2] - a[5] / 2, b[2] - b[5] / 2), 0.0)
    inter = overlap * dz
    return inter / max(a[3] * a[4] * a[5] + b[3] * b[4] * b[5] - inter, 1e-6)


def test_iou3d_agrees_with_the_reference_bev_iou_and_z_overlap():
    rng = np.random.default_rng(0)
    a, b = _random_boxes(rng, 40), _random_boxes(rng, 30)
    b[:10] = a[:10] + rng.normal(0, 0.2, (10, 7))  # some heavy overlaps
    got = boxes_iou3d(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    want = np.array([[_iou3d_reference(x, y) for y in b] for x in a])
    assert (want > 0.3).sum() >= 10
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert boxes_iou3d(torch.from_numpy(a), torch.zeros(0, 7, dtype=torch.float64)).shape == (40, 0)


def _ious(fg, hard, easy):
    return torch.tensor([0.9] * fg + [0.3] * hard + [0.05] * easy)


@pytest.mark.parametrize(
    "fg, hard, easy, n_fg, n_hard",
    [
        (100, 300, 100, 64, 51),  # 64 fg of 100; bg 64: int(64 * 0.8) = 51 hard, 13 easy
        (10, 300, 100, 10, 94),  # few fg: the rest is background, int(118 * 0.8) hard
        (10, 5, 100, 10, 5),  # few hard: all background not hard is easy
        (10, 0, 100, 10, 0),
        (0, 20, 20, 0, 20),  # only background: min(int(128 * 0.8), 20) hard
        (7, 0, 0, 128, 0),  # only foreground: 128 draws with replacement
    ],
)
def test_roi_sampling_follows_the_proposal_target_layer(fg, hard, easy, n_fg, n_hard):
    iou = _ious(fg, hard, easy)
    keep = rt.subsample_rois(iou, rt.RoiSampling(), torch.Generator().manual_seed(0))
    got = iou[keep]
    assert len(keep) == 128
    assert int((got >= 0.55).sum()) == n_fg and int(((got >= 0.1) & (got < 0.55)).sum()) == n_hard
    assert bool((got[:n_fg] >= 0.55).all())  # foreground first
    if fg and (hard or easy):
        assert len(set(keep[:n_fg].tolist())) == n_fg  # foreground without replacement


def test_sampled_rois_get_same_class_ious_soft_labels_and_their_box():
    gt = torch.tensor([[10.0, 0, 0, 4, 2, 1.5, 0], [20.0, 5, 0, 0.8, 0.6, 1.7, 0]])
    gt_labels = torch.tensor([1, 2])
    shifts = [0.0, 0.4, 0.9, 1.5, 2.5]  # along x: IoU falls from 1
    rois = torch.stack(
        [gt[0] + torch.tensor([s, 0, 0, 0, 0, 0, 0]) for s in shifts]
        + [gt[1], gt[1] + torch.tensor([0.01, 0, 0, 0, 0, 0, 0])]
    )
    roi_labels = torch.tensor([1] * 5 + [2, 1])  # the last: a Car roi on a pedestrian
    iou, index = rt.max_iou_same_class(rois, roi_labels, gt, gt_labels)
    want = [1.0, 3.6 / 4.4, 3.1 / 4.9, 2.5 / 5.5, 1.5 / 6.5, 1.0, 0.0]  # 0.0: no Car box there
    np.testing.assert_allclose(iou.numpy(), want, atol=1e-6)
    assert index.tolist()[:6] == [0, 0, 0, 0, 0, 1]
    t = rt.sample_rois(
        rois, roi_labels, gt, gt_labels, rt.RoiSampling(roi_per_image=40), torch.Generator().manual_seed(0)
    )
    for roi, i, label, valid, box in zip(t["rois"], t["iou"], t["cls_labels"], t["reg_valid"], t["gt_of_rois"]):
        k = next(j for j in range(7) if torch.equal(rois[j], roi))
        i = float(i)
        assert i == pytest.approx(want[k])
        soft = 1.0 if i > 0.75 else 0.0 if i < 0.25 else (i - 0.25) / 0.5  # CLS_SCORE_TYPE roi_iou
        assert float(label) == pytest.approx(soft) and bool(valid) == (i > 0.55)
        assert torch.equal(box, gt[int(index[k])])
    assert len(t["rois"]) == 40 and 0 < float(t["cls_labels"].sum()) < 40


def test_residuals_in_the_canonical_frame_decode_back_to_the_box():
    rng = np.random.default_rng(1)
    rois = torch.from_numpy(_random_boxes(rng, 50))
    gt = rois + torch.from_numpy(rng.normal(0, [0.3, 0.3, 0.1, 0.2, 0.1, 0.1, 0.3], (50, 7)))
    gt[:, 3:6] = gt[:, 3:6].abs() + 0.1
    gt[25:, 6] += math.pi  # half of them point backwards
    local = rt.canonical_boxes(rois, gt)
    assert bool((local[:, 6].abs() <= math.pi / 2).all())
    centred = torch.cat([torch.zeros(50, 3, dtype=rois.dtype), rois[:, 3:6], torch.zeros(50, 1, dtype=rois.dtype)], 1)
    back = decode_roi_residuals(encode_boxes(local, centred), rois)
    np.testing.assert_allclose(back[:, :6].numpy(), gt[:, :6].numpy(), atol=1e-9)
    turn = torch.remainder(back[:, 6] - gt[:, 6], math.pi)  # the heading up to a half turn
    assert bool(((turn < 1e-9) | (turn > math.pi - 1e-9)).all())
    assert float(rt.corner_loss(back, gt).max()) < 1e-9  # the flip costs no corner loss
    moved = back + torch.tensor([0.5, 0, 0, 0, 0, 0, 0], dtype=back.dtype)  # every corner 0.5 m off
    loss = rt.corner_loss(moved, gt)  # smooth-L1(0.5, beta 1) = 0.125,
    assert float(loss.max()) <= 0.125 + 1e-9 and float(loss.median()) == pytest.approx(0.125)  # less for a
    # small box's nearer flipped corner


def test_point_labels_mark_inside_shell_and_outside():
    gt = torch.tensor([[5.0, 0, 0, 4, 2, 2, math.pi / 2]])  # 4 m along y, 2 m along x
    points = torch.tensor([[5.0, 1.9, 0], [5.0, 2.05, 0], [5.0, 2.2, 0], [5.95, 0, 0], [6.05, 0, 0], [5, 0, 1.05]])
    labels = rt.point_labels(points, torch.ones(6, dtype=torch.bool), gt)
    assert labels.tolist() == [1, -1, 0, 1, -1, -1]
    assert rt.point_labels(points, torch.zeros(6, dtype=torch.bool), gt).tolist() == [-1] * 6


def test_roi_head_loss_is_zero_for_a_perfect_refinement_and_grows_with_error():
    rois = torch.tensor([[10.0, 2, 0, 4, 2, 1.5, 0.3], [20.0, -2, 0, 4, 2, 1.5, -1.0]])
    gt = rois + torch.tensor([[0.3, -0.2, 0.1, 0.2, 0.1, 0.0, 0.2], [0.0, 0, 0, 0, 0, 0, 0]])
    t = {
        "rois": rois,
        "gt_of_rois": gt,
        "reg_valid": torch.tensor([True, True]),
        "cls_labels": torch.tensor([1.0, 1.0]),
    }
    centred = torch.cat([torch.zeros(2, 3), rois[:, 3:6], torch.zeros(2, 1)], 1)
    perfect = encode_boxes(rt.canonical_boxes(rois, gt), centred)
    terms = rt.roi_head_loss(torch.tensor([20.0, 20.0]), perfect, t)
    assert float(terms["rcnn_reg"]) < 1e-6 and float(terms["rcnn_corner"]) < 1e-5 and float(terms["rcnn_cls"]) < 1e-6
    worse = rt.roi_head_loss(torch.tensor([0.0, 0.0]), perfect + 0.3, t)
    assert all(float(worse[k]) > 0.05 for k in worse)


def test_a_two_stage_card_trains_and_its_losses_fall(tmp_path):
    """The tiny two-stage card, 8 epochs on 8 frames (validated on the same frames, at the start and
    the end): the total loss and the stage-two classification terms fall, validation AP rises above
    the seeded network's, and the best checkpoint exports."""
    data = tmp_path / "set"
    res = invoke("make-benchmark", "--task", "detection", "--out", data, "--drives", 3, "--frames", 20, "--seed", 3)
    assert res.exit_code == 0, res.output
    res = invoke(
        "train",
        "--model",
        "maffnet-tiny-full",
        "--config",
        MAFFNET_TINY_FULL_CARD,
        "--data",
        data,
        "--output",
        tmp_path / "run",
        "--json",
        "--epochs",
        8,
        "--batch-size",
        2,
        "--lr",
        0.003,
        "--set",
        "train_frames=8",
        "--validation",
        "train",
        "--set",
        "val_frames=8",
        "--set",
        "val_every=8",
        "--set",
        "augment=false",
        "--set",
        "train_proposals=64",
        "--set",
        "roi_per_image=32",
    )
    assert res.exit_code == 0, res.output
    rows = json.loads(res.stdout)["epochs"]
    assert rows[-1]["loss"] < 0.7 * rows[1]["loss"], [r["loss"] for r in rows]
    for term in ("loss_point", "loss_rcnn_cls"):
        assert rows[-1][term] < rows[1][term], (term, [r[term] for r in rows[1:]])
    assert any(r["loss_rcnn_reg"] > 0 for r in rows[1:])  # foreground rois were regressed
    assert rows[-1]["mAP3d"] > rows[0]["mAP3d"] + 1.0, (rows[0]["mAP3d"], rows[-1]["mAP3d"])
    res = invoke(
        "export",
        "--model",
        "maffnet-tiny-full",
        "--config",
        MAFFNET_TINY_FULL_CARD,
        "--checkpoint",
        tmp_path / "run" / "best.pth",
        "--output",
        tmp_path / "t.onnx",
    )
    assert res.exit_code == 0, res.output
