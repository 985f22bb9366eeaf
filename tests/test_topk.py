"""TopK in TensorRT-sized pieces (K < 3840 per TopK) equals one TopK, in torch and onnxruntime."""

import numpy as np
import pytest
import torch
from torch import nn

from radaredge.ops.topk import TOPK_LIMIT, topk_indices


class Largest(nn.Module):
    def __init__(self, k):
        super().__init__()
        self.k = k

    def forward(self, x):
        return topk_indices(x, self.k)


@pytest.mark.parametrize("k", [1, 100, TOPK_LIMIT, TOPK_LIMIT + 1, 5000, 9000])
def test_pieces_are_one_topk(k):
    x = torch.from_numpy(np.random.default_rng(k).permutation(10_000).astype(np.float64))  # no ties
    assert torch.equal(topk_indices(x, k), torch.topk(x, k).indices)


def test_every_exported_topk_stays_below_the_tensorrt_limit(onnx_roundtrip, tmp_path):
    import onnx

    x = torch.from_numpy(np.random.default_rng(0).permutation(9000).astype(np.float64))
    rt = onnx_roundtrip(Largest(8000), {"x": x}, ["idx"])
    ref, got = rt({"x": x})
    np.testing.assert_array_equal(got["idx"], ref["idx"])
    np.testing.assert_array_equal(got["idx"], torch.topk(x, 8000).indices.numpy())
    proto = onnx.load(str(tmp_path / "Largest.onnx"))
    ks = [
        onnx.numpy_helper.to_array(i).item()
        for n in proto.graph.node
        if n.op_type == "TopK"
        for i in proto.graph.initializer
        if i.name == n.input[1]
    ]
    ks += [
        onnx.numpy_helper.to_array(n2.attribute[0].t).item()
        for n in proto.graph.node
        if n.op_type == "TopK"
        for n2 in proto.graph.node
        if n2.op_type == "Constant" and n2.output[0] == n.input[1]
    ]
    assert ks and max(ks) < 3840, ks
