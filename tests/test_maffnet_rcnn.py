"""MAFF-Net stage two: proposals, CDA keypoints, VSA, point head, ROI head and the whole two-stage
detector, export formulation against reference (torch and onnxruntime), upstream keys, stages,
memory."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_close, assert_parses_in_tensorrt, export_with_cli, invoke, summary_of

from radaredge import runtime
from radaredge.cards import load_card
from radaredge.models import create_model, model_spec
from radaredge.models.maffnet.rcnn import (
    CDAKeypointSampler,
    KeypointConfig,
    ProposalConfig,
    ProposalLayer,
    decode_roi_residuals,
)

ROOT = Path(__file__).resolve().parents[1]
TINY_FULL = Path(__file__).parent / "cards" / "maffnet-tiny-full.yaml"


@pytest.fixture(scope="module")
def tiny():
    card = load_card(TINY_FULL)
    model = create_model(card)
    with torch.no_grad():  # non-trivial BN statistics in stage two
        gen = torch.Generator().manual_seed(1)
        for name, m in model.named_modules():
            if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)) and name.split(".")[0] in (
                "pfe",
                "point_head",
                "roi_head",
            ):
                m.running_mean.copy_(torch.rand(m.num_features, generator=gen) - 0.5)
                m.running_var.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
    return card, model


# ----------------------------------------------------------------------------- proposals


def test_proposal_layer_matches_reference_and_pads():
    rng = np.random.default_rng(0)
    base = np.array(
        [[5, 0, -1, 3.9, 1.6, 1.5, 0.0], [10, 3, -1, 0.8, 0.6, 1.7, 1.0], [20, -4, -1, 1.8, 0.6, 1.7, 2.0]], np.float32
    )
    boxes = np.repeat(base, 30, 0) + rng.normal(0, 0.02, (90, 7)).astype(np.float32)  # 3 clusters
    logits = rng.normal(0, 3, (90, 3)).astype(np.float32) - 5.0  # all negative
    logits[7] = logits[7, [1, 1, 1]]  # a tie between classes
    layer = ProposalLayer(ProposalConfig(pre_max=64, iou_thresh=0.7, post_max=8))
    got = layer(torch.from_numpy(logits), torch.from_numpy(boxes))
    ref = layer.reference(torch.from_numpy(logits), torch.from_numpy(boxes))
    for g, r in zip(got, ref):
        np.testing.assert_array_equal(g.numpy(), r.numpy())
    rois, labels, valid = ref
    n = int(valid.sum())
    assert 3 <= n < 8 and valid[:n].all()  # no score threshold: negative logits compete
    assert (rois[n:] == 0).all() and (labels[n:] == 0).all() and set(labels[:n].tolist()) <= {1, 2, 3}
    best = logits.max(1).argmax()
    assert_close(rois[0].numpy(), boxes[best], 0, "the best anchor is the first roi")


# ----------------------------------------------------------------------------- CDA keypoints


def _cda_case(seed, n=600):
    rng = np.random.default_rng(seed)
    xyz = np.stack([rng.uniform(0, 30, n), rng.uniform(-10, 10, n), rng.uniform(-2, 2, n)], 1).astype(np.float32)
    cluster = rng.random(n) < 0.6
    scan = rng.random(n) < 0.9
    cluster &= scan
    rois = np.zeros((6, 7), np.float32)
    rois[:4] = [[5, 0, 0, 4, 2, 1.5, 0], [15, 5, 1, 1, 1, 1, 0], [25, -5, -1, 2, 2, 2, 0], [10, -8, 3, 1, 1, 1, 0]]
    valid = np.array([True] * 4 + [False] * 2)  # two zero-padded rois at the origin
    return xyz, cluster, scan, rois, valid


def _inside(p, roi, r=2.5, h=3.0):
    """Upstream's cylinder test for one point and one roi, in float64 (for the assertions only)."""
    radius = max(roi[3], roi[4]) / 2 + r
    return np.hypot(p[0] - roi[0], p[1] - roi[1]) <= radius and abs(p[2] - roi[2]) <= (roi[5] + h) / 2


