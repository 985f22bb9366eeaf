"""MAFF-Net stage two (test time): upstream TRV-Lab/MAFF-Net's PV-RCNN-style refinement.

For one scan, after stage one's anchor head (radar frame: x forward, y left, z up; metres,
radians; boxes in OpenPCDet's (x, y, z, dx, dy, dz, heading) layout):

1. proposals (``roi_head.proposal_layer``, :class:`ProposalLayer`): per anchor the best class
   logit and its 1-based label; class-agnostic: the ``pre_max`` best, rotated BEV NMS at
   ``iou_thresh``, the first ``post_max`` -> rois [R, 7] zero-padded, roi_labels [R] (0 when
   padded) and roi_valid [R]. No score threshold (upstream has none here).
2. CDA keypoints (:class:`CDAKeypointSampler`, upstream ``VoxelSetAbstraction_cda`` with
   SAMPLE_METHOD CDA): the CFA's cluster points inside a cylinder around any roi row, in index
   order (FPS above ``num_keypoints``), then filled to exactly ``num_keypoints`` by FPS over all
   scan points -> keypoints [K, 3] + keypoint_valid.
3. VSA (``pfe``, :class:`VoxelSetAbstractionCDA`): per keypoint [the fuser's output bilinearly
   interpolated, multi-scale set abstraction ``SA_clusterpoints`` over all scan points] =
   point_features_before_fusion, then Linear + BN + ReLU -> point_features.
4. ``point_head`` (PointHeadSimple, class agnostic): point_cls_scores = sigmoid(MLP(before fusion)).
5. ``roi_head`` (:class:`PVRCNNHead`): a grid_size^3 grid per roi, set abstraction of the
   valid keypoints' point_features * point_cls_scores around each grid point, shared FCs, a class
   logit and 7 residuals per roi, decoded against the roi (ResidualCoder, centre-free, then
   rotated by the roi heading and moved to the roi centre).
6. final class-agnostic NMS on the refined boxes (score = sigmoid(rcnn logit), label = roi
   label); padded rois are never emitted (ours: upstream can emit the zero-size boxes of padding).

Upstream's behaviour is reproduced where it is odd (the zero rois of empty slots take part in
the CDA cylinder test unless ``keypoints.padded_rois: valid``); where it crashes (an empty scan
divides by zero in the fill) the graph returns invalid keypoints instead. docs/models/maffnet.md
lists every such choice.

Every module has the export formulation (``forward``: fixed shapes; the only data-dependent
parts are the NMS's candidate pairs and Loop and the FPS Loop) and a ``reference`` (Python loops
over proposals, points, rois and grid points; variable-size sets; the plain greedy NMS).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from ...cards import ModelCard
from ...config import Range, card_ranges, check_numbers, config_from_dict, positive
from ...errors import ConfigError
from ...ops.bev_interp import bev_interpolate, bev_interpolate_reference
from ...ops.nms import NmsConfig, class_agnostic_nms, class_agnostic_nms_eager, class_agnostic_nms_reference
from ...ops.point_sampling import farthest_point_sample_masked, farthest_point_sample_reference
from ...ops.set_abstraction import SAModuleMSG

# ----------------------------------------------------------------------------- configuration


@card_ranges(pre_max=(1, 2**20), iou_thresh=(0.0, 1.0), post_max=(1, 2**16))
@dataclass(frozen=True)
class ProposalConfig:
    """``stage_two.proposals`` (ROI_HEAD.NMS_CONFIG.TEST)."""

    pre_max: int = 1024  # NMS_PRE_MAXSIZE
    iou_thresh: float = 0.7  # NMS_THRESH
    post_max: int = 100  # NMS_POST_MAXSIZE = number of roi slots

    def nms(self) -> NmsConfig:
        """No score threshold: every anchor competes (scores are logits, any sign)."""
        return NmsConfig(
            score_thresh=-math.inf, iou_thresh=self.iou_thresh, pre_max=self.pre_max, post_max=self.post_max
        )


@card_ranges(
    num_keypoints=(1, 2**16), sample_radius_r=positive(1000.0), sample_radius_h=positive(1000.0), num_sectors=(1, 64)
)
@dataclass(frozen=True)
class KeypointConfig:
    """``stage_two.keypoints`` (PFE NUM_KEYPOINTS, CDAM_SAMPLING)."""

    num_keypoints: int = 1024  # NUM_KEYPOINTS: keypoints per scan, always filled to this count
    sample_radius_r: float = 2.5  # m, SAMPLE_RADIUS_R: cylinder radius = max(dx, dy) / 2 + this
    sample_radius_h: float = 3.0  # m, SAMPLE_RADIUS_H: cylinder height = dz + this, centred on the roi
    num_sectors: int = 1  # NUM_SECTORS of the sector FPS (only 1 is supported)
    padded_rois: str = "upstream"  # "upstream": the zero rois of empty slots count (a cylinder of radius
    # SAMPLE_RADIUS_R at the origin); "valid": only rois that NMS kept

    def __post_init__(self):
        if self.num_sectors != 1:
            raise ConfigError("stage_two.keypoints.num_sectors: only 1 sector is supported (upstream's configs)")
        if self.padded_rois not in ("upstream", "valid"):
            raise ConfigError(
                f"stage_two.keypoints.padded_rois must be 'upstream' or 'valid', got {self.padded_rois!r}"
            )


@card_ranges(radii=positive(100.0), nsample=(1, 1024), mlps=(1, 4096))
@dataclass(frozen=True)
class SAConfig:
    """A StackSAModuleMSG: radii (m), nsample and MLP widths per scale."""

    radii: tuple = (0.4, 0.8)
    nsample: tuple = (16, 16)
    mlps: tuple = ((16, 16), (16, 16))

    def __post_init__(self):
        if not len(self.radii) == len(self.nsample) == len(self.mlps) >= 1:
            raise ValueError(
                f"radii, nsample and mlps need one entry per scale (one scale or more), got "
                f"{len(self.radii)}, {len(self.nsample)} and {len(self.mlps)} entries"
            )
        if not all(isinstance(m, tuple) and m for m in self.mlps):
            raise ValueError(f"mlps needs a list of widths per scale, got {list(self.mlps)}")


@card_ranges(bev_stride=(1, 64), num_output_features=(1, 4096))
@dataclass(frozen=True)
class VsaConfig:
    """``stage_two.vsa`` scalars (the SA branch is ``stage_two.vsa.sa_clusterpoints``)."""

    bev_stride: int = 1  # stride of the BEV source relative to the pillar grid
    num_output_features: int = 128  # NUM_OUTPUT_FEATURES


@card_ranges(
    shared_fc=(1, 4096), cls_fc=(1, 4096), reg_fc=(1, 4096), dropout=Range(0.0, 1.0, high_open=True), grid_size=(1, 32)
)
@dataclass(frozen=True)
class RoiHeadConfig:
    """``stage_two.roi_head`` scalars (the pooling is ``stage_two.roi_head.roi_grid_pool``)."""

    shared_fc: tuple = (256, 256)  # SHARED_FC
    cls_fc: tuple = (256, 256)  # CLS_FC
    reg_fc: tuple = (256, 256)  # REG_FC
    dropout: float = 0.3  # DP_RATIO (identity at test time)
    grid_size: int = 6  # ROI_GRID_POOL.GRID_SIZE

    def __post_init__(self):
        empty = [n for n in ("shared_fc", "cls_fc", "reg_fc") if not getattr(self, n)]
        if empty:
            raise ValueError(f"{', '.join(empty)} need one layer width or more (upstream's SHARED_FC, CLS_FC, REG_FC)")


@dataclass(frozen=True)
class StageTwoConfig:
    """The whole ``stage_two`` card section."""

    proposals: ProposalConfig = field(default_factory=ProposalConfig)
    keypoints: KeypointConfig = field(default_factory=KeypointConfig)
    vsa: VsaConfig = field(default_factory=VsaConfig)
    sa_clusterpoints: SAConfig = field(default_factory=SAConfig)
    point_head_fc: tuple = (256, 256)
    roi_head: RoiHeadConfig = field(default_factory=RoiHeadConfig)
    roi_grid_pool: SAConfig = field(default_factory=lambda: SAConfig((0.8, 1.6), (16, 16), ((64, 64), (64, 64))))
    post_processing: NmsConfig = field(default_factory=NmsConfig)


def read_stage_two(card: ModelCard) -> StageTwoConfig | None:
    """``stage_two`` of the card, or None for a stage-one card."""
    raw = card.get("stage_two")
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ConfigError(f"{card.where}: stage_two must be a mapping")
    known = {"proposals", "keypoints", "vsa", "point_head", "roi_head", "post_processing"}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{card.where}: stage_two: unknown field(s) {unknown}; expected some of {sorted(known)}")
    vsa = dict(raw.get("vsa") or {})
    roi = dict(raw.get("roi_head") or {})
    where = f"{card.where}: stage_two"
    return StageTwoConfig(
        proposals=card.section("stage_two.proposals", ProposalConfig),
        keypoints=card.section("stage_two.keypoints", KeypointConfig),
        vsa=config_from_dict(VsaConfig, {k: v for k, v in vsa.items() if k != "sa_clusterpoints"}, where + ".vsa"),
        sa_clusterpoints=card.section("stage_two.vsa.sa_clusterpoints", SAConfig),
        point_head_fc=_point_head_fc(card),
        roi_head=config_from_dict(
            RoiHeadConfig, {k: v for k, v in roi.items() if k != "roi_grid_pool"}, where + ".roi_head"
        ),
        roi_grid_pool=card.section("stage_two.roi_head.roi_grid_pool", SAConfig),
        post_processing=card.section("stage_two.post_processing", NmsConfig),
    )


def _point_head_fc(card: ModelCard) -> tuple:
    """``stage_two.point_head.cls_fc``: the point head's hidden widths (each 1 .. 4096)."""
    fc = card.get("stage_two.point_head.cls_fc", [256, 256])
    where = f"{card.where}: stage_two.point_head.cls_fc"
    if not isinstance(fc, (list, tuple)) or not fc:
        raise ConfigError(f"{where}: expected a non-empty list of widths, got {fc!r}")
    check_numbers(fc, Range(1, 4096), True, where)
    return tuple(int(v) for v in fc)


