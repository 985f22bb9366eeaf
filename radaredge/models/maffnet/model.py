"""MAFF-Net stage one (Bi et al., RA-L 2025; upstream TRV-Lab/MAFF-Net, an OpenPCDet fork).

Pipeline for one radar scan (points [N, F], columns as the card names them, radar frame, metres):
1. vfe: RadarPillarVFE = OpenPCDet's PillarVFE on the raw features + 6 offsets (Linear 64, BN,
   ReLU, max over the pillar's points) scattered to the canvas [64, ny, nx];
2. map_to_bev_module: sparse pillar attention (SPA) with the 2-D rotary term
   (:mod:`radaredge.ops.pillar_attention`);
3. image_backbone: clustering-feature assistance (CFA) = a clustering map -> 3x3 convs 3 -> 16 ->
   32 -> 64; the map is the fork's GridDensityBEV (:mod:`radaredge.ops.grid_density`) or, with
   ``cfa.method: dbscan``, upstream CQCA_cfa's sklearn-DBSCAN map (:mod:`radaredge.ops.dbscan`);
4. fuser: upstream's CQCA_caf at test time (:mod:`radaredge.models.maffnet.fuser`): the CFA tokens query
   the pillar tokens, the result is upsampled onto the pillar map, SE, concat, conv;
5. backbone_2d: OpenPCDet's BaseBEVBackbone; dense_head: AnchorHeadSingle (class, box and
   direction 1x1 convs), residual box decoding with the direction bin;
6. post-processing: sigmoid scores, best class per anchor, score threshold and class-agnostic
   rotated NMS (:mod:`radaredge.ops.nms`);
   or, for a card with ``stage_two``, the PV-RCNN-style second stage instead
   (:mod:`radaredge.models.maffnet.rcnn`: proposals, CDA keypoints, VSA, point head, ROI head,
   final NMS), whose refined detections are then ``boxes``/``scores``/``labels``.

Module names follow upstream's state-dict keys (``vfe.pfn_layers.0.linear.weight``,
``map_to_bev_module.pillar_attention_rope.q_mlp.weight``, ``image_backbone.conv.0.weight``,
``backbone_2d.blocks.0.1.weight``, ``dense_head.conv_cls.weight``, ``fuser.crossfusion.pos_emb_ir``...),
so an upstream checkpoint loads by name; upstream parameters that never reach the output are
dropped by the rules of :meth:`MAFFNet.checkpoint_drop_rules` (docs/models/maffnet.md lists them).

``forward`` is the export formulation; ``run(..., reference=True)`` computes the same function
with the reference ops (dynamic voxelization, NonZero-based SPA, GridDensityBEV or DBSCAN with
Python loops, plain-Python greedy NMS).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ...cards import ModelCard
from ...config import Range, card_ranges, config_from_dict, positive
from ...errors import CapacityError, ConfigError
from ...ops.dbscan import DbscanConfig, cqca_cfa_map, cqca_cfa_map_reference
from ...ops.grid_density import GridDensityBEV, GridDensityConfig, grid_density_bev_reference
from ...ops.input_flags import (
    column_bounds,
    drop_implausible,
    drop_implausible_reference,
    frame_flags,
    frame_flags_reference,
)
from ...ops.nms import NmsConfig, class_agnostic_nms, class_agnostic_nms_reference
from ...ops.pillar_attention import SparsePillarAttention, sparse_pillar_attention_reference
from ...ops.pillars import (
    PillarConfig,
    PillarFeatureNet,
    SlotMoments,
    outside_grid,
    pillar_canvas,
    pillar_features_reference,
    point_drops_reference,
    scatter_pillars_reference,
)
from . import rcnn as two
from .fuser import UNUSED_FUSER_KEYS, CafConfig, CrossAttentionFusion

# ----------------------------------------------------------------------------- configuration


@card_ranges(capacity=(1, 3839))
@dataclass(frozen=True)
class SpaConfig:
    """Card section ``spa``. The capacity is a TopK's K in the graph, which TensorRT caps below 3840."""

    enabled: bool = True  # upstream IS_SPA
    capacity: int = 1024  # pillar slots of the exported attention; more pillars are reported


CFA_METHODS = ("grid_density", "dbscan")