@pytest.mark.parametrize(
    "case", ["normal", "few", "no-selection", "no-cluster", "nothing", "padded-only", "padded-valid-only"]
)
def test_cda_sampler_matches_reference(case):
    xyz, cluster, scan, rois, valid = _cda_case(3)
    npoint, padded = 16, "upstream"
    if case == "few":
        cluster[:] = False
        cluster[[3, 50, 120]] = True
        scan[[3, 50, 120]] = True
        xyz[[3, 50, 120]] = [[5, 0.5, 0], [5.5, 0, 0.2], [25, -5, -1]]
        xyz[:, 0] += np.where(cluster, 0, 40).astype(np.float32)  # nothing else near the origin's padded rois
    if case == "no-selection":
        rois[:4, :2] += 100  # no cluster point near a valid roi
        xyz[:, 0] += 3  # nor near the padded rois at the origin
    if case == "no-cluster":
        cluster[:] = False
    if case == "nothing":
        cluster[:] = False
        scan[:] = False
    if case in ("padded-only", "padded-valid-only"):
        valid[:] = False
        rois[:] = 0
        xyz[:5] = 0.0  # points at the padded rois' centre
        cluster[:5] = scan[:5] = True
        padded = "upstream" if case == "padded-only" else "valid"
    sampler = CDAKeypointSampler(KeypointConfig(num_keypoints=npoint, padded_rois=padded))
    got = sampler(*(torch.from_numpy(a) for a in (xyz, cluster, scan, rois, valid)))
    ref = sampler.reference(xyz, cluster, scan, rois, valid)
    for name, g, r in zip(("keypoints", "valid"), got, ref):
        np.testing.assert_array_equal(g.numpy(), r.numpy(), err_msg=f"{case}: {name}")
    kp, kp_valid = (t.numpy() for t in ref)
    assert kp_valid.all() != (case == "nothing")  # every slot filled unless the scan is empty
    if case == "few":  # the cylinder points first, in index order
        np.testing.assert_array_equal(kp[:3], xyz[[3, 50, 120]])
        # then FPS over the scan from its first point
        np.testing.assert_array_equal(kp[3], xyz[np.flatnonzero(scan)[0]])
    if case == "no-selection":  # upstream points[:1]: the first cluster point
        np.testing.assert_array_equal(kp[0], xyz[np.flatnonzero(cluster)[0]])
    if case == "padded-only":  # upstream: the zero rois select around the origin
        np.testing.assert_array_equal(kp[:5], np.zeros((5, 3), np.float32))
    if case == "padded-valid-only":  # "valid": nothing selected, first cluster point,
        np.testing.assert_array_equal(kp[:2], np.zeros((2, 3), np.float32))  # then the fill's FPS from the
        assert (kp[2:5] != 0).any(1).all()  # first scan point: the same point
    if case == "normal":  # more cylinder points than slots: all inside
        assert all(any(_inside(p, roi) for roi in rois) for p in kp)


# ----------------------------------------------------------------------------- ROI head pieces


def test_decode_zero_residual_gives_the_roi():
    rois = torch.tensor([[5.0, 2.0, -1.0, 3.9, 1.6, 1.5, 0.7], [0, 0, 0, 0, 0, 0, 0.0]])
    assert_close(decode_roi_residuals(torch.zeros(2, 7), rois).numpy(), rois.numpy(), 1e-6)
    # a residual along the roi's own x axis moves the centre along its heading, scaled by the diagonal
    reg = torch.tensor([[0.1, 0, 0, 0, 0, 0, 0], [0.0] * 7])
    out = decode_roi_residuals(reg, rois)[0].numpy()
    diag = math.hypot(3.9, 1.6)
    assert_close(out[:2], [5 + 0.1 * diag * math.cos(0.7), 2 + 0.1 * diag * math.sin(0.7)], 1e-5)