# ----------------------------------------------------------------------------- proposals


def _pad(rows: torch.Tensor, slots: int) -> torch.Tensor:
    """The first ``slots`` rows of ``rows`` followed by zero rows: [slots, ...]."""
    return torch.cat([rows, torch.zeros((slots, *rows.shape[1:]), dtype=rows.dtype, device=rows.device)])[:slots]


class ProposalLayer(nn.Module):
    """Stage one's anchors -> rois (no parameters; a module so its ONNX nodes carry its scope)."""

    def __init__(self, cfg: ProposalConfig):
        super().__init__()
        self.cfg, self.nms = cfg, cfg.nms()

    def _finish(self, boxes, label, sel):
        r = self.cfg.post_max
        return _pad(boxes[sel], r), _pad(label[sel] + 1, r), torch.arange(r, device=boxes.device) < sel.shape[0]

    def forward(self, cls_logits: torch.Tensor, boxes: torch.Tensor):
        """Export formulation: cls_logits [A, classes], boxes [A, 7] -> (rois [R, 7], roi_labels [R]
        int64, roi_valid [R] bool)."""
        score, label = cls_logits.max(-1)
        return self._finish(boxes, label, class_agnostic_nms(boxes, score, self.nms))

    def reference(self, cls_logits: torch.Tensor, boxes: torch.Tensor):
        """Reference: the plain greedy NMS (Python loop) on the best logit per anchor."""
        score, label = cls_logits.max(-1)
        sel = torch.from_numpy(class_agnostic_nms_reference(boxes.numpy(), score.numpy(), self.nms))
        return self._finish(boxes, label, sel)

    def eager(self, cls_logits: torch.Tensor, boxes: torch.Tensor):
        """Training-time validation: :func:`class_agnostic_nms_eager` (the same selection as
        ``forward``, fast when thousands of candidates are left)."""
        score, label = cls_logits.max(-1)
        return self._finish(boxes, label, class_agnostic_nms_eager(boxes, score, self.nms))


