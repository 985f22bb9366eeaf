"""radaredge's MAFF-Net == upstream TRV-Lab/MAFF-Net on upstream-format weights.

The yardstick is tests/references/maffnet_upstream.py, written from upstream's source and sharing
no code with radaredge. Weights are random upstream-format state_dicts (the reference modules'
own keys), loaded into radaredge through ``load_checkpoint`` as a user's checkpoint would be.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from references.maffnet_upstream import (
    UpstreamCQCACaf,
    UpstreamVSA,
    randomise,
    upstream_cda_keypoints,
    upstream_scan_mask,
)

from radaredge.cards import load_card
from radaredge.models import create_model, load_checkpoint
from radaredge.models.maffnet.model import UNUSED_FUSER_KEYS
from radaredge.models.maffnet.rcnn import CDAKeypointSampler, KeypointConfig, scan_points

ROOT = Path(__file__).resolve().parents[1]
TINY_FULL = ROOT / "tests" / "cards" / "maffnet-tiny-full.yaml"


def _with_upstream_part(model, prefix: str, part_state: dict, tmp_path: Path) -> Path:
    """An OpenPCDet checkpoint of ``model`` whose ``prefix`` keys are replaced by ``part_state``."""
    state = {k: v for k, v in model.state_dict().items() if not k.startswith(prefix)}
    state.update({prefix + k: v for k, v in part_state.items()})
    path = tmp_path / "upstream.pth"
    torch.save({"model_state": state, "optimizer_state": {}, "epoch": 80, "it": 1000, "version": "pcdet+0.6.0"}, path)
    return path


@pytest.mark.parametrize("card_path, side", [(TINY_FULL, 40), (ROOT / "models" / "maffnet-vod.yaml", 320)])
def test_fuser_equals_upstream_cqca_caf(card_path, side, tmp_path):
    card = load_card(card_path)
    model = create_model(card)
    caf = card.get("caf")
    upstream = UpstreamCQCACaf(
        64, 128, caf["out_channels"], caf["pool_size"], caf["heads"], caf["ffn_ratio"], caf["se_reduction"]
    ).eval()
    state = randomise(upstream, seed=side)
    report = load_checkpoint(model, _with_upstream_part(model, "fuser.", state, tmp_path))
    dropped = report.dropped["upstream fuser parameters with no effect at test time"]
    assert dropped and all(k.startswith(UNUSED_FUSER_KEYS) for k in dropped)
    assert report.loaded + len(dropped) == len(model.state_dict()) - 36 + len(state)  # 36 = our fuser tensors
    g = torch.Generator().manual_seed(1)
    for trial in range(3):
        pillar = torch.randn(1, 64, side, side, generator=g)
        cfa = torch.relu(torch.randn(1, 64, side, side, generator=g))
        if trial == 2:  # sparse maps, as radar gives them
            pillar = pillar * (torch.rand(1, 1, side, side, generator=g) < 0.05)
        with torch.no_grad():
            ours = model.fuser(pillar, cfa)
            ref = upstream(cfa, pillar)
        assert ours.shape == ref.shape == (1, caf["out_channels"], side, side)
        err, scale = float((ours - ref).abs().max()), float(ref.abs().max())
        assert 0.1 < scale < 20, f"trial {trial}: output scale {scale} (the check wants maps of magnitude ~1)"
        assert err <= 1e-4, f"trial {trial}: fuser differs from upstream by {err} (output scale {scale:.2f})"


def _scan(seed: int, n: int, spread: float = 1.0):
    """Points in the tiny card's range (12.8 m x 12.8 m) plus some outside it, a cluster mask and rois."""
    rng = np.random.default_rng(seed)
    pts = np.stack(
        [
            rng.uniform(-1, 14, n) * spread,
            rng.uniform(-7.5, 7.5, n) * spread,
            rng.uniform(-4, 3, n),
            *rng.normal(size=(4, n)),
        ],
        1,
    ).astype(np.float32)
    cluster = rng.random(n) < 0.5
    rois = np.zeros((12, 7), np.float32)
    rois[:5] = [
        [3, 0, -1, 3.9, 1.6, 1.5, 0.3],
        [8, 3, -0.5, 0.8, 0.6, 1.7, 1.2],
        [2, -4, -1, 1.8, 0.6, 1.7, -2.0],
        [11, 5, 0, 2, 2, 2, 3.0],
        [6, -2, -2.5, 4, 1.8, 1.6, 0.0],
    ]
    return pts, cluster, rois