def test_roi_grid_points_layout(tiny):
    _, model = tiny
    head = model.roi_head
    g = head.grid_size
    rois = torch.tensor([[10.0, -2.0, 0.5, 3.0, 1.5, 0.9, 0.4], [0.0] * 7, [3, 3, -1, 1, 2, 3, -2.5]])
    grid = head.grid_points(rois)
    np.testing.assert_array_equal(grid.numpy(), head.grid_points_reference(rois.numpy()))
    # grid index ix * G^2 + iy * G + iz: the last grid point is the (+, +, +) corner cell centre
    corner = (np.array([g - 0.5] * 3) / g - 0.5) * [3.0, 1.5, 0.9]
    c, s = math.cos(0.4), math.sin(0.4)
    expect = [10 + corner[0] * c - corner[1] * s, -2 + corner[0] * s + corner[1] * c, 0.5 + corner[2]]
    assert_close(grid[0, -1].numpy(), expect, 1e-5)
    assert_close(grid[0, 1].numpy() - grid[0, 0].numpy(), [0, 0, 0.9 / g], 1e-5, "iz is the fastest index")
    assert (grid[1] == 0).all()  # a padded roi collapses to its (zero) centre


def test_pfe_point_head_roi_head_match_reference(tiny):
    """VSA, point head and ROI head on a case with invalid keypoints, empty balls and padded rois."""
    _, model = tiny
    rng = np.random.default_rng(5)
    n, k = 150, model.keypoint_sampler.cfg.num_keypoints
    xyz = np.stack([rng.uniform(0, 12.8, n), rng.uniform(-6.4, 6.4, n), rng.uniform(-2, 1, n)], 1).astype(np.float32)
    feats = rng.normal(size=(n, 4)).astype(np.float32)
    cluster = rng.random(n) < 0.7
    kp_idx = rng.choice(np.flatnonzero(cluster), k)
    keypoints = xyz[kp_idx]
    keypoints[-3:] = [50.0, 50.0, 0.0]  # far away: empty balls
    kp_valid = np.arange(k) < k - 10  # the last 10 slots are invalid
    bev = rng.normal(size=(32, 40, 40)).astype(np.float32)  # the fuser's output (caf.out_channels)
    t = {
        name: torch.from_numpy(a)
        for name, a in dict(
            xyz=xyz, feats=feats, cluster=cluster, keypoints=keypoints, kp_valid=kp_valid, bev=bev
        ).items()
    }
    with torch.no_grad():
        before, pf = model.pfe(t["bev"], t["keypoints"], t["xyz"], t["feats"], t["cluster"])
        before_r, pf_r = model.pfe.reference(t["bev"], t["keypoints"], t["xyz"], t["feats"], t["cluster"])
        assert model.pfe.SA_clusterpoints.out_channels == 16
        assert before.shape == (k, 32 + 16)
        assert_close(before.numpy(), before_r.numpy(), 1e-5, "point_features_before_fusion")
        assert_close(pf.numpy(), pf_r.numpy(), 1e-5, "point_features")
        scores = model.point_head(before)
        feats_roi = pf * scores[:, None]
        rois = torch.zeros(model.proposal_layer.cfg.post_max, 7)
        rois[:5] = torch.tensor(
            [
                [4, 0, -0.5, 3.9, 1.6, 1.5, 0.3],
                [8, 3, -0.5, 0.8, 0.6, 1.7, 1.2],
                [2, -4, -0.5, 1.8, 0.6, 1.7, -2.0],
                [11, 5, 0, 2, 2, 2, 3.0],
                [40, 40, 0, 2, 2, 2, 0.0],
            ]
        )  # the last one pools nothing
        cls, reg = model.roi_head(rois, t["keypoints"], t["kp_valid"], feats_roi)
        cls_r, reg_r = model.roi_head.reference(rois, t["keypoints"], t["kp_valid"], feats_roi)
    assert_close(cls.numpy(), cls_r.numpy(), 1e-5, "rcnn cls")
    assert_close(reg.numpy(), reg_r.numpy(), 1e-5, "rcnn reg")
    assert np.isfinite(cls.numpy()).all() and np.isfinite(reg.numpy()).all()