@dataclass(frozen=True)
class CfaConfig:
    """Card section ``cfa`` scalars; the method's own settings are ``cfa.grid`` (GridDensityConfig)
    or ``cfa.dbscan`` (DbscanConfig)."""

    velocity_feature: str = "v_r_comp"  # card feature column used as the map's velocity (upstream DBSCAN_V)
    method: str = "grid_density"  # "grid_density" (the fthbng77 fork) or "dbscan" (upstream CQCA_cfa)
    not_converged: str = ""  # radaredge.runtime on cfa_converged False: "warn" or "error";
    # "" = the method's ("warn" for grid_density, "error" for dbscan)

    def __post_init__(self):
        if self.method not in CFA_METHODS:
            raise ValueError(f"method must be one of {CFA_METHODS}, got {self.method!r}")
        if self.not_converged not in ("", "warn", "error"):
            raise ValueError(f"not_converged must be 'warn' or 'error', got {self.not_converged!r}")


@card_ranges(scans_accumulated=(1, 64))
@dataclass(frozen=True)
class InputConfig:
    """Card section ``input``: what one call of the graph expects (upstream's test-time input)."""

    scans_accumulated: int = 1  # scans accumulated into one cloud (VoD radar_5frames: 5, time <= 0 s)
    crop: str = "none"  # "camera_fov": points outside the camera's view removed beforehand

    def __post_init__(self):
        if not isinstance(self.scans_accumulated, int) or self.scans_accumulated < 1:
            raise ValueError(f"scans_accumulated must be an integer >= 1, got {self.scans_accumulated!r}")
        if self.crop not in ("none", "camera_fov"):
            raise ValueError(f"crop must be 'none' or 'camera_fov', got {self.crop!r}")


@card_ranges(
    layer_nums=(0, 64),
    layer_strides=(1, 8),
    num_filters=(1, 4096),
    upsample_strides=positive(16.0),
    num_upsample_filters=(1, 4096),
)
@dataclass(frozen=True)
class BackboneConfig:
    """Card section ``backbone_2d`` (OpenPCDet BaseBEVBackbone)."""

    layer_nums: tuple = (3, 5, 5)
    layer_strides: tuple = (2, 2, 2)
    num_filters: tuple = (64, 128, 512)
    upsample_strides: tuple = (1, 2, 4)
    num_upsample_filters: tuple = (128, 128, 128)

    def __post_init__(self):
        lengths = {
            f: len(getattr(self, f))
            for f in ("layer_nums", "layer_strides", "num_filters", "upsample_strides", "num_upsample_filters")
        }
        if len(set(lengths.values())) != 1 or not lengths["layer_nums"]:
            raise ValueError(
                f"the lists {', '.join(f'{k} ({v})' for k, v in lengths.items())} must have one "
                f"length, one entry per backbone block (at least one)"
            )


@card_ranges(
    anchor_sizes=positive(1000.0),
    anchor_rotations=(-7.0, 7.0),
    anchor_bottom_heights=(-1000.0, 1000.0),
    feature_map_stride=(1, 64),
    matched_threshold=(0.0, 1.0),
    unmatched_threshold=(0.0, 1.0),
)
@dataclass(frozen=True)
class AnchorClass:
    """One entry of ``dense_head.anchors`` (OpenPCDet ANCHOR_GENERATOR_CONFIG)."""

    class_name: str
    anchor_sizes: tuple  # ((dx, dy, dz),) metres
    anchor_rotations: tuple = (0.0, 1.57)
    anchor_bottom_heights: tuple = (0.0,)
    align_center: bool = False
    feature_map_stride: int = 2
    matched_threshold: float | None = None  # training only (radaredge train's target assigner);
    unmatched_threshold: float | None = None  # None: upstream's value for the class


@card_ranges(
    dir_offset=(-7.0, 7.0), dir_limit_offset=(0.0, 1.0), num_dir_bins=(1, 64), cls_prior=Range(0.0, 1.0, True, True)
)
@dataclass(frozen=True)
class HeadConfig:
    """Card section ``dense_head`` scalars (the anchors are read separately)."""

    dir_offset: float = 0.78539
    dir_limit_offset: float = 0.0
    num_dir_bins: int = 2
    cls_prior: float = 0.01  # OpenPCDet AnchorHeadSingle.init_weights: bias = -log((1 - pi) / pi)


# ----------------------------------------------------------------------------- modules


def _conv_bn_relu(cin: int, cout: int, k: int = 3, stride: int = 1, padding: int = 1) -> list[nn.Module]:
    return [
        nn.Conv2d(cin, cout, k, stride=stride, padding=padding, bias=False),
        nn.BatchNorm2d(cout, eps=1e-3, momentum=0.01),
        nn.ReLU(),
    ]


