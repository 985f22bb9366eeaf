"""Multiply-accumulates per inference and the machine's measured fp32 GEMM peak.

Counting runs the export formulation once under torch's FlopCounterMode, which counts matrix
products and convolutions. We add the work that common counters report as zero:
- bilinear sampling (``grid_sample``: alignment and deformable attention) counts 4 MACs per
  output element and channel, one per corner;
- scatter reductions (``index_add``, ``scatter_reduce``: the pillar scatter and the density
  map) count 1 MAC per source element.
Pointwise ops (activations, norms, masks) are not counted.
"""

from __future__ import annotations

import math
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

aten = torch.ops.aten


def _numel(shape) -> int:
    return math.prod(shape) if shape is not None else 0


def _grid_sample_flops(input_shape, grid_shape, *args, out_shape=None, **kwargs) -> int:
    n, c = input_shape[0], input_shape[1]
    return 2 * 4 * n * c * grid_shape[1] * grid_shape[2]


def _index_add_flops(self_shape, dim, index_shape, source_shape, *args, out_shape=None, **kwargs) -> int:
    return 2 * _numel(source_shape)


def _scatter_reduce_flops(self_shape, dim, index_shape, src_shape, *args, out_shape=None, **kwargs) -> int:
    return 2 * _numel(src_shape)


EXTRA_FORMULAS = {
    aten.grid_sampler_2d: _grid_sample_flops,
    aten.index_add: _index_add_flops,
    aten.scatter_reduce.two: _scatter_reduce_flops,
}


def count_macs(run, *args) -> dict[str, float]:
    """MACs of ``run(*args)`` by aten op name, plus a ``total`` entry."""
    counter = FlopCounterMode(display=False, custom_mapping=EXTRA_FORMULAS)
    with counter, torch.no_grad():
        run(*args)
    per_op: dict[str, float] = {}
    for op, flops in counter.get_flop_counts()["Global"].items():
        name = str(op).split(".")[1] if str(op).startswith("aten.") else str(op)
        per_op[name] = per_op.get(name, 0.0) + flops / 2
    per_op["total"] = counter.get_total_flops() / 2
    return per_op


def gemm_peak_gflops(threads: int = 2, size: int = 1024, repeats: int = 20) -> float:
    """Measured fp32 GEMM peak (GFLOP/s) of torch on ``threads`` threads: the fastest of
    ``repeats`` products of two ``size`` x ``size`` matrices after one warm-up (a peak is the
    best the machine sustains; slower repeats are interference from other load)."""
    torch.set_num_threads(threads)
    a = torch.randn(size, size)
    b = torch.randn(size, size)
    torch.mm(a, b)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.mm(a, b)
        times.append(time.perf_counter() - t0)
    return 2 * size**3 / min(times) / 1e9
