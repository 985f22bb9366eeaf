"""radaredge.train.maffnet_head: OpenPCDet's target assignment, residual coding and head loss
on the tiny MAFF-Net card (the int8 experiment's head is only as good as these)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from radaredge.cards import load_card
from radaredge.models import create_model
from radaredge.train import maffnet_head as fh
from radaredge.models.maffnet.model import decode_boxes

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
    car = anchors[(classes == 0).nonzero()[40, 0]].clone()               # a car exactly on an anchor
    ped = anchors[(classes == 1).nonzero()[300, 0]].clone()
    ped[:2] += 0.45                                                      # a pedestrian between anchors
    gt = torch.stack([car, ped])
    t = fh.assign_targets(anchors, classes, gt, torch.tensor([0, 1]), CARD.get("classes"))
    labels = t["labels"]
    exact = (classes == 0).nonzero()[40, 0]
    assert labels[exact] == 1 and torch.allclose(t["box_targets"][exact], torch.zeros(7), atol=1e-6)
    assert (labels == 2).sum() >= 1                                      # forced: the pedestrian's best anchor
    assert torch.all(labels[classes == 2] == 0)                          # no cyclist: cyclist anchors are background
    far = (anchors[:, 0] - car[0]).abs() + (anchors[:, 1] - car[1]).abs() > 8
    assert torch.all(labels[far & (classes == 0)] == 0)
    assert (labels == -1).any()                                          # between the thresholds: ignored
    pos = labels > 0
    assert torch.all(t["matched"][pos].abs().sum(1) > 0)


def test_nearest_bev_swaps_length_and_width_near_the_y_axis():
    boxes = torch.tensor([[0, 0, 0, 4.0, 2.0, 1, 0.0], [0, 0, 0, 4.0, 2.0, 1, math.pi / 2 - 0.1],
                          [0, 0, 0, 4.0, 2.0, 1, math.pi]])
    rect = fh.nearest_bev(boxes)
    np.testing.assert_allclose(rect[:, 2] - rect[:, 0], [4.0, 2.0, 4.0], atol=1e-6)


def _fitting_case(train_backbone: bool):
    model, classes = _setup()
    examples = fh.synthetic_examples(CARD, [5, 6])
    feats = [fh.cached_input(model, p, train_backbone) for p, _, _ in examples]
    targets = [fh.assign_targets(model.anchors, classes, torch.from_numpy(g), torch.from_numpy(lab),
                                 CARD.get("classes")) for _, g, lab in examples]
    return model, feats, targets


def _loss(model, feats, targets, train_backbone: bool) -> float:
    with torch.no_grad():
        return sum(float(fh.head_loss(*model.dense_head(model.backbone_2d(f) if train_backbone else f), t,
                                      model.head_config, 3)) for f, t in zip(feats, targets))


def test_fitting_lowers_the_loss_on_tiny_scans():
    """A few steps of fit reduce the head loss: gradients reach only the head."""
    model, feats, targets = _fitting_case(False)
    backbone_before = {k: v.clone() for k, v in model.backbone_2d.state_dict().items()}
    fh.reset_head(model.dense_head)
    start = _loss(model, feats, targets, False)
    fh.fit(model, feats, targets, epochs=15, lr=3e-3, log=lambda *_: None)
    assert _loss(model, feats, targets, False) < 0.7 * start
    assert all(torch.equal(v, model.backbone_2d.state_dict()[k]) for k, v in backbone_before.items())


def test_fitting_the_backbone_too_trains_it_and_leaves_the_front_frozen():
    """With train_backbone the features are the fusion's maps, BaseBEVBackbone learns with the
    head (its batch-norm statistics too), the layers before it stay as they were, and the model
    ends in eval mode."""
    model, feats, targets = _fitting_case(True)
    assert feats[0].shape[1] == CARD.get("caf.out_channels")
    front = {k: v.clone() for k, v in model.state_dict().items() if not k.startswith(("backbone_2d.", "dense_head."))}
    backbone_before = {k: v.clone() for k, v in model.backbone_2d.state_dict().items()}
    fh.reset_head(model.dense_head)
    start = _loss(model, feats, targets, True)
    fh.fit(model, feats, targets, epochs=6, lr=1e-3, train_backbone=True, log=lambda *_: None)
    assert not model.training and not model.backbone_2d.training
    assert _loss(model, feats, targets, True) < 0.7 * start
    changed = [k for k, v in backbone_before.items() if not torch.equal(v, model.backbone_2d.state_dict()[k])]
    assert any(k.endswith("weight") for k in changed) and any(k.endswith("running_mean") for k in changed)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in front.items())


def test_detection_recall_counts_ground_truth_found_with_its_class():
    """Detections (labels 1-based, as the graph outputs them) that repeat the ground truth find all
    of it; the same boxes with another class find none."""
    examples = fh.synthetic_examples(CARD, [5, 6])

    class Oracle:
        def __init__(self, shift):
            self.shift, self.scan = shift, iter(examples)

        def run(self, points):
            _, gt, labels = next(self.scan)
            return {"boxes": torch.from_numpy(gt), "scores": torch.ones(len(gt)),
                    "labels": torch.from_numpy(labels + 1 + self.shift)}

    boxes = sum(len(g) for _, g, _ in examples)
    assert boxes > 0
    assert fh.detection_recall(Oracle(0), examples) == (1.0, boxes / 2)
    assert fh.detection_recall(Oracle(1), examples) == (0.0, boxes / 2)


def test_head_fit_is_the_maffnet_recipe_of_radaredge_train(tmp_path):
    """`radaredge train --data synthetic` runs the head fit: a run directory whose best.pth
    export loads, a report with the held-out recall; recorded data and drive options are refused."""
    from click.testing import CliRunner

    from radaredge.cli import main

    tiny = Path(__file__).parent / "cards" / "maffnet-tiny.yaml"
    run = tmp_path / "run"
    res = CliRunner().invoke(main, ["train", "--model", "maffnet-tiny", "--config", str(tiny), "--data", "synthetic",
                                    "--output", str(run), "--epochs", "1", "--set", "train_scans=2",
                                    "--set", "test_scans=1", "--json"])
    assert res.exit_code == 0, res.output
    import json
    report = json.loads(res.stdout)
    assert report["metric"] == "recall_bev_iou_0.5" and 0.0 <= report["epochs"][0]["recall_bev_iou_0.5"] <= 1.0
    assert (run / "best.pth").is_file() and (run / "train-log.json").is_file()
    model = create_model(CARD, run / "best.pth")
    assert not torch.equal(model.dense_head.conv_cls.bias, create_model(CARD).dense_head.conv_cls.bias)
    for extra, says in ((["--data", str(tmp_path)], "reads no recorded data"),
                        (["--data", "synthetic", "--validation", "x"], "--validation: not used"),
                        (["--data", "synthetic", "--device", "cuda"], "head fit runs on the CPU"),
                        (["--data", "synthetic", "--set", "epoch=3"], "unknown MAFF-Net head fit training option")):
        res = CliRunner().invoke(main, ["train", "--model", "maffnet-tiny", "--config", str(tiny), *extra,
                                        "--output", str(tmp_path / "other")])
        assert res.exit_code == 2 and says in res.output, res.output