class ClusteringFeatureAssist(nn.Module):
    """CFA (upstream ``image_backbone``): a clustering map [3, H, W] -> CNN -> [64, H, W].

    The map is GridDensityBEV's (``grid``, the fork's) or upstream CQCA_cfa's DBSCAN map
    (``dbscan``, :mod:`radaredge.ops.dbscan`): sklearn's DBSCAN on (x, y, velocity) of the scan
    points, computed in the graph; channels velocity, raw cluster size, raw label."""

    def __init__(self, grid: GridDensityConfig | None = None, dbscan: DbscanConfig | None = None):
        super().__init__()
        if (grid is None) == (dbscan is None):
            raise ConfigError("cfa: exactly one of a GridDensityBEV grid and a DBSCAN config is needed")
        self.grid_density = GridDensityBEV(grid) if grid is not None else None
        self.dbscan = dbscan
        self.conv = nn.Sequential(*_conv_bn_relu(3, 16), *_conv_bn_relu(16, 32), *_conv_bn_relu(32, 64))

    def forward(self, xyv: torch.Tensor, scan: torch.Tensor):
        """Export formulation: (map [3, H, W], cluster_points [N] bool, converged [] bool) for points
        xyv [N, 3] (x, y in m, velocity in m/s); ``scan`` marks the points upstream's model sees.
        (A forward, so the exported nodes carry the ``image_backbone`` scope for the stage split.)"""
        if self.grid_density is not None:
            return self.grid_density(xyv, torch.ones(xyv.shape[0], dtype=torch.bool, device=xyv.device))
        # the scan points first, in index order, so ``capacity`` counts scan points; then back
        n = xyv.shape[0]
        ar = torch.arange(n, device=xyv.device)
        order = torch.argsort(torch.where(scan, ar, ar + n))
        bev, mask, converged = cqca_cfa_map(xyv[order], scan[order], self.dbscan)
        return bev, torch.zeros(n, dtype=torch.bool, device=xyv.device).scatter(0, order, mask), converged

    def reference(self, xyv: torch.Tensor, scan: torch.Tensor):
        """Reference formulation of :meth:`forward` (Python loops over points and cells)."""
        if self.grid_density is not None:
            bev, mask, converged = grid_density_bev_reference(
                xyv.numpy(), np.ones(len(xyv), bool), self.grid_density.config
            )
            return torch.from_numpy(bev), torch.from_numpy(mask), torch.tensor(converged)
        s = scan.numpy()
        order = np.concatenate([np.flatnonzero(s), np.flatnonzero(~s)])
        bev, mask, converged = cqca_cfa_map_reference(xyv.numpy()[order], s[order], self.dbscan)
        back = np.zeros(len(s), bool)
        back[order] = mask
        return torch.as_tensor(bev), torch.from_numpy(back), torch.tensor(bool(converged))


# Upstream's stage-two modules, dropped from a checkpoint by the stage-one cards.
STAGE_TWO_PREFIXES = ("pfe.", "point_head.", "roi_head.")
# TJ4D's RadarPillarVFE_TJ builds an SE layer on its 11 inputs with reduction 16 (0-wide tensors)
# and never calls it.
UNUSED_VFE_KEYS = ("vfe.se.",)


class BaseBEVBackbone(nn.Module):
    """OpenPCDet's BaseBEVBackbone: strided conv blocks, transposed-conv upsampling, concat."""

    def __init__(self, cin: int, cfg: BackboneConfig):
        super().__init__()
        self.blocks, self.deblocks = nn.ModuleList(), nn.ModuleList()
        chans = [cin, *cfg.num_filters[:-1]]
        for i, (n, stride, f) in enumerate(zip(cfg.layer_nums, cfg.layer_strides, cfg.num_filters)):
            layers = [nn.ZeroPad2d(1), *_conv_bn_relu(chans[i], f, stride=stride, padding=0)]
            for _ in range(n):
                layers += _conv_bn_relu(f, f)
            self.blocks.append(nn.Sequential(*layers))
            up, uf = cfg.upsample_strides[i], cfg.num_upsample_filters[i]
            if up >= 1:
                self.deblocks.append(
                    nn.Sequential(
                        nn.ConvTranspose2d(f, uf, up, stride=up, bias=False),
                        nn.BatchNorm2d(uf, eps=1e-3, momentum=0.01),
                        nn.ReLU(),
                    )
                )
            else:
                k = round(1 / up)
                self.deblocks.append(
                    nn.Sequential(
                        nn.Conv2d(f, uf, k, stride=k, bias=False),
                        nn.BatchNorm2d(uf, eps=1e-3, momentum=0.01),
                        nn.ReLU(),
                    )
                )
        self.num_bev_features = sum(cfg.num_upsample_filters)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ups = []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)
            ups.append(deblock(x))
        return torch.cat(ups, 1) if len(ups) > 1 else ups[0]


