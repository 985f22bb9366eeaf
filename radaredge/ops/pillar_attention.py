"""MAFF-Net's sparse pillar attention (SPA): one single-head attention over the non-empty pillars.

What it computes, as upstream's ``PointPillarScatter_spa`` / ``PillarAttentionWithRoPE``
(TRV-Lab/MAFF-Net, pcdet/models/backbones_2d/map_to_bev) does for one scan, on the pillar canvas
[C, ny, nx] (OpenPCDet layout, row = y cell) and the set of non-empty pillars:

1. rotary position term: with half = C / 2, theta_i = 10000^(-i / half), row coordinate
   h = linspace(-1, 1, ny)[iy], column coordinate w = linspace(-1, 1, nx)[ix] and the channel
   halves x1, x2: rope(x) = [x1 cos(h θ) cos(w θ) - x2 sin(h θ) sin(w θ),
   x1 sin(h θ) sin(w θ) + x2 cos(h θ) cos(w θ)]; every cell becomes f = x + rope(x) (empty
   cells stay 0);
2. over the non-empty pillars only: n = LayerNorm1(f); Q, K, V = Linear(n) (64 -> 64 each);
   a = softmax(Q K^T) V (no 1/sqrt(d) scaling, as upstream) + f;
   out = FFN(LayerNorm2(a)) + a with FFN = Linear, GELU, Linear;
3. the non-empty cells of the canvas take ``out``; every other cell is 0.

Export formulation (:class:`SparsePillarAttention`): the non-empty pillars are gathered into
S = min(N points, capacity) slots with a TopK over the cell index (no NonZero); padded slots are
masked out of the keys and dropped on the way back. A scan cannot have more non-empty pillars
than points, so the slots are only ever short when the scan has more than ``capacity`` pillars:
then ``overflow`` is True and callers must report it (the runtime raises CapacityError), the
capacity being a model-card field.

Training formulation (:meth:`SparsePillarAttention.forward_pillars`): the same attention on the
non-empty pillars as :meth:`radaredge.ops.pillars.PillarFeatureNet.pillars` lists them, for
eager training (no canvas-wide gather or scatter in the backward).

Reference formulation (:func:`sparse_pillar_attention_reference`): boolean-mask indexing of the
dense canvas (NonZero), as upstream.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .pillars import pillar_canvas


def rope_angles(h: torch.Tensor, w: torch.Tensor, channels: int):
    """(cos h θ, sin h θ, cos w θ, sin w θ), each [..., C/2], for row/column coordinates h, w in [-1, 1]."""
    half = channels // 2
    theta = 10000.0 ** (-(torch.arange(half, dtype=torch.float32, device=h.device) / half))
    ht, wt = h.unsqueeze(-1) * theta, w.unsqueeze(-1) * theta
    return torch.cos(ht), torch.sin(ht), torch.cos(wt), torch.sin(wt)


def add_rope(x: torch.Tensor, angles) -> torch.Tensor:
    """x + rope(x) for features x [..., C] and :func:`rope_angles` of the same cells."""
    hc, hs, wc, ws = angles
    half = x.shape[-1] // 2
    x1, x2 = x[..., :half], x[..., half:]
    rot = torch.cat([x1 * hc * wc - x2 * hs * ws, x1 * hs * ws + x2 * hc * wc], -1)
    return x + rot


class PillarAttentionWithRoPE(nn.Module):
    """The attention block's weights under upstream's names (q_mlp, k_mlp, v_mlp, ffn, norm1, norm2)."""

    def __init__(self, pillar_dim: int = 64, hidden_dim: int = 64):
        super().__init__()
        self.q_mlp = nn.Linear(pillar_dim, hidden_dim)
        self.k_mlp = nn.Linear(pillar_dim, hidden_dim)
        self.v_mlp = nn.Linear(pillar_dim, hidden_dim)
        self.ffn = nn.Sequential(nn.Linear(hidden_dim, hidden_dim), nn.GELU(), nn.Linear(hidden_dim, pillar_dim))
        self.norm1 = nn.LayerNorm(pillar_dim)
        self.norm2 = nn.LayerNorm(pillar_dim)

    def attend(self, f: torch.Tensor, key_valid: torch.Tensor | None = None) -> torch.Tensor:
        """Step 2 of the module docstring on pillar features f [S, C] (with rope); padded keys
        (``key_valid`` False) get no weight."""
        n = self.norm1(f)
        scores = self.q_mlp(n) @ self.k_mlp(n).T
        if key_valid is not None:
            scores = torch.where(key_valid.unsqueeze(0), scores, torch.full_like(scores, -1e30))
        a = F.softmax(scores, dim=-1) @ self.v_mlp(n) + f
        return self.ffn(self.norm2(a)) + a


class SparsePillarAttention(nn.Module):
    """Export formulation. forward(canvas [C, ny, nx], occupied [ny*nx] bool, num_points int) ->
    (canvas [C, ny, nx], num_pillars [] int64, overflow [] bool)."""

    def __init__(self, channels: int, capacity: int):
        super().__init__()
        if capacity < 1:
            raise ValueError("SPA capacity must be >= 1")
        self.capacity = capacity
        self.pillar_attention_rope = PillarAttentionWithRoPE(channels, channels)

    def forward(self, canvas: torch.Tensor, occupied: torch.Tensor, num_points):
        c, ny, nx = canvas.shape
        ncell = ny * nx
        slots = torch.sym_min(num_points, self.capacity)
        cell = torch.arange(ncell, dtype=torch.int64, device=canvas.device)
        key = torch.where(occupied, ncell - cell, torch.zeros_like(cell))  # occupied cells first, by index
        top = torch.topk(key, slots)
        slot_valid = top.values > 0
        idx = top.indices
        flat = canvas.reshape(c, ncell).T  # [ncell, C]
        h = -1.0 + (idx // nx).to(torch.float32) * (2.0 / max(ny - 1, 1))  # linspace(-1, 1, ny)[iy]
        w = -1.0 + (idx % nx).to(torch.float32) * (2.0 / max(nx - 1, 1))
        f = add_rope(flat[idx], rope_angles(h, w, c))
        out = self.pillar_attention_rope.attend(f, slot_valid)
        target = torch.where(slot_valid, idx, torch.full_like(idx, ncell))
        result = torch.zeros(ncell + 1, c, dtype=canvas.dtype, device=canvas.device).index_copy(0, target, out)
        num_pillars = occupied.sum()
        return result[:ncell].T.reshape(c, ny, nx), num_pillars, num_pillars > self.capacity

    def forward_pillars(self, features: torch.Tensor, cells: torch.Tensor, ny: int, nx: int):
        """Training formulation of :meth:`forward` on the non-empty pillars only (features [P, C],
        cells [P] ascending, as :meth:`radaredge.ops.pillars.PillarFeatureNet.pillars` gives
        them): the same (canvas, num_pillars, overflow). The first ``capacity`` pillars by cell
        attend, as the export's slots do (a scan has at least as many points as pillars); the
        canvas is :func:`radaredge.ops.pillars.pillar_canvas`'s (channels last)."""
        c = features.shape[1]
        num_pillars = torch.tensor(cells.shape[0], dtype=torch.int64, device=cells.device)
        idx, f = cells[: self.capacity], features[: self.capacity]
        h = -1.0 + (idx // nx).to(torch.float32) * (2.0 / max(ny - 1, 1))
        w = -1.0 + (idx % nx).to(torch.float32) * (2.0 / max(nx - 1, 1))
        out = self.pillar_attention_rope.attend(add_rope(f, rope_angles(h, w, c)))
        return pillar_canvas(out, idx, ny, nx), num_pillars, num_pillars > self.capacity


def sparse_pillar_attention_reference(
    block: PillarAttentionWithRoPE, canvas: torch.Tensor, occupied: torch.Tensor
) -> torch.Tensor:
    """Reference formulation (upstream's dense rope and boolean-mask gather/scatter): [C, ny, nx]."""
    c, ny, nx = canvas.shape
    h, w = torch.meshgrid(torch.linspace(-1, 1, ny), torch.linspace(-1, 1, nx), indexing="ij")
    f = add_rope(canvas.permute(1, 2, 0), rope_angles(h, w, c)).reshape(ny * nx, c)
    out = f.clone()
    out[occupied] = block.attend(f[occupied])
    return out.T.reshape(c, ny, nx)
