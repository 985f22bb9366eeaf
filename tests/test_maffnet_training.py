"""radaredge train for MAFF-Net: upstream's recipe (radaredge.training.maffnet) learns, fine-tunes an
upstream-format checkpoint key for key, freezes, resumes, and refuses what it cannot do."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import MAFFNET_TINY_CARD, MAFFNET_TINY_FULL_CARD, MAFFNET_TINY_FULL_DBSCAN_CARD, invoke, one_error_line
from references.maffnet_upstream_keys import openpcdet_checkpoint, trained_like_state_dict

from radaredge.cards import load_card
from radaredge.models import create_model
from radaredge.models.factory import save_checkpoint
from radaredge.training import maffnet as tm

CARD = load_card(MAFFNET_TINY_CARD)


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """A labelled synthetic VoD-layout set (version 1: consecutive frames, dense near points for the tiny
    card's 12.8 m): 2 training drives of 20 frames, 1 validation drive."""
    out = tmp_path_factory.mktemp("train-set") / "set"
    res = invoke(
        "make-benchmark",
        "--task",
        "detection",
        "--out",
        out,
        "--drives",
        3,
        "--frames",
        20,
        "--seed",
        3,
        "--version",
        1,
    )
    assert res.exit_code == 0, res.output
    return out


def _train(labelled, out, *extra):
    res = invoke(
        "train",
        "--model",
        "maffnet-tiny",
        "--config",
        MAFFNET_TINY_CARD,
        "--data",
        labelled,
        "--output",
        out,
        "--json",
        *extra,
    )
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout)


def test_training_lowers_the_loss_and_raises_validation_ap(labelled, tmp_path):
    """60 steps of upstream's recipe on the tiny card (12 frames, no augmentation, AP measured on
    the same frames): the loss falls, AP rises above the seeded network's, the best epoch's weights
    are best.pth and export. (The tiny card sees 12.8 m; most labelled objects lie beyond it, so
    its AP stays low: the test is that the loop learns, docs/models/maffnet.md what a card reaches.)"""
    report = _train(
        labelled,
        tmp_path / "run",
        "--epochs",
        10,
        "--batch-size",
        2,
        "--lr",
        0.003,
        "--set",
        "train_frames=12",
        "--validation",
        "train",
        "--set",
        "val_frames=12",
        "--set",
        "augment=false",
    )
    rows = report["epochs"]
    assert [r["epoch"] for r in rows] == list(range(11))
    assert rows[-1]["loss"] < 0.3 * rows[1]["loss"]
    assert rows[0]["mAP3d"] < 1.0
    best = max(r["mAP3d"] for r in rows[1:])
    assert best > rows[0]["mAP3d"] + 5.0, [r["mAP3d"] for r in rows]
    assert report["best_epoch"] == max(rows[1:], key=lambda r: r["mAP3d"])["epoch"]
    state = torch.load(tmp_path / "run" / "best.pth", weights_only=True)
    assert state["epoch"] == report["best_epoch"] and math.isclose(state["metrics"]["mAP3d"], best)
    res = invoke(
        "export",
        "--model",
        "maffnet-tiny",
        "--config",
        MAFFNET_TINY_CARD,
        "--checkpoint",
        tmp_path / "run" / "best.pth",
        "--output",
        tmp_path / "t.onnx",
    )
    assert res.exit_code == 0, res.output