# ----------------------------------------------------------------------------- whole detector


def test_tiny_full_export_formulation_equals_reference(tiny):
    card, model = tiny
    spec = model_spec(card).graph()
    assert spec.output_names(card)[-7:] == [
        "rois",
        "roi_labels",
        "roi_valid",
        "keypoints",
        "keypoint_valid",
        "rcnn_scores",
        "rcnn_boxes",
    ]
    seen_valid_kp = set()
    for name, feeds in spec.make_cases(card, 4, 2):
        with torch.no_grad():
            e = spec.run_export(model, feeds)
            r = spec.run_reference(model, feeds)
        for k in ("roi_labels", "roi_valid", "keypoint_valid", "labels"):
            np.testing.assert_array_equal(e[k].numpy(), r[k].numpy(), err_msg=f"{name}: {k}")
        for k, tol in (
            ("rois", 1e-5),
            ("keypoints", 0.0),
            ("rcnn_scores", 1e-5),
            ("rcnn_boxes", 1e-4),
            ("boxes", 1e-4),
            ("scores", 1e-5),
        ):
            assert_close(e[k].numpy(), r[k].numpy(), tol, f"{name}: {k}")
        assert len(e["boxes"]) > 0, name
        assert int(e["roi_valid"].sum()) == len(e["rois"])  # the tiny grid always fills the roi slots
        seen_valid_kp.add(int(e["keypoint_valid"].sum()))
        # the final detections are refined rois: valid ones only, labels from the rois
        assert set(e["labels"].tolist()) <= set(e["roi_labels"][e["roi_valid"]].tolist())
    assert max(seen_valid_kp) > 1


def test_tiny_full_stage_times(tiny):
    from radaredge.models.maffnet.model import stage_times

    card, model = tiny
    pts = torch.from_numpy(model_spec(card).graph().make_cases(card, 1, 0)[0][1]["points"])
    for reference in (False, True):
        laps = stage_times(model, pts, reference)
        assert list(laps) == [
            "VFE+SPA",
            "CFA",
            "CAF",
            "backbone+head",
            "proposals+CDA",
            "VSA+point head",
            "ROI head",
            "final NMS",
        ]
        assert all(v > 0 for v in laps.values())


@pytest.fixture(scope="module")
def tiny_full_onnx(tmp_path_factory):
    return export_with_cli(tmp_path_factory.mktemp("maffnet-full"), "maffnet-tiny-full", TINY_FULL)


