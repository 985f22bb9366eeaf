"""Radar ego-velocity from Doppler by RANSAC, and the static/dynamic point split (TDFANet eq. 1-3).

Model. A static point i at unit direction r_i (radar frame, x forward, y left, z up) measured
with radial velocity v_r,i (m/s, positive = moving away) satisfies

    v_r,i = r_i . (0 - v_e)   <=>   v_r,i + r_i . v_e = 0,

with v_e the radar's velocity w.r.t. the world, expressed in the radar frame (m/s). Points on
moving objects violate it and are RANSAC outliers.

Algorithm (both formulations, step for step):
1. Eligible points: finite, ``valid``, range within [min_range, max_range], |azimuth| and
   |elevation| within the FOV limits (detections at the FOV border have biased Doppler). The
   gates are evaluated as x > 0, |y| <= tan(az_max) x and |z| <= tan(el_max) sqrt(x^2 + y^2),
   exact equivalents of the angle limits for limits below 90 degrees.
2. ``num_hypotheses`` minimal samples of 3 distinct eligible points, drawn from a fixed seeded
   integer table (:func:`hypothesis_table`) by modular arithmetic, so any N works without
   data-dependent control flow and the reference sees exactly the same samples.
3. Each hypothesis: solve the 3x3 system r_k . v = -v_r,k in closed form (Cramer's rule via
   cross products); near-singular samples (|det| < ``min_det``) are discarded.
4. Inliers: eligible points with |v_r + r . v| < ``inlier_threshold``. The hypothesis with the
   most inliers wins (first one on ties).
5. Refit: least squares on the winner's inliers (normal equations, eq. 3), then the static mask
   is re-evaluated with the refitted velocity on all finite, valid points.

Defined results for bad input (never NaN, never an exception inside the graph):
- NaN/Inf coordinates or velocity: the point is masked out (``static_mask`` False) and never
  sampled.
- Fewer than 3 eligible points, no non-degenerate hypothesis, fewer than ``min_inliers``
  inliers, fewer than ``min_inlier_ratio`` of the eligible points as inliers, a singular refit,
  or an implausible speed (``|v_ego| > max_speed``, default 70 m/s = 252 km/h; scans with no
  static points or a swapped Doppler column produce such fits): ``valid`` is False, ``v_ego`` is 0,
  and ``static_mask`` keeps
  every finite, valid point (nothing can be classified, so nothing is removed).
- An all-zero-velocity scan (ego standing still, static world) is a regular case: v_ego = 0,
  every point static, ``valid`` True.

Both formulations compute in float64 (the export graph casts its inputs): with a narrow
elevation FOV the vertical velocity is poorly conditioned, and float32 normal equations would
leave ~1e-4 m/s between the two.

Default parameters follow the public radar ego-velocity estimator REVE / RIO (Doer & Trommer,
christopherdoer/reve: ``inlier_thresh: 0.15``, 3-point samples, ``outlier_prob: 0.4`` with
``success_prob: 0.9999`` giving 38 iterations, azimuth/elevation and min/max distance gates).
We draw 64 hypotheses, above REVE's 38, to cover samples lost to degeneracy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..config import Range, card_ranges, positive
from ..errors import InputError

# Table values stay below 2**24, where float32 holds every integer: OpenVINO's CPU plugin
# computes an integer Mod in float32, and with the earlier 2**30 it drew other samples than
# onnxruntime and the reference (ego velocity off by up to 0.05 m/s).
_TABLE_MAX = 2**24


@card_ranges(
    inlier_threshold=positive(100.0),
    num_hypotheses=(1, 65_536),
    min_inliers=(3, 2**24),
    min_range=(0.0, 10_000.0),
    max_range=positive(10_000.0),
    max_azimuth_deg=Range(0, 90, True, True),
    max_elevation_deg=Range(0, 90, True, True),
    min_det=(0.0, 1.0),
    seed=(0, 2**32 - 1),
    max_speed=positive(1000.0),
    min_inlier_ratio=(0.0, 1.0),
)
@dataclass(frozen=True)
class RansacConfig:
    """Model-card section ``preprocess.ransac`` (units: m/s, m, degrees)."""

    inlier_threshold: float = 0.15  # m/s, |v_r + r.v_e| below this is static (REVE 0.15)
    num_hypotheses: int = 64  # 3-point samples (REVE needs 38 at 40 % outliers)
    min_inliers: int = 5  # fewer inliers -> estimate flagged invalid
    min_range: float = 1.0  # m, REVE min_dist (near-field clutter)
    max_range: float = 400.0  # m, REVE max_dist
    max_azimuth_deg: float = 60.0  # |atan2(y, x)| limit for eligible points (< 90)
    max_elevation_deg: float = 22.5  # |elevation| limit (REVE elevation_thresh_deg)
    min_det: float = 1e-3  # |det| of a 3-point sample below this is degenerate
    seed: int = 0  # seed of the hypothesis table
    max_speed: float = 70.0  # m/s; a faster estimate is implausible -> invalid
    min_inlier_ratio: float = 0.2  # winner's inliers / eligible points below this -> invalid

    def __post_init__(self):
        if self.inlier_threshold <= 0:
            raise ValueError("inlier_threshold must be > 0 m/s")
        if self.num_hypotheses < 1:
            raise ValueError("num_hypotheses must be >= 1")
        if self.min_inliers < 3:
            raise ValueError("min_inliers must be >= 3")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError("need 0 <= min_range < max_range")
        if not (0 < self.max_azimuth_deg < 90 and 0 < self.max_elevation_deg < 90):
            raise ValueError("max_azimuth_deg and max_elevation_deg must lie in (0, 90)")


def hypothesis_table(num_hypotheses: int, seed: int) -> np.ndarray:
    """Seeded int64 table [H, 3] in [0, 2**24) from which both formulations draw samples."""
    return np.random.default_rng(seed).integers(0, _TABLE_MAX, size=(num_hypotheses, 3), dtype=np.int64)


def sample_ranks(table: np.ndarray, n: int) -> np.ndarray:
    """Ranks (among ``n`` eligible points) of the 3 distinct points of each hypothesis, [H, 3].

    r0 = t0 mod n; r1 is drawn from the n-1 others, r2 from the n-2 remaining, by skipping the
    already chosen ranks. For n < 3 the ranks are clamped into range (the estimate is invalid).
    """
    n = int(n)
    r0 = table[:, 0] % max(n, 1)
    s1 = table[:, 1] % max(n - 1, 1)
    r1 = s1 + (s1 >= r0)
    lo, hi = np.minimum(r0, r1), np.maximum(r0, r1)
    s2 = table[:, 2] % max(n - 2, 1)
    s2 = s2 + (s2 >= lo)
    r2 = s2 + (s2 >= hi)
    return np.minimum(np.stack([r0, r1, r2], axis=1), max(n - 1, 0))


def _validate_numpy(xyz, v_r):
    xyz = np.asarray(xyz)
    v_r = np.asarray(v_r)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must be [N, 3] (x, y, z in metres), got shape {xyz.shape}")
    if v_r.shape != (xyz.shape[0],):
        raise InputError(f"v_r must be [N] = [{xyz.shape[0]}] (m/s), got shape {v_r.shape}")
    return xyz, v_r


# ----------------------------------------------------------------------------- reference


def estimate_ego_velocity_reference(xyz, v_r, config: RansacConfig = RansacConfig(), valid=None):
    """Plain numpy RANSAC (float64): returns (v_ego [3] m/s, static_mask [N] bool, valid bool).

    Same algorithm and hypothesis samples as the export formulation, written as loops.
    """
    xyz, v_r = _validate_numpy(xyz, v_r)
    xyz = xyz.astype(np.float64)
    v_r = v_r.astype(np.float64)
    n = xyz.shape[0]
    usable = np.ones(n, bool) if valid is None else np.asarray(valid, bool).copy()
    usable &= np.isfinite(xyz).all(1) & np.isfinite(v_r)
    safe_xyz = np.where(usable[:, None], xyz, 0.0)
    rng = np.linalg.norm(safe_xyz, axis=1)
    dirs = safe_xyz / np.maximum(rng, 1e-9)[:, None]
    x, y, z = safe_xyz.T
    in_fov = (
        (x > 0)
        & (np.abs(y) <= np.tan(np.radians(config.max_azimuth_deg)) * x)
        & (np.abs(z) <= np.tan(np.radians(config.max_elevation_deg)) * np.sqrt(x * x + y * y))
    )
    eligible = usable & (rng >= config.min_range) & (rng <= config.max_range) & in_fov
    fallback = (np.zeros(3), usable, False)
    elig_idx = np.flatnonzero(eligible)
    if len(elig_idx) < 3:
        return fallback
    v_safe = np.where(usable, v_r, 0.0)
    ranks = sample_ranks(hypothesis_table(config.num_hypotheses, config.seed), len(elig_idx))
    best_count, best_inliers = 0, None
    for sample in elig_idx[ranks]:
        a = dirs[sample]
        if abs(np.linalg.det(a)) < config.min_det:
            continue
        v = np.linalg.solve(a, -v_safe[sample])
        inliers = eligible & (np.abs(v_safe + dirs @ v) < config.inlier_threshold)
        count = int(inliers.sum())
        if count > best_count:
            best_count, best_inliers = count, inliers
    if best_inliers is None or best_count < config.min_inliers:
        return fallback
    if best_count < config.min_inlier_ratio * len(elig_idx):
        return fallback
    p = dirs[best_inliers]
    normal = p.T @ p
    if abs(np.linalg.det(normal)) < config.min_det:
        return fallback
    v_ego = np.linalg.solve(normal, -p.T @ v_safe[best_inliers])
    if np.linalg.norm(v_ego) > config.max_speed:
        return fallback
    static = usable & (np.abs(v_safe + dirs @ v_ego) < config.inlier_threshold)
    return v_ego, static, True


# ----------------------------------------------------------------------------- export


def _solve3(rows: torch.Tensor, rhs: torch.Tensor):
    """Closed-form solve of rows @ v = rhs for a batch of 3x3 systems.

    rows [..., 3, 3] (row vectors a0, a1, a2), rhs [..., 3]. Returns (v [..., 3], det [...]).
    With c0 = a1 x a2, c1 = a2 x a0, c2 = a0 x a1 and det = a0 . c0, the inverse's columns are
    c_k / det, so v = (rhs0 c0 + rhs1 c1 + rhs2 c2) / det. Singular systems return v = 0.
    """
    a0, a1, a2 = rows[..., 0, :], rows[..., 1, :], rows[..., 2, :]
    c0 = torch.linalg.cross(a1, a2, dim=-1)
    c1 = torch.linalg.cross(a2, a0, dim=-1)
    c2 = torch.linalg.cross(a0, a1, dim=-1)
    det = (a0 * c0).sum(-1)
    num = rhs[..., 0:1] * c0 + rhs[..., 1:2] * c1 + rhs[..., 2:3] * c2
    safe = torch.where(det.abs() > 0, det, torch.ones_like(det))
    return torch.where(det.abs().unsqueeze(-1) > 0, num / safe.unsqueeze(-1), torch.zeros_like(num)), det


class EgoVelocityRansac(nn.Module):
    """Export formulation: fixed-shape RANSAC for any N (dynamic axis).

    forward(xyz [N, 3] m, v_r [N] m/s, valid [N] bool) -> (v_ego [3] m/s, static_mask [N] bool,
    valid_estimate [] bool). :meth:`estimate_frames` runs K scans at once, concatenated. See the module
    docstring for the algorithm and the defined results for degenerate input.
    """

    def __init__(self, config: RansacConfig = RansacConfig()):
        super().__init__()
        self.config = config
        self.register_buffer(
            "table", torch.from_numpy(hypothesis_table(config.num_hypotheses, config.seed)), persistent=False
        )

    def _ranks(self, n: torch.Tensor) -> torch.Tensor:
        """Tensor version of :func:`sample_ranks` for each scan's count ``n`` [K] (int64) -> [K, H, 3]."""
        n = n.unsqueeze(1)  # [K, 1]
        one = torch.ones_like(n)
        t = self.table
        r0 = torch.remainder(t[:, 0], torch.maximum(n, one))
        s1 = torch.remainder(t[:, 1], torch.maximum(n - 1, one))
        r1 = s1 + (s1 >= r0).long()
        lo, hi = torch.minimum(r0, r1), torch.maximum(r0, r1)
        s2 = torch.remainder(t[:, 2], torch.maximum(n - 2, one))
        s2 = s2 + (s2 >= lo).long()
        r2 = s2 + (s2 >= hi).long()
        return torch.minimum(torch.stack([r0, r1, r2], 2), torch.clamp(n - 1, min=0).unsqueeze(2))

    def forward(self, xyz: torch.Tensor, v_r: torch.Tensor, valid: torch.Tensor):
        frame = torch.zeros(xyz.shape[0], dtype=torch.int64, device=xyz.device)
        v_ego, static, ok = self.estimate_frames(xyz, v_r, valid, frame, 1)
        return v_ego[0], static, ok[0]

    def estimate_frames(
        self, xyz: torch.Tensor, v_r: torch.Tensor, valid: torch.Tensor, frame: torch.Tensor, count: int
    ):
        """``count`` scans concatenated along N: xyz [N, 3] m, v_r [N] m/s, valid [N] bool, and
        ``frame`` [N] int64, the scan (0 .. count-1) each point belongs to
        (:func:`radaredge.ops.scan_batch.concat_scans`).
        Returns (v_ego [count, 3] m/s, static_mask [N] bool, valid_estimate [count] bool), each
        scan's result exactly as if it ran alone: samples, inliers and refit see only its points.
        An exported graph then holds one RANSAC for all scans instead of one per scan."""
        cfg = self.config
        n_in = xyz.shape[0]
        out_dtype = xyz.dtype
        dev = xyz.device
        # Three padding points keep every reduction non-empty for N = 0; they are never eligible.
        xyz = torch.cat([xyz.double(), torch.zeros(3, 3, dtype=torch.float64, device=dev)], 0)
        v_r = torch.cat([v_r.double(), torch.zeros(3, dtype=torch.float64, device=dev)], 0)
        usable = torch.cat([valid, torch.zeros(3, dtype=torch.bool, device=dev)], 0)
        usable = usable & torch.isfinite(xyz).all(1) & torch.isfinite(v_r)
        xyz = torch.where(usable.unsqueeze(1), xyz, torch.zeros_like(xyz))
        v_r = torch.where(usable, v_r, torch.zeros_like(v_r))

        rng = torch.linalg.vector_norm(xyz, dim=1)
        dirs = xyz / torch.clamp(rng, min=1e-9).unsqueeze(1)
        x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        in_fov = (
            (x > 0)
            & (y.abs() <= math.tan(math.radians(cfg.max_azimuth_deg)) * x)
            & (z.abs() <= math.tan(math.radians(cfg.max_elevation_deg)) * torch.sqrt(x * x + y * y))
        )
        eligible = usable & (rng >= cfg.min_range) & (rng <= cfg.max_range) & in_fov
        frame = torch.cat([frame, torch.zeros(3, dtype=torch.int64, device=dev)], 0)
        member = frame.unsqueeze(0) == torch.arange(count, dtype=torch.int64, device=dev).unsqueeze(1)  # [K, N]
        own_eligible = eligible.unsqueeze(0) & member  # [K, N]

        # Indices of eligible points in input order, without a sort (TensorRT's TopK stops at
        # K = 3839): each eligible point's rank among them (a float32 CumSum, exact below 2**24
        # points) is where its index is written; the rest write to a spare slot. Scan k's
        # eligible points (scans are concatenated in order) start at the number of eligible
        # points of the scans before it.
        n = xyz.shape[0]
        pos = torch.arange(n, dtype=torch.int64, device=dev)
        rank = (torch.cumsum(eligible.to(torch.float32), 0) - 1.0).to(torch.int64)
        slot = torch.where(eligible, rank, torch.full_like(rank, n))
        order = torch.zeros(n + 1, dtype=torch.int64, device=dev).scatter(0, slot, pos)[:n]
        n_elig = own_eligible.long().sum(1)  # [K]
        counts = n_elig.to(torch.float32)
        first = (torch.cumsum(counts, 0) - counts).to(torch.int64)  # [K]
        sample = order[first.view(-1, 1, 1) + self._ranks(n_elig)]  # [K, H, 3]

        rows = dirs[sample]  # [K, H, 3, 3]
        v_hyp, det = _solve3(rows, -v_r[sample])  # [K, H, 3], [K, H]
        resid = (v_r + v_hyp @ dirs.T).abs()  # [K, H, N]
        inl = (resid < cfg.inlier_threshold) & own_eligible.unsqueeze(1)
        counts = torch.where(det.abs() >= cfg.min_det, inl.long().sum(2), torch.full_like(det, -1, dtype=torch.int64))
        best = torch.argmax(counts, 1, keepdim=True)  # [K, 1], first on ties
        best_count = counts.gather(1, best).squeeze(1)
        w = inl.gather(1, best.unsqueeze(2).expand(-1, -1, n)).squeeze(1).to(xyz.dtype)  # [K, N]

        normal = (dirs.unsqueeze(0) * w.unsqueeze(2)).transpose(1, 2) @ dirs  # [K, 3, 3]
        rhs = -(dirs.unsqueeze(0) * (w * v_r).unsqueeze(2)).sum(1)  # [K, 3]
        v_ego, det_n = _solve3(normal, rhs)
        ok = (
            (n_elig >= 3)
            & (best_count >= cfg.min_inliers)
            & (det_n.abs() >= cfg.min_det)
            & (best_count.double() >= cfg.min_inlier_ratio * n_elig.double())
            & (torch.linalg.vector_norm(v_ego, dim=1) <= cfg.max_speed)
        )
        v_ego = torch.where(ok.unsqueeze(1), v_ego, torch.zeros_like(v_ego))
        static = usable & (~ok[frame] | ((v_r + (dirs * v_ego[frame]).sum(1)).abs() < cfg.inlier_threshold))
        return v_ego.to(out_dtype), static[:n_in], ok