@pytest.mark.parametrize("name", ["maffnet-vod", "maffnet-vod-full"])
def test_an_upstream_checkpoint_fine_tunes_key_for_key(labelled, tmp_path, name):
    """maffnet-vod (its stage two dropped by the card's rule) and maffnet-vod-full from an OpenPCDet
    checkpoint with upstream's keys: one epoch moves every trained tensor a little from the
    checkpoint's value and re-initialises none (the class bias keeps the checkpoint's, not the
    recipe's prior)."""
    ckpt = trained_like_state_dict("vod", stage_two=True, seed=4)
    torch.save(openpcdet_checkpoint(ckpt), tmp_path / "up.pth")
    res = invoke(
        "train",
        "--model",
        name,
        "--data",
        labelled,
        "--output",
        tmp_path / "ft",
        "--checkpoint",
        tmp_path / "up.pth",
        "--epochs",
        1,
        "--batch-size",
        2,
        "--set",
        "train_frames=2",
        "--set",
        "val_frames=1",
        "--set",
        "bn_scans=0",
        "--json",
    )  # bn_scans re-estimates the statistics
    assert res.exit_code == 0, res.output
    after = torch.load(tmp_path / "ft" / "last.pth", weights_only=True)["model_state"]
    model = create_model(load_card(name))
    assert set(after) == set(model.state_dict())
    loaded = {k: v for k, v in ckpt.items() if k in after}
    assert set(loaded) == set(after)  # every tensor came from the checkpoint
    params = {n for n, _ in model.named_parameters()}
    momentum = {
        f"{n}.{stat}": m.momentum
        for n, m in model.named_modules()
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)
        for stat in ("running_mean", "running_var")
    }
    moved, counted = 0, {}
    for key, value in after.items():
        if key.endswith("num_batches_tracked"):  # every norm counts on from the checkpoint's count
            counted[key] = int(value) - int(loaded[key])
        elif not value.is_floating_point():
            continue
        elif key in params:  # one Adam step: at most ~lr per element
            diff = float((value - loaded[key]).abs().max())
            assert diff < 0.05, f"{key} moved {diff} from the checkpoint: re-initialised?"
            moved += diff > 0
        elif value.numel() > 8 and momentum[key] <= 0.01:  # stage one's running statistics (momentum 0.01);
            # stage two's BatchNorm1d keep torch's 0.1, as upstream's, and move further in two scans
            corr = np.corrcoef(value.double().numpy().ravel(), loaded[key].double().numpy().ravel())[0, 1]
            assert corr > 0.9, f"{key} no longer follows the checkpoint's values (correlation {corr:.2f})"
    assert moved > 0.9 * len(params)
    assert counted.pop("vfe.pfn_layers.0.norm.num_batches_tracked") == 1  # once per batch of 2 scans, as upstream
    assert set(counted.values()) == {2}  # the 2-D norms: once per scan


def test_freeze_keeps_parameters_and_their_norm_statistics(labelled, tmp_path):
    start = create_model(CARD).state_dict()
    _train(
        labelled,
        tmp_path / "run",
        "--epochs",
        1,
        "--set",
        "train_frames=4",
        "--set",
        "val_frames=2",
        "--freeze",
        "vfe",
        "--freeze",
        "backbone_2d.blocks.*",
    )
    after = torch.load(tmp_path / "run" / "last.pth", weights_only=True)["model_state"]
    for key, value in after.items():
        same = torch.equal(value, start[key])
        if key.startswith(("vfe.", "backbone_2d.blocks.")) and "num_batches" not in key:
            assert same, key  # weights and running statistics alike
        elif key in ("dense_head.conv_box.weight", "backbone_2d.deblocks.0.0.weight"):
            assert not same, key


STAGE_ONE = ("vfe", "map_to_bev_module", "image_backbone", "fuser", "backbone_2d", "dense_head")


def test_stage_one_weights_start_a_two_stage_card(labelled, tmp_path):
    """``stage_one_weights``: a one-stage checkpoint (maffnet-tiny's) starts maffnet-tiny-full's
    stage one key for key (frozen here, so it must come out unchanged, class bias included), stage
    two starts seeded and trains; a checkpoint missing a stage-one key, or given together with
    --checkpoint, is refused."""
    one = create_model(CARD)
    with torch.no_grad():
        for p in one.parameters():
            p.add_(0.01)  # unlike the full card's seeded stage one
    save_checkpoint(one, tmp_path / "one.pth")
    common = [
        "train",
        "--model",
        "maffnet-tiny-full",
        "--config",
        MAFFNET_TINY_FULL_CARD,
        "--data",
        labelled,
        "--epochs",
        1,
        "--set",
        "train_frames=2",
        "--set",
        "val_frames=1",
        "--set",
        "freeze=" + ",".join(STAGE_ONE),
    ]
    res = invoke(*common, "--output", tmp_path / "run", "--set", f"stage_one_weights={tmp_path / 'one.pth'}")
    assert res.exit_code == 0, res.output
    assert f"stage_one_weights: {len(one.state_dict())} tensors" in res.output
    after = torch.load(tmp_path / "run" / "last.pth", weights_only=True)["model_state"]
    seeded = create_model(load_card(MAFFNET_TINY_FULL_CARD)).state_dict()
    for key, value in one.state_dict().items():
        if "num_batches" not in key:
            assert torch.equal(after[key], value), key
    stage_two = [k for k in after if k.startswith(("pfe.", "point_head.", "roi_head.")) and k.endswith("weight")]
    assert stage_two and any(not torch.equal(after[k], seeded[k]) for k in stage_two)
    partial = {k: v for k, v in one.state_dict().items() if k != "dense_head.conv_cls.bias"}
    torch.save(partial, tmp_path / "partial.pth")
    res = invoke(*common, "--output", tmp_path / "bad", "--set", f"stage_one_weights={tmp_path / 'partial.pth'}")
    one_error_line(res, "outside stage two: missing keys (1): dense_head.conv_cls.bias")
    torch.save(seeded, tmp_path / "full.pth")
    res = invoke(
        *common,
        "--output",
        tmp_path / "bad",
        "--set",
        f"stage_one_weights={tmp_path / 'one.pth'}",
        "--checkpoint",
        tmp_path / "full.pth",
    )
    one_error_line(res, "--checkpoint and stage_one_weights both give initial weights")