@pytest.mark.parametrize("case", ["some", "many", "none-inside", "no-cluster", "short-scan", "padding-only"])
def test_cda_keypoints_equal_upstream(case):
    pts, cluster, rois = _scan(7, 400)
    k = 64
    valid = np.arange(len(rois)) < 5
    if case == "many":
        k = 16  # more cylinder points than keypoints: FPS
    if case == "none-inside":
        rois[:5, :2] += 100
    if case == "no-cluster":
        cluster[:] = False
    if case == "short-scan":
        pts, cluster, k = pts[:30], cluster[:30], 64  # fewer scan points than slots: cyclic fill
    if case == "padding-only":
        rois[:] = 0
        valid[:] = False
    r = (0.0, -6.4, -3.0, 12.8, 6.4, 2.0)
    xyz, _, scan = scan_points(torch.from_numpy(pts), r)
    sampler = CDAKeypointSampler(KeypointConfig(num_keypoints=k, sample_radius_r=2.5, sample_radius_h=3.0))
    kp, kp_valid = sampler(xyz, torch.from_numpy(cluster) & scan, scan, torch.from_numpy(rois), torch.from_numpy(valid))
    m = upstream_scan_mask(pts, r)
    ref = upstream_cda_keypoints(pts[m, :3], pts[m & cluster, :3], rois, k, 2.5, 3.0)
    assert len(ref) == k and bool(kp_valid.all())
    np.testing.assert_array_equal(kp.numpy(), ref, err_msg=case)
    kr, _ = sampler.reference(xyz.numpy(), (torch.from_numpy(cluster) & scan).numpy(), scan.numpy(), rois, valid)
    np.testing.assert_array_equal(kr.numpy(), ref, err_msg=f"{case}: project reference")


