"""Upstream object-encoder weights (Text2Pos's PointNet++, a Text2Loc / Des4Pos checkpoint) load
into the full Des4Pos card key for key; files that do not fit are named with their keys."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from references import text2pos_pointnet as text2pos

from radaredge.cards import load_card
from radaredge.errors import ConfigError
from radaredge.models import create_model
from radaredge.models.des4pos.weights import load_object_weights


def _bn_mlp(prefix: str, dims: list[int], g: torch.Generator) -> dict:
    """Text2Pos get_mlp keys: <prefix>.<i>.0 Linear, <prefix>.<i>.1 BatchNorm1d."""
    sd = {}
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        sd[f"{prefix}.{i}.0.weight"] = torch.randn(b, a, generator=g)
        sd[f"{prefix}.{i}.0.bias"] = torch.randn(b, generator=g)
        sd[f"{prefix}.{i}.1.weight"] = torch.rand(b, generator=g) + 0.5
        sd[f"{prefix}.{i}.1.bias"] = torch.randn(b, generator=g)
        sd[f"{prefix}.{i}.1.running_mean"] = torch.randn(b, generator=g)
        sd[f"{prefix}.{i}.1.running_var"] = torch.rand(b, generator=g) + 0.5
        sd[f"{prefix}.{i}.1.num_batches_tracked"] = torch.tensor(1000)
    return sd


def text2pos_pointnet(seed: int = 0) -> dict:
    """A state_dict in the layout of Text2Pos's pointnet_acc0.86_lr1_p256.pth (22 classes, 8 colours)."""
    g = torch.Generator().manual_seed(seed)
    sd = {
        **_bn_mlp("sa1.point_conv.local_nn", [6, 32, 64], g),
        **_bn_mlp("sa2.point_conv.local_nn", [67, 128, 128], g),
        **_bn_mlp("sa3.point_conv.local_nn", [131, 256, 256], g),
        **_bn_mlp("ga.mlp", [259, 512, 1024], g),
    }
    for name, (o, i) in {
        "lin1": (512, 1024),
        "lin2": (256, 512),
        "class_classifier": (22, 256),
        "color_classifier": (8, 256),
    }.items():
        sd[f"{name}.weight"], sd[f"{name}.bias"] = torch.randn(o, i, generator=g), torch.randn(o, generator=g)
    return sd


@pytest.fixture(scope="module")
def model():
    return create_model(load_card("des4pos"))


def test_text2pos_pointnet_loads_key_for_key(model, tmp_path):
    sd = text2pos_pointnet()
    assert len(sd) == 64
    path = tmp_path / "pointnet_acc0.86_lr1_p256.pth"
    torch.save(sd, path)
    before = model.submap.objects.mlp_pointnet[0][0].weight.clone()
    report = load_object_weights(model, path)
    assert report.loaded == 64 and report.source == "Text2Pos PointNet++" and report.parts == ["pointnet"]
    own = model.submap.objects.pointnet.state_dict()
    for k, v in sd.items():
        assert torch.equal(own[k], v), k
    assert torch.equal(model.submap.objects.mlp_pointnet[0][0].weight, before)  # the rest untouched
    assert "64 tensors" in report.summary()


def test_text2loc_checkpoint_object_encoder_loads(model, tmp_path):
    g = torch.Generator().manual_seed(1)
    objects = {f"object_encoder.{k}": v for k, v in model.submap.objects.state_dict().items()}
    objects = {k: torch.randn(v.shape, generator=g) if v.is_floating_point() else v for k, v in objects.items()}
    ckpt = {
        **objects,
        "object_encoder.class_embedding.weight": torch.randn(22, 256),
        "object_encoder.color_embedding.weight": torch.randn(8, 256),
        "language_encoder.x.weight": torch.randn(2),
    }
    path = tmp_path / "coarse.pth"
    torch.save({"model": ckpt}, path)  # wrapped, as training scripts save it
    report = load_object_weights(model, path)
    assert report.source == "Text2Loc/Des4Pos checkpoint"
    assert report.unused == ["object_encoder.class_embedding.weight", "object_encoder.color_embedding.weight"]
    assert torch.equal(model.submap.objects.mlp_merge[0][0].weight, objects["object_encoder.mlp_merge.0.0.weight"])


def test_weights_that_do_not_fit_name_their_keys(model, tmp_path):
    sd = text2pos_pointnet()
    sd["class_classifier.weight"] = torch.randn(9, 256)
    sd["class_classifier.bias"] = torch.randn(9)
    path = tmp_path / "nine.pth"
    torch.save(sd, path)
    with pytest.raises(ConfigError, match=r"class_classifier.weight \(file \(9, 256\), card \(22, 256\)\)"):
        load_object_weights(model, path)
    del sd["sa2.point_conv.local_nn.0.0.weight"]
    torch.save(sd, path)
    with pytest.raises(
        ConfigError, match="PointNet\\+\\+ keys missing \\(1\\): pointnet.sa2.point_conv.local_nn.0.0.weight"
    ):
        load_object_weights(model, path)
    torch.save({"backbone.conv.weight": torch.zeros(2)}, path)
    with pytest.raises(ConfigError, match="neither Text2Pos PointNet"):
        load_object_weights(model, path)


def test_text2pos_weights_compute_text2pos_features(model, tmp_path):
    """With Text2Pos's weights loaded, both formulations of the object network give the 256-d
    feature of the upstream reference (tests/references/text2pos_pointnet.py, written from
    Text2Pos's PointNet2 and PyG's fps / radius / PointConv) for objects in cell units."""
    sd = text2pos_pointnet(seed=4)
    for k, v in sd.items():  # weights of a scale a trained net has: activations stay O(1)
        if k.endswith(".0.weight") or k.startswith(("lin1", "lin2")) and k.endswith("weight"):
            sd[k] = v / v.shape[1] ** 0.5
    path = tmp_path / "pointnet.pth"
    torch.save(sd, path)
    load_object_weights(model, path)
    net = model.submap.objects.pointnet.eval()
    rng = np.random.default_rng(7)
    for size in (0.12, 0.35):  # a pole-sized and a box-sized object
        xyz = (rng.uniform(0.3, 0.3 + size, (256, 3))).astype(np.float32)
        rgb = rng.uniform(0, 1, (256, 3)).astype(np.float32)
        want = text2pos.features2(xyz, rgb, sd)
        with torch.no_grad():
            export = net(torch.from_numpy(xyz)[None], torch.from_numpy(rgb)[None])[0].numpy()
            reference = net.reference(xyz, torch.from_numpy(rgb)).numpy()
        scale = np.abs(want).max()
        assert scale > 0.1
        for got in (export, reference):
            assert np.abs(got - want).max() <= 1e-4 * scale, (size, np.abs(got - want).max(), scale)