def test_resume_continues_the_same_run(labelled, tmp_path):
    """A run stopped after epoch 1 and resumed gives the weights and history of one uninterrupted run
    (validated after epoch 2 only: its summary marks epoch 1's missing AP)."""
    import radaredge

    opts = {"epochs": 2, "train_frames": 4, "val_frames": 2, "val_every": 2}
    whole = radaredge.train(MAFFNET_TINY_CARD, labelled, tmp_path / "a", options=opts)

    class Stop(Exception):
        pass

    def stop_after_epoch_1(line):
        if line.startswith("epoch   1"):
            raise Stop

    with pytest.raises(Stop):
        radaredge.train(MAFFNET_TINY_CARD, labelled, tmp_path / "b", options=opts, log=stop_after_epoch_1)
    assert torch.load(tmp_path / "b" / "last.pth", weights_only=True)["epoch"] == 1
    resumed = radaredge.train(MAFFNET_TINY_CARD, labelled, tmp_path / "b", options=opts, resume=True)
    a = torch.load(tmp_path / "a" / "last.pth", weights_only=True)["model_state"]
    b = torch.load(tmp_path / "b" / "last.pth", weights_only=True)["model_state"]
    assert all(torch.equal(a[k], b[k]) for k in a)

    def history(report):  # as text: the initial row's loss is NaN
        return json.dumps([{k: v for k, v in r.items() if k != "seconds"} for r in report.epochs])

    assert history(whole) == history(resumed)
    epoch_1 = next(line for line in resumed.lines() if line.split()[:1] == ["1"])
    assert "-" in epoch_1.split() and "AP3d_Car" in "".join(resumed.lines())


def test_bf16_precision_follows_the_fp32_gradient_and_trains(labelled, tmp_path):
    """``precision: bf16`` (autocast over the fuser, backbone and head): one scan's loss and
    gradient stay close to fp32's, the point stages and the outputs the losses see stay fp32, and a
    run with it trains and exports as an fp32 one does."""
    model = create_model(CARD)
    model.train()
    scan = tm.load_split(CARD, labelled, "train", None, 1)[0]
    keep = tm.boxes_in_range(scan.boxes, CARD.get("pillars.point_cloud_range"))
    inputs = (torch.from_numpy(scan.points), torch.from_numpy(scan.boxes[keep]), torch.from_numpy(scan.classes[keep]))
    grads, losses = {}, {}
    for name, dtype in tm.PRECISIONS.items():
        setup = tm.LossSetup(tm.anchor_classes(CARD, len(model.anchors)), tm.class_thresholds(CARD), None, dtype)
        model.zero_grad()
        terms = tm.scan_terms(model, *inputs, setup)
        assert terms["loss"].dtype == torch.float32
        terms["loss"].backward()
        losses[name] = float(terms["loss"].detach())
        grads[name] = torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])
    assert grads["bf16"].abs().sum() > 0 and not torch.equal(grads["bf16"], grads["fp32"])  # autocast was on
    assert torch.nn.functional.cosine_similarity(grads["bf16"], grads["fp32"], dim=0) > 0.99
    assert losses["bf16"] == pytest.approx(losses["fp32"], rel=0.05)
    report = _train(
        labelled,
        tmp_path / "run",
        "--epochs",
        1,
        "--set",
        "train_frames=4",
        "--set",
        "val_frames=2",
        "--set",
        "precision=bf16",
    )
    assert report["options"]["precision"] == "bf16" and math.isfinite(report["epochs"][-1]["loss"])
    best = torch.load(tmp_path / "run" / "best.pth", weights_only=True)["model_state"]
    assert all(v.dtype != torch.bfloat16 for v in best.values())