def test_vsa_equals_upstream(tmp_path):
    card = load_card(TINY_FULL)
    model = create_model(card)
    sa = card.get("stage_two.vsa.sa_clusterpoints")
    r, v = card.get("pillars.point_cloud_range"), card.get("pillars.voxel_size")
    upstream = UpstreamVSA(
        7,
        card.get("caf.out_channels"),
        sa["radii"],
        sa["nsample"],
        sa["mlps"],
        card.get("stage_two.vsa.num_output_features"),
        r,
        v,
    ).eval()
    state = randomise(upstream, seed=3)
    load_checkpoint(model, _with_upstream_part(model, "pfe.", state, tmp_path))
    pts, _, _ = _scan(11, 300)
    xyz, feats, scan = scan_points(torch.from_numpy(pts), r)
    keypoints = torch.from_numpy(pts[:64, :3].copy())
    keypoints[-4:] = torch.tensor([40.0, 40.0, 0.0])  # far away: empty balls, clamped BEV corners
    bev = torch.randn(card.get("caf.out_channels"), 40, 40, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        before, feats_out = model.pfe(bev, keypoints, xyz, feats, scan)
        m = upstream_scan_mask(pts, r)
        before_r, feats_r = upstream(keypoints.numpy(), bev, pts[m])
    assert float((before - before_r).abs().max()) <= 1e-4
    assert float((feats_out - feats_r).abs().max()) <= 1e-4


def test_tiny_full_fused_map_and_keypoints_equal_upstream_on_its_own_rois(tmp_path):
    """The whole tiny two-stage model with upstream-format fuser weights: the fused map and the
    graph's keypoints (exactly K, every scan) equal upstream's given the same rois."""
    card = load_card(TINY_FULL)
    model = create_model(card)
    caf = card.get("caf")
    fuser = UpstreamCQCACaf(
        64, 128, caf["out_channels"], caf["pool_size"], caf["heads"], caf["ffn_ratio"], caf["se_reduction"]
    ).eval()
    load_checkpoint(model, _with_upstream_part(model, "fuser.", randomise(fuser, 5), tmp_path))
    from radaredge.models import model_spec

    spec = model_spec(card).graph()
    k = card.get("stage_two.keypoints.num_keypoints")
    r = card.get("pillars.point_cloud_range")
    for name, feeds in spec.make_cases(card, 4, 9):
        pts = feeds["points"]
        trace: dict = {}
        with torch.no_grad():
            out = model.run(torch.from_numpy(pts), trace=trace)
            cfa_feat, _, _, cluster = model.cfa_stage(torch.from_numpy(pts), reference=False)
            pillar, _, _ = model.pillar_stage(torch.from_numpy(pts), reference=False)
            fused_ref = fuser(cfa_feat, pillar.unsqueeze(0))
        assert float((trace["fused"] - fused_ref).abs().max()) <= 1e-4, name
        m = upstream_scan_mask(pts, r) & np.isfinite(pts).all(1)
        ref = upstream_cda_keypoints(pts[m, :3], pts[m & cluster.numpy(), :3], out["rois"].numpy(), k, 2.5, 3.0)
        assert out["keypoint_valid"].numpy().all(), name
        np.testing.assert_array_equal(out["keypoints"].numpy(), ref, err_msg=name)


def test_vod_full_keypoints_and_vsa_equal_upstream(tmp_path):
    """maffnet-vod-full with upstream-format fuser and pfe weights, on a drive scan and a dense
    5-frame cloud: exactly 1024 keypoints, equal to upstream's CDA given the graph's own rois and
    cluster points, and VSA features within 1e-4 of upstream's VoxelSetAbstraction_cda."""
    from radaredge.models.maffnet.spec import five_frame_points

    card = load_card(ROOT / "models" / "maffnet-vod-full.yaml")
    model = create_model(card)
    fuser = UpstreamCQCACaf().eval()
    sa = card.get("stage_two.vsa.sa_clusterpoints")
    r, v = card.get("pillars.point_cloud_range"), card.get("pillars.voxel_size")
    vsa = UpstreamVSA(7, 64, sa["radii"], sa["nsample"], sa["mlps"], 128, r, v).eval()
    state = {k: t for k, t in model.state_dict().items() if not k.startswith(("fuser.", "pfe."))}
    state.update({"fuser." + k: t for k, t in randomise(fuser, 8).items()})
    state.update({"pfe." + k: t for k, t in randomise(vsa, 9).items()})
    torch.save({"model_state": state}, tmp_path / "upstream.pth")
    load_checkpoint(model, tmp_path / "upstream.pth")
    from radaredge.models import model_spec

    clouds = [model_spec(card).graph().make_cases(card, 1, 5)[0][1]["points"], five_frame_points(3, card)]
    for pts in clouds:
        trace: dict = {}
        with torch.no_grad():
            out = model.run(torch.from_numpy(pts), trace=trace)
            _, _, _, cluster = model.cfa_stage(torch.from_numpy(pts), reference=False)
            cfa_feat, _, _, _ = model.cfa_stage(torch.from_numpy(pts), reference=False)
            pillar, _, _ = model.pillar_stage(torch.from_numpy(pts), reference=False)
            fused_ref = fuser(cfa_feat, pillar.unsqueeze(0))[0]  # upstream's spatial_features
        m = upstream_scan_mask(pts, r) & np.isfinite(pts).all(1)
        ref = upstream_cda_keypoints(pts[m, :3], pts[m & cluster.numpy(), :3], out["rois"].numpy(), 1024, 2.5, 3.0)
        assert out["keypoints"].shape == (1024, 3) and out["keypoint_valid"].all()
        np.testing.assert_array_equal(out["keypoints"].numpy(), ref)
        with torch.no_grad():  # the graph's own VSA output, as wired
            _, features_ref = vsa(ref, fused_ref, pts[m])
        assert float((trace["point_features"] - features_ref).abs().max()) <= 1e-4
