"""Sparse pillar attention: slot-gathered export formulation == upstream's boolean-mask reference."""

from __future__ import annotations

import pytest
import torch
from conftest import assert_close

from radaredge.ops.pillar_attention import SparsePillarAttention, sparse_pillar_attention_reference


def _scene(seed, ny=24, nx=20, c=16, pillars=30):
    g = torch.Generator().manual_seed(seed)
    occupied = torch.zeros(ny * nx, dtype=torch.bool)
    occupied[torch.randperm(ny * nx, generator=g)[:pillars]] = True
    canvas = torch.randn(c, ny * nx, generator=g) * occupied
    return canvas.reshape(c, ny, nx), occupied


def _spa(c=16, capacity=64):
    torch.manual_seed(0)
    return SparsePillarAttention(c, capacity).eval()


def test_matches_reference_and_ignores_padding():
    spa = _spa()
    for seed, pillars in [(0, 30), (1, 1), (2, 64), (3, 0)]:
        canvas, occ = _scene(seed, pillars=pillars)
        with torch.no_grad():
            ref = sparse_pillar_attention_reference(spa.pillar_attention_rope, canvas, occ)
            for n_points in (pillars, pillars + 5, 500):  # slots = min(points, capacity)
                got, num, overflow = spa(canvas, occ, n_points)
                assert_close(got.numpy(), ref.numpy(), 1e-5, f"seed {seed} points {n_points}")
                assert int(num) == pillars and not bool(overflow)
        assert (ref.reshape(16, -1)[:, ~occ] == 0).all()  # empty cells stay empty


def test_overflow_is_reported():
    spa = _spa(capacity=10)
    canvas, occ = _scene(4, pillars=25)
    with torch.no_grad():
        _, num, overflow = spa(canvas, occ, 100)
    assert int(num) == 25 and bool(overflow)


@pytest.mark.parametrize("pillars, capacity", [(30, 64), (25, 10), (1, 64)])
def test_training_formulation_gives_the_export_output_and_gradient(pillars, capacity):
    """forward_pillars on the non-empty pillars == forward on the canvas (an overflowing scan's
    first ``capacity`` pillars by cell attend, the rest stay 0), values and weight gradients;
    k_mlp's bias is left out: softmax cancels it, so its gradient is float noise in both."""
    canvas, occ = _scene(5, pillars=pillars)
    c, ny, nx = canvas.shape
    cells = torch.nonzero(occ)[:, 0]
    features = canvas.reshape(c, -1)[:, cells].T.contiguous()
    export, training = _spa(capacity=capacity), _spa(capacity=capacity)
    want, num, overflow = export(canvas, occ, 200)
    got, num_t, overflow_t = training.forward_pillars(features, cells, ny, nx)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    assert (int(num_t), bool(overflow_t)) == (int(num), bool(overflow)) == (pillars, pillars > capacity)
    weights = torch.randn(want.shape, generator=torch.Generator().manual_seed(1))
    (want * weights).sum().backward()
    (got * weights).sum().backward()
    for (name, a), b in zip(export.named_parameters(), training.parameters()):
        if name != "pillar_attention_rope.k_mlp.bias":
            torch.testing.assert_close(b.grad, a.grad, atol=1e-4, rtol=1e-4, msg=name)


def test_onnx_roundtrip_any_point_count(onnx_roundtrip):
    class Wrap(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.spa = _spa()

        def forward(self, canvas, occupied, points):
            return self.spa(canvas, occupied, points.shape[0])

    canvas, occ = _scene(5)
    rt = onnx_roundtrip(
        Wrap(),
        {"canvas": canvas, "occupied": occ, "points": torch.zeros(40, 3)},
        ["out", "num", "overflow"],
        {"points": {0: "n"}},
    )
    spa = rt.module.spa
    for seed, pillars, n in [(6, 30, 31), (7, 5, 5), (8, 0, 0), (9, 64, 300), (10, 70, 80)]:
        canvas, occ = _scene(seed, pillars=pillars)
        ref, got = rt({"canvas": canvas, "occupied": occ, "points": torch.zeros(n, 3)})
        assert_close(got["out"], ref["out"], 1e-5, f"seed {seed}")
        assert int(got["num"]) == pillars and bool(got["overflow"]) == (pillars > spa.capacity)
        if pillars <= spa.capacity:
            with torch.no_grad():
                expect = sparse_pillar_attention_reference(spa.pillar_attention_rope, canvas, occ).numpy()
            assert_close(got["out"], expect, 1e-5, f"seed {seed} vs reference")
