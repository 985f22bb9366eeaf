"""Multi-scale deformable attention (Zhu et al., Deformable DETR), as TDFANet eq. 8 uses it.

Convention (Deformable DETR's ``ms_deform_attn``):
- ``value`` [N, sum_l H_l*W_l, M, D]: M heads of D channels; the L levels' maps are flattened
  row-major (index = row*W + col) and concatenated in level order;
- ``spatial_shapes``: (H_l, W_l) per level, an int64 tensor [L, 2] or a list of (H, W) tuples;
  pass the list when exporting, so the traced graph splits the levels with static sizes;
- ``sampling_locations`` [N, Lq, M, L, P, 2]: normalised (x, y) in [0, 1] of each level's map,
  x across the width (columns), y across the height (rows); values outside [0, 1] are allowed;
- ``attention_weights`` [N, Lq, M, L, P], already normalised by the caller (softmax over L*P).

The output [N, Lq, M*D] is, per query and head, the attention-weighted sum of the bilinear
samples of the value map: a location (x, y) falls at continuous pixel coordinates
(col, row) = (x*W - 0.5, y*H - 0.5), pixel centres at integers (align_corners=False), and pixels
outside the map read as zero. :func:`ms_deform_attn` computes it with ``grid_sample`` (grid
2*loc - 1), :func:`ms_deform_attn_reference` by gathering the four neighbouring pixels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import ConfigError, InputError
from .alignment import bilinear_sample_reference


def _shape_list(spatial_shapes) -> list[tuple[int, int]]:
    """(H, W) of every level as Python ints, from a tensor [L, 2] or a list of pairs."""
    rows = spatial_shapes.tolist() if isinstance(spatial_shapes, torch.Tensor) else spatial_shapes
    return [(int(h), int(w)) for h, w in rows]


def _level_shapes(spatial_shapes, value: torch.Tensor, sampling_locations: torch.Tensor) -> list[tuple[int, int]]:
    """:func:`_shape_list`, checked against ``value`` and ``sampling_locations``."""
    shapes = _shape_list(spatial_shapes)
    total = sum(h * w for h, w in shapes)
    if value.shape[1] != total:
        raise InputError(f"value has {value.shape[1]} positions but spatial_shapes {shapes} hold {total}")
    if sampling_locations.shape[3] != len(shapes):
        raise InputError(
            f"sampling_locations has {sampling_locations.shape[3]} levels (axis 3), spatial_shapes has {len(shapes)}"
        )
    return shapes


def _level_maps(value: torch.Tensor, shapes: list[tuple[int, int]]) -> list[torch.Tensor]:
    """Split ``value`` [N, sum HW, M, D] into one [N*M, D, H, W] image per level."""
    n, _, m, d = value.shape
    parts = value.split([h * w for h, w in shapes], dim=1)
    return [p.permute(0, 2, 3, 1).reshape(n * m, d, h, w) for p, (h, w) in zip(parts, shapes)]


def _weighted_sum(samples: list[torch.Tensor], attention_weights: torch.Tensor) -> torch.Tensor:
    """Per-level samples [N*M, D, Lq, P] and head-major weights [N, M, Lq, L, P] -> output
    [N, M*D, Lq], channels first (channel m*D + d is head m's channel d)."""
    n, m, lq, levels, p = attention_weights.shape
    stacked = torch.stack(samples, -2).flatten(-2)  # [N*M, D, Lq, L*P]
    out = (stacked * attention_weights.reshape(n * m, 1, lq, levels * p)).sum(-1)  # [N*M, D, Lq]
    return out.reshape(n, m * out.shape[1], lq)


def ms_deform_attn(
    value: torch.Tensor, spatial_shapes, sampling_locations: torch.Tensor, attention_weights: torch.Tensor
) -> torch.Tensor:
    """Export formulation of multi-scale deformable attention -> [N, Lq, M*D] (module docstring)."""
    grids = (2.0 * sampling_locations - 1.0).transpose(1, 2)
    return ms_deform_attn_heads(value, spatial_shapes, grids, attention_weights.transpose(1, 2)).transpose(1, 2)


def ms_deform_attn_heads(
    value: torch.Tensor, spatial_shapes, grids: torch.Tensor, attention_weights: torch.Tensor
) -> torch.Tensor:
    """:func:`ms_deform_attn` in the layout grid_sample works in: locations already in its [-1, 1]
    coordinates (grid = 2 * location - 1), heads before queries (grids [N, M, Lq, L, P, 2],
    weights [N, M, Lq, L, P]), output channels first, [N, M*D, Lq]."""
    n, m, lq, levels, p, _ = grids.shape
    shapes = _level_shapes(spatial_shapes, value, grids)
    samples = []
    # one level needs no slice (a slice copies every sample location)
    per_level = grids.unbind(3) if levels > 1 else [grids]
    for level_grid, image in zip(per_level, _level_maps(value, shapes)):
        grid = level_grid.reshape(n * m, lq, p, 2)
        samples.append(F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False))
    return _weighted_sum(samples, attention_weights)


