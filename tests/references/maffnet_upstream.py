"""Upstream MAFF-Net (TRV-Lab/MAFF-Net) at test time, written from reading its source, for tests only.

Shares no code with radaredge (not its ops, not its models): it is the yardstick that proves
radaredge's MAFF-Net computes upstream's function with upstream's weights. Read from:

- ``pcdet/models/backbones_2d/fuser/CQCA_caf.py`` (CQCA_caf, TransformerFusionBlock,
  CrossTransformerBlock, CrossAttention, ImageEmbedder, DynamicPositionBias), ``fuser/common.py``
  (AdaptivePool2d, LearnableCoefficient, LearnableWeights) and ``fuser/se_module.py`` (SELayer);
- ``pcdet/models/backbones_3d/pfe/voxel_set_abstraction.py`` (VoxelSetAbstraction_cda:
  sample_points_with_roi2, sector_fps, get_sampled_points with SAMPLE_METHOD CDA,
  interpolate_from_bev_features / bilinear_interpolate_torch, the cluster_points SA branch);
- ``pcdet/ops/pointnet2/pointnet2_stack`` (StackSAModuleMSG with QueryAndGroup, max pooling; the
  CUDA ball query: strict ``d2 < r^2``, first hits in index order, slot fill with the first hit,
  empty balls zeroed) and ``pointnet2_batch`` / ``pointnet2_stack`` farthest point sampling
  (start at index 0, running minimum of squared distances, arg-max).

:class:`UpstreamCQCACaf` carries every parameter upstream's module has (the ones its test-time
output never reads too), so its ``state_dict()`` has upstream's keys and shapes and a random
instance is an upstream-format checkpoint of the fuser. Its ``forward`` computes both attention
directions and both token branches as upstream does, and returns what upstream returns.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

# ----------------------------------------------------------------------------- fuser (CQCA_caf)


class _Coefficient(nn.Module):
    def __init__(self):
        super().__init__()
        self.bias = nn.Parameter(torch.tensor([1.0]))


class _Weights(nn.Module):
    def __init__(self):
        super().__init__()
        self.w1 = nn.Parameter(torch.tensor([0.5]))
        self.w2 = nn.Parameter(torch.tensor([0.5]))


class _NoParams(nn.Module):
    """Stands in for an einops Rearrange / a Dropout: keeps Sequential indices as upstream's."""

    def forward(self, x):
        return x


def _adaptive_pool(x: torch.Tensor, out: int, kind: str) -> torch.Tensor:
    """Upstream AdaptivePool2d: stride = size // out, kernel = size - (out - 1) * stride; no pooling
    when neither side is larger than ``out``."""
    h, w = x.shape[2:]
    if h <= out and w <= out:
        return x
    sh, sw = h // out, w // out
    kernel = (h - (out - 1) * sh, w - (out - 1) * sw)
    pool = nn.AvgPool2d(kernel, (sh, sw)) if kind == "avg" else nn.MaxPool2d(kernel, (sh, sw))
    return pool(x)


class _CrossAttention(nn.Module):
    def __init__(self, d_model: int, h: int):
        super().__init__()
        self.h, self.dk = h, d_model // h
        q = d_model // 4
        self.dpb = nn.Sequential(
            nn.Linear(2, q),
            nn.LayerNorm(q),
            nn.ReLU(),
            nn.Linear(q, q),
            nn.LayerNorm(q),
            nn.ReLU(),
            nn.Linear(q, q),
            nn.LayerNorm(q),
            nn.ReLU(),
            nn.Linear(q, 1),
        )
        for side in ("vis", "ir"):
            for kind in ("que", "key", "val"):
                setattr(self, f"{kind}_proj_{side}", nn.Linear(d_model, d_model))
        self.out_proj_vis = nn.Linear(d_model, d_model)
        self.out_proj_ir = nn.Linear(d_model, d_model)
        self.LN1 = nn.LayerNorm(d_model)
        self.LN2 = nn.LayerNorm(d_model)

    def forward(self, vis: torch.Tensor, ir: torch.Tensor):
        b, n, _ = vis.shape

        def split(t):  # (b, n, h*dk) -> (b, h, n, dk)
            return t.contiguous().view(b, n, self.h, self.dk).permute(0, 2, 1, 3)

        v_in, i_in = self.LN1(vis), self.LN2(ir)
        q_vis, k_vis, v_vis = (
            split(self.que_proj_vis(v_in)),
            split(self.key_proj_vis(v_in)),
            split(self.val_proj_vis(v_in)),
        )
        q_ir, k_ir, v_ir = split(self.que_proj_ir(i_in)), split(self.key_proj_ir(i_in)), split(self.val_proj_ir(i_in))
        att_vis = torch.softmax(q_ir @ k_vis.transpose(-1, -2) / np.sqrt(self.dk), -1)  # pillar queries, CFA keys
        att_ir = torch.softmax(q_vis @ k_ir.transpose(-1, -2) / np.sqrt(self.dk), -1)  # CFA queries, pillar keys
        out_vis = (att_vis @ v_vis).permute(0, 2, 1, 3).contiguous().view(b, n, -1)
        out_ir = (att_ir @ v_ir).permute(0, 2, 1, 3).contiguous().view(b, n, -1)
        return self.out_proj_vis(out_vis), self.out_proj_ir(out_ir)


