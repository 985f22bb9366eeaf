"""sklearn DBSCAN and MAFF-Net's CQCA_cfa clustering map, built from fixed-shape tensor ops.

What it computes, as TRV-Lab/MAFF-Net's ``CQCA_cfa.generate_map``
(pcdet/models/backbones_image/CQCA_cfa.py) does for one scan, with points_xyv [N, 3] float32 =
(x forward in m, y left in m, velocity in m/s -- VoD's ego-compensated ``v_r_comp``, upstream's
DBSCAN_V column):

1. ``labels``: ``sklearn.cluster.DBSCAN(eps, min_samples).fit_predict(points_xyv)`` on all three
   columns, so metres and m/s are mixed in one Euclidean distance (upstream's choice; ``eps`` is
   in those mixed units). The neighbourhood of i is every j with ||p_i - p_j|| <= eps, i itself
   included; i is a *core* point when its neighbourhood holds >= ``min_samples`` points.
   sklearn numbers the clusters in order of discovery: it scans i in index order and starts a
   new cluster at each still unlabelled core point, so the cluster id is the rank of a
   core-connected component by its smallest core index (0, 1, 2, ...). A border point
   (non-core, within eps of a core point) takes the first cluster that reaches it, i.e. the
   smallest cluster id among its core neighbours; every other point is noise, -1.
2. ``density[i]``: the number of points carrying i's label (border points included), 0 for noise.
3. Points of clusters with more than ``max_cluster_size`` (100) points become noise (-1);
   ``density`` keeps its value. The non-noise points are upstream's ``cluster_points``.
4. ``map`` [3, rows, cols] float32, zeros, then for each point with label > 0 in index order the
   channels (v, density, float(label)) are written to cell
   ``row = int((y + y_offset) / resolution) - 1, col = int(x / resolution) - 1`` (float32
   arithmetic, ``int`` truncating toward zero as torch ``.long()`` does); the last point
   written to a cell wins. VoD: eps 0.4, min_samples 10, 320 x 320 cells of 0.16 m,
   y_offset 25.6. TJ4D: eps 2, min_samples 4, y_offset 39.68 and upstream's
   ``zeros((DBSCAN_MAP_W, DBSCAN_MAP_H, 3))`` indexed ``[bev_y, bev_x]``, i.e. 496 rows (y)
   by 432 columns (x); ``map_rows`` / ``map_cols`` name the two sizes explicitly.

Upstream quirks reproduced on purpose (weights were trained with them):
- cluster 0 is left out of the map (upstream keeps ``labels > 0``), though its points stay in
  ``cluster_points``;
- the -1 in both cell indices shifts the map by one cell, so a point in the first 0.16 m
  (x in [0, 0.16), or y + y_offset in [0, 0.16)) gets index -1, which wraps to the last
  column / row as torch's negative indexing does;
- ``density`` of a relabelled (> 100 points) cluster is kept, it just is never written.

Deliberate differences, for a defined edge-deployment contract:
- a cell index outside [0, size) other than -1 is not written. Upstream's torch indexing would
  wrap -2 .. -size too and raise IndexError beyond; such points lie outside the point-cloud
  range that the datasets crop to, where only -1 (the first 0.16 m) can occur;
- points with ``valid`` False or a NaN/Inf coordinate are dropped: never anybody's neighbour,
  label -1, False in ``cluster_points``, not counted. That is upstream run on the remaining
  points (sklearn refuses non-finite input).

Distances are computed in float64 from the float32 inputs as sklearn's KD-tree (the algorithm
DBSCAN picks for N >= 12) does: per-coordinate differences, ``dx*dx + dy*dy + dz*dz``, compared
``<= eps * eps``. A pair at *exactly* eps is a neighbour, as in sklearn; pairs within rounding of
eps may still be decided differently by sklearn's tree bounds or, for N < 12, by its brute-force
``|a|^2 - 2ab + |b|^2`` distances, so tests keep clear of such ties.

Connected components of the core graph (core points, edges between core points within eps) use
the hook-and-contract rounds of :mod:`radaredge.ops.components`, with the neighbour roots taken
from the dense [M, M] adjacency (masked max / min over each row) instead of a 3 x 3 max-pool.
Every round starts with all trees being stars and (1) gathers per root r the largest and
smallest root adjacent to its star (``up``, ``down``), (2) hooks a root with ``up[r] > r`` onto
``up[r]`` (conditional), (3) hooks a root that neither hooked nor was hooked onto onto a smaller
adjacent root ``down[r]`` (stagnant), (4) makes every tree a star again by pointer jumping.
Proof sketch, n = ``capacity``: conditional hooks raise the root id and a stagnant hook targets
a root that hooked conditionally, so no cycle forms; in a component with s >= 2 stars every star
has an adjacent star and hooks or is hooked onto, so each new tree holds >= 2 stars and
s_{k+1} <= floor(s_k / 2) <= floor(n / 2^{k+1}); after R = floor(log2 n) rounds every component
is one star. A new tree in round k is at most floor(n / 2^k) parent steps deep, and a jump
halves depth, so J_k = max(1, ceil(log2 floor(n / 2^k))) jumps flatten it
(:func:`radaredge.ops.components.exact_schedule` with H x W = n x 1). Capacity 2048: 11 rounds,
66 jumps, independent of the data and of N. Ids are then made canonical: the component id is
its smallest core index (scatter-min onto the roots), the cluster number its rank among the
components (cumulative sum of "i is its component's smallest index"), and a border point takes
the smallest cluster number among its core neighbours (masked min over its row).

Capacity contract: the graph takes any N (a dynamic ONNX axis) and works on the first
M = min(N, capacity) points as they come, so memory is O(M^2) (M = 2048: about 32 MB per float64
[M, M] tensor). Points beyond ``capacity`` are not clustered: label -1, not counted, not written.
``converged`` is False exactly when such a point was valid and finite (it would have joined
upstream's clustering) or when the components did not settle (impossible with the proven round
count; it is computed honestly for the ``rounds`` override). ``converged`` False means the
labels, ``cluster_points`` and map are not upstream's.

Export (opset 18, dynamic N): Sub/Mul/Add/LessOrEqual in float64 for the distances; per round
two float32 Mul + ReduceMax over [M, M] for the neighbour roots, ScatterElements (max / min)
onto the roots and GatherElements for the jumps; ReduceMin, CumSum, ScatterElements (add, max),
Gather, Where, Slice and Concat around them. The Python loops have constant trip counts and
unroll, so the node count grows with log2(capacity) only; the run time grows with M^2 (the
Speed section of docs/models/maffnet.md compares it with GridDensityBEV). Beside each export op lives its
plain numpy reference (:func:`dbscan_labels_reference`, :func:`cqca_cfa_map_reference`), and
:func:`cqca_cfa_map_sklearn` runs upstream's own steps (sklearn, a per-point Python loop), the
baseline that ``benchmarks/cfa_speedup.py`` times.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from ..config import card_ranges, positive
from ..errors import InputError
from .components import exact_schedule, hook_roots
from .grid_density import MAX_MAP_CELLS


@card_ranges(
    eps=positive(100.0),
    min_samples=(1, 100_000),
    max_cluster_size=(0, 2**24),
    capacity=(1, 2**24 - 1),
    map_rows=(1, 8192),
    map_cols=(1, 8192),
    resolution=positive(100.0),
    y_offset=(-1000.0, 1000.0),
)
@dataclass(frozen=True)
class DbscanConfig:
    """CQCA_cfa's DBSCAN and map settings (mixed m and m/s for eps, metres, cells); VoD by default."""

    eps: float = 0.4  # DBSCAN radius over (x m, y m, v m/s) (DBSCAN_EPS)
    min_samples: int = 10  # neighbourhood size of a core point, itself included (DBSCAN_SAMPLE)
    max_cluster_size: int = 100  # larger clusters become noise (upstream's hard-coded 100)
    capacity: int = 2048  # points clustered per scan; the rest are dropped (see docstring)
    map_rows: int = 320  # y cells, first map dim (upstream's DBSCAN_MAP_W)
    map_cols: int = 320  # x cells, second map dim (upstream's DBSCAN_MAP_H)
    resolution: float = 0.16  # m per cell (RESOLUTION)
    y_offset: float = 25.6  # m added to y before binning (DBSCAN_Y)

    def __post_init__(self):
        if not (self.eps > 0 and np.isfinite(self.eps)):
            raise ValueError(f"eps must be a finite number > 0, got {self.eps}")
        if self.min_samples < 1:
            raise ValueError(f"min_samples must be >= 1, got {self.min_samples}")
        if self.max_cluster_size < 0:
            raise ValueError(f"max_cluster_size must be >= 0, got {self.max_cluster_size}")
        if not 1 <= self.capacity < 2**24:
            raise ValueError(f"capacity must be in [1, 2^24), got {self.capacity}")
        if self.map_rows < 1 or self.map_cols < 1 or self.map_rows * self.map_cols > MAX_MAP_CELLS:
            raise ValueError(
                f"map_rows and map_cols must be >= 1 with at most {MAX_MAP_CELLS} cells (the CFA "
                f"convolves the map at 64 channels: 256 MiB), got {self.map_rows} x {self.map_cols}"
            )
        if not (self.resolution > 0 and np.isfinite(self.resolution)):
            raise ValueError(f"resolution must be a finite number > 0, got {self.resolution}")
        if not np.isfinite(self.y_offset):
            raise ValueError(f"y_offset must be finite, got {self.y_offset}")


