"""Pillar scatter: fixed-shape export formulation == dynamic-voxelization reference; ONNX."""

import numpy as np
import pytest
import torch

from radaredge.errors import CapacityError
from radaredge.ops.pillars import (
    PillarConfig,
    PillarFeatureNet,
    pillar_canvas,
    pillar_scatter_reference,
    voxelize_reference,
)
from radaredge.ops.scan_batch import concat_scans

SMALL = PillarConfig(
    point_cloud_range=(0.0, -8.0, -3.0, 16.0, 8.0, 5.0),
    voxel_size=(0.5, 0.5, 8.0),
    max_points_per_pillar=4,
    out_channels=16,
)


def make_net(cfg=SMALL, f=5, seed=0):
    torch.manual_seed(seed)
    net = PillarFeatureNet(f, cfg).eval()
    with torch.no_grad():  # non-trivial BN statistics so relu(BN(0)) padding matters
        bn = net.pfn_layers[0].norm
        bn.running_mean.uniform_(-0.5, 0.5)
        bn.running_var.uniform_(0.5, 2.0)
        bn.bias.uniform_(-0.5, 0.5)
    return net


def scan(n, seed, cfg=SMALL):
    """Uniform points over and beyond the range, plus a crowded pillar that exceeds the cap."""
    rng = np.random.default_rng(seed)
    r = cfg.point_cloud_range
    lo = [r[0] - 2, r[1] - 2, r[2] - 1, -5, -10]
    hi = [r[3] + 2, r[4] + 2, r[5] + 1, 5, 20]
    pts = rng.uniform(lo, hi, (n, 5))
    crowd = np.array([[3.1, 0.2, 0.0, 1.0, 5.0]]) + rng.normal(0, 0.05, (9, 5))
    return np.concatenate([pts, crowd]).astype(np.float32)


def run(net, pts, valid=None):
    valid = np.ones(len(pts), bool) if valid is None else valid
    with torch.no_grad():
        return net(torch.from_numpy(pts), torch.from_numpy(valid)).numpy()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_dynamic_voxelization_reference(seed):
    net = make_net(seed=seed)
    pts = scan(300, seed)
    with torch.no_grad():
        ref = pillar_scatter_reference(net, pts).numpy()
    np.testing.assert_allclose(run(net, pts), ref, atol=1e-5)


def test_cap_keeps_first_points_in_input_order():
    cfg = SMALL
    pts = scan(0, 0)  # only the crowded pillar: 9 points, cap 4
    voxels, num, _ = voxelize_reference(pts, cfg)
    assert num.tolist() == [4]
    np.testing.assert_array_equal(voxels[0], pts[:4])
    # Changing a dropped point changes nothing; changing a kept one does.
    net = make_net()
    base = run(net, pts)
    moved = pts.copy()
    moved[6, 3] += 3.0
    np.testing.assert_array_equal(run(net, moved), base)
    moved[1, 3] += 3.0
    assert np.abs(run(net, moved) - base).max() > 0


def test_out_of_range_points_are_dropped_not_wrapped():
    net = make_net()
    r = SMALL.point_cloud_range
    outside = np.array(
        [
            [r[3] + 0.1, 0, 0, 1, 1],
            [r[0] - 0.1, 0, 0, 1, 1],
            [1, r[4], 0, 1, 1],
            [1, 0, r[5] + 0.5, 1, 1],
            [r[3], 0, 0, 1, 1],
        ],
        np.float32,
    )
    assert np.abs(run(net, outside)).max() == 0


def test_non_finite_and_invalid_points_are_dropped():
    net = make_net()
    pts = scan(100, 3)
    bad = pts.copy()
    bad[0, 0] = np.nan
    bad[1, 4] = np.inf
    valid = np.ones(len(pts), bool)
    valid[2] = False
    keep = np.ones(len(pts), bool)
    keep[:3] = False
    np.testing.assert_allclose(run(net, bad, valid), run(net, pts[keep]), atol=1e-6)


def test_empty_scan_gives_empty_canvas():
    net = make_net()
    out = run(net, np.zeros((0, 5), np.float32))
    nx, ny, _ = SMALL.grid_size
    assert out.shape == (16, ny, nx) and not out.any()


def test_reference_reports_pillar_capacity():
    cfg = PillarConfig(**{**SMALL.__dict__, "max_pillars": 3})
    with pytest.raises(CapacityError, match="max_pillars=3"):
        voxelize_reference(scan(200, 0), cfg)


def test_openpcdet_parameter_names():
    names = set(make_net().state_dict())
    assert {"pfn_layers.0.linear.weight", "pfn_layers.0.norm.weight", "pfn_layers.0.norm.running_mean"} <= names


def test_onnx_export_matches_torch(onnx_roundtrip):
    net = make_net()
    pts = scan(50, 0)
    example = {"points": torch.from_numpy(pts), "valid": torch.ones(len(pts), dtype=torch.bool)}
    rt = onnx_roundtrip(net, example, ["canvas"], {"points": {0: "N"}, "valid": {0: "N"}})
    for n, seed in [(400, 1), (3, 2), (0, 3)]:
        p = scan(n, seed)[:n] if n == 0 else scan(n, seed)
        ref, got = rt({"points": torch.from_numpy(p), "valid": torch.ones(len(p), dtype=torch.bool)})
        np.testing.assert_allclose(got["canvas"], ref["canvas"], atol=1e-5)


class _ScansAtOnce(torch.nn.Module):
    """PillarFeatureNet.scatter_frames over scans given as separate inputs, for export."""

    def __init__(self, net, count):
        super().__init__()
        self.net, self.count = net, count

    def forward(self, *scans):
        pts, frame = concat_scans(list(scans))
        return self.net.scatter_frames(pts, torch.ones(pts.shape[0], dtype=torch.bool), frame, self.count)


