"""FPS, ball query and grouping: the dense export formulation equals the loop reference, in torch
and in onnxruntime."""

import numpy as np
import pytest
import torch

from radaredge.ops.point_sampling import (
    ball_query,
    ball_query_reference,
    farthest_point_sample,
    farthest_point_sample_reference,
    group_points,
    group_points_reference,
)


def _sets(seed, g=5, n=64):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(g, n, 3)).astype(np.float32)
    xyz[1] = xyz[1, rng.integers(0, 5, n)]  # only 5 distinct points: FPS must repeat
    xyz[2, :, 2] = 0.0  # a flat set
    xyz[3] = np.round(xyz[3] * 2) / 2  # many exact distance ties
    return xyz


@pytest.mark.parametrize("seed", [0, 1])
def test_fps_matches_reference(seed):
    xyz = _sets(seed)
    got = farthest_point_sample(torch.from_numpy(xyz), 24).numpy()
    for g in range(len(xyz)):
        np.testing.assert_array_equal(got[g], farthest_point_sample_reference(xyz[g], 24), err_msg=f"set {g}")
    assert got[:, 0].tolist() == [0] * len(xyz)
    assert len(set(got[0].tolist())) == 24  # distinct points are never picked twice


def test_fps_spreads_out():
    """On a line of points the first picks are the start, the far end and the middle."""
    xyz = np.zeros((11, 3), np.float32)
    xyz[:, 0] = np.arange(11)
    assert farthest_point_sample_reference(xyz, 3).tolist() == [0, 10, 5]
    assert farthest_point_sample(torch.from_numpy(xyz[None]), 3)[0].tolist() == [0, 10, 5]


@pytest.mark.parametrize("radius, nsample", [(0.5, 8), (1.0, 16), (3.0, 4), (1e-4, 6)])
def test_ball_query_matches_reference(radius, nsample):
    xyz = _sets(3)
    centres_idx = np.stack([farthest_point_sample_reference(x, 16) for x in xyz])
    centres = np.take_along_axis(xyz, centres_idx[..., None], 1)
    got = ball_query(torch.from_numpy(xyz), torch.from_numpy(centres), radius, nsample).numpy()
    for g in range(len(xyz)):
        np.testing.assert_array_equal(
            got[g], ball_query_reference(xyz[g], centres[g], radius, nsample), err_msg=f"set {g}"
        )


def test_ball_query_conventions():
    xyz = np.array([[0, 0, 0], [5, 0, 0], [0.5, 0, 0], [0.2, 0, 0]], np.float32)
    centres = np.array([[0, 0, 0], [5, 0, 0], [9, 9, 9]], np.float32)
    ref = ball_query_reference(xyz, centres, 0.6, 5)
    assert ref.tolist() == [[0, 2, 3, 0, 0], [1, 1, 1, 1, 1], [0, 0, 0, 0, 0]]
    got = ball_query(torch.from_numpy(xyz[None]), torch.from_numpy(centres[None]), 0.6, 5)[0]
    assert got.tolist() == ref.tolist()


def test_group_points_matches_reference():
    rng = np.random.default_rng(4)
    feats = rng.normal(size=(3, 20, 7)).astype(np.float32)
    idx = rng.integers(0, 20, (3, 6, 4))
    got = group_points(torch.from_numpy(feats), torch.from_numpy(idx)).numpy()
    for g in range(3):
        np.testing.assert_array_equal(got[g], group_points_reference(feats[g], idx[g]))


class _Sampler(torch.nn.Module):
    def forward(self, xyz):
        fps = farthest_point_sample(xyz, 16)
        centres = torch.gather(xyz, 1, fps.unsqueeze(-1).expand(-1, -1, 3))
        nb = ball_query(xyz, centres, 0.8, 8)
        return fps, nb, group_points(xyz, nb)


def test_onnx_roundtrip(onnx_roundtrip):
    rt = onnx_roundtrip(
        _Sampler(), {"xyz": torch.from_numpy(_sets(0, n=48))}, ["fps", "neighbours", "grouped"], {"xyz": {0: "sets"}}
    )
    for seed in (1, 2):
        ref, got = rt({"xyz": torch.from_numpy(_sets(seed, g=3 + seed, n=48))})
        np.testing.assert_array_equal(got["fps"], ref["fps"])
        np.testing.assert_array_equal(got["neighbours"], ref["neighbours"])
        np.testing.assert_array_equal(got["grouped"], ref["grouped"])