VOD = DbscanConfig()
TJ4D = DbscanConfig(eps=2.0, min_samples=4, map_rows=496, map_cols=432, resolution=0.16, y_offset=39.68)


def dbscan_rounds(capacity: int) -> list[int]:
    """Pointer jumps per hooking round that suffice for ``capacity`` points (one entry per round)."""
    return exact_schedule(capacity, 1)


def _check_inputs(xyv: torch.Tensor, valid: torch.Tensor, what: str) -> None:
    if xyv.dtype != torch.float32 or xyv.dim() != 2 or xyv.shape[1] != 3:
        raise InputError(
            f"{what}: points_xyv must be a [N, 3] float32 tensor (x m, y m, v m/s), "
            f"got {xyv.dtype} of shape {tuple(xyv.shape)}"
        )
    if valid.dtype != torch.bool or valid.dim() != 1 or valid.shape[0] != xyv.shape[0]:
        raise InputError(
            f"{what}: valid must be a [N] bool tensor (N = {xyv.shape[0]} points), got "
            f"{valid.dtype} of shape {tuple(valid.shape)}"
        )


# ----------------------------------------------------------------------------- export: DBSCAN


def dbscan_labels(xyv: torch.Tensor, valid: torch.Tensor, cfg: DbscanConfig, rounds: int | None = None):
    """sklearn's ``DBSCAN(eps, min_samples).fit_predict`` on the valid, finite points.

    ``xyv`` [N, 3] float32, ``valid`` [N] bool. Returns ``(labels [N] int64, core [N] bool,
    converged [] bool)``: labels numbered as sklearn numbers them, -1 for noise, invalid points
    and points beyond ``cfg.capacity``; ``core`` marks sklearn's core samples. ``rounds``
    overrides the proven number of hooking rounds (tests only).
    """
    _check_inputs(xyv, valid, "dbscan_labels")
    n = xyv.shape[0]
    cap = cfg.capacity
    head = xyv[:cap]
    # One always-invalid sentinel point keeps every row reduction non-empty (N = 0 included).
    pts = torch.cat([head, head.new_zeros(1, 3)])
    ok = torch.cat([valid[:cap], valid.new_zeros(1)]) & torch.isfinite(pts).all(1)
    m = pts.shape[0]  # min(N, capacity) + 1
    idx = torch.arange(m, device=xyv.device)

    p = torch.where(ok.unsqueeze(1), pts, 0.0).to(torch.float64)
    dx, dy, dz = (p[:, k].unsqueeze(1) - p[:, k].unsqueeze(0) for k in range(3))  # [M, M] float64, exact
    d2 = dx * dx + dy * dy + dz * dz  # sklearn's rdist order: ((dx^2 + dy^2) + dz^2)
    near = (d2 <= float(cfg.eps) * float(cfg.eps)) & ok.unsqueeze(1) & ok.unsqueeze(0)
    core = ok & (near.to(torch.float32).sum(1) >= cfg.min_samples)  # counts exact in float32
    adj = near & core.unsqueeze(1) & core.unsqueeze(0)  # core graph, self loops on core points
    adj = adj.to(torch.float32)  # a 0/1 mask for the row maxima below

    schedule = exact_schedule(cap, 1, rounds)  # proven rounds unless overridden
    parent = idx
    for jumps in schedule:
        parent = _hook(parent, adj, core, idx, m)
        for _ in range(jumps):
            parent = parent.gather(0, parent)

    nb_max, nb_min = _neighbour_roots(parent, adj, m)
    star = parent.gather(0, parent) == parent
    settled = ~core | ((nb_max == parent) & (nb_min == parent))
    beyond = valid[cap:] & torch.isfinite(xyv[cap:]).all(1)
    converged = (star & settled).all() & (beyond.to(torch.int64).sum() == 0)  # sum: empty-safe in ORT

    # canonical numbering: component id = smallest core index, cluster = rank of that index
    low = idx.scatter_reduce(0, parent, idx, reduce="amin", include_self=True).gather(0, parent)
    first = core & (low == idx)
    # a float32 CumSum (TensorRT refuses integer ones): exact up to 2**24 points, where capacity stops
    rank = (torch.cumsum(first.to(torch.float32), 0) - 1.0).to(torch.int64)
    cluster = torch.where(core, rank.gather(0, low), m)
    reach = near & core.unsqueeze(0)  # j is a core point within eps of i
    border = torch.where(reach, cluster.unsqueeze(0), m).amin(1)
    labels = torch.where(border < m, border, -1)[: m - 1]
    core = core[: m - 1]
    tail = n - (m - 1)  # points beyond capacity
    labels = torch.cat([labels, labels.new_full((tail,), -1)])
    core = torch.cat([core, core.new_zeros(tail)])
    return labels, core, converged


