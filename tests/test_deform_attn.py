"""Multi-scale deformable attention: grid_sample path == gather reference, pixel-centre
exactness, Deformable DETR init, padding mask, ONNX round trips of the op and the module."""

import pytest
import torch
from conftest import assert_close
from torch import nn

from radaredge.errors import ConfigError, InputError
from radaredge.ops.deform_attn import MSDeformAttn, ms_deform_attn, ms_deform_attn_reference

SHAPES = [(9, 13), (5, 7), (3, 4)]


def random_inputs(shapes, n=2, lq=17, heads=3, dim=4, points=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    levels = len(shapes)
    value = torch.randn(n, sum(h * w for h, w in shapes), heads, dim, generator=g)
    loc = torch.rand(n, lq, heads, levels, points, 2, generator=g) * 1.4 - 0.2  # [-0.2, 1.2]
    weights = torch.rand(n, lq, heads, levels * points, generator=g).softmax(-1)
    return value, loc, weights.reshape(n, lq, heads, levels, points)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_export_matches_reference(seed):
    value, loc, weights = random_inputs(SHAPES, seed=seed)
    got = ms_deform_attn(value, torch.tensor(SHAPES), loc, weights)
    assert got.shape == (2, 17, 3 * 4)
    assert_close(got, ms_deform_attn_reference(value, SHAPES, loc, weights), 1e-5, "grid_sample vs gather")


def test_pixel_centres_return_pixel_values_and_outside_reads_zero():
    shapes = [(4, 6), (2, 3)]
    value = torch.arange(30 * 2, dtype=torch.float32).reshape(1, 30, 1, 2)
    # query 0: pixel centre (row 2, col 5) of level 0; query 1: between cols 0 and 1 of level 1's
    # row 1; query 2: far outside level 0.
    loc = torch.zeros(1, 3, 1, 2, 1, 2)
    loc[0, 0, 0, 0, 0] = torch.tensor([5.5 / 6, 2.5 / 4])
    loc[0, 1, 0, 1, 0] = torch.tensor([1.0 / 3, 1.5 / 2])
    loc[0, 2, 0, 0, 0] = torch.tensor([-0.5, 0.3])
    weights = torch.zeros(1, 3, 1, 2, 1)
    weights[0, 0, 0, 0], weights[0, 1, 0, 1], weights[0, 2, 0, 0] = 1.0, 1.0, 1.0
    level1 = value[0, 24:, 0].reshape(2, 3, 2)
    expected = torch.stack([value[0, 2 * 6 + 5, 0], (level1[1, 0] + level1[1, 1]) / 2, torch.zeros(2)])[None]
    assert torch.equal(ms_deform_attn_reference(value, shapes, loc, weights), expected)
    assert_close(ms_deform_attn(value, shapes, loc, weights), expected, 1e-5, "grid_sample")


def test_shape_mismatches_are_input_errors():
    value, loc, weights = random_inputs(SHAPES)
    with pytest.raises(InputError, match="positions"):
        ms_deform_attn(value, SHAPES[:2], loc[:, :, :, :2], weights[:, :, :, :2])
    with pytest.raises(InputError, match="levels"):
        ms_deform_attn_reference(value, SHAPES, loc[:, :, :, :2], weights)


def value_flat(shapes, n=2, d_model=16, seed=1):
    return torch.randn(n, sum(h * w for h, w in shapes), d_model, generator=torch.Generator().manual_seed(seed))


def randomise(module, seed=0):
    """Non-zero attention weights, so the softmax is not uniform (init leaves them zero)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.attention_weights.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
        module.sampling_offsets.weight.copy_(torch.randn(module.sampling_offsets.weight.shape, generator=g) * 0.3)
    return module.eval()


def test_module_reference_path_matches_export_path():
    torch.manual_seed(0)
    attn = randomise(MSDeformAttn(16, n_levels=3, n_heads=4, n_points=2))
    g = torch.Generator().manual_seed(2)
    query, ref = torch.randn(2, 11, 16, generator=g), torch.rand(2, 11, 3, 2, generator=g)
    value = value_flat(SHAPES)
    with torch.no_grad():
        got = attn(query, ref, value, SHAPES)
        expected = attn(query, ref, value, torch.tensor(SHAPES), reference=True)
    assert_close(got, expected, 1e-5, "module")


def test_deformable_detr_init():
    attn = MSDeformAttn(32, n_levels=2, n_heads=8, n_points=3)
    bias = attn.sampling_offsets.bias.detach().reshape(8, 2, 3, 2)
    assert torch.equal(bias[0, 1, 2], torch.tensor([3.0, 0.0]))  # head 0: +x, point k at k+1
    assert torch.allclose(bias[1, 0, 0], torch.tensor([1.0, 1.0]))  # head 1: 45 deg on the ring
    assert torch.allclose(bias[6, 0, 1], torch.tensor([0.0, -2.0]), atol=1e-6)  # head 6: 270 deg
    assert not attn.sampling_offsets.weight.any() and not attn.attention_weights.weight.any()
    with pytest.raises(ConfigError):
        MSDeformAttn(30, n_heads=8)


def test_offsets_are_in_pixels_of_each_level():
    """With zero attention logits and init offsets, head 0's points sit k+1 pixels right of the
    reference point: on a constant-per-column map the output is the mean of those columns."""
    attn = MSDeformAttn(2, n_levels=1, n_heads=1, n_points=2)
    with torch.no_grad():
        attn.value_proj.weight.copy_(torch.eye(2))
        attn.output_proj.weight.copy_(torch.eye(2))
    h, w = 3, 8
    cols = torch.arange(w, dtype=torch.float32).repeat(h)  # value = column index
    value = torch.stack([cols, -cols], -1)[None]
    ref = torch.tensor([[[[2.5 / w, 1.5 / h]]]])  # centre of (row 1, col 2)
    with torch.no_grad():
        out = attn(torch.zeros(1, 1, 2), ref, value, [(h, w)])
    assert_close(out, torch.tensor([[[3.5, -3.5]]]), 1e-5, "offset units")  # cols 3 and 4


def test_padding_mask_zeroes_masked_values():
    torch.manual_seed(0)
    attn = randomise(MSDeformAttn(16, n_levels=1, n_heads=4, n_points=4))
    shapes = [(6, 5)]
    value = value_flat(shapes)
    mask = torch.zeros(2, 30, dtype=torch.bool)
    mask[:, 20:] = True
    query, ref = torch.randn(2, 7, 16), torch.rand(2, 7, 1, 2)
    with torch.no_grad():
        masked = attn(query, ref, value, shapes, mask)
        junk = value.clone()
        junk[:, 20:] = 1e3
        assert_close(attn(query, ref, junk, shapes, mask), masked, 1e-5, "masked positions ignored")
        assert (attn(query, ref, value, shapes) - masked).abs().max() > 1e-3


class DeformOp(nn.Module):
    def __init__(self, shapes):
        super().__init__()
        self.shapes = shapes

    def forward(self, value, sampling_locations, attention_weights):
        return ms_deform_attn(value, self.shapes, sampling_locations, attention_weights)


def test_onnx_export_of_the_op(onnx_roundtrip):
    value, loc, weights = random_inputs(SHAPES)
    example = {"value": value, "sampling_locations": loc, "attention_weights": weights}
    rt = onnx_roundtrip(
        DeformOp(SHAPES), example, ["out"], {"sampling_locations": {1: "Lq"}, "attention_weights": {1: "Lq"}}
    )
    for lq, seed in [(17, 1), (40, 2), (1, 3)]:
        value, loc, weights = random_inputs(SHAPES, lq=lq, seed=seed)
        ref, got = rt({"value": value, "sampling_locations": loc, "attention_weights": weights})
        assert_close(got["out"], ref["out"], 1e-5, "onnxruntime vs torch")


class AttnWithShapes(nn.Module):
    def __init__(self, attn, shapes):
        super().__init__()
        self.attn, self.shapes = attn, shapes

    def forward(self, query, reference_points, value_flat):
        return self.attn(query, reference_points, value_flat, self.shapes)


@pytest.mark.parametrize("shapes", [[(12, 10)], SHAPES], ids=["one-level", "three-levels"])
def test_onnx_export_of_the_module(onnx_roundtrip, shapes):
    torch.manual_seed(0)
    attn = randomise(MSDeformAttn(16, n_levels=len(shapes), n_heads=4, n_points=2))
    module = AttnWithShapes(attn, shapes)

    def inputs(n, lq, seed):
        g = torch.Generator().manual_seed(seed)
        return {
            "query": torch.randn(n, lq, 16, generator=g),
            "reference_points": torch.rand(n, lq, len(shapes), 2, generator=g) * 1.2 - 0.1,
            "value_flat": value_flat(shapes, n=n, seed=seed),
        }

    rt = onnx_roundtrip(module, inputs(2, 9, 0), ["out"], {"query": {1: "Lq"}, "reference_points": {1: "Lq"}})
    for lq, seed in [(9, 1), (33, 2)]:
        feeds = inputs(2, lq, seed)
        ref, got = rt(feeds)
        assert_close(got["out"], ref["out"], 1e-5, "onnxruntime vs torch")
        with torch.no_grad():
            reference = attn(*feeds.values(), shapes, reference=True)
        assert_close(got["out"], reference, 1e-5, "onnxruntime vs reference sampler")