@pytest.mark.parametrize("card_path", [MAFFNET_TINY_CARD, MAFFNET_TINY_FULL_DBSCAN_CARD])
def test_training_pillar_stage_gives_the_export_canvas_and_gradient(labelled, card_path):
    """The pillar stage training runs (non-empty pillars only, channels-last canvas) == the
    export formulation's: canvas, pillar count, overflow and every gradient of the pillar
    stage (train mode), on scans of the labelled set."""
    card = load_card(card_path)
    model = create_model(card).train()
    for scan in tm.load_split(card, labelled, "train", None, 2):
        points = tm.drop_implausible(torch.from_numpy(scan.points), *model.point_bounds)[0]
        outputs, grads = [], []
        for stage in (lambda p: model.pillar_stage(p, False), model.pillar_stage_training):
            model.zero_grad()
            canvas, num, overflow = stage(points)
            (canvas * torch.linspace(-1, 1, canvas.numel()).reshape(canvas.shape)).sum().backward()
            outputs.append((canvas.detach(), int(num), bool(overflow)))
            grads.append(
                {n: p.grad for n, p in model.named_parameters() if p.grad is not None and not n.endswith("k_mlp.bias")}
            )
        (want, *counts), (got, *counts_t) = outputs
        assert counts_t == counts and counts[0] > 10
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
        assert got.unsqueeze(0).is_contiguous(memory_format=torch.channels_last)
        assert grads[0].keys() == grads[1].keys() and grads[0]
        for name, g in grads[0].items():
            torch.testing.assert_close(grads[1][name], g, atol=1e-4, rtol=1e-4, msg=name)


def test_augmentation_moves_points_and_boxes_together():
    rng = np.random.default_rng(0)
    recipe = tm.DetectionRecipe()
    points = np.array([[10.0, 2.0, 0.5, 1, 2, 3, 0], [20.0, -3.0, 1.0, 1, 2, 3, 0]], np.float32)
    boxes = np.array([[10.0, 2.0, 0.5, 4.0, 2.0, 1.5, 0.3], [20.0, -3.0, 1.0, 1.0, 0.6, 1.7, -2.9]], np.float32)
    for _ in range(20):
        p, b = tm.augment(points, boxes, [0, 1, 2], recipe, rng)
        np.testing.assert_allclose(p[:, :3], b[:, :3], atol=1e-4)  # each point stays at its box centre
        np.testing.assert_allclose(p[:, 3:], points[:, 3:])  # speeds, rcs, time unchanged
        ratio = b[:, 3:6] / boxes[:, 3:6]
        assert np.allclose(ratio, ratio[0, 0]) and 0.95 <= ratio[0, 0] <= 1.05
        assert np.all(b[:, 6] >= -np.pi) and np.all(b[:, 6] < np.pi)


def test_translate_std_z_lifts_points_and_boxes_by_one_offset_per_scan():
    points = np.array([[10.0, 2.0, 0.5, 1, 2, 3, 0], [20.0, -3.0, 1.0, 1, 2, 3, 0]], np.float32)
    boxes = np.array([[10.0, 2.0, 0.5, 4.0, 2.0, 1.5, 0.3], [20.0, -3.0, 1.0, 1.0, 0.6, 1.7, -2.9]], np.float32)
    lifted = tm.DetectionRecipe(flip_x=False, rotation=0.0, scale_min=1.0, scale_max=1.0, translate_std_z=0.3)
    offsets = []
    for seed in range(200):
        p, b = tm.augment(points, boxes, [0, 1, 2], lifted, np.random.default_rng(seed))
        dz = p[:, 2] - points[:, 2]
        assert np.allclose(dz, dz[0], atol=1e-6) and np.allclose(b[:, 2] - boxes[:, 2], dz[0], atol=1e-6)
        np.testing.assert_array_equal(p[:, [0, 1, 3, 4, 5, 6]], points[:, [0, 1, 3, 4, 5, 6]])
        np.testing.assert_array_equal(b[:, [0, 1, 3, 4, 5, 6]], boxes[:, [0, 1, 3, 4, 5, 6]])
        offsets.append(dz[0])
    assert abs(np.mean(offsets)) < 0.06 and 0.25 < np.std(offsets) < 0.35
    # off by default (upstream's MAFF-Net configs), and then no draw is taken from the generator
    plain = tm.DetectionRecipe(flip_x=False, rotation=0.0, scale_min=1.0, scale_max=1.0)
    rng, ref = np.random.default_rng(0), np.random.default_rng(0)
    p, _ = tm.augment(points, boxes, [0, 1, 2], plain, rng)
    np.testing.assert_array_equal(p, points)
    ref.uniform(1.0, 1.0)  # the scaling's one draw
    assert rng.uniform() == ref.uniform()