def estimate_ego_velocity(xyz, v_r, config: RansacConfig = RansacConfig(), valid=None):
    """Ego velocity (m/s, radar frame) and static-point mask with the export formulation.

    Accepts torch tensors or numpy arrays; returns the same kind: (v_ego [3], static_mask [N],
    valid). Shape errors raise :class:`radaredge.errors.InputError`.
    """
    as_numpy = not isinstance(xyz, torch.Tensor)
    if as_numpy:
        xyz, v_r = _validate_numpy(xyz, v_r)
        xyz = torch.from_numpy(np.ascontiguousarray(xyz, np.float32))
        v_r = torch.from_numpy(np.ascontiguousarray(v_r, np.float32))
    elif xyz.ndim != 2 or xyz.shape[1] != 3 or v_r.shape != (xyz.shape[0],):
        raise InputError(f"xyz must be [N, 3] and v_r [N]; got {tuple(xyz.shape)} and {tuple(v_r.shape)}")
    if valid is None:
        valid = torch.ones(xyz.shape[0], dtype=torch.bool)
    elif not isinstance(valid, torch.Tensor):
        valid = torch.from_numpy(np.asarray(valid, bool))
    with torch.no_grad():
        v_ego, static, ok = EgoVelocityRansac(config)(xyz.double(), v_r.double(), valid)
    if as_numpy:
        return v_ego.numpy(), static.numpy(), bool(ok)
    return v_ego, static, ok