def ms_deform_attn_reference(
    value: torch.Tensor, spatial_shapes, sampling_locations: torch.Tensor, attention_weights: torch.Tensor
) -> torch.Tensor:
    """Reference formulation: explicit four-corner bilinear gathers at (x*W - 0.5, y*H - 0.5)."""
    shapes = _level_shapes(spatial_shapes, value, sampling_locations)
    n, lq, m, _, p, _ = sampling_locations.shape
    samples = []
    for level, (image, (h, w)) in enumerate(zip(_level_maps(value, shapes), shapes)):
        loc = sampling_locations[:, :, :, level].transpose(1, 2).reshape(n * m, lq * p, 2)
        got = bilinear_sample_reference(image, loc[..., 1] * h - 0.5, loc[..., 0] * w - 0.5)
        samples.append(got.reshape(n * m, -1, lq, p))
    return _weighted_sum(samples, attention_weights.transpose(1, 2)).transpose(1, 2)


class MSDeformAttn(nn.Module):
    """Deformable DETR's multi-scale deformable attention module (same parameters and init).

    forward(query [N, Lq, C], reference_points [N, Lq, L, 2] normalised (x, y) in [0, 1],
    value_flat [N, sum HW, C], spatial_shapes, padding_mask [N, sum HW] bool (True = padding,
    read as zero) or None, reference=False) -> [N, Lq, C]. Each head predicts P offsets per level
    in pixels of that level, normalised by the level's (W, H) and added to the reference point;
    ``reference=True`` samples with :func:`ms_deform_attn_reference` instead of grid_sample.
    """

    def __init__(self, d_model: int = 256, n_levels: int = 4, n_heads: int = 8, n_points: int = 4):
        super().__init__()
        if d_model % n_heads:
            raise ConfigError(f"d_model ({d_model}) must be divisible by n_heads ({n_heads})")
        self.d_model, self.n_levels, self.n_heads, self.n_points = d_model, n_levels, n_heads, n_points
        self.sampling_offsets = nn.Linear(d_model, n_heads * n_levels * n_points * 2)
        self.attention_weights = nn.Linear(d_model, n_heads * n_levels * n_points)
        self.value_proj = nn.Linear(d_model, d_model)
        self.output_proj = nn.Linear(d_model, d_model)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Deformable DETR init: offset biases point head h in direction 2*pi*h/M on the square
        ring (max-norm 1), point k at distance k+1 pixels; zero offset and attention weights."""
        nn.init.zeros_(self.sampling_offsets.weight)
        theta = torch.arange(self.n_heads, dtype=torch.float32) * (2.0 * math.pi / self.n_heads)
        ring = torch.stack([theta.cos(), theta.sin()], -1)
        ring = ring / ring.abs().max(-1, keepdim=True).values  # [M, 2]
        scale = torch.arange(1, self.n_points + 1, dtype=torch.float32).view(1, 1, -1, 1)
        bias = ring.view(self.n_heads, 1, 1, 2) * scale  # [M, 1, P, 2]
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(bias.expand(-1, self.n_levels, -1, -1).reshape(-1))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        for proj in (self.value_proj, self.output_proj):
            nn.init.xavier_uniform_(proj.weight)
            nn.init.zeros_(proj.bias)

    def forward(
        self,
        query: torch.Tensor,
        reference_points: torch.Tensor,
        value_flat: torch.Tensor,
        spatial_shapes,
        padding_mask: torch.Tensor | None = None,
        reference: bool = False,
    ) -> torch.Tensor:
        n, lq, _ = query.shape
        m, levels, p = self.n_heads, self.n_levels, self.n_points
        if reference_points.shape[2:] != (levels, 2):
            raise InputError(f"reference_points must be [N, Lq, {levels}, 2], got {list(reference_points.shape)}")
        value = self.value_proj(value_flat)
        if padding_mask is not None:
            value = value.masked_fill(padding_mask[..., None], 0.0)
        value = value.reshape(n, value.shape[1], m, self.d_model // m)
        size_xy = torch.tensor(
            [[w, h] for h, w in _shape_list(spatial_shapes)], dtype=query.dtype, device=query.device
        )  # [L, 2]
        if reference:
            weights = self.attention_weights(query).reshape(n, lq, m, levels * p).softmax(-1)
            weights = weights.reshape(n, lq, m, levels, p)
            offsets = self.sampling_offsets(query).reshape(n, lq, m, levels, p, 2)
            locations = reference_points[:, :, None, :, None, :] + offsets / size_xy[:, None, :]
            return self.output_proj(ms_deform_attn_reference(value, spatial_shapes, locations, weights))
        # The same locations in grid_sample coordinates, 2 * (ref + offset / size) - 1. The factor
        # 2 / size per offset column folds into the projection's weights (constants at export), so
        # the graph has no broadcast divide over every sample. Both projections run head-major,
        # [N, 1, Lq, C] @ [M, C, K] -> [N, M, Lq, K]: grids and weights come out in grid_sample's
        # layout, and the graph transposes none of these per-sample tensors.
        c = self.d_model
        scale = (2.0 / size_xy).view(1, levels, 1, 2).expand(m, levels, p, 2).reshape(-1)
        w_off = (self.sampling_offsets.weight * scale[:, None]).reshape(m, levels * p * 2, c).transpose(1, 2)
        b_off = (self.sampling_offsets.bias * scale).reshape(m, 1, levels * p * 2)
        w_att = self.attention_weights.weight.reshape(m, levels * p, c).transpose(1, 2)
        b_att = self.attention_weights.bias.reshape(m, 1, levels * p)
        rows = query.unsqueeze(1)  # [N, 1, Lq, C]
        # The biases are expanded over the queries and the offset bias joins the reference grid
        # (laid out like the offset columns), so each sum is one add of [1, M, Lq, K] operands
        # broadcast over N only: a broadcast over an inner axis of 2 or P is slow in onnxruntime.
        # onnxruntime folds the expanded bias at session start, and the grid base too when the
        # reference points are constants (the DFA layers' cell centres).
        ref_grid = (2.0 * reference_points - 1.0)[:, None, :, :, None, :].expand(-1, -1, -1, -1, p, -1)
        grid_base = ref_grid.reshape(ref_grid.shape[0], 1, lq, -1) + b_off.unsqueeze(0)
        grids = grid_base + torch.matmul(rows, w_off)
        logits = b_att.unsqueeze(0).expand(-1, -1, lq, -1) + torch.matmul(rows, w_att)
        head_weights = logits.softmax(-1)  # [N, M, Lq, L*P]
        out = ms_deform_attn_heads(
            value, spatial_shapes, grids.reshape(n, m, lq, levels, p, 2), head_weights.reshape(n, m, lq, levels, p)
        )
        return self.output_proj(out.transpose(1, 2))
