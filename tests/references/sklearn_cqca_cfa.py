"""MAFF-Net's CQCA_cfa.generate_map for one scan, with sklearn's DBSCAN and a per-point loop.

Written from TRV-Lab/MAFF-Net pcdet/models/backbones_image/CQCA_cfa.py (``generate_map``),
independently of radaredge (it imports nothing from it), to check
``radaredge.ops.dbscan`` against. What upstream does, step by step:

1. ``sklearn.cluster.DBSCAN(eps, min_samples).fit_predict`` on the float32 (x, y, v) tensor.
2. Per point, the number of points that carry its label (0 for noise), in float32.
3. Points whose cluster has more than 100 points are relabelled -1; their density stays.
4. The points with label > 0 (cluster 0 is left out) write (v, density, label) into a
   zeros((DBSCAN_MAP_W, DBSCAN_MAP_H, 3)) map at [bev_y, bev_x] with
   bev_x = (x / RESOLUTION).long() - 1 and bev_y = ((y + DBSCAN_Y) / RESOLUTION).long() - 1,
   in float32 torch arithmetic; the map is returned channels first. With duplicate cells the
   last point in index order holds the cell.

Two things upstream leaves undefined get the contract radaredge documents: points with a
NaN/Inf value or ``valid`` False are removed before DBSCAN (sklearn rejects non-finite input)
and get label -1; of the cell indices outside the map only -1 is written, to the last row /
column as Python indexing wraps it, and any other out-of-map index is skipped (upstream's torch
indexing would wrap -2 .. -size as well and raise beyond). ``rows`` is upstream's first map
dimension (DBSCAN_MAP_W, the y cells) and ``cols`` the second (DBSCAN_MAP_H, the x cells).
"""

from __future__ import annotations

import numpy as np
import torch
from sklearn.cluster import DBSCAN


def upstream_dbscan(points_xyv, valid=None, eps: float = 0.4, min_samples: int = 10):
    """sklearn DBSCAN on the usable points: (labels [N] int64, core [N] bool) for all N points."""
    points = np.asarray(points_xyv, np.float32).reshape(-1, 3)
    usable = np.isfinite(points).all(1)
    if valid is not None:
        usable &= np.asarray(valid, bool)
    labels = np.full(len(points), -1, np.int64)
    core = np.zeros(len(points), bool)
    if usable.any():
        where = np.flatnonzero(usable)
        model = DBSCAN(eps=eps, min_samples=min_samples).fit(torch.from_numpy(points[usable]))
        labels[where] = model.labels_
        core[where[model.core_sample_indices_]] = True
    return labels, core


def upstream_map(
    points_xyv,
    valid=None,
    eps: float = 0.4,
    min_samples: int = 10,
    rows: int = 320,
    cols: int = 320,
    resolution: float = 0.16,
    y_offset: float = 25.6,
    max_cluster_size: int = 100,
):
    """The clustering map as upstream builds it: (map [3, rows, cols] float32, labels [N] int64).

    ``labels`` are the final ones (clusters above ``max_cluster_size`` are -1); upstream's
    ``cluster_points`` are the points with label != -1.
    """
    xyv = torch.as_tensor(np.asarray(points_xyv, np.float32).reshape(-1, 3))
    labels, _ = upstream_dbscan(xyv.numpy(), valid, eps, min_samples)
    labels = torch.from_numpy(labels)

    density = torch.zeros(len(labels), dtype=torch.float32)
    for i in range(len(labels)):
        if labels[i] != -1:
            density[i] = int((labels == labels[i]).sum())
    for i in range(len(labels)):
        if density[i] > max_cluster_size and labels[i] != -1:
            labels[i] = -1

    bev = np.zeros((rows, cols, 3), np.float32)
    for i in range(len(labels)):
        if labels[i] <= 0:
            continue
        bev_x = int((xyv[i, 0] / resolution).long()) - 1  # float32 tensor maths, as upstream
        bev_y = int(((xyv[i, 1] + y_offset) / resolution).long()) - 1
        if -1 <= bev_y < rows and -1 <= bev_x < cols:  # -1 wraps to the last row / column
            bev[bev_y, bev_x] = (float(xyv[i, 2]), float(density[i]), float(labels[i]))
    return np.ascontiguousarray(bev.transpose(2, 0, 1)), labels.numpy()