# ----------------------------------------------------------------------------- CDA keypoints


def _first_true(mask: torch.Tensor) -> torch.Tensor:
    """Index of the first True of ``mask`` [N], or N when there is none (N = 0 included: a
    sentinel keeps the ArgMax input non-empty)."""
    return torch.argmax(torch.cat([mask, torch.ones(1, dtype=torch.bool, device=mask.device)]).to(torch.int64))


class CDAKeypointSampler(nn.Module):
    """Upstream VoxelSetAbstraction_cda's CDA keypoints of one scan (no parameters).

    Inputs: xyz [N, 3] (finite; m), cluster [N] bool (the CFA's cluster points), scan [N] bool
    (upstream's batch points: finite and inside the range's x/y box), rois [R, 7] (zero rows in
    empty slots), roi_valid [R]. Output keypoints [K, 3], keypoint_valid [K], K = num_keypoints:

    1. a cluster point is kept when it lies in some roi's cylinder: horizontal distance
       sqrt(dx^2 + dy^2) <= max(roi dx, roi dy) / 2 + SAMPLE_RADIUS_R and roi z - h / 2 <= z <=
       roi z + h / 2 with h = roi dz + SAMPLE_RADIUS_H (float32, in that order). With
       ``padded_rois: upstream`` the zero rois of empty slots count like any roi. Nothing kept:
       the first cluster point (upstream's ``points[:1]``), or nothing without cluster points;
    2. more than K kept: FPS over them (one sector), K picks in FPS order; else the kept points
       in index order;
    3. the remaining slots: FPS over all scan points, repeated cyclically when there are fewer
       scan points than slots (upstream's ``repeat``). Every slot is valid unless the scan is empty.
    FPS as :func:`radaredge.ops.point_sampling.farthest_point_sample_masked` (start at the first
    point, ties to the lowest index; the CUDA kernel breaks exact ties by thread order).
    """

    def __init__(self, cfg: KeypointConfig):
        super().__init__()
        self.cfg = cfg

    def cylinder_mask(self, xyz, rois, roi_valid):
        """[N, R] bool: point inside roi's cylinder (step 1's test), export formulation."""
        c = self.cfg
        radius = torch.maximum(rois[:, 3], rois[:, 4]) / 2 + c.sample_radius_r
        height = rois[:, 5] + c.sample_radius_h
        z_lo, z_hi = rois[:, 2] - height / 2, rois[:, 2] + height / 2
        dx, dy = xyz[:, None, 0] - rois[None, :, 0], xyz[:, None, 1] - rois[None, :, 1]
        z = xyz[:, 2:3]
        inside = (torch.sqrt(dx * dx + dy * dy) <= radius) & (z >= z_lo) & (z <= z_hi)
        return inside & roi_valid[None, :] if c.padded_rois == "valid" else inside

    def forward(self, xyz, cluster, scan, rois, roi_valid):
        k, n = self.cfg.num_keypoints, xyz.shape[0]
        selected = cluster & self.cylinder_mask(xyz, rois, roi_valid).any(1)
        ar = torch.arange(n, device=xyz.device)
        first_cluster = (ar == _first_true(cluster)) & cluster
        kept = selected | (first_cluster & ~selected.any())
        count = kept.sum()
        slots = torch.arange(k, device=xyz.device)
        # step 2: index order (first K kept points) or FPS when more than K are kept
        key = torch.where(kept, ar, ar + n).to(torch.float32)
        pad = torch.arange(k, dtype=torch.float32, device=xyz.device) + 2 * n  # K keys above any point's: N < K works
        ordered = torch.topk(torch.cat([key, pad]), k, largest=False, sorted=True).values.to(torch.int64)
        over = count > k
        fps_kept = farthest_point_sample_masked(xyz, kept, k, torch.where(over, k, 0))
        first = torch.where(over, fps_kept, torch.where(ordered >= n, 0, ordered))
        n1 = torch.clamp(count, max=k)
        # step 3: fill from FPS over the scan points, cyclic when the scan is short
        n_scan = scan.sum()
        picks = torch.minimum(k - n1, n_scan)
        fill = farthest_point_sample_masked(xyz, scan, k, picks)
        cyc = torch.remainder(slots - n1, torch.clamp(picks, min=1))
        idx = torch.where(slots < n1, first, torch.gather(fill, 0, cyc))
        valid = (slots < n1) | (n_scan > 0)
        padded = torch.cat([xyz, xyz.new_zeros(1, 3)])  # an empty scan reads the zero row
        return padded[torch.where(valid, idx, n)], valid

    def reference(
        self, xyz: np.ndarray, cluster: np.ndarray, scan: np.ndarray, rois: np.ndarray, roi_valid: np.ndarray
    ):
        """Python loops over points and rois; FPS on the compacted sets; the fill as a list."""
        c, f32, k = self.cfg, np.float32, self.cfg.num_keypoints
        kept = []
        for i, p in enumerate(xyz):
            if not cluster[i]:
                continue
            for roi, ok in zip(rois, roi_valid):
                if c.padded_rois == "valid" and not ok:
                    continue
                radius = max(roi[3], roi[4]) / f32(2) + f32(c.sample_radius_r)
                height = roi[5] + f32(c.sample_radius_h)
                dx, dy = p[0] - roi[0], p[1] - roi[1]
                if np.sqrt(dx * dx + dy * dy) <= radius and roi[2] - height / f32(2) <= p[2] <= roi[2] + height / f32(
                    2
                ):
                    kept.append(i)
                    break
        if not kept:
            kept = list(np.flatnonzero(cluster)[:1])
        kept = np.array(kept, np.int64)
        if len(kept) > k:
            kept = kept[farthest_point_sample_reference(xyz[kept], k)]
        idx = list(kept)
        scan_idx = np.flatnonzero(scan)
        need = k - len(idx)
        if need > 0 and len(scan_idx):
            picks = scan_idx[farthest_point_sample_reference(xyz[scan_idx], min(need, len(scan_idx)))]
            idx += [picks[j % len(picks)] for j in range(need)]
        keypoints = np.zeros((k, 3), np.float32)  # slots without a point stay zero
        keypoints[: len(idx)] = xyz[np.array(idx, np.int64)]
        return torch.from_numpy(keypoints), torch.from_numpy(np.arange(k) < len(idx))