class AnchorHeadSingle(nn.Module):
    """OpenPCDet's AnchorHeadSingle: 1x1 convs for class scores, box residuals and direction bins."""

    def __init__(self, cin: int, anchors_per_location: int, num_classes: int, cfg: HeadConfig):
        super().__init__()
        self.num_classes, self.num_dir_bins = num_classes, cfg.num_dir_bins
        self.conv_cls = nn.Conv2d(cin, anchors_per_location * num_classes, 1)
        self.conv_box = nn.Conv2d(cin, anchors_per_location * 7, 1)
        self.conv_dir_cls = nn.Conv2d(cin, anchors_per_location * cfg.num_dir_bins, 1)
        nn.init.constant_(self.conv_cls.bias, -math.log((1 - cfg.cls_prior) / cfg.cls_prior))
        nn.init.normal_(self.conv_box.weight, mean=0.0, std=0.001)

    def forward(self, x: torch.Tensor):
        """x [1, C, H, W] -> (cls [A, classes] logits, box [A, 7] residuals, dir [A, bins]) per anchor."""

        def flat(t, k):
            return t[0].permute(1, 2, 0).reshape(-1, k)

        return (
            flat(self.conv_cls(x), self.num_classes),
            flat(self.conv_box(x), 7),
            flat(self.conv_dir_cls(x), self.num_dir_bins),
        )


def generate_anchors(classes: list[AnchorClass], point_cloud_range, grid_xy: tuple[int, int]) -> torch.Tensor:
    """OpenPCDet's AnchorGenerator for a single-stride head: anchors [A, 7] in the order the head's
    channels use (row y, column x, class, size, rotation), z at the box centre."""
    r = point_cloud_range
    per_class = []
    strides = {c.feature_map_stride for c in classes}
    if len(strides) != 1:
        raise ConfigError("dense_head.anchors: every class needs the same feature_map_stride (single head)")
    for c in classes:
        fx, fy = grid_xy[0] // c.feature_map_stride, grid_xy[1] // c.feature_map_stride
        if c.align_center:
            sx, sy = (r[3] - r[0]) / fx, (r[4] - r[1]) / fy
            ox, oy = sx / 2, sy / 2
        else:
            sx, sy = (r[3] - r[0]) / (fx - 1), (r[4] - r[1]) / (fy - 1)
            ox = oy = 0.0
        xs = torch.arange(r[0] + ox, r[3] + 1e-5, step=sx, dtype=torch.float32)[:fx]
        ys = torch.arange(r[1] + oy, r[4] + 1e-5, step=sy, dtype=torch.float32)[:fy]
        sizes = torch.tensor(c.anchor_sizes, dtype=torch.float32).reshape(-1, 3)
        rots = torch.tensor(c.anchor_rotations, dtype=torch.float32)
        if len(c.anchor_bottom_heights) != 1:
            raise ConfigError(f"dense_head.anchors[{c.class_name}]: one anchor_bottom_height expected")
        z = float(c.anchor_bottom_heights[0])
        ns, nr = len(sizes), len(rots)
        a = torch.zeros(fy, fx, ns, nr, 7)
        a[..., 0] = xs.view(1, fx, 1, 1)
        a[..., 1] = ys.view(fy, 1, 1, 1)
        a[..., 3:6] = sizes.view(1, 1, ns, 1, 3)
        a[..., 2] = z + a[..., 5] / 2
        a[..., 6] = rots.view(1, 1, 1, nr)
        per_class.append(a)
    return torch.cat(per_class, 2).reshape(-1, 7)


def decode_boxes(
    residuals: torch.Tensor, anchors: torch.Tensor, dir_logits: torch.Tensor, cfg: HeadConfig
) -> torch.Tensor:
    """OpenPCDet ResidualCoder.decode_torch plus the direction-bin heading fix: boxes [A, 7]."""
    xa, ya, za, dxa, dya, dza, ra = anchors.unbind(-1)
    xt, yt, zt, dxt, dyt, dzt, rt = residuals.unbind(-1)
    diagonal = torch.sqrt(dxa**2 + dya**2)
    heading = rt + ra
    period = 2 * math.pi / cfg.num_dir_bins
    dir_label = torch.argmax(dir_logits, -1).to(residuals.dtype)
    val = heading - cfg.dir_offset
    rot = val - torch.floor(val / period + cfg.dir_limit_offset) * period
    heading = rot + cfg.dir_offset + period * dir_label
    return torch.stack(
        [
            xt * diagonal + xa,
            yt * diagonal + ya,
            zt * dza + za,
            torch.exp(dxt) * dxa,
            torch.exp(dyt) * dya,
            torch.exp(dzt) * dza,
            heading,
        ],
        -1,
    )