def test_scans_at_once_equal_scans_alone():
    """scatter_frames(): each scan's canvas and occupancy are those of the scan alone, also when
    a crowded pillar of one scan sits in the same cell as another scan's points."""
    net = make_net()
    scans = [scan(200, 5), scan(0, 6)[:0], scan(0, 7), scan(300, 8)]
    with torch.no_grad():
        canvas, occupied = _ScansAtOnce(net, len(scans))(*[torch.from_numpy(s) for s in scans])
        for k, s in enumerate(scans):
            alone, occ = net.scatter(torch.from_numpy(s), torch.ones(len(s), dtype=torch.bool))
            np.testing.assert_array_equal(canvas[k].numpy(), alone.numpy(), err_msg=f"scan {k}")
            np.testing.assert_array_equal(occupied[k].numpy(), occ.numpy(), err_msg=f"scan {k}")


def test_scans_at_once_onnx_matches_torch(onnx_roundtrip):
    net = make_net()
    example = {f"points_{k}": torch.from_numpy(scan(40, k)) for k in range(3)}
    rt = onnx_roundtrip(
        _ScansAtOnce(net, 3), example, ["canvas", "occupied"], {n: {0: f"N{k}"} for k, n in enumerate(example)}
    )
    for sizes in [(400, 3, 90), (0, 120, 0)]:
        inputs = {
            f"points_{k}": torch.from_numpy(scan(n, 10 + k)[: n if n == 0 else None]) for k, n in enumerate(sizes)
        }
        ref, got = rt(inputs)
        np.testing.assert_allclose(got["canvas"], ref["canvas"], atol=1e-5)
        assert np.array_equal(got["occupied"], ref["occupied"])


@pytest.mark.parametrize("voxel", [(0.0, 0.5, 8.0), (-0.5, 0.5, 8.0), (float("nan"), 0.5, 8.0)])
def test_a_voxel_size_that_is_not_positive_is_refused_by_name(voxel):
    with pytest.raises(ValueError, match="voxel_size entries must be > 0"):
        PillarConfig(**{**SMALL.__dict__, "voxel_size": voxel})


def test_batch_statistics_of_scans_run_alone_equal_the_batch_run_at_once():
    """Train mode: scans encoded one at a time inside PFNLayer.batch_statistics(the batch's input
    moments) give the canvases, the weight gradient and the running statistics of the batch
    encoded at once (OpenPCDet's BatchNorm1d over every slot of every scan); without it each
    scan normalises alone, and a z offset common to a scan's points would vanish."""
    scans = [torch.from_numpy(scan(200, 5)), torch.from_numpy(scan(300, 8) + np.float32([0, 0, 0.7, 0, 0]))]
    at_once, alone = make_net().train(), make_net().train()
    pts, frame = concat_scans(scans)
    joint = at_once.scatter_frames(pts, torch.ones(len(pts), dtype=torch.bool), frame, len(scans))[0]
    weights = torch.linspace(0, 1, joint.numel()).reshape(joint.shape)
    (joint * weights).sum().backward()
    layer = alone.pfn_layers[0]
    ones = [torch.ones(len(s), dtype=torch.bool) for s in scans]
    moments = alone.input_moments(scans[0], ones[0]) + alone.input_moments(scans[1], ones[1])
    with layer.batch_statistics(moments):
        for k, s in enumerate(scans):
            canvas = alone.scatter(s, ones[k])[0]
            torch.testing.assert_close(canvas, joint[k].detach(), atol=1e-5, rtol=1e-5)
            (canvas * weights[k]).sum().backward()
    torch.testing.assert_close(layer.linear.weight.grad, at_once.pfn_layers[0].linear.weight.grad, atol=1e-4, rtol=1e-4)
    for name in ("running_mean", "running_var", "num_batches_tracked"):
        torch.testing.assert_close(getattr(layer.norm, name), getattr(at_once.pfn_layers[0].norm, name))
    own = make_net().train().scatter(scans[1], ones[1])[0]
    assert (own - joint[1]).abs().max() > 1e-2


@pytest.mark.parametrize("seed", [0, 3])
def test_training_formulation_gives_the_canvas_and_gradient_of_the_export_one(seed):
    """PillarFeatureNet.pillars (non-empty pillars only, eager training) drawn onto a canvas by
    pillar_canvas == scatter's canvas, bit for bit, and so is the weight gradient (train-mode
    norm; the crowded pillar's cap and the points outside the grid included)."""
    pts = torch.from_numpy(scan(400, seed))
    valid = torch.from_numpy(np.random.default_rng(seed).random(len(pts)) > 0.1)
    dense, compact = make_net(seed=seed).train(), make_net(seed=seed).train()
    canvas, occupied = dense.scatter(pts, valid)
    features, cells = compact.pillars(pts, valid)
    nx, ny, _ = SMALL.grid_size
    drawn = pillar_canvas(features, cells, ny, nx)
    assert torch.equal(drawn, canvas) and torch.equal(cells, torch.nonzero(occupied)[:, 0])
    assert drawn.unsqueeze(0).is_contiguous(memory_format=torch.channels_last)
    weights = torch.randn(canvas.shape, generator=torch.Generator().manual_seed(seed))
    (canvas * weights).sum().backward()
    (drawn * weights).sum().backward()
    for a, b in zip(dense.parameters(), compact.parameters()):
        torch.testing.assert_close(b.grad, a.grad, atol=1e-5, rtol=1e-5)