def _mlp(d: int, exp: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d, exp * d), nn.GELU(), nn.Linear(exp * d, d), _NoParams())


class _CrossTransformerBlock(nn.Module):
    def __init__(self, d_model: int, h: int, block_exp: int):
        super().__init__()
        self.ln_input = nn.LayerNorm(d_model)
        self.ln_output = nn.LayerNorm(d_model)
        self.crossatt = _CrossAttention(d_model, h)
        self.mlp_vis, self.mlp_ir, self.mlp = (
            _mlp(d_model, block_exp),
            _mlp(d_model, block_exp),
            _mlp(d_model, block_exp),
        )
        self.LN1 = nn.LayerNorm(d_model)
        self.LN2 = nn.LayerNorm(d_model)
        for i in range(1, 9):
            setattr(self, f"coefficient{i}", _Coefficient())

    def c(self, i: int, x: torch.Tensor) -> torch.Tensor:
        return x * getattr(self, f"coefficient{i}").bias

    def forward(self, vis: torch.Tensor, ir: torch.Tensor):
        out_vis, out_ir = self.crossatt(vis, ir)
        vis_att = self.c(1, vis) + self.c(2, out_vis)
        ir_att = self.c(3, ir) + self.c(4, out_ir)
        vis = self.c(5, vis_att) + self.c(6, self.mlp_vis(self.LN2(vis_att)))
        ir = self.c(7, ir_att) + self.c(8, self.mlp_ir(self.LN2(ir_att)))
        return vis, ir