# ----------------------------------------------------------------------------- the detector


class MAFFNet(nn.Module):
    """MAFF-Net stage one with both formulations. Build it with :func:`build_maffnet`."""

    def __init__(
        self,
        features: list[str],
        classes: list[str],
        pillars: PillarConfig,
        spa: SpaConfig,
        cfa: CfaConfig,
        grid: GridDensityConfig | DbscanConfig,
        caf: CafConfig,
        backbone: BackboneConfig,
        head: HeadConfig,
        anchors: list[AnchorClass],
        nms: NmsConfig,
        stage_two=None,
        vfe_features: list[str] | None = None,
    ):
        super().__init__()
        if features[:3] != ["x", "y", "z"]:
            raise ConfigError(f"features must start with x, y, z; got {features}")
        vfe_features = list(features if vfe_features is None else vfe_features)
        if (
            vfe_features[:3] != ["x", "y", "z"]
            or len(set(vfe_features)) != len(vfe_features)
            or not set(vfe_features) <= set(features)
        ):
            raise ConfigError(
                f"vfe_features must start with x, y, z and name each of the card's features {features} "
                f"at most once; got {vfe_features}"
            )
        if cfa.velocity_feature not in features:
            raise ConfigError(f"cfa.velocity_feature {cfa.velocity_feature!r} is not a card feature {features}")
        if [a.class_name for a in anchors] != list(classes):
            raise ConfigError(f"dense_head.anchors classes {[a.class_name for a in anchors]} != classes {classes}")
        nx, ny, nz = pillars.grid_size
        if nz != 1:
            raise ConfigError(f"pillars: the z range must be one voxel (got {nz})")
        rows, cols = (grid.map_rows, grid.map_cols) if isinstance(grid, DbscanConfig) else (grid.map_h, grid.map_w)
        if (rows, cols) != (ny, nx):
            section = "cfa.dbscan" if isinstance(grid, DbscanConfig) else "cfa.grid"
            raise ConfigError(f"{section} is {rows} x {cols} cells but the pillar grid is {ny} x {nx}")
        self.features, self.classes = list(features), list(classes)
        self.velocity_index = features.index(cfa.velocity_feature)
        self.cfa_method = "dbscan" if isinstance(grid, DbscanConfig) else "grid_density"
        self.spa_config, self.head_config, self.nms_config = spa, head, nms
        self.point_bounds = ([-math.inf] * len(features), [math.inf] * len(features))  # build: the card's plausible
        # the VFE's input columns in its own order (upstream RadarPillarVFE_TJ reads SNR before v_r);
        # None: the card's columns as they come
        self.vfe_columns = None if vfe_features == list(features) else [list(features).index(f) for f in vfe_features]
        self.vfe = PillarFeatureNet(len(vfe_features), pillars)
        self.map_to_bev_module = SparsePillarAttention(pillars.out_channels, spa.capacity) if spa.enabled else None
        self.image_backbone = (
            ClusteringFeatureAssist(dbscan=grid)
            if isinstance(grid, DbscanConfig)
            else ClusteringFeatureAssist(grid=grid)
        )
        self.fuser = CrossAttentionFusion(pillars.out_channels, 64, caf)
        self.backbone_2d = BaseBEVBackbone(caf.out_channels, backbone)
        per_loc = sum(len(a.anchor_sizes) * len(a.anchor_rotations) for a in anchors)
        self.dense_head = AnchorHeadSingle(self.backbone_2d.num_bev_features, per_loc, len(classes), head)
        self.register_buffer(
            "anchors", generate_anchors(anchors, pillars.point_cloud_range, (nx, ny)), persistent=False
        )
        self.stage_two_config = stage_two  # StageTwoConfig or None (stage one only)
        if stage_two is not None:
            r, v = pillars.point_cloud_range, pillars.voxel_size
            two.build_stage_two(self, stage_two, len(features) - 3, caf.out_channels, (r[0], r[1]), (v[0], v[1]))

    def checkpoint_drop_rules(self) -> list[tuple[str, tuple[str, ...], bool]]:
        """Upstream checkpoint keys this model drops on load: (rule, key prefixes, only zero-size
        tensors) per rule (see export.load_checkpoint)."""
        rules = [
            ("upstream fuser parameters with no effect at test time", UNUSED_FUSER_KEYS, False),
            ("upstream RadarPillarVFE_TJ's zero-width SE layer, never called", UNUSED_VFE_KEYS, True),
        ]
        if self.stage_two_config is None:
            rules.append(("stage-two modules on a stage-one card", STAGE_TWO_PREFIXES, False))
        return rules

    def init_kaiming(self) -> None:
        """He-normal (fan_out, ReLU) weights for every conv before the head, so an untrained
        model keeps unit-scale activations through the 13-layer backbone (torch's default init
        shrinks them layer by layer, which leaves every anchor score within 1e-3 of the prior)."""
        for name, m in self.named_modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)) and not name.startswith("dense_head"):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    # -- stages ---------------------------------------------------------------------
    def pillar_input_moments(self, points: torch.Tensor) -> SlotMoments:
        """The moments of the VFE's PFN input for the scan ``points`` (implausible rows already
        NaN, as :meth:`pillar_stage` takes them), to normalise a batch of scans run one at a time
        (:meth:`radaredge.ops.pillars.PFNLayer.batch_statistics`)."""
        if self.vfe_columns is not None:
            points = points[:, self.vfe_columns]
        return self.vfe.input_moments(points, torch.ones(points.shape[0], dtype=torch.bool, device=points.device))

    def pillar_stage(self, points: torch.Tensor, reference: bool, drops: dict | None = None):
        """VFE + SPA: (canvas [C, ny, nx], num_pillars [] int64, overflow [] bool); ``drops``
        receives the export formulation's left-out points (:meth:`PillarFeatureNet.scatter_frames`).
        The VFE sees the card's ``vfe_features`` columns, in that order."""
        if self.vfe_columns is not None:
            points = points[:, self.vfe_columns]
        if not reference:
            canvas, occupied = self.vfe.scatter(
                points, torch.ones(points.shape[0], dtype=torch.bool, device=points.device), drops
            )
            if self.map_to_bev_module is None:
                num = occupied.sum()
                return canvas, num, torch.zeros((), dtype=torch.bool, device=points.device)
            return self.map_to_bev_module(canvas, occupied, points.shape[0])
        cfg = self.vfe.config
        nx, ny, _ = cfg.grid_size
        feats, coords = pillar_features_reference(self.vfe, points.numpy())
        canvas = scatter_pillars_reference(feats, coords, cfg)
        num = torch.tensor(len(coords), dtype=torch.int64)
        if self.map_to_bev_module is not None:
            if len(coords) > self.spa_config.capacity:
                raise CapacityError(
                    f"scan has {len(coords)} non-empty pillars; spa.capacity is {self.spa_config.capacity}"
                )
            occupied = torch.zeros(ny * nx, dtype=torch.bool)
            occupied[torch.from_numpy(coords[:, 1] * nx + coords[:, 0])] = True
            canvas = sparse_pillar_attention_reference(self.map_to_bev_module.pillar_attention_rope, canvas, occupied)
        return canvas, num, torch.zeros((), dtype=torch.bool)

    def pillar_stage_training(self, points: torch.Tensor):
        """Training formulation of :meth:`pillar_stage` (export formulation): the same (canvas,
        num_pillars, overflow) from the non-empty pillars only
        (:meth:`~radaredge.ops.pillars.PillarFeatureNet.pillars`,
        :meth:`~radaredge.ops.pillar_attention.SparsePillarAttention.forward_pillars`), so the
        backward touches the pillars instead of every cell; the canvas is channels last. Eager
        only (its shapes follow the data)."""
        if self.vfe_columns is not None:
            points = points[:, self.vfe_columns]
        features, cells = self.vfe.pillars(points, torch.ones(points.shape[0], dtype=torch.bool, device=points.device))
        nx, ny, _ = self.vfe.config.grid_size
        if self.map_to_bev_module is not None:
            return self.map_to_bev_module.forward_pillars(features, cells, ny, nx)
        num = torch.tensor(cells.shape[0], dtype=torch.int64, device=points.device)
        return pillar_canvas(features, cells, ny, nx), num, torch.zeros((), dtype=torch.bool, device=points.device)

    def cfa_stage(self, points: torch.Tensor, reference: bool):
        """CFA: (features [1, 64, H, W], map [3, H, W], converged [] bool, cluster_points [N] bool:
        GridDensityBEV's points of non-noise cells, or DBSCAN's non-noise scan points)."""
        xyv = torch.stack([points[:, 0], points[:, 1], points[:, self.velocity_index]], 1)
        scan = two.scan_points(points, self.vfe.config.point_cloud_range)[2]
        cfa = self.image_backbone
        bev, mask, converged = cfa.reference(xyv, scan) if reference else cfa(xyv, scan)
        return self.image_backbone.conv(bev.unsqueeze(0)), bev, converged, mask

    def input_flags(
        self,
        points: torch.Tensor,
        reference: bool,
        drops: dict,
        overflow: torch.Tensor,
        converged: torch.Tensor,
        implausible: torch.Tensor,
    ) -> torch.Tensor:
        """int32 [1]: :mod:`radaredge.runtime.flags` of the scan. A DBSCAN map that did not converge
        left points beyond its capacity out (``capacity``); a GridDensityBEV map stopped its
        components short (``not_converged``); ``implausible`` [N] marks the points
        :meth:`run` turned into NaN rows."""
        dbscan = self.cfa_method == "dbscan"
        capacity = overflow | (~converged if dbscan else torch.zeros_like(converged))
        not_converged = torch.zeros_like(converged) if dbscan else ~converged
        cfg = self.vfe.config
        if reference:
            outside, full = point_drops_reference(points.numpy(), cfg)
            return frame_flags_reference(
                [points.numpy()],
                None,
                [outside],
                [full],
                capacity.numpy(),
                not_converged.numpy(),
                [implausible.numpy()],
            )
        frame = torch.zeros(points.shape[0], dtype=torch.int64, device=points.device)
        return frame_flags(
            points, frame, 1, None, outside_grid(points, cfg), drops["full"], capacity, not_converged, implausible
        )

    def head_stage(self, fused: torch.Tensor):
        """Backbone + head + decoding: (class logits [A, classes], boxes [A, 7])."""
        cls, box, direction = self.dense_head(self.backbone_2d(fused))
        return cls, decode_boxes(box, self.anchors, direction, self.head_config)

    def postprocess(self, scores: torch.Tensor, boxes: torch.Tensor, reference: bool):
        """Best class per anchor, threshold, NMS: (boxes [M, 7], scores [M], labels [M] 1-based)."""
        best, label = scores.max(-1)
        if reference:
            sel = torch.from_numpy(class_agnostic_nms_reference(boxes.numpy(), best.numpy(), self.nms_config))
        else:
            sel = class_agnostic_nms(boxes, best, self.nms_config)
        return boxes[sel], best[sel], label[sel] + 1

    # -- the two formulations -----------------------------------------------------------
    def forward(self, points: torch.Tensor):
        """Export formulation: points [N, F] -> (boxes [M, 7], scores [M], labels [M] int64 1-based,
        anchor_scores [A, classes], anchor_boxes [A, 7], num_pillars [] int64, spa_overflow [] bool,
        cfa_converged [] bool, input_flags [1] int32), then with stage two ``anchor_logits``
        [A, classes] (what the proposal layer ranks) and the STAGE_TWO_OUTPUTS; boxes, scores and
        labels are then the refined detections."""
        out = self.run(points)
        return tuple(out[k] for k in output_names(self.stage_two_config is not None))

    def run(self, points: torch.Tensor, reference: bool = False, trace: dict | None = None) -> dict[str, torch.Tensor]:
        """Both formulations; ``trace`` (a dict) receives intermediates for divergence reports.
        Points with a value outside the card's plausible range become NaN rows first, which
        every stage leaves out (:func:`radaredge.ops.input_flags.drop_implausible`)."""
        if reference:
            cleaned, bad = drop_implausible_reference(points.numpy(), *self.point_bounds)
            points, implausible = torch.from_numpy(cleaned), torch.from_numpy(bad)
        else:
            points, implausible = drop_implausible(points, *self.point_bounds)
        drops: dict = {}
        pillar, num_pillars, overflow = self.pillar_stage(points, reference, drops)
        cfa, cfa_map, converged, cluster = self.cfa_stage(points, reference)
        fused = self.fuser(pillar.unsqueeze(0), cfa)
        logits, boxes = self.head_stage(fused)
        scores = torch.sigmoid(logits)
        if trace is not None:
            trace.update(pillar_bev=pillar, cfa_map=cfa_map, cfa_features=cfa, fused=fused, cluster_points=cluster)
        out = {
            "anchor_scores": scores,
            "anchor_boxes": boxes,
            "num_pillars": num_pillars,
            "spa_overflow": overflow,
            "cfa_converged": converged,
            "input_flags": self.input_flags(points, reference, drops, overflow, converged, implausible),
        }
        if self.stage_two_config is None:
            out["boxes"], out["scores"], out["labels"] = self.postprocess(scores, boxes, reference)
        else:
            out["anchor_logits"] = logits
            out.update(two.run_stage_two(self, points, fused[0], cluster, logits, boxes, reference, trace))
        return out