# ----------------------------------------------------------------------------- VSA and point head


class VoxelSetAbstractionCDA(nn.Module):
    """Upstream ``pfe`` (VoxelSetAbstraction_cda, FEATURES_SOURCE [bev, cluster_points]): per keypoint
    [the fused BEV map (the fuser's output, upstream's overwritten ``spatial_features``) bilinearly
    interpolated, multi-scale set abstraction ``SA_clusterpoints`` over ALL scan points (upstream
    runs that branch on ``batch_dict['points']`` with their features beyond xyz)] = before_fusion,
    then Linear + BN + ReLU -> point_features.

    ``origin`` (x_min, y_min) and ``cell`` (vx, vy) in metres place the BEV map (the pillar grid).
    """

    def __init__(self, point_channels: int, bev_channels: int, vsa: VsaConfig, sa: SAConfig, origin, cell):
        super().__init__()
        self.origin, self.cell, self.stride = tuple(origin), tuple(cell), vsa.bev_stride
        self.SA_clusterpoints = SAModuleMSG(point_channels, sa.radii, sa.nsample, sa.mlps)
        self.num_before_fusion = bev_channels + self.SA_clusterpoints.out_channels
        self.vsa_point_feature_fusion = nn.Sequential(
            nn.Linear(self.num_before_fusion, vsa.num_output_features, bias=False),
            nn.BatchNorm1d(vsa.num_output_features),
            nn.ReLU(),
        )

    def forward(self, bev, keypoints, xyz, feats, scan):
        """Export formulation: bev [C, H, W], keypoints [K, 3], points xyz [N, 3], feats [N, F],
        scan [N] (the points SA may group) -> (before_fusion [K, C + SA], point_features [K, out])."""
        before = torch.cat(
            [
                bev_interpolate(bev, keypoints[:, :2], self.origin, self.cell, self.stride),
                self.SA_clusterpoints(xyz, scan, feats, keypoints),
            ],
            1,
        )
        return before, self.vsa_point_feature_fusion(before)

    def reference(self, bev, keypoints, xyz, feats, scan):
        kp = keypoints.numpy()
        before = torch.cat(
            [
                torch.from_numpy(
                    bev_interpolate_reference(bev.numpy(), kp[:, :2], self.origin, self.cell, self.stride)
                ),
                self.SA_clusterpoints.reference(xyz.numpy(), scan.numpy(), feats.numpy(), kp),
            ],
            1,
        )
        return before, self.vsa_point_feature_fusion(before)