def _hook(parent, adj, core, idx, m):
    """One hooking step on the core graph (:func:`radaredge.ops.components.hook_roots`); the
    neighbour roots are row extrema over the dense adjacency. Non-core points are their own
    isolated roots."""
    return hook_roots(parent, core, idx, *_neighbour_roots(parent, adj, m), dim=0)


def _neighbour_roots(parent, adj, m):
    """Largest and smallest ``parent`` over each row of the 0/1 core adjacency (-1 / m on empty rows).

    Both are row maxima of ``adj * weight`` with a positive weight per column, ``parent + 1`` and
    ``m - parent``, in float32 (exact: ids < 2^24). A product and a max vectorise far better in
    onnxruntime than a broadcast int64 Where (1000 points: about 4x faster).
    """
    up = (adj * (parent + 1).to(torch.float32).unsqueeze(0)).amax(1)
    down = (adj * (m - parent).to(torch.float32).unsqueeze(0)).amax(1)
    return up.to(torch.int64) - 1, m - down.to(torch.int64)


# ----------------------------------------------------------------------------- export: map


def cqca_cfa_map(xyv: torch.Tensor, valid: torch.Tensor, cfg: DbscanConfig):
    """CQCA_cfa's clustering map for one scan (see the module docstring).

    ``xyv`` [N, 3] float32 (x m, y m, v m/s), ``valid`` [N] bool. Returns ``(map [3, rows, cols]
    float32 with channels (v, cluster size, label), cluster_points [N] bool, converged [] bool)``.
    """
    _check_inputs(xyv, valid, "cqca_cfa_map")
    labels, _, converged = dbscan_labels(xyv, valid, cfg)
    n = xyv.shape[0]
    rows, cols, cap = cfg.map_rows, cfg.map_cols, cfg.capacity

    clustered = labels >= 0
    slot = torch.where(clustered, labels, cap)  # labels < capacity; slot cap collects noise
    counts = torch.zeros(cap + 1, device=xyv.device).scatter_add(0, slot, torch.ones(n, device=xyv.device))
    density = torch.where(clustered, counts.gather(0, slot), 0.0)
    labels = torch.where(density > cfg.max_cluster_size, -1, labels)
    cluster_points = labels != -1

    finite = torch.isfinite(xyv).all(1, keepdim=True)
    pts = torch.where(finite, xyv, 0.0)
    col = _cell_index(pts[:, 0] / cfg.resolution, cols)
    row = _cell_index((pts[:, 1] + cfg.y_offset) / cfg.resolution, rows)
    write = (labels > 0) & (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    cell = torch.where(write, row * cols + col, rows * cols)  # rows*cols = not written
    winner = torch.full((rows * cols + 1,), -1, dtype=torch.int64, device=xyv.device).scatter_reduce(
        0, cell, torch.arange(n, device=xyv.device), reduce="amax", include_self=True
    )[: rows * cols]
    values = torch.stack([pts[:, 2], density, labels.to(torch.float32)], 1)
    values = torch.cat([values, values.new_zeros(1, 3)])  # row n: an empty cell
    bev = values.index_select(0, torch.where(winner >= 0, winner, n))  # [rows * cols, 3]
    return bev.t().reshape(3, rows, cols), cluster_points, converged


def _cell_index(q: torch.Tensor, size: int) -> torch.Tensor:
    """Upstream's ``q.long() - 1`` with -1 wrapped to size - 1; other out-of-map values stay out.

    ``q`` is clamped to [-4, size + 4] first (it cannot change an in-map index) so that huge
    coordinates cast to int64 safely.
    """
    index = q.clamp(-4.0, size + 4.0).to(torch.int64) - 1
    return torch.where(index == -1, size - 1, index)


# ----------------------------------------------------------------------------- reference


def dbscan_labels_reference(xyv, valid, cfg: DbscanConfig):
    """Reference formulation of :func:`dbscan_labels`: numpy neighbourhoods and a Python search.

    Clusters are grown breadth-first from each unlabelled core point in index order, expanding
    core points only, as sklearn's ``dbscan_inner`` does. Returns numpy
    ``(labels [N] int64, core [N] bool, converged bool)``.
    """
    points = np.asarray(xyv, np.float32).reshape(-1, 3)
    n = len(points)
    ok = np.asarray(valid, bool).reshape(-1) & np.isfinite(points).all(1)
    converged = not ok[cfg.capacity :].any()
    ok[cfg.capacity :] = False
    p = points.astype(np.float64)
    e2 = float(cfg.eps) * float(cfg.eps)
    hood: list[np.ndarray] = []
    for i in range(n):
        if not ok[i]:
            hood.append(np.zeros(0, np.int64))
            continue
        d = p - p[i]
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        hood.append(np.flatnonzero(ok & (d2 <= e2)))
    core = np.array([ok[i] and len(hood[i]) >= cfg.min_samples for i in range(n)], bool)
    labels = np.full(n, -1, np.int64)
    number = 0
    for start in range(n):
        if labels[start] != -1 or not core[start]:
            continue
        labels[start] = number
        queue = deque([start])
        while queue:
            i = queue.popleft()
            if not core[i]:
                continue
            for j in hood[i]:
                if labels[j] == -1:
                    labels[j] = number
                    queue.append(j)
        number += 1
    return labels, core, converged


def cqca_cfa_map_reference(xyv, valid, cfg: DbscanConfig):
    """Reference formulation of :func:`cqca_cfa_map`: an explicit loop over the points.

    Returns numpy ``(map [3, rows, cols] float32, cluster_points [N] bool, converged bool)``.
    """
    points = np.asarray(xyv, np.float32).reshape(-1, 3)
    labels, _, converged = dbscan_labels_reference(points, valid, cfg)
    sizes: dict[int, int] = {}
    for label in labels:
        if label >= 0:
            sizes[int(label)] = sizes.get(int(label), 0) + 1
    density = np.array([sizes[int(lab)] if lab >= 0 else 0 for lab in labels], np.float32)
    labels = np.where(density > cfg.max_cluster_size, -1, labels)
    bev = np.zeros((3, cfg.map_rows, cfg.map_cols), np.float32)
    res, off = np.float32(cfg.resolution), np.float32(cfg.y_offset)
    for i, (x, y, v) in enumerate(points):
        if labels[i] <= 0:
            continue
        col = int(x / res) - 1  # float32 arithmetic, truncation toward zero
        row = int((y + off) / res) - 1
        col = cfg.map_cols - 1 if col == -1 else col
        row = cfg.map_rows - 1 if row == -1 else row
        if 0 <= row < cfg.map_rows and 0 <= col < cfg.map_cols:
            bev[:, row, col] = (v, density[i], np.float32(labels[i]))
    return bev, labels != -1, converged


# ----------------------------------------------------------------------------- upstream, for timing


def cqca_cfa_map_sklearn(xyv, cfg: DbscanConfig = VOD, vectorised: bool = False):
    """Upstream CQCA_cfa.generate_map as upstream runs it: the baseline ``benchmarks/cfa_speedup.py``
    times against GridDensityBEV. Needs scikit-learn (the ``dev`` extra).

    ``xyv`` [N, 3] (x m, y m, v m/s), all points used (sklearn refuses non-finite values);
    ``cfg.capacity`` does not apply. The steps of the module docstring in upstream's own form:
    sklearn ``DBSCAN(eps, min_samples)`` on the three columns, then each point's cluster size
    counted by one ``torch.where`` over all labels per point (upstream's O(N^2) Python loop;
    ``vectorised`` counts with ``np.unique`` instead, DBSCAN's best case), then one torch index
    write of the points with label > 0 into the map (of several points in one cell, CPU torch
    keeps the last, as the module docstring's contract says). Returns torch ``(map [3, rows,
    cols] float32 with channels (v, cluster size, label), labels [N] int64 after the size cut)``.
    """
    # optional: scikit-learn (dev extra) is the reference DBSCAN of tests, never on the export path
    from sklearn.cluster import DBSCAN

    xyv = torch.as_tensor(np.asarray(xyv, np.float32).reshape(-1, 3))
    labels = torch.as_tensor(
        DBSCAN(eps=cfg.eps, min_samples=cfg.min_samples).fit_predict(xyv.numpy()), dtype=torch.int64
    )
    if vectorised:
        _, inverse, counts = np.unique(labels.numpy(), return_inverse=True, return_counts=True)
        density = torch.as_tensor(np.where(labels.numpy() >= 0, counts[inverse], 0), dtype=torch.float32)
    else:
        density = torch.zeros(len(labels), dtype=torch.float32)
        for i, label in enumerate(labels):
            if label != -1:
                density[i] = len(torch.where(labels == label)[0])
    labels = torch.where((density > cfg.max_cluster_size) & (labels != -1), -1, labels)
    keep = labels > 0
    col = (xyv[keep, 0] / cfg.resolution).long() - 1
    row = ((xyv[keep, 1] + cfg.y_offset) / cfg.resolution).long() - 1
    col = torch.where(col == -1, cfg.map_cols - 1, col)
    row = torch.where(row == -1, cfg.map_rows - 1, row)
    values = torch.stack([xyv[keep, 2], density[keep], labels[keep].float()], 1)
    inside = (col >= 0) & (col < cfg.map_cols) & (row >= 0) & (row < cfg.map_rows)
    bev = torch.zeros(cfg.map_rows, cfg.map_cols, 3)
    bev[row[inside], col[inside]] = values[inside]
    return bev.permute(2, 0, 1).contiguous(), labels