def stage_times(model: MAFFNet, points: torch.Tensor, reference: bool) -> dict[str, float]:
    """Seconds per stage of one scan in torch: VFE+SPA, CFA, CAF, backbone+head, then NMS, or with
    stage two: proposals+CDA, VSA+point head, ROI head, final NMS."""
    out, t = {}, time.perf_counter()

    def lap(name):
        nonlocal t
        now = time.perf_counter()
        out[name] = now - t
        t = now

    with torch.no_grad():
        pillar, _, _ = model.pillar_stage(points, reference)
        lap("VFE+SPA")
        cfa, _, _, cluster = model.cfa_stage(points, reference)
        lap("CFA")
        fused = model.fuser(pillar.unsqueeze(0), cfa)
        lap("CAF")
        logits, boxes = model.head_stage(fused)
        scores = torch.sigmoid(logits)
        lap("backbone+head")
        if model.stage_two_config is None:
            model.postprocess(scores, boxes, reference)
            lap("NMS")
            return out
        two.run_stage_two(model, points, fused[0], cluster, logits, boxes, reference, lap=lap)
    return out


OUTPUT_NAMES = (
    "boxes",
    "scores",
    "labels",
    "anchor_scores",
    "anchor_boxes",
    "num_pillars",
    "spa_overflow",
    "cfa_converged",
    "input_flags",
)


