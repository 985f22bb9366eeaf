"""Masked FPS, strict masked ball query, set abstraction and BEV interpolation: the export
formulation equals the loop reference, in torch and in onnxruntime."""

import numpy as np
import pytest
import torch
from conftest import assert_close

from radaredge.ops.bev_interp import bev_interpolate, bev_interpolate_reference
from radaredge.ops.point_sampling import (
    ball_query_masked,
    ball_query_masked_reference,
    farthest_point_sample_masked,
    farthest_point_sample_masked_reference,
)
from radaredge.ops.set_abstraction import SAModuleMSG, group_relative_reference


def _cloud(seed, n=80):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 1.5, (n, 3)).astype(np.float32)
    xyz[5:10] = xyz[0]  # duplicates: FPS distance ties at 0
    xyz[20:30] = np.round(xyz[20:30] * 2) / 2  # exact distance ties
    return xyz, rng


@pytest.mark.parametrize("seed, keep", [(0, 0.5), (1, 0.1), (2, 1.0), (3, 0.0)])
def test_masked_fps_matches_reference(seed, keep):
    xyz, rng = _cloud(seed)
    valid = rng.random(len(xyz)) < keep
    for npoint in (6, 32):  # fewer and more slots than valid points
        got = farthest_point_sample_masked(torch.from_numpy(xyz), torch.from_numpy(valid), npoint).numpy()
        ref = farthest_point_sample_masked_reference(xyz, valid, npoint)
        np.testing.assert_array_equal(got, ref, err_msg=f"keep {keep}, npoint {npoint}")
        if valid.any():
            assert got[0] == np.flatnonzero(valid)[0]  # starts at the first valid point
            assert valid[got].all()  # never an invalid point
        else:
            assert (got == 0).all()


def test_masked_fps_stops_after_the_given_picks():
    xyz, rng = _cloud(5)
    valid = rng.random(len(xyz)) < 0.7
    full = farthest_point_sample_masked_reference(xyz, valid, 20)
    for picks in (0, 1, 7, 20, 25):
        got = farthest_point_sample_masked(
            torch.from_numpy(xyz), torch.from_numpy(valid), 20, torch.tensor(picks)
        ).numpy()
        done = max(min(picks, 20), 1)  # slot 0 is the start in any case
        np.testing.assert_array_equal(got[:done], full[:done], err_msg=f"picks {picks}")
        assert (got[done:] == full[0]).all()  # the rest hold the start index
    empty = farthest_point_sample_masked(torch.zeros(0, 3), torch.zeros(0, dtype=torch.bool), 4, torch.tensor(0))
    assert empty.tolist() == [0, 0, 0, 0]


def test_masked_fps_line():
    xyz = np.zeros((12, 3), np.float32)
    xyz[:, 0] = np.arange(12)
    valid = np.ones(12, bool)
    valid[[0, 11]] = False  # the ends are masked out
    assert farthest_point_sample_masked_reference(xyz, valid, 3).tolist() == [1, 10, 5]
    assert farthest_point_sample_masked(torch.from_numpy(xyz), torch.from_numpy(valid), 3).tolist() == [1, 10, 5]


@pytest.mark.parametrize(
    "radius, nsample, strict", [(0.5, 8, True), (1.0, 16, True), (3.0, 4, True), (1e-4, 6, True), (1.0, 16, False)]
)
def test_masked_ball_query_matches_reference(radius, nsample, strict):
    xyz, rng = _cloud(4)
    valid = rng.random(len(xyz)) < 0.6
    centres = np.concatenate([xyz[:20], rng.normal(0, 3, (20, 3)).astype(np.float32)])
    got_idx, got_empty = ball_query_masked(
        torch.from_numpy(xyz)[None],
        torch.from_numpy(valid)[None],
        torch.from_numpy(centres)[None],
        radius,
        nsample,
        strict,
    )
    ref_idx, ref_empty = ball_query_masked_reference(xyz, valid, centres, radius, nsample, strict)
    np.testing.assert_array_equal(got_idx[0].numpy(), ref_idx)
    np.testing.assert_array_equal(got_empty[0].numpy(), ref_empty)
    assert valid[ref_idx[~ref_empty]].all()  # masked points are never hits


def test_ball_query_strict_boundary_and_empty():
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0, 0], [0, 0.2, 0]], np.float32)
    valid = np.array([True, True, True, False])
    centres = np.array([[0, 0, 0], [9, 9, 9]], np.float32)
    # point 1 lies exactly on the sphere of radius 1: a hit for <=, not for <; point 3 is masked
    for strict, row in ((True, [0, 2, 0, 0]), (False, [0, 1, 2, 0])):
        idx, empty = ball_query_masked_reference(xyz, valid, centres, 1.0, 4, strict)
        assert idx[0].tolist() == row and empty.tolist() == [False, True] and idx[1].tolist() == [0] * 4
        gi, ge = ball_query_masked(
            torch.from_numpy(xyz)[None], torch.from_numpy(valid)[None], torch.from_numpy(centres)[None], 1.0, 4, strict
        )
        assert gi[0].tolist() == idx.tolist() and ge[0].tolist() == empty.tolist()


def test_group_relative_reference_zeroes_empty_balls():
    xyz = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    feats = np.array([[10.0], [20.0]], np.float32)
    out = group_relative_reference(
        xyz, feats, np.array([[1, 1, 1], [0, 0, 0]], np.float32), np.array([[1, 0], [0, 0]]), np.array([False, True])
    )
    assert out[0].tolist() == [[3, 4, 5, 20], [0, 1, 2, 10]] and (out[1] == 0).all()


def _sa(seed=0):
    torch.manual_seed(seed)
    sa = SAModuleMSG(4, [0.4, 1.0], [8, 16], [[16, 16], [8, 12]]).eval()
    for m in sa.modules():  # non-trivial BN statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    return sa


