"""radaredge.training.anchor_targets: OpenPCDet's target assignment, residual coding and head loss
on the tiny MAFF-Net card (MAFF-Net training is only as good as these)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from radaredge.cards import load_card
from radaredge.errors import ConfigError
from radaredge.models import create_model
from radaredge.models.maffnet.model import decode_boxes
from radaredge.training import anchor_targets as fh

CARD = load_card(Path(__file__).parent / "cards" / "maffnet-tiny.yaml")


def _setup():
    model = create_model(CARD)
    return model, fh.anchor_classes(CARD, len(model.anchors))


def test_anchor_classes_follow_the_head_layout():
    model, classes = _setup()
    # per location: Car x 2 rotations, Pedestrian x 2, Cyclist x 2; sizes tell the classes apart
    assert classes[:6].tolist() == [0, 0, 1, 1, 2, 2] and len(classes) == len(model.anchors)
    lengths = model.anchors[:, 3]
    assert torch.all(lengths[classes == 0] == 3.9) and torch.all(lengths[classes == 1] == 0.8)


def test_encode_inverts_decode_with_the_direction_bin():
    model, _ = _setup()
    g = torch.Generator().manual_seed(0)
    idx = torch.randint(0, len(model.anchors), (50,), generator=g)
    anchors = model.anchors[idx]
    gt = anchors.clone()
    gt[:, :3] += torch.randn(50, 3, generator=g) * 0.5
    gt[:, 3:6] *= torch.exp(torch.randn(50, 3, generator=g) * 0.2)
    gt[:, 6] = torch.rand(50, generator=g) * 2 * math.pi - math.pi
    residuals = fh.encode_boxes(gt, anchors)
    bins = fh.direction_targets(gt, model.head_config)
    logits = torch.nn.functional.one_hot(bins, model.head_config.num_dir_bins).float()
    back = decode_boxes(residuals, anchors, logits, model.head_config)
    np.testing.assert_allclose(back[:, :6].numpy(), gt[:, :6].numpy(), atol=1e-4)
    heading_err = torch.remainder(back[:, 6] - gt[:, 6] + math.pi, 2 * math.pi) - math.pi
    assert heading_err.abs().max() < 1e-4


def test_assignment_per_class_thresholds_and_forced_best_anchor():
    model, classes = _setup()
    anchors = model.anchors
    car = anchors[(classes == 0).nonzero()[40, 0]].clone()  # a car exactly on an anchor
    ped = anchors[(classes == 1).nonzero()[300, 0]].clone()
    ped[:2] += 0.45  # a pedestrian between anchors
    gt = torch.stack([car, ped])
    t = fh.assign_targets(anchors, classes, gt, torch.tensor([0, 1]), fh.class_thresholds(CARD))
    labels = t["labels"]
    exact = (classes == 0).nonzero()[40, 0]
    assert labels[exact] == 1 and torch.allclose(t["box_targets"][exact], torch.zeros(7), atol=1e-6)
    assert (labels == 2).sum() >= 1  # forced: the pedestrian's best anchor
    assert torch.all(labels[classes == 2] == 0)  # no cyclist: cyclist anchors are background
    far = (anchors[:, 0] - car[0]).abs() + (anchors[:, 1] - car[1]).abs() > 8
    assert torch.all(labels[far & (classes == 0)] == 0)
    assert (labels == -1).any()  # between the thresholds: ignored
    pos = labels > 0
    assert torch.all(t["matched"][pos].abs().sum(1) > 0)


def test_nearest_bev_swaps_length_and_width_near_the_y_axis():
    boxes = torch.tensor(
        [[0, 0, 0, 4.0, 2.0, 1, 0.0], [0, 0, 0, 4.0, 2.0, 1, math.pi / 2 - 0.1], [0, 0, 0, 4.0, 2.0, 1, math.pi]]
    )
    rect = fh.nearest_bev(boxes)
    np.testing.assert_allclose(rect[:, 2] - rect[:, 0], [4.0, 2.0, 4.0], atol=1e-6)


def test_head_loss_is_zero_for_perfect_predictions_and_counts_each_term():
    """Logits saturated at the targets, residuals equal to them and the right direction bin leave
    only the focal loss's vanishing remainder; a wrong bin costs the direction term alone."""
    model, classes = _setup()
    gt = model.anchors[(classes == 0).nonzero()[40, 0]].clone().unsqueeze(0)
    t = fh.assign_targets(model.anchors, classes, gt, torch.tensor([0]), fh.class_thresholds(CARD))
    one_hot = torch.nn.functional.one_hot(t["labels"].clamp(min=0), 4)[:, 1:].float()
    logits = (one_hot * 2 - 1) * 30
    bins = fh.direction_targets(t["matched"], model.head_config)
    direction = torch.nn.functional.one_hot(bins, 2).float() * 30
    terms = fh.head_loss(logits, t["box_targets"], direction, t, model.head_config, 3)
    assert float(terms["loss"]) < 1e-6
    wrong = fh.head_loss(logits, t["box_targets"], direction.flip(1), t, model.head_config, 3)
    assert float(wrong["dir"]) > 1.0 and float(wrong["cls"]) < 1e-6 and float(wrong["loc"]) < 1e-6


def test_thresholds_come_from_the_card_or_upstream():
    assert fh.class_thresholds(CARD) == [(0.6, 0.45), (0.5, 0.35), (0.5, 0.35)]
    data = dict(CARD.data)
    anchors = [dict(a) for a in data["dense_head"]["anchors"]]
    anchors[0].update(matched_threshold=0.7, unmatched_threshold=0.5)
    anchors[1]["class_name"] = "Tram"
    data["dense_head"] = dict(data["dense_head"], anchors=anchors[:1])
    from radaredge.cards import parse_card

    assert fh.class_thresholds(parse_card(data, Path("x.yaml"))) == [(0.7, 0.5)]
    data["dense_head"] = dict(data["dense_head"], anchors=anchors[1:2])
    with pytest.raises(ConfigError, match=r"anchors\[0\] \(Tram\) needs matched_threshold"):
        fh.class_thresholds(parse_card(data, Path("x.yaml")))