def output_names(stage_two: bool) -> tuple[str, ...]:
    """Graph outputs: stage one's, plus the class logits the proposal layer ranks and the
    stage-two outputs (maffnet_rcnn.STAGE_TWO_OUTPUTS)."""
    return OUTPUT_NAMES + ("anchor_logits",) + two.STAGE_TWO_OUTPUTS if stage_two else OUTPUT_NAMES


def read_anchors(card: ModelCard) -> list[AnchorClass]:
    """``dense_head.anchors`` as AnchorClass entries, with errors naming the entry."""
    raw = card.get("dense_head.anchors")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{card.where}: dense_head.anchors must be a non-empty list")
    out = []
    for i, entry in enumerate(raw):
        a = config_from_dict(AnchorClass, entry, f"{card.where}: dense_head.anchors[{i}]")
        out.append(dataclasses.replace(a, anchor_sizes=tuple(tuple(s) for s in a.anchor_sizes)))
    return out


def read_vfe_features(card: ModelCard) -> list[str] | None:
    """The card's ``vfe_features``: the columns the pillar VFE takes, in its input order (upstream's
    RadarPillarVFE_TJ selects SNR before v_r whatever order the points have); None when absent
    (the card's ``features`` as they come)."""
    cols = card.get("vfe_features")
    if cols is None:
        return None
    if not isinstance(cols, list) or not all(isinstance(c, str) for c in cols):
        raise ConfigError(f"{card.where}: vfe_features must be a list of the card's feature columns, got {cols!r}")
    return cols