def _fc_stack(cin: int, widths, linear: bool, dropout: float | None = None) -> list[nn.Module]:
    """[Linear/Conv1d (no bias), BatchNorm1d, ReLU] per width; a Dropout after the first when given."""
    layers: list[nn.Module] = []
    for k, w in enumerate(widths):
        layers += [
            nn.Linear(cin, w, bias=False) if linear else nn.Conv1d(cin, w, 1, bias=False),
            nn.BatchNorm1d(w),
            nn.ReLU(),
        ]
        if dropout is not None and dropout >= 0 and k == 0:
            layers.append(nn.Dropout(dropout))
        cin = w
    return layers


class PointHeadSimple(nn.Module):
    """Upstream ``point_head`` (class agnostic): keypoint foreground score sigmoid(MLP(x)) [K]."""

    def __init__(self, cin: int, fc):
        super().__init__()
        self.cls_layers = nn.Sequential(*_fc_stack(cin, fc, linear=True), nn.Linear(fc[-1], 1))

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """The foreground logit [K] of each keypoint (what training's focal loss takes)."""
        return self.cls_layers(x)[:, 0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.logits(x))


# ----------------------------------------------------------------------------- ROI head


def decode_roi_residuals(reg: torch.Tensor, rois: torch.Tensor) -> torch.Tensor:
    """Refined boxes [R, 7]: ResidualCoder.decode against the roi with its centre zeroed, then the
    centre rotated by the roi heading (x' = x cos - y sin, y' = x sin + y cos) plus the roi centre."""
    xt, yt, zt, dxt, dyt, dzt, rt = reg.unbind(-1)
    dxa, dya, dza, ra = rois[:, 3], rois[:, 4], rois[:, 5], rois[:, 6]
    diag = torch.sqrt(dxa**2 + dya**2)
    x, y = xt * diag, yt * diag
    c, s = torch.cos(ra), torch.sin(ra)
    return torch.stack(
        [
            x * c - y * s + rois[:, 0],
            x * s + y * c + rois[:, 1],
            zt * dza + rois[:, 2],
            torch.exp(dxt) * dxa,
            torch.exp(dyt) * dya,
            torch.exp(dzt) * dza,
            rt + ra,
        ],
        -1,
    )


