"""TDFANet: sequential 4D-radar place recognition (Lu et al., TDFANet paper, sections III-A to III-D).

Pipeline for the latest K scans (oldest first, the last one is the current scan t):
1. per frame: RANSAC ego velocity and dynamic-point removal (eq. 1-3), pillar BEV encoding;
2. trajectory-guided alignment (eq. 4-5): each past map is warped into frame t by the grid
   displacement integrated from the estimated ego velocities and the frame timestamps;
3. spatio-temporal pyramid: 3 residual stages with stride 2, channels doubling (shared by all
   frames), levels l = 0..3;
4. spatio-temporal pyramid deformable transformer (eq. 6-9): Q_3 = F_t,3; for l < 3,
   Q_l = Linear([F_t,l, Upsample(A_l+1)]); per past frame D = Linear([Q_l, F^a_l]) drives a
   deformable attention over that frame's map; A_l = FFN(LN(Dropout(sum_k M_k) + Q_l));
5. MLP to 256 channels and GeM pooling -> descriptor (and its L2-normalised copy).

Both formulations share one set of weights: ``forward`` is the export formulation (fixed-shape
ops only); ``run(..., reference=True)`` computes the same function with the reference ops
(numpy RANSAC, dynamic voxelization, explicit bilinear alignment, gather-based deformable
attention).

The export formulation also runs batched for training (:meth:`TDFANet.prepare` once per window,
then :meth:`TDFANet.describe` over many windows at once), with BatchNorm batch statistics and
dropout in train mode. The paper's ablations (Table II) are card fields of ``network``:
``remove_dynamic`` (DPR), ``align`` (FA) and ``aggregation: sum`` (the plain TDFANet, no pyramid
and no deformable attention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ...cards import ModelCard
from ...config import Range, card_ranges, positive
from ...errors import ConfigError
from ...ops.alignment import BevGrid, align_bev, align_bev_reference, grid_displacement
from ...ops.deform_attn import MSDeformAttn
from ...ops.ego_velocity import EgoVelocityRansac, RansacConfig, estimate_ego_velocity_reference
from ...ops.gem import GeM
from ...ops.input_flags import (
    column_bounds,
    drop_implausible,
    drop_implausible_reference,
    frame_flags,
    frame_flags_reference,
)
from ...ops.pillars import PillarConfig, PillarFeatureNet, outside_grid, pillar_scatter_reference, point_drops_reference
from ...ops.scan_batch import concat_scans

AGGREGATIONS = ("deformable", "sum")


@card_ranges(
    pyramid_stages=(1, 6),
    heads=(1, 64),
    points=(1, 64),
    ffn_ratio=(1, 16),
    dropout=Range(0.0, 1.0, high_open=True),
    descriptor_dim=(1, 4096),
    mlp_hidden=(0, 4096),
    gem_p=positive(100.0),
    gem_eps=positive(1.0),
)
@dataclass(frozen=True)
class TDFANetConfig:
    """Model-card section ``network``. Values the paper leaves open are justified in the card."""

    pyramid_stages: int = 3  # stride-2 residual stages -> levels 0..3 (paper: 3)
    heads: int = 8  # deformable attention heads (Deformable DETR: 8)
    points: int = 4  # sampling points per head (Deformable DETR: 4)
    ffn_ratio: int = 4  # FFN hidden width = ffn_ratio * level channels (Transformer: 4)
    dropout: float = 0.1  # eq. 9 dropout (identity at inference)
    descriptor_dim: int = 256  # paper: 256-d descriptor
    mlp_hidden: int = 0  # hidden width of the channel MLP to 256; 0 = descriptor_dim
    gem_p: float = 3.0  # GeM initial p (Radenovic et al.: 3)
    gem_eps: float = 1e-6
    remove_dynamic: bool = True  # Table II DPR: RANSAC outliers (moving points) stay out of the BEV maps
    align: bool = True  # Table II FA: past maps are warped along the ego-velocity trajectory
    aggregation: str = "deformable"  # "deformable": pyramid + DFA layers (TSP + DA); "sum": the plain
    # TDFANet of Table II, the K BEV maps summed

    def __post_init__(self):
        if self.pyramid_stages < 1:
            raise ValueError("pyramid_stages must be >= 1")
        if self.aggregation not in AGGREGATIONS:
            raise ValueError(f"aggregation must be one of {list(AGGREGATIONS)}, got {self.aggregation!r}")


@dataclass
class PreparedWindow:
    """The parameter-free front of one K-frame window (:meth:`TDFANet.prepare`): ``points``
    [N, F] its K scans concatenated (oldest first), ``frame`` [N] int64 the scan of each point,
    ``keep`` [N] bool the points that enter the BEV maps (RANSAC inliers, or every point without
    dynamic-point removal), ``cells`` [K, 2] the grid displacement of each scan to the last one
    (eq. 5, cells; zero without alignment), ``ego_velocity`` [K, 3] m/s and ``ego_valid`` [K];
    ``implausible`` [N] bool the points whose values left the card's plausible range (their rows
    in ``points`` are NaN and left out everywhere)."""

    points: torch.Tensor
    frame: torch.Tensor
    keep: torch.Tensor
    cells: torch.Tensor
    ego_velocity: torch.Tensor
    ego_valid: torch.Tensor
    implausible: torch.Tensor

    def to(self, device) -> "PreparedWindow":
        return PreparedWindow(
            *(
                t.to(device)
                for t in (
                    self.points,
                    self.frame,
                    self.keep,
                    self.cells,
                    self.ego_velocity,
                    self.ego_valid,
                    self.implausible,
                )
            )
        )


class ResidualStage(nn.Module):
    """A ResNet basic block with a stride-2 3x3 conv; channels in -> out, resolution halved (ceil)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=2, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=2, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.bn1(self.conv1(x)))
        return torch.relu(self.bn2(self.conv2(y)) + self.down(x))