class _ImageEmbedder(nn.Module):
    def __init__(self, dim: int, image_size: int, patch_size: int, channels: int):
        super().__init__()
        patches, patch_dim = (image_size // patch_size) ** 2, channels * patch_size**2
        self.to_patch_embedding = nn.Sequential(
            _NoParams(), nn.LayerNorm(patch_dim), nn.Linear(patch_dim, dim), nn.LayerNorm(dim)
        )
        self.pos_embedding = nn.Parameter(torch.randn(1, patches + 1, dim))


class _TransformerFusionBlock(nn.Module):
    def __init__(self, d_model: int, anchors: int, h: int, block_exp: int):
        super().__init__()
        self.anchors = anchors
        self.pos_emb_vis = nn.Parameter(torch.zeros(1, anchors * anchors, d_model))
        self.pos_emb_ir = nn.Parameter(torch.zeros(1, anchors * anchors, d_model))
        self.bev_embedder = _ImageEmbedder(d_model, 320, 20, d_model)
        self.vis_coefficient, self.ir_coefficient = _Weights(), _Weights()
        self.crosstransformer = nn.Sequential(_CrossTransformerBlock(d_model, h, block_exp))

    def tokens(self, x: torch.Tensor, weights: _Weights, pos: torch.Tensor) -> torch.Tensor:
        mixed = (
            _adaptive_pool(x, self.anchors, "avg") * weights.w1 + _adaptive_pool(x, self.anchors, "max") * weights.w2
        )
        b, c = mixed.shape[:2]
        return mixed.contiguous().view(b, c, -1).permute(0, 2, 1) + pos

    def forward(self, cfa: torch.Tensor, pillar: torch.Tensor) -> torch.Tensor:
        b, c, h, w = cfa.shape
        vis = self.tokens(cfa, self.vis_coefficient, self.pos_emb_vis)
        ir = self.tokens(pillar, self.ir_coefficient, self.pos_emb_ir)
        vis, ir = self.crosstransformer[0](vis, ir)
        s = self.anchors
        ir_map = ir.contiguous().view(b, s, s, c).permute(0, 3, 1, 2)
        return F.interpolate(ir_map, size=[h, w], mode="bilinear") + pillar  # eval mode: bilinear


class _SE(nn.Module):
    def __init__(self, channel: int, reduction: int = 16):
        super().__init__()
        self.fc = nn.Sequential(
            nn.Linear(channel, channel // reduction, bias=False),
            nn.ReLU(),
            nn.Linear(channel // reduction, channel, bias=False),
            nn.Sigmoid(),
        )

    def forward(self, x):
        b, c = x.shape[:2]
        return x * self.fc(F.adaptive_avg_pool2d(x, 1).view(b, c)).view(b, c, 1, 1)


class UpstreamCQCACaf(nn.Module):
    """Upstream ``fuser`` (CQCA_caf) with all of its parameters; eval-mode forward (dropouts off)."""

    def __init__(
        self,
        in_channel_cross: int = 64,
        in_channel: int = 128,
        out_channel: int = 64,
        anchors: int = 16,
        heads: int = 8,
        block_exp: int = 4,
        se_reduction: int = 16,
    ):
        super().__init__()
        self.crossfusion = _TransformerFusionBlock(in_channel_cross, anchors, heads, block_exp)
        self.se = _SE(in_channel_cross, se_reduction)
        self.conv = nn.Sequential(
            nn.Conv2d(in_channel, out_channel, 3, padding=1, bias=False), nn.BatchNorm2d(out_channel), nn.ReLU(True)
        )

    def forward(self, spatial_features_img: torch.Tensor, spatial_features: torch.Tensor) -> torch.Tensor:
        out = self.se(self.crossfusion(spatial_features_img, spatial_features))
        return self.conv(torch.cat([spatial_features, out], 1))


def randomise(module: nn.Module, seed: int, std: float = 0.1) -> dict[str, torch.Tensor]:
    """A random upstream-format state_dict of ``module`` (float tensors N(0, std), BatchNorm
    variances in [0.5, 1.5]); loaded into the module too."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for k, v in module.state_dict().items():
        if v.dtype.is_floating_point:
            t = torch.randn(v.shape, generator=g) * std
            if k.endswith("running_var"):
                t = torch.rand(v.shape, generator=g) + 0.5
            state[k] = t
        else:
            state[k] = v.clone()
    module.load_state_dict(state)
    return state


# ----------------------------------------------------------------------------- CDA keypoints


def _fps(xyz: np.ndarray, npoint: int) -> list[int]:
    """pointnet2 farthest point sampling on one set: start at 0, keep every point's smallest
    squared distance (float32, dx^2 + dy^2 + dz^2) to the picks (initially 1e10), take the first
    arg-max as the next pick (numpy over the points, one pick at a time)."""
    xyz = np.asarray(xyz, np.float32)
    temp = np.full(len(xyz), 1e10, np.float32)
    picks, old = [0], 0
    for _ in range(1, npoint):
        d = xyz - xyz[old]
        temp = np.minimum(temp, d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        old = int(np.argmax(temp))
        picks.append(old)
    return picks


def upstream_cda_keypoints(
    points: np.ndarray, cluster_points: np.ndarray, rois: np.ndarray, num_keypoints: int, r_add: float, h_add: float
) -> np.ndarray:
    """VoxelSetAbstraction_cda.get_sampled_points for one scan with SAMPLE_METHOD CDA, one sector.

    points [N, 3] = batch_dict['points'] xyz (the range-masked scan), cluster_points [M, 3] (the
    CFA's non-noise points, in scan order), rois [R, 7] (all roi rows, padding included)
    -> keypoints [num_keypoints, 3] float32.
    """
    cp = torch.as_tensor(cluster_points, dtype=torch.float32)
    r = torch.as_tensor(rois, dtype=torch.float32)
    # sample_points_with_roi2
    radius = torch.max(r[:, 3], r[:, 4]) / 2 + r_add
    height = r[:, 5] + h_add
    d_xy = torch.sqrt((cp[:, None, 0] - r[None, :, 0]) ** 2 + (cp[:, None, 1] - r[None, :, 1]) ** 2)
    z_ok = (cp[:, None, 2] >= (r[:, 2] - height / 2)[None]) & (cp[:, None, 2] <= (r[:, 2] + height / 2)[None])
    mask = ((d_xy <= radius[None]) & z_ok).any(1)
    first = cp[:1] if int(mask.sum()) == 0 else cp[mask]
    first = first.numpy()
    if len(first) > num_keypoints:  # sector_fps with one sector
        first = first[_fps(first, num_keypoints)]
    need = num_keypoints - len(first)
    pts = np.asarray(points, np.float32)
    if need > 0:
        idx = _fps(pts, need) if len(pts) >= need else _fps(pts, len(pts))
        if len(pts) < need:
            idx = (idx * (need // len(pts) + 1))[:need]
        fill = pts[idx]
    else:
        fill = np.zeros((0, 3), np.float32)
    return np.concatenate([first, fill]).astype(np.float32)


# ----------------------------------------------------------------------------- VSA (pfe)


def _bilinear(im: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """bilinear_interpolate_torch: im [H, W, C], x/y in cells -> [N, C]."""
    x0, y0 = torch.floor(x).long(), torch.floor(y).long()
    x1, y1 = x0 + 1, y0 + 1
    x0, x1 = x0.clamp(0, im.shape[1] - 1), x1.clamp(0, im.shape[1] - 1)
    y0, y1 = y0.clamp(0, im.shape[0] - 1), y1.clamp(0, im.shape[0] - 1)
    wa = (x1.type_as(x) - x) * (y1.type_as(y) - y)
    wb = (x1.type_as(x) - x) * (y - y0.type_as(y))
    wc = (x - x0.type_as(x)) * (y1.type_as(y) - y)
    wd = (x - x0.type_as(x)) * (y - y0.type_as(y))
    return (im[y0, x0].t() * wa).t() + (im[y1, x0].t() * wb).t() + (im[y0, x1].t() * wc).t() + (im[y1, x1].t() * wd).t()


class _StackSAModuleMSG(nn.Module):
    def __init__(self, c_in: int, radii, nsamples, mlps):
        super().__init__()
        self.radii, self.nsamples = list(radii), list(nsamples)
        self.mlps = nn.ModuleList()
        for spec in mlps:
            layers, c = [], c_in + 3
            for w in spec:
                layers += [nn.Conv2d(c, w, 1, bias=False), nn.BatchNorm2d(w), nn.ReLU()]
                c = w
            self.mlps.append(nn.Sequential(*layers))

    def forward(self, xyz: np.ndarray, features: np.ndarray, new_xyz: np.ndarray) -> torch.Tensor:
        outs = []
        for radius, nsample, mlp in zip(self.radii, self.nsamples, self.mlps):
            r2 = np.float32(radius * radius)
            grouped = np.zeros((len(new_xyz), 3 + features.shape[1], nsample), np.float32)
            for m, c in enumerate(new_xyz):
                d = xyz - c
                d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
                hits = np.flatnonzero(d2 < r2)[:nsample].tolist()  # the kernel's scan in index order
                if not hits:  # empty ball: grouped xyz and features zeroed
                    continue
                hits += [hits[0]] * (nsample - len(hits))
                grouped[m, :3] = (xyz[hits] - c).T
                grouped[m, 3:] = features[hits].T
            x = torch.from_numpy(grouped).permute(1, 0, 2).unsqueeze(0)  # (1, C, M, nsample)
            x = mlp(x)
            outs.append(F.max_pool2d(x, kernel_size=[1, x.size(3)]).squeeze(-1)[0].t())
        return torch.cat(outs, 1)


class UpstreamVSA(nn.Module):
    """Upstream ``pfe`` (VoxelSetAbstraction_cda) with FEATURES_SOURCE [bev, cluster_points]."""

    def __init__(
        self,
        num_rawpoint_features: int,
        bev_channels: int,
        radii,
        nsamples,
        mlps,
        out_features: int,
        point_cloud_range,
        voxel_size,
    ):
        super().__init__()
        self.pc_range, self.voxel = point_cloud_range, voxel_size
        self.SA_clusterpoints = _StackSAModuleMSG(num_rawpoint_features - 3, radii, nsamples, mlps)
        c_in = bev_channels + sum(m[-1] for m in mlps)
        self.vsa_point_feature_fusion = nn.Sequential(
            nn.Linear(c_in, out_features, bias=False), nn.BatchNorm1d(out_features), nn.ReLU()
        )

    def forward(self, keypoints: np.ndarray, spatial_features: torch.Tensor, points: np.ndarray, stride: int = 1):
        """keypoints [K, 3], spatial_features [C, H, W] (the fuser output), points [N, 3 + F] (the scan)
        -> (point_features_before_fusion [K, C + SA], point_features [K, out])."""
        kp = torch.as_tensor(keypoints, dtype=torch.float32)
        x = (kp[:, 0] - self.pc_range[0]) / self.voxel[0] / stride
        y = (kp[:, 1] - self.pc_range[1]) / self.voxel[1] / stride
        bev = _bilinear(spatial_features.permute(1, 2, 0), x, y)
        pts = np.asarray(points, np.float32)
        sa = self.SA_clusterpoints(pts[:, :3], pts[:, 3:], np.asarray(keypoints, np.float32))
        before = torch.cat([bev, sa], 1)
        return before, self.vsa_point_feature_fusion(before)


def upstream_scan_mask(points: np.ndarray, point_cloud_range) -> np.ndarray:
    """common_utils.mask_points_by_range: x and y inside the range, bounds included (z untested)."""
    r = point_cloud_range
    return (points[:, 0] >= r[0]) & (points[:, 0] <= r[3]) & (points[:, 1] >= r[1]) & (points[:, 1] <= r[4])