def build_maffnet(card: ModelCard) -> MAFFNet:
    """MAFF-Net from a model card, with a seeded initialisation (card ``seed``, default 0)."""
    torch.manual_seed(int(card.get("seed", 0)))
    head = dict(card.get("dense_head", {}) or {})
    head.pop("anchors", None)
    cfa = config_from_dict(
        CfaConfig,
        {k: v for k, v in (card.get("cfa", {}) or {}).items() if k not in ("grid", "dbscan")},
        f"{card.where}: cfa",
    )
    card.section("input", InputConfig)  # validated here; docs/models/maffnet.md explains it
    unused = "grid" if cfa.method == "dbscan" else "dbscan"
    if card.get(f"cfa.{unused}") is not None:
        raise ConfigError(f"{card.where}: cfa.{unused} is set but cfa.method is {cfa.method!r}; remove one")
    model = MAFFNet(
        features=card.features,
        classes=list(card.get("classes", [])),
        pillars=card.section("pillars", PillarConfig),
        spa=card.section("spa", SpaConfig),
        cfa=cfa,
        grid=(
            card.section("cfa.dbscan", DbscanConfig)
            if cfa.method == "dbscan"
            else card.section("cfa.grid", GridDensityConfig)
        ),
        caf=card.section("caf", CafConfig),
        backbone=card.section("backbone_2d", BackboneConfig),
        head=config_from_dict(HeadConfig, head, f"{card.where}: dense_head"),
        anchors=read_anchors(card),
        nms=card.section("post_processing", NmsConfig),
        stage_two=two.read_stage_two(card),
        vfe_features=read_vfe_features(card),
    )
    model.point_bounds = column_bounds(card)  # plausible (low, high) per point column
    init = card.get("init", "torch")
    if init == "kaiming":
        model.init_kaiming()
    elif init != "torch":
        raise ConfigError(f"{card.where}: init must be 'torch' or 'kaiming', got {init!r}")
    return model.eval()