class DeformableAggregationLayer(nn.Module):
    """One DFA layer of the pyramid transformer at level l (eq. 6-9), channels d."""

    def __init__(self, d: int, d_coarser: int | None, heads: int, points: int, ffn_ratio: int, dropout: float):
        super().__init__()
        self.query_fuse = nn.Linear(d + d_coarser, d) if d_coarser else None  # eq. 6
        self.advanced_query = nn.Linear(2 * d, d)  # eq. 7
        self.attn = MSDeformAttn(d, n_levels=1, n_heads=heads, n_points=points)  # eq. 8
        self.dropout = nn.Dropout(dropout)
        self.norm = nn.LayerNorm(d)
        self.ffn = nn.Sequential(
            nn.Linear(d, ffn_ratio * d), nn.ReLU(), nn.Dropout(dropout), nn.Linear(ffn_ratio * d, d)
        )

    def forward(
        self, current: torch.Tensor, past: torch.Tensor, coarser: torch.Tensor | None, reference: bool = False
    ) -> torch.Tensor:
        """current F_t,l [B, d, H, W], past F^a_t-k,l [B, K-1, d, H, W], coarser A_l+1 [B, d', H', W']
        (None at the top level) -> A_l [B, d, H, W]; B windows at once."""
        b, d, h, w = current.shape
        kp = past.shape[1]
        q = current.flatten(2).transpose(1, 2)  # [B, HW, d]
        if self.query_fuse is not None:
            up = F.interpolate(coarser, size=(h, w), mode="bilinear", align_corners=False)
            q = self.query_fuse(torch.cat([q, up.flatten(2).transpose(1, 2)], -1))
        value = past.flatten(3).transpose(2, 3).reshape(b * kp, h * w, d)  # [B(K-1), HW, d]
        per_past = q.unsqueeze(1).expand(b, kp, h * w, d).reshape(b * kp, h * w, d)
        adv = self.advanced_query(torch.cat([per_past, value], -1))  # [B(K-1), HW, d]
        ref = _pixel_centres(h, w, q.device).expand(b * kp, -1, -1, -1)  # [B(K-1), HW, 1, 2]
        m = self.attn(adv, ref, value, [(h, w)], reference=reference).reshape(b, kp, h * w, d).sum(1)
        x = self.norm(self.dropout(m) + q)
        a = x + self.ffn(x)  # Transformer FFN sublayer
        return a.transpose(1, 2).reshape(b, d, h, w)


def _pixel_centres(h: int, w: int, device=None) -> torch.Tensor:
    """Normalised (x, y) reference points of every cell centre of an h x w map, [1, h*w, 1, 2]."""
    ys = (torch.arange(h, dtype=torch.float32, device=device) + 0.5) / h
    xs = (torch.arange(w, dtype=torch.float32, device=device) + 0.5) / w
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy], -1).reshape(1, h * w, 1, 2)


