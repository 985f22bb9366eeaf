"""PointNet++ set abstraction over a masked point set, as OpenPCDet's ``StackSAModuleMSG`` runs it
at test time for one scan (PV-RCNN's VSA branches and ROI-grid pooling).

For candidate points xyz [N, 3] (metres, radar frame: x forward, y left, z up) with features
[N, C] and a ``valid`` mask, and centres [S, 3], each scale k (radius r_k, nsample K_k, MLP widths
m_k) computes:

1. ball query (:func:`radaredge.ops.point_sampling.ball_query_masked`, strict ``d2 < r^2`` as
   the CUDA kernel): the first K_k valid hits in index order, unfilled slots repeat the first
   hit; a centre without hits is *empty*;
2. grouping: per slot the vector [neighbour xyz - centre xyz (3, m, not normalised), neighbour
   features (C)]; an empty ball's grouped xyz and features are all zero;
3. a shared MLP of 1x1 Conv2d (no bias) + BatchNorm2d + ReLU per width (upstream layout, state
   dict keys ``mlps.{k}.{0,1,3,4,...}``), applied to every slot -- an empty ball therefore
   yields MLP(0), not 0;
4. max over the K_k slots; the scales are concatenated -> [S, sum_k m_k[-1]].

Export formulation (:meth:`SAModuleMSG.forward`): fixed shapes, channel-last. The first layer is
linear, so W [rel_xyz, f] = W_xyz rel_xyz + W_f f: W_f f is computed once per *point* and then
gathered (the grouped tensor has m_k[0] channels instead of 3 + C, which is what keeps the
ROI-grid pooling of VoD under 100 MB per intermediate), rel_xyz is gathered and subtracted
exactly as upstream. BatchNorm is applied in its eval form (scale and shift); in training mode
(``radaredge train``) with the batch's statistics, as upstream trains.

Reference formulation (:meth:`SAModuleMSG.reference`): the per-centre ball-query loop, explicit
grouping into [1, 3 + C, S, K] and the upstream Conv2d/BatchNorm2d modules, then max.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .point_sampling import ball_query_masked, ball_query_masked_reference, group_points


def group_relative_reference(
    xyz: np.ndarray, features: np.ndarray, centres: np.ndarray, idx: np.ndarray, empty: np.ndarray
) -> np.ndarray:
    """Step 2 on one set, plainly: xyz [N, 3], features [N, C], centres [S, 3], idx [S, K], empty [S]
    -> [S, K, 3 + C] = [neighbour xyz - centre, features], all zero for an empty ball (loops)."""
    s, k = idx.shape
    out = np.zeros((s, k, 3 + features.shape[1]), np.float32)
    for i in range(s):
        if empty[i]:
            continue
        for j in range(k):
            out[i, j, :3] = xyz[idx[i, j]] - centres[i]
            out[i, j, 3:] = features[idx[i, j]]
    return out


def _bn(bn: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """BatchNorm on the last axis of x [S, K, C]: the eval form (scale and shift) at test time; in
    training mode the module itself, so its batch statistics cover every slot of every centre
    (upstream's BatchNorm2d over [1, C, S, K]) and its running averages are updated. The input is
    made contiguous first: torch 2.13's CPU BatchNorm2d backward returns a wrong input gradient for
    the channels-last strides a permuted view has (tests/test_set_abstraction.py checks)."""
    if bn.training:
        return bn(x.permute(2, 0, 1).unsqueeze(0).contiguous())[0].permute(1, 2, 0)
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return x * scale + (bn.bias - bn.running_mean * scale)


def shared_mlp(cin: int, widths) -> nn.Sequential:
    """Upstream's per-scale MLP: [Conv2d 1x1 (no bias), BatchNorm2d, ReLU] per width."""
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Conv2d(cin, w, 1, bias=False), nn.BatchNorm2d(w), nn.ReLU()]
        cin = w
    return nn.Sequential(*layers)


class SAModuleMSG(nn.Module):
    """Multi-scale set abstraction (upstream ``StackSAModuleMSG``, max pooling, use_xyz).

    ``in_channels`` C of the point features; ``radii`` (m), ``nsamples`` and ``mlps`` (widths
    per scale, without the 3 + C input) one entry per scale. Output width ``out_channels``.
    """

    def __init__(self, in_channels: int, radii, nsamples, mlps):
        super().__init__()
        if not len(radii) == len(nsamples) == len(mlps):
            raise ValueError("radii, nsample and mlps need one entry per scale")
        self.radii, self.nsamples = [float(r) for r in radii], [int(n) for n in nsamples]
        self.mlps = nn.ModuleList(shared_mlp(3 + in_channels, m) for m in mlps)
        self.out_channels = sum(m[-1] for m in mlps)

    def forward(
        self, xyz: torch.Tensor, valid: torch.Tensor, features: torch.Tensor, centres: torch.Tensor
    ) -> torch.Tensor:
        """Export formulation: xyz [N, 3], valid [N] bool, features [N, C], centres [S, 3] -> [S, out].

        The point set is padded with max(nsample) invalid rows, so any N (0 included) gives the
        ball query at least nsample candidates and every gathered index a row to read."""
        pad = max(self.nsamples)
        xyz = torch.cat([xyz, xyz.new_zeros(pad, 3)])
        valid = torch.cat([valid, valid.new_zeros(pad)])
        features = torch.cat([features, features.new_zeros(pad, features.shape[1])])
        out = []
        for radius, nsample, mlp in zip(self.radii, self.nsamples, self.mlps):
            idx, empty = ball_query_masked(xyz.unsqueeze(0), valid.unsqueeze(0), centres.unsqueeze(0), radius, nsample)
            idx, empty = idx[0], empty[0]  # [S, K], [S]
            w = mlp[0].weight.flatten(1)  # [m0, 3 + C]
            per_point = features @ w[:, 3:].t()  # [N, m0]
            rel = group_points(xyz.unsqueeze(0), idx.unsqueeze(0))[0] - centres.unsqueeze(1)
            h = rel @ w[:, :3].t() + group_points(per_point.unsqueeze(0), idx.unsqueeze(0))[0]
            h = torch.where(empty.view(-1, 1, 1), torch.zeros_like(h), h)
            h = torch.relu(_bn(mlp[1], h))
            for j in range(3, len(mlp), 3):
                h = torch.relu(_bn(mlp[j + 1], h @ mlp[j].weight.flatten(1).t()))
            out.append(h.amax(1))
        return torch.cat(out, -1)

    def reference(self, xyz: np.ndarray, valid: np.ndarray, features: np.ndarray, centres: np.ndarray) -> torch.Tensor:
        """Reference formulation (numpy in): loop ball query, explicit grouping, upstream modules."""
        xyz, features = np.asarray(xyz, np.float32), np.asarray(features, np.float32)
        centres = np.asarray(centres, np.float32)
        out = []
        for radius, nsample, mlp in zip(self.radii, self.nsamples, self.mlps):
            idx, empty = ball_query_masked_reference(xyz, valid, centres, radius, nsample)
            grouped = torch.from_numpy(group_relative_reference(xyz, features, centres, idx, empty))
            h = mlp(grouped.permute(2, 0, 1).unsqueeze(0))  # [1, m, S, K]
            out.append(h.amax(3)[0].t())
        return torch.cat(out, -1)