def test_tiny_full_onnx_parity(tiny_full_onnx):
    side = json.loads(tiny_full_onnx.with_suffix(".json").read_text())
    assert [o["name"] for o in side["outputs"]][-7:] == [
        "rois",
        "roi_labels",
        "roi_valid",
        "keypoints",
        "keypoint_valid",
        "rcnn_scores",
        "rcnn_boxes",
    ]
    assert side["op_histogram"].get("Loop", 0) >= 3  # proposal NMS, FPS, final NMS
    res = invoke(
        "parity-check",
        "--model",
        "maffnet-tiny-full",
        "--config",
        str(TINY_FULL),
        "--onnx",
        str(tiny_full_onnx),
        "--cases",
        "4",
        "--json",
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert summary_of(report)["boxes"]["mismatches"] == 0
    assert summary_of(report)["rcnn_scores"]["max_abs"] <= 1e-4
    # the torch-free runtime loads the two-stage detector like stage one
    model = runtime.load(tiny_full_onnx)
    card = load_card(TINY_FULL)
    out = model.run(model_spec(card).graph().make_cases(card, 1, 3)[0][1]["points"])
    assert out["boxes"].shape[1] == 7 and len(out["boxes"]) == len(out["scores"]) == len(out["labels"])
    assert out["keypoints"].shape == (64, 3) and set(out["labels"].tolist()) <= {1, 2, 3}
    # fewer points than keypoint slots, and an empty scan: the graph equals the torch export formulation
    net = create_model(card)
    full = model_spec(card).graph().make_cases(card, 1, 3)[0][1]["points"]
    inside = full[(full[:, 0] >= 0) & (full[:, 0] <= 12.8) & (np.abs(full[:, 1]) <= 6.4)]
    for pts in (inside[:3], full[:0]):
        got = model.run(pts)
        with torch.no_grad():
            want = net.run(torch.from_numpy(pts))
        for k in ("keypoints", "keypoint_valid", "rois", "boxes"):
            np.testing.assert_allclose(got[k], want[k].numpy(), atol=1e-5, err_msg=f"{len(pts)} points: {k}")
        assert got["keypoint_valid"].all() == (len(pts) > 0)


def test_tiny_full_onnx_nodes_attributed_to_stages(tiny_full_onnx):
    import onnx

    from radaredge.benchmarking.profiling import node_stages

    spec = model_spec(load_card(TINY_FULL)).graph()
    stages = [s for s, _ in spec.onnx_stages]
    assert stages == [
        "VFE+SPA",
        "CFA",
        "CAF",
        "backbone+head",
        "proposals+CDA",
        "VSA+point head",
        "ROI head",
        "final NMS",
    ]
    model = onnx.load(str(tiny_full_onnx), load_external_data=False)
    stage = node_stages(model, list(spec.onnx_stages), spec.onnx_post_outputs)
    nodes = {n.name: n for n in model.graph.node}
    producers = {o: nodes[n] for n in nodes for o in nodes[n].output}
    loops = sorted(stage[n] for n in nodes if nodes[n].op_type == "Loop")
    # full pillars' peels, proposal NMS, FPS over the cylinder points (above K), FPS fill over the scan; final NMS
    assert loops == ["VFE+SPA", "final NMS", "proposals+CDA", "proposals+CDA", "proposals+CDA"], loops
    assert stage[producers["rois"].name] == "proposals+CDA"
    assert stage[producers["keypoints"].name] == "proposals+CDA"
    assert stage[producers["rcnn_scores"].name] == "ROI head"
    assert stage[producers["boxes"].name] == "final NMS"
    assert set(stage.values()) == set(stages)


# ----------------------------------------------------------------------------- the VoD card


def _bn(prefix, c):
    return {
        **{f"{prefix}.{n}": (c,) for n in ("weight", "bias", "running_mean", "running_var")},
        f"{prefix}.num_batches_tracked": (),
    }


def expected_vod_stage_two_keys() -> dict[str, tuple]:
    """Upstream keys and shapes of MAFF-Net_vod.yaml's stage two (VoxelSetAbstraction_cda, PointHeadSimple,
    PVRCNNHead)."""
    keys: dict[str, tuple] = {}
    for s in (0, 1):
        keys[f"pfe.SA_clusterpoints.mlps.{s}.0.weight"] = (16, 7, 1, 1)
        keys[f"pfe.SA_clusterpoints.mlps.{s}.3.weight"] = (16, 16, 1, 1)
        keys.update({**_bn(f"pfe.SA_clusterpoints.mlps.{s}.1", 16), **_bn(f"pfe.SA_clusterpoints.mlps.{s}.4", 16)})
        keys[f"roi_head.roi_grid_pool_layer.mlps.{s}.0.weight"] = (64, 131, 1, 1)
        keys[f"roi_head.roi_grid_pool_layer.mlps.{s}.3.weight"] = (64, 64, 1, 1)
        keys.update(
            {
                **_bn(f"roi_head.roi_grid_pool_layer.mlps.{s}.1", 64),
                **_bn(f"roi_head.roi_grid_pool_layer.mlps.{s}.4", 64),
            }
        )
    keys["pfe.vsa_point_feature_fusion.0.weight"] = (128, 96)
    keys.update(_bn("pfe.vsa_point_feature_fusion.1", 128))
    keys.update(
        {
            "point_head.cls_layers.0.weight": (256, 96),
            "point_head.cls_layers.3.weight": (256, 256),
            "point_head.cls_layers.6.weight": (1, 256),
            "point_head.cls_layers.6.bias": (1,),
            **_bn("point_head.cls_layers.1", 256),
            **_bn("point_head.cls_layers.4", 256),
        }
    )
    keys.update(
        {
            "roi_head.shared_fc_layer.0.weight": (256, 27648, 1),
            "roi_head.shared_fc_layer.4.weight": (256, 256, 1),
            **_bn("roi_head.shared_fc_layer.1", 256),
            **_bn("roi_head.shared_fc_layer.5", 256),
        }
    )
    for name, out in (("cls_layers", 1), ("reg_layers", 7)):
        keys.update(
            {
                f"roi_head.{name}.0.weight": (256, 256, 1),
                f"roi_head.{name}.4.weight": (256, 256, 1),
                f"roi_head.{name}.7.weight": (out, 256, 1),
                f"roi_head.{name}.7.bias": (out,),
                **_bn(f"roi_head.{name}.1", 256),
                **_bn(f"roi_head.{name}.5", 256),
            }
        )
    return keys


VOD_FULL = ROOT / "models" / "maffnet-vod-full.yaml"


def test_vod_full_card_keys_and_stage_one():
    from test_maffnet import expected_vod_keys

    card = load_card(VOD_FULL)
    model = create_model(card)
    own = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    two = expected_vod_stage_two_keys()
    assert {k: own.get(k) for k in two} == two
    stage_one = {k: v for k, v in own.items() if k.split(".")[0] not in ("pfe", "point_head", "roi_head")}
    one = create_model(load_card(ROOT / "models" / "maffnet-vod.yaml")).state_dict()
    assert stage_one == {k: tuple(v.shape) for k, v in one.items()}  # all of maffnet-vod, unchanged
    assert set(expected_vod_keys()) <= set(stage_one)
    assert set(own) == set(stage_one) | set(two)
    # the stage-one part of the two cards is the same card; int8 also keeps the ROI head in fp32
    full, base = load_card(VOD_FULL).data, load_card(ROOT / "models" / "maffnet-vod.yaml").data
    assert {
        k: v for k, v in full.items() if k not in ("name", "description", "stage_two", "source", "quantization")
    } == {k: v for k, v in base.items() if k not in ("name", "description", "source", "quantization")}
    assert full["quantization"] == {
        **base["quantization"],
        "keep_fp32": ["roi_head", *base["quantization"]["keep_fp32"]],
    }


def _scan_5000(card, seed=0) -> np.ndarray:
    """A synthetic VoD scan padded to 5,000 points with clutter inside the range."""
    spec = model_spec(card).graph()
    pts = spec.make_cases(card, 1, seed)[0][1]["points"]
    rng = np.random.default_rng(seed)
    extra = np.zeros((5000 - len(pts), pts.shape[1]), np.float32)
    extra[:, 0] = rng.uniform(0, 51.2, len(extra))
    extra[:, 1] = rng.uniform(-25.6, 25.6, len(extra))
    extra[:, 2] = rng.uniform(-2.5, 1.5, len(extra))
    extra[:, 3:] = rng.normal(0, 1, (len(extra), pts.shape[1] - 3))
    return np.concatenate([pts, extra])


@pytest.fixture(scope="module")
def vod_full_onnx(tmp_path_factory):
    """maffnet-vod-full exported from an upstream-format checkpoint (OpenPCDet wrapper, every
    upstream key, random values at a trained network's scales; not our seeded weights)."""
    from references.maffnet_upstream_keys import openpcdet_checkpoint, trained_like_state_dict

    out = tmp_path_factory.mktemp("maffnet-vod-full")
    own = create_model(load_card(VOD_FULL)).state_dict()
    torch.save(openpcdet_checkpoint(trained_like_state_dict("vod", seed=1)), out / "upstream.pth")
    path = out / "maffnet-vod-full.onnx"
    res = invoke("export", "--model", "maffnet-vod-full", "--output", str(path), "--checkpoint", out / "upstream.pth")
    assert res.exit_code == 0, res.output
    assert (
        f"loaded {len(own)} tensors from {out / 'upstream.pth'}; dropped 47 (upstream fuser parameters with "
        f"no effect at test time); ignored global_step"
    ) in res.output
    return path


def test_vod_full_export_and_parity(vod_full_onnx):
    """Six cases, the dense 5-frame cloud (the fifth) among them: stage two's outputs follow
    discrete decisions (proposal NMS, keypoint sampling), matched as sets. The default 20 cases
    take about 5 minutes here; they are run by hand when the card or its ops change."""
    assert_parses_in_tensorrt(vod_full_onnx)
    res = invoke(
        "parity-check",
        "--model",
        "maffnet-vod-full",
        "--onnx",
        str(vod_full_onnx),
        "--checkpoint",
        vod_full_onnx.parent / "upstream.pth",
        "--cases",
        "6",
        "--json",
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    summary = summary_of(report)
    assert len(report["graphs"]["maffnet"]["cases"]) == 6
    assert summary["boxes"]["mismatches"] == 0 and summary["rois"]["mismatches"] == 0


def test_tj4d_full_export_and_parity(tmp_path):
    onnx_path = tmp_path / "maffnet-tj4d-full.onnx"
    res = invoke("export", "--model", "maffnet-tj4d-full", "--output", onnx_path)
    assert res.exit_code == 0, res.output
    assert_parses_in_tensorrt(onnx_path)
    res = invoke("parity-check", "--model", "maffnet-tj4d-full", "--onnx", onnx_path, "--cases", "2", "--json")
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert summary_of(report)["boxes"]["mismatches"] == 0


def test_vod_full_intermediates_under_256_mb(vod_full_onnx, tmp_path):
    """No node output of the ONNX graph exceeds 256 MB on a 5,000-point scan (onnxruntime profile)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.enable_profiling = True
    opts.profile_file_prefix = str(tmp_path / "prof")
    opts.intra_op_num_threads = 2
    sess = ort.InferenceSession(str(vod_full_onnx), opts, providers=["CPUExecutionProvider"])
    sess.run(None, {"points": _scan_5000(load_card(VOD_FULL))})
    events = json.loads(Path(sess.end_profiling()).read_text())
    sizes = {
        e["name"]: int(e["args"]["output_size"])
        for e in events
        if e.get("cat") == "Node" and "output_size" in e.get("args", {})
    }
    assert sizes, "no node events in the profile"
    name, biggest = max(sizes.items(), key=lambda kv: kv[1])
    assert biggest <= 256 * 2**20, f"{name} writes {biggest / 2**20:.0f} MB"
    assert biggest >= 50 * 2**20  # the ROI-grid pooling's [21600, 1024] distances do show up


def test_bench_reports_stage_two_split_and_memory(tiny_full_onnx, tmp_path):
    res = invoke(
        "bench",
        "--model",
        "maffnet-tiny-full",
        "--config",
        TINY_FULL,
        "--onnx",
        tiny_full_onnx,
        "--runs",
        "2",
        "--warmup",
        "1",
        "--save",
        tmp_path / "bench.json",
    )
    assert res.exit_code == 0, res.output
    saved = json.loads((tmp_path / "bench.json").read_text())["graphs"]["maffnet"]
    stages = ["VFE+SPA", "CFA", "CAF", "backbone+head", "proposals+CDA", "VSA+point head", "ROI head", "final NMS"]
    for row in ("torch export", "torch reference"):
        assert list(saved["stage_ms"][row]) == stages
    ort = saved["stage_ms"]["onnxruntime"]
    assert list(ort)[:8] == stages and all(ort[s] > 0 for s in stages)
    # the runtime process holds onnxruntime, numpy and the graph: tens of MiB, never gigabytes
    assert 20 < saved["onnxruntime_peak_rss_mib"] < 2048
    assert "onnxruntime peak RSS" in res.output