class PVRCNNHead(nn.Module):
    """Upstream ``roi_head`` (PVRCNNHead): ROI-grid pooling, shared FCs, cls and reg layers.

    The grid point g = ix * G^2 + iy * G + iz of a roi sits at local (i + 0.5) / G * size - size / 2
    (per axis, m), rotated by the roi heading about z and moved to the roi centre. Both
    formulations compute the grid in float64 and round it to float32 once: cos and sin differ in
    their last float32 bit between libraries, and a grid point one bit off can move a keypoint
    across a ball-query radius, so the grid must not depend on the runtime's trigonometry.
    Pooled features [R, G^3, C] are flattened channel-major (c * G^3 + g) as upstream's
    view/permute does.
    """

    def __init__(self, point_channels: int, cfg: RoiHeadConfig, pool: SAConfig):
        super().__init__()
        self.grid_size = cfg.grid_size
        self.roi_grid_pool_layer = SAModuleMSG(point_channels, pool.radii, pool.nsample, pool.mlps)
        pre = cfg.grid_size**3 * self.roi_grid_pool_layer.out_channels
        self.shared_fc_layer = nn.Sequential(*_fc_stack(pre, cfg.shared_fc, False, cfg.dropout))
        c = cfg.shared_fc[-1]
        self.cls_layers = nn.Sequential(*_fc_stack(c, cfg.cls_fc, False, cfg.dropout), nn.Conv1d(cfg.cls_fc[-1], 1, 1))
        self.reg_layers = nn.Sequential(*_fc_stack(c, cfg.reg_fc, False, cfg.dropout), nn.Conv1d(cfg.reg_fc[-1], 7, 1))
        g = torch.arange(cfg.grid_size, dtype=torch.float32)
        dense = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)  # [G^3, 3] (ix, iy, iz)
        self.register_buffer("dense_idx", dense, persistent=False)

    def init_upstream(self) -> None:
        """Upstream init_weights('xavier'): Xavier-normal convs, zero biases, reg output N(0, 0.001)."""
        for m in [*self.shared_fc_layer, *self.cls_layers, *self.reg_layers]:
            if isinstance(m, nn.Conv1d):
                nn.init.xavier_normal_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        nn.init.normal_(self.reg_layers[-1].weight, mean=0.0, std=0.001)

    def grid_points(self, rois: torch.Tensor) -> torch.Tensor:
        """Export formulation: grid points [R, G^3, 3] float32 of rois [R, 7] (float64 inside)."""
        r64 = rois.to(torch.float64)
        size = r64[:, None, 3:6]
        local = (self.dense_idx.to(torch.float64) + 0.5) / self.grid_size * size - size / 2  # [R, G^3, 3]
        c, s = torch.cos(r64[:, 6:7]), torch.sin(r64[:, 6:7])
        lx, ly = local[..., 0], local[..., 1]
        grid = torch.stack([lx * c - ly * s, lx * s + ly * c, local[..., 2]], -1) + r64[:, None, :3]
        return grid.to(torch.float32)

    def grid_points_reference(self, rois: np.ndarray) -> np.ndarray:
        """Reference: the grid of one roi at a time, grid point by grid point, in float64 rounded
        to float32 once."""
        n = self.grid_size
        out = np.zeros((len(rois), n**3, 3), np.float32)
        for r, roi in enumerate(np.asarray(rois, np.float64)):
            cos, sin = np.cos(roi[6]), np.sin(roi[6])
            for ix in range(n):
                for iy in range(n):
                    for iz in range(n):
                        local = [(i + 0.5) / n * roi[3 + a] - roi[3 + a] / 2 for a, i in enumerate((ix, iy, iz))]
                        out[r, ix * n * n + iy * n + iz] = [
                            local[0] * cos - local[1] * sin + roi[0],
                            local[0] * sin + local[1] * cos + roi[1],
                            local[2] + roi[2],
                        ]
        return out

    def _head(self, pooled: torch.Tensor):
        """pooled [R, C * G^3] channel-major -> (cls logit [R], residuals [R, 7])."""
        shared = self.shared_fc_layer(pooled.unsqueeze(-1))
        return self.cls_layers(shared)[:, 0, 0], self.reg_layers(shared)[:, :, 0]

    def forward(self, rois, keypoints, keypoint_valid, features):
        """Export formulation: rois [R, 7], keypoints [K, 3], keypoint_valid [K], features [K, C]
        (point_features * point_cls_scores) -> (cls logit [R], residuals [R, 7])."""
        r = rois.shape[0]
        grid = self.grid_points(rois).reshape(-1, 3)
        pooled = self.roi_grid_pool_layer(keypoints, keypoint_valid, features, grid)  # [R*G^3, C]
        return self._head(pooled.reshape(r, self.grid_size**3, -1).transpose(1, 2).reshape(r, -1))

    def reference(self, rois, keypoints, keypoint_valid, features):
        grids = self.grid_points_reference(rois.numpy())
        pooled = []
        for grid in grids:  # one roi at a time
            p = self.roi_grid_pool_layer.reference(
                keypoints.numpy(), keypoint_valid.numpy(), features.numpy(), grid
            )  # [G^3, C]
            pooled.append(p.t().reshape(-1))
        return self._head(torch.stack(pooled))


