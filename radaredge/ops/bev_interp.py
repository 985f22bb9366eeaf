"""Bilinear interpolation of a BEV feature map at point positions, as OpenPCDet's
``bilinear_interpolate_torch`` (PV-RCNN's VoxelSetAbstraction ``interpolate_from_bev_features``).

For a map [C, H, W] (rows = y cells, columns = x cells) of a grid whose cell (0, 0) starts at
(x_min, y_min) (metres, radar frame) with cells of (vx, vy) metres and a feature stride ``stride``,
a point (x, y) reads the map at the continuous index

    u = (x - x_min) / vx / stride,   v = (y - y_min) / vy / stride

with x0 = floor(u), x1 = x0 + 1 (likewise y0, y1), all four clamped to [0, W - 1] / [0, H - 1],
and the weights computed from the *clamped* integer indices, exactly as upstream does:
wa = (x1 - u)(y1 - v) at (y0, x0), wb = (x1 - u)(v - y0) at (y1, x0), wc = (u - x0)(y1 - v) at
(y0, x1), wd = (u - x0)(v - y0) at (y1, x1). Inside the map the weights sum to 1; in the last
row/column (x1 clamped onto x0) they do not -- upstream's behaviour, kept.

Export formulation: one Gather per corner on the flattened map. Reference: a Python loop over
the points in numpy float32.
"""

from __future__ import annotations

import math

import numpy as np
import torch


def bev_interpolate(bev: torch.Tensor, xy: torch.Tensor, origin, cell, stride: int = 1) -> torch.Tensor:
    """Export formulation. bev [C, H, W], xy [K, 2] metres -> [K, C]."""
    c, h, w = bev.shape
    u = (xy[:, 0] - origin[0]) / cell[0] / stride
    v = (xy[:, 1] - origin[1]) / cell[1] / stride
    x0, y0 = torch.floor(u), torch.floor(v)
    x1 = torch.clamp(x0 + 1, 0, w - 1)
    y1 = torch.clamp(y0 + 1, 0, h - 1)
    x0, y0 = torch.clamp(x0, 0, w - 1), torch.clamp(y0, 0, h - 1)
    flat = bev.reshape(c, h * w).t()  # [H*W, C]

    def at(yi, xi):
        return flat[(yi * w + xi).to(torch.int64)]

    wa = (x1 - u) * (y1 - v)
    wb = (x1 - u) * (v - y0)
    wc = (u - x0) * (y1 - v)
    wd = (u - x0) * (v - y0)
    return (
        at(y0, x0) * wa.unsqueeze(1)
        + at(y1, x0) * wb.unsqueeze(1)
        + at(y0, x1) * wc.unsqueeze(1)
        + at(y1, x1) * wd.unsqueeze(1)
    )


def bev_interpolate_reference(bev: np.ndarray, xy: np.ndarray, origin, cell, stride: int = 1) -> np.ndarray:
    """Reference formulation, one point at a time (numpy float32). -> [K, C]."""
    bev = np.asarray(bev, np.float32)
    c, h, w = bev.shape
    f32 = np.float32
    out = np.zeros((len(xy), c), np.float32)
    for k, (x, y) in enumerate(np.asarray(xy, np.float32)):
        u = (x - f32(origin[0])) / f32(cell[0]) / f32(stride)
        v = (y - f32(origin[1])) / f32(cell[1]) / f32(stride)
        x0, y0 = math.floor(u), math.floor(v)
        x1, y1 = min(max(x0 + 1, 0), w - 1), min(max(y0 + 1, 0), h - 1)
        x0, y0 = min(max(x0, 0), w - 1), min(max(y0, 0), h - 1)
        wa = (f32(x1) - u) * (f32(y1) - v)
        wb = (f32(x1) - u) * (v - f32(y0))
        wc = (u - f32(x0)) * (f32(y1) - v)
        wd = (u - f32(x0)) * (v - f32(y0))
        out[k] = bev[:, y0, x0] * wa + bev[:, y1, x0] * wb + bev[:, y0, x1] * wc + bev[:, y1, x1] * wd
    return out