class TDFANet(nn.Module):
    """TDFANet with both formulations. Build it with :func:`build_tdfanet` from a model card."""

    def __init__(
        self,
        features: Sequence[str],
        frames: int,
        frame_rate: float,
        ransac: RansacConfig,
        pillars: PillarConfig,
        net: TDFANetConfig,
    ):
        super().__init__()
        features = list(features)
        if frames < 2:
            raise ConfigError("TDFANet needs frames >= 2 (the paper uses K = 3)")
        if features[:3] != ["x", "y", "z"] or "v_r" not in features:
            raise ConfigError(
                f"TDFANet's features must start with x, y, z and include v_r (the radial velocity "
                f"the RANSAC reads, m/s); got {features}"
            )
        self.features = features
        self.v_column = features.index("v_r")
        self.point_bounds = ([-math.inf] * len(features), [math.inf] * len(features))  # build: the card's plausible
        self.frames, self.frame_rate, self.net_config = frames, frame_rate, net
        self.ransac = EgoVelocityRansac(ransac)
        self.vfe = PillarFeatureNet(len(features), pillars)
        self.grid = BevGrid.from_range(pillars.point_cloud_range, pillars.voxel_size)
        c = pillars.out_channels
        if net.aggregation == "deformable":
            if c % net.heads:
                raise ConfigError(f"pillars.out_channels ({c}) must be divisible by network.heads ({net.heads})")
            chans = [c * 2**i for i in range(net.pyramid_stages + 1)]
            self.pyramid = nn.ModuleList(ResidualStage(chans[i], chans[i + 1]) for i in range(net.pyramid_stages))
            self.dfa = nn.ModuleList(
                DeformableAggregationLayer(
                    chans[l],
                    chans[l + 1] if l < net.pyramid_stages else None,
                    net.heads,
                    net.points,
                    net.ffn_ratio,
                    net.dropout,
                )
                for l in range(net.pyramid_stages + 1)
            )
        hidden = net.mlp_hidden or net.descriptor_dim
        self.mlp = nn.Sequential(nn.Conv2d(c, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, net.descriptor_dim, 1))
        self.gem = GeM(p=net.gem_p, eps=net.gem_eps)

    # -- shared stages ---------------------------------------------------------------
    def aggregate(self, bev: torch.Tensor, cells: torch.Tensor, reference: bool, trace: dict | None) -> torch.Tensor:
        """bev [B*K, C, ny, nx] (window-major, oldest scan first), cells [B*K, 2] grid displacement of
        each scan to its window's current one (eq. 5) -> descriptors [B, D] (before L2 normalisation)."""
        k = self.frames
        b = bev.shape[0] // k
        maps = bev.unflatten(0, (b, k))  # [B, K, C, H, W]
        if self.net_config.align:
            align = align_bev_reference if reference else align_bev
            past = align(
                maps[:, : k - 1].flatten(0, 1), cells.unflatten(0, (b, k))[:, : k - 1].flatten(0, 1), grid=self.grid
            )
            maps = torch.cat([past.unflatten(0, (b, k - 1)), maps[:, k - 1 :]], 1)
        else:
            # a copy of the scatter's canvas: without it, backward through the pyramid straight
            # into the canvas corrupted memory in torch 2.13's CPU autograd (a segfault or a
            # double free in the first training step); the forward values are the same
            maps = maps.clone(memory_format=torch.contiguous_format)
        if trace is not None:
            trace["aligned_bev"] = maps.flatten(0, 1)
        if self.net_config.aggregation == "sum":
            return self.gem(self.mlp(maps.sum(1)))
        levels = [maps.flatten(0, 1)]
        for stage in self.pyramid:
            levels.append(stage(levels[-1]))
        a = None
        for l in range(len(levels) - 1, -1, -1):
            feats = levels[l].unflatten(0, (b, k))
            a = self.dfa[l](feats[:, k - 1], feats[:, : k - 1], a, reference=reference)
            if trace is not None:
                trace[f"aggregated_l{l}"] = a
        return self.gem(self.mlp(a))

    def prepare(self, frames: list[torch.Tensor], timestamps: torch.Tensor) -> PreparedWindow:
        """The parameter-free front of one window, export formulation: the K scans (oldest first,
        [N_k, F] each) through one RANSAC (eq. 1-3), the BEV point mask and the grid displacement
        from the ego velocities and ``timestamps`` [K] s (eq. 4-5)."""
        # The K scans run through one RANSAC and one pillar scatter, concatenated: the same
        # per-scan results as K separate passes, with a third of their nodes in the graph.
        pts, frame = concat_scans(frames)
        pts, implausible = drop_implausible(pts, *self.point_bounds)
        valid = torch.ones(pts.shape[0], dtype=torch.bool, device=pts.device)
        v_ego, static, ok = self.ransac.estimate_frames(pts[:, :3], pts[:, self.v_column], valid, frame, len(frames))
        keep = static if self.net_config.remove_dynamic else valid
        cells = grid_displacement(v_ego, self.vfe.config.voxel_size, timestamps=timestamps)
        if not self.net_config.align:
            cells = torch.zeros_like(cells)
        return PreparedWindow(pts, frame, keep, cells, v_ego, ok, implausible)

    def describe(
        self, windows: Sequence[PreparedWindow], trace: dict | None = None, drops: dict | None = None
    ) -> torch.Tensor:
        """Descriptors [B, D] (before L2 normalisation) of B prepared windows in one batched pass:
        one pillar scatter over their B*K scans, then the aggregation. In train mode BatchNorm
        takes its statistics over the whole batch, as a batch of tuples trains. ``drops`` receives
        the pillar scatter's left-out points (:meth:`PillarFeatureNet.scatter_frames`)."""
        if len(windows) == 1:
            w = windows[0]
            pts, frame, keep, cells = w.points, w.frame, w.keep, w.cells
        else:
            pts = torch.cat([w.points for w in windows])
            frame = torch.cat([w.frame + i * self.frames for i, w in enumerate(windows)])
            keep = torch.cat([w.keep for w in windows])
            cells = torch.cat([w.cells for w in windows])
        bev = self.vfe.scatter_frames(pts, keep, frame, len(windows) * self.frames, drops)[0]
        if trace is not None:
            trace["bev"] = bev
        return self.aggregate(bev, cells, False, trace)

    # -- the two formulations --------------------------------------------------------------
    def forward(self, *inputs: torch.Tensor):
        """Export formulation: (points_0 [N0, F], ..., points_{K-1} [N, F], timestamps [K] s) ->
        (descriptor [D], descriptor_normalized [D], ego_velocity [K, 3] m/s, ego_valid [K] bool,
        input_flags [K] int32, :mod:`radaredge.ops.input_flags`)."""
        out = self.run(list(inputs[: self.frames]), inputs[self.frames])
        return (
            out["descriptor"],
            out["descriptor_normalized"],
            out["ego_velocity"],
            out["ego_valid"],
            out["input_flags"],
        )

    def run(
        self, frames: list[torch.Tensor], timestamps: torch.Tensor, reference: bool = False, trace: dict | None = None
    ) -> dict[str, torch.Tensor]:
        """Both formulations: ``reference=True`` uses the reference ops. Returns named outputs;
        ``trace`` (a dict) receives intermediate tensors for divergence reports. Points with a
        value outside the card's plausible range become NaN rows first, which every stage leaves
        out (:func:`radaredge.ops.input_flags.drop_implausible`)."""
        cfg = self.vfe.config
        if reference:
            vels, valids, bevs, outside, full, implausible = [], [], [], [], [], []
            for raw in frames:
                cleaned, bad = drop_implausible_reference(raw.numpy(), *self.point_bounds)
                pts = torch.from_numpy(cleaned)
                implausible.append(bad)
                v, static, ok = estimate_ego_velocity_reference(
                    pts[:, :3].numpy(), pts[:, self.v_column].numpy(), self.ransac.config
                )
                vels.append(torch.tensor(v, dtype=torch.float32))
                valids.append(torch.tensor(ok))
                keep = static if self.net_config.remove_dynamic else None
                bevs.append(pillar_scatter_reference(self.vfe, pts.numpy(), keep))
                outside.append(point_drops_reference(pts.numpy(), cfg)[0])
                full.append(point_drops_reference(pts.numpy(), cfg, keep)[1])
            v_ego, ok, bev = torch.stack(vels), torch.stack(valids), torch.stack(bevs)
            cells = grid_displacement(v_ego, cfg.voxel_size, timestamps=timestamps)
            if trace is not None:
                trace["bev"] = bev
            desc = self.aggregate(bev, cells, True, trace)[0]
            flags = frame_flags_reference(
                [f.numpy() for f in frames], timestamps.numpy(), outside, full, implausible=implausible
            )
        else:
            prepared = self.prepare(frames, timestamps)
            v_ego, ok = prepared.ego_velocity, prepared.ego_valid
            drops: dict = {}
            desc = self.describe([prepared], trace, drops)[0]
            flags = frame_flags(
                prepared.points,
                prepared.frame,
                len(frames),
                timestamps,
                outside_grid(prepared.points, cfg),
                drops["full"],
                implausible=prepared.implausible,
            )
        if trace is not None:
            trace["ego_velocity"] = v_ego
        return {
            "descriptor": desc,
            "descriptor_normalized": desc / torch.clamp(torch.linalg.vector_norm(desc), min=1e-12),
            "ego_velocity": v_ego,
            "ego_valid": ok,
            "input_flags": flags,
        }


def build_tdfanet(card: ModelCard) -> TDFANet:
    """TDFANet from a model card, with a seeded initialisation (card ``seed``, default 0)."""
    torch.manual_seed(int(card.get("seed", 0)))
    model = TDFANet(
        features=card.features,
        frames=int(card.get("frames", 3)),
        frame_rate=float(card.get("frame_rate", 10.0)),
        ransac=card.section("preprocess.ransac", RansacConfig),
        pillars=card.section("pillars", PillarConfig),
        net=card.section("network", TDFANetConfig),
    )
    model.point_bounds = column_bounds(card)  # plausible (low, high) per point column
    return model.eval()