# ----------------------------------------------------------------------------- composition


STAGE_TWO_MODULES = ("pfe", "point_head", "roi_head")  # stage two's weights (upstream's module names)


def build_stage_two(
    model: nn.Module, cfg: StageTwoConfig, num_point_features: int, bev_channels: int, origin, cell
) -> None:
    """Attach stage two's modules to ``model`` under upstream's names (pfe, point_head, roi_head)
    plus our parameter-free proposal_layer and keypoint_sampler."""
    model.proposal_layer = ProposalLayer(cfg.proposals)
    model.keypoint_sampler = CDAKeypointSampler(cfg.keypoints)
    model.pfe = VoxelSetAbstractionCDA(num_point_features, bev_channels, cfg.vsa, cfg.sa_clusterpoints, origin, cell)
    model.point_head = PointHeadSimple(model.pfe.num_before_fusion, cfg.point_head_fc)
    model.roi_head = PVRCNNHead(cfg.vsa.num_output_features, cfg.roi_head, cfg.roi_grid_pool)
    model.roi_head.init_upstream()


def scan_points(points: torch.Tensor, point_cloud_range) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(xyz [N, 3], features [N, F - 3], scan [N]): rows with a non-finite value are zeroed and
    left out; scan = the points upstream's data processor keeps (mask_points_by_range: x and y
    inside the range, bounds included; z is not tested), i.e. its ``batch_dict['points']``."""
    finite = torch.isfinite(points).all(1)
    clean = torch.where(finite[:, None], points, torch.zeros_like(points))
    r = point_cloud_range
    x, y = clean[:, 0], clean[:, 1]
    scan = finite & (x >= r[0]) & (x <= r[3]) & (y >= r[1]) & (y <= r[4])
    return clean[:, :3], clean[:, 3:], scan


def proposals_and_keypoints(
    model, cls_logits, boxes, xyz, cluster, scan, reference: bool, eager_nms: bool = False
) -> dict:
    """Stage "proposals+CDA": rois, roi_labels, roi_valid, keypoints, keypoint_valid; ``eager_nms``:
    the export formulation with the training-time NMS (:meth:`ProposalLayer.eager`)."""
    if eager_nms:
        rois, labels, valid = model.proposal_layer.eager(cls_logits, boxes)
        kp, kp_valid = model.keypoint_sampler(xyz, cluster, scan, rois, valid)
    elif reference:
        rois, labels, valid = model.proposal_layer.reference(cls_logits, boxes)
        kp, kp_valid = model.keypoint_sampler.reference(
            xyz.numpy(), cluster.numpy(), scan.numpy(), rois.numpy(), valid.numpy()
        )
    else:
        rois, labels, valid = model.proposal_layer(cls_logits, boxes)
        kp, kp_valid = model.keypoint_sampler(xyz, cluster, scan, rois, valid)
    return {"rois": rois, "roi_labels": labels, "roi_valid": valid, "keypoints": kp, "keypoint_valid": kp_valid}


def keypoint_features(model, bev, s: dict, xyz, feats, scan, reference: bool):
    """Stage "VSA+point head": (point_features [K, C], point_cls_scores [K])."""
    run = model.pfe.reference if reference else model.pfe
    before, point_features = run(bev, s["keypoints"], xyz, feats, scan)
    return point_features, model.point_head(before)


def refine(model, s: dict, point_features, point_scores, reference: bool):
    """Stage "ROI head": (rcnn_scores [R] = sigmoid(logit), rcnn_boxes [R, 7])."""
    run = model.roi_head.reference if reference else model.roi_head
    cls, reg = run(s["rois"], s["keypoints"], s["keypoint_valid"], point_features * point_scores[:, None])
    return torch.sigmoid(cls), decode_roi_residuals(reg, s["rois"])


def final_nms(model, rcnn_boxes, rcnn_scores, roi_labels, roi_valid, reference: bool, eager_nms: bool = False):
    """Stage "final NMS": (boxes [M, 7], scores [M], labels [M]); padded rois score -inf, never kept."""
    cfg = model.stage_two_config.post_processing
    scores = torch.where(roi_valid, rcnn_scores, torch.full_like(rcnn_scores, -math.inf))
    if eager_nms:
        sel = class_agnostic_nms_eager(rcnn_boxes, scores, cfg)
    elif reference:
        sel = torch.from_numpy(class_agnostic_nms_reference(rcnn_boxes.numpy(), scores.numpy(), cfg))
    else:
        sel = class_agnostic_nms(rcnn_boxes, scores, cfg)
    return rcnn_boxes[sel], scores[sel], roi_labels[sel]


def run_stage_two(
    model,
    points,
    fused_bev,
    cluster,
    cls_logits,
    boxes,
    reference: bool,
    trace: dict | None = None,
    lap=None,
    eager_nms: bool = False,
) -> dict:
    """Stages 1-6 of the module docstring -> the refined detections and the stage-two outputs;
    ``fused_bev`` [C, H, W] is the fuser's output. ``lap(stage)``, if given, is called as each
    bench stage ends (see maffnet.stage_times). ``eager_nms`` (training's validation): both NMS
    with :func:`class_agnostic_nms_eager`, the rest in the export formulation."""
    lap = lap or (lambda stage: None)
    xyz, feats, scan = scan_points(points, model.vfe.config.point_cloud_range)
    cluster = cluster & scan
    s = proposals_and_keypoints(model, cls_logits, boxes, xyz, cluster, scan, reference, eager_nms)
    lap("proposals+CDA")
    point_features, point_scores = keypoint_features(model, fused_bev, s, xyz, feats, scan, reference)
    lap("VSA+point head")
    rcnn_scores, rcnn_boxes = refine(model, s, point_features, point_scores, reference)
    lap("ROI head")
    out_boxes, out_scores, out_labels = final_nms(
        model, rcnn_boxes, rcnn_scores, s["roi_labels"], s["roi_valid"], reference, eager_nms
    )
    lap("final NMS")
    if trace is not None:
        trace.update(point_features=point_features, point_cls_scores=point_scores)
    return {
        "boxes": out_boxes,
        "scores": out_scores,
        "labels": out_labels,
        **s,
        "rcnn_scores": rcnn_scores,
        "rcnn_boxes": rcnn_boxes,
    }


STAGE_TWO_OUTPUTS = ("rois", "roi_labels", "roi_valid", "keypoints", "keypoint_valid", "rcnn_scores", "rcnn_boxes")