@pytest.mark.parametrize("card_path", [MAFFNET_TINY_CARD, MAFFNET_TINY_FULL_CARD, MAFFNET_TINY_FULL_DBSCAN_CARD])
def test_training_makes_every_tensor_on_the_scans_device(labelled, card_path):
    """--device cuda: a training step (batch statistics, losses of both stages, backward) and the
    validation detections make every tensor on the device of the scan and the weights. Checked
    without a GPU: with torch's default device set to 'meta', a tensor made without naming its
    device lands on meta and the first op that mixes it with the scan's CPU tensors fails."""
    card = load_card(card_path)
    model = create_model(card).train()
    scan = tm.load_split(card, labelled, "train", None)[3]
    sampling = tm.DetectionRecipe().roi_sampling() if model.stage_two_config is not None else None
    setup = tm.LossSetup(tm.anchor_classes(card, len(model.anchors)), tm.class_thresholds(card), sampling, None)
    points = torch.from_numpy(scan.points)
    torch.set_default_device("meta")
    try:
        with tm.batch_norm_statistics(model, [points]):
            terms = tm.scan_terms(model, points, torch.from_numpy(scan.boxes), torch.from_numpy(scan.classes), setup)
        terms["loss"].backward()
        model.eval()
        with torch.no_grad():
            boxes, scores, labels = tm.detect(model, points)
    finally:
        torch.set_default_device(None)
    assert math.isfinite(float(terms["loss"].detach())) and len(boxes) == len(scores) == len(labels)
    assert all(p.grad is None or p.grad.device.type == "cpu" for p in model.parameters())


def test_boxes_in_range_keeps_a_box_with_one_corner_inside():
    r = [0.0, -6.4, -3.0, 12.8, 6.4, 2.0]
    boxes = np.array([[13.5, 0, 0, 4, 2, 1, 0], [16, 0, 0, 4, 2, 1, 0], [5, 0, 0, 4, 2, 1, 0]], np.float32)
    assert tm.boxes_in_range(boxes, r).tolist() == [True, False, True]


@pytest.mark.parametrize(
    "extra, says",
    [
        (("--freeze", "nope"), "--freeze 'nope' matches no parameter"),
        (("--freeze", "*"), "freezes every parameter"),
        (("--validation", "val", "--validation", "test"), "validates on one split"),
        (("--validation", "nosuch"), "nosuch.txt: split file missing"),
        (("--format", "transloc"), "--format transloc"),
        (("--set", "epoch=3"), "unknown MAFF-Net training option"),
        (("--set", "scale_min=1.2"), "scale_min (1.2) must not exceed scale_max"),
        (("--set", "precision=fp16"), "precision must be one of fp32, bf16, not 'fp16'"),
        (
            ("--set", "stage_one_weights=x.pth"),
            "stage_one_weights is for a card with a second stage; maffnet-tiny has none",
        ),
        (("--radar-topic", "/r"), "--radar-topic describe ROS bag drives"),
        (("--resume",), "--resume"),
    ],
)
def test_bad_options_are_one_error_line(labelled, tmp_path, extra, says):
    res = invoke(
        "train",
        "--model",
        "maffnet-tiny",
        "--config",
        MAFFNET_TINY_CARD,
        "--data",
        labelled,
        "--output",
        tmp_path / "run",
        "--epochs",
        1,
        *extra,
    )
    one_error_line(res, says)
    assert not (tmp_path / "run").exists()


def test_a_set_without_labels_of_the_card_is_an_error(tmp_path):
    res = invoke(
        "train",
        "--model",
        "maffnet-tiny",
        "--config",
        MAFFNET_TINY_CARD,
        "--data",
        tmp_path,
        "--output",
        tmp_path / "run",
    )
    one_error_line(res, "no training/ folder")