def test_sa_module_matches_reference():
    sa = _sa()
    assert sorted(k for k in sa.state_dict() if k.endswith("weight")) == [
        f"mlps.{s}.{i}.weight" for s in (0, 1) for i in (0, 1, 3, 4)
    ]
    xyz, rng = _cloud(5, 120)
    xyz *= 0.5
    feats = rng.normal(size=(120, 4)).astype(np.float32)
    valid = rng.random(120) < 0.7
    centres = np.concatenate([xyz[:30], np.full((3, 3), 50.0, np.float32)])  # 3 empty balls
    with torch.no_grad():
        got = sa(*(torch.from_numpy(a) for a in (xyz, valid, feats, centres))).numpy()
        ref = sa.reference(xyz, valid, feats, centres).numpy()
    assert got.shape == (33, 28)
    assert_close(got, ref, 1e-5, "SA")
    with torch.no_grad():  # an empty ball gives MLP(0), not 0
        zero = sa.reference(xyz[:0], valid[:0], feats[:0], centres[-1:]).numpy()
    assert_close(got[-1], zero[0], 1e-6, "empty ball")
    assert np.abs(zero).max() > 0


def test_sa_module_in_training_mode_normalises_with_the_batch_like_the_upstream_modules():
    """radaredge train: every slot of every centre is one BatchNorm2d sample, as upstream's
    [1, C, S, K] layout makes it; both formulations give the same output, gradients and running
    averages (an empty ball's slots count too)."""
    import copy

    xyz, rng = _cloud(6, 120)
    xyz *= 0.5
    feats = rng.normal(size=(120, 4)).astype(np.float32)
    valid = rng.random(120) < 0.7
    centres = np.concatenate([xyz[:30], np.full((2, 3), 50.0, np.float32)])
    export, reference = _sa().train(), _sa().train()
    got = export(*(torch.from_numpy(a) for a in (xyz, valid, feats, centres)))
    ref = reference.reference(xyz, valid, feats, centres)
    assert_close(got.detach().numpy(), ref.detach().numpy(), 1e-4, "SA, batch statistics")
    assert not torch.allclose(
        got, copy.deepcopy(export).eval()(*(torch.from_numpy(a) for a in (xyz, valid, feats, centres)))
    )
    got.square().sum().backward()
    ref.square().sum().backward()
    for (name, a), b in zip(export.state_dict().items(), reference.state_dict().values()):
        assert_close(a.double().numpy(), b.double().numpy(), 1e-4, name)  # running averages updated alike
    for (name, a), b in zip(export.named_parameters(), reference.parameters()):
        assert_close(a.grad.numpy(), b.grad.numpy(), 1e-3 * float(b.grad.abs().max()), f"{name} gradient")


def test_bev_interpolate_matches_reference():
    rng = np.random.default_rng(6)
    bev = rng.normal(size=(5, 8, 10)).astype(np.float32)  # C, H (y), W (x)
    origin, cell = (0.0, -1.6), (0.16, 0.2)
    xy = np.stack([rng.uniform(-0.2, 1.8, 50), rng.uniform(-1.8, 0.2, 50)], 1).astype(np.float32)
    xy[0] = [0.0, -1.6]  # cell corner
    xy[1] = [1.6 - 1e-3, 0.0 - 1e-3]  # last column and row (clamped x1, y1)
    got = bev_interpolate(torch.from_numpy(bev), torch.from_numpy(xy), origin, cell, 2).numpy()
    ref = bev_interpolate_reference(bev, xy, origin, cell, 2)
    assert_close(got, ref, 1e-5, "bev")
    assert_close(ref[0], bev[:, 0, 0], 1e-6, "at a cell corner the map value")
    # halfway between two cells along x: the mean of the two
    mid = bev_interpolate_reference(bev, np.array([[0.16 * 2 * 1.5, -1.6]], np.float32), origin, cell, 2)
    assert_close(mid[0], (bev[:, 0, 1] + bev[:, 0, 2]) / 2, 1e-5, "halfway")


class _Ops(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.sa = _sa()

    def forward(self, xyz, valid, feats, bev):
        fps = farthest_point_sample_masked(xyz, valid, 16)
        centres = xyz[fps]
        idx, empty = ball_query_masked(xyz[None], valid[None], centres[None], 0.8, 8)
        return (
            fps,
            idx[0],
            empty[0],
            self.sa(xyz, valid, feats, centres),
            bev_interpolate(bev, xyz[:, :2], (-3.0, -3.0), (0.5, 0.5)),
        )


def test_onnx_roundtrip(onnx_roundtrip):
    def inputs(seed, n):
        xyz, rng = _cloud(seed, n)
        return {
            "xyz": torch.from_numpy(xyz),
            "valid": torch.from_numpy(rng.random(n) < 0.5),
            "feats": torch.from_numpy(rng.normal(size=(n, 4)).astype(np.float32)),
            "bev": torch.from_numpy(rng.normal(size=(3, 12, 12)).astype(np.float32)),
        }

    rt = onnx_roundtrip(
        _Ops(),
        inputs(0, 60),
        ["fps", "idx", "empty", "sa", "interp"],
        {"xyz": {0: "n"}, "valid": {0: "n"}, "feats": {0: "n"}},
    )
    for seed, n in ((1, 40), (2, 90)):
        ref, got = rt(inputs(seed, n))
        for k in ("fps", "idx", "empty"):
            np.testing.assert_array_equal(got[k], ref[k], err_msg=k)
        assert_close(got["sa"], ref["sa"], 1e-5, "sa")
        assert_close(got["interp"], ref["interp"], 1e-5, "interp")
