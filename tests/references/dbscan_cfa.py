"""MAFF-Net's original clustering-feature step (CQCA_cfa.generate_map), point labels only.

CQCA_cfa (TRV-Lab/MAFF-Net; read in the fthbng77/MAFF-Net fork's
pcdet/models/backbones_image/CQCA_cfa.py) runs sklearn
``DBSCAN(eps=DBSCAN_EPS, min_samples=DBSCAN_SAMPLE)`` (VoD: 0.4 m, 10) on each scan's points,
then marks every point of a cluster with more than 100 points as noise; the non-noise points
are its ``cluster_points``. Upstream feeds the three columns (x, y, v_r_comp) to DBSCAN, mixing
metres and m/s in one distance. GridDensityBEV clusters in the BEV plane only, so the
like-for-like comparison uses (x, y); ``with_velocity``
gives upstream's exact input.
"""

from __future__ import annotations

import numpy as np
from sklearn.cluster import DBSCAN


def dbscan_cfa_labels(points_xyv: np.ndarray, eps: float = 0.4, min_samples: int = 10,
                      max_cluster_size: int = 100, with_velocity: bool = False) -> np.ndarray:
    """Cluster id per point (>= 0), or -1 for noise; points_xyv [N, 3] = x, y (m), velocity (m/s)."""
    points = np.asarray(points_xyv, np.float64)
    features = points if with_velocity else points[:, :2]
    labels = DBSCAN(eps=eps, min_samples=min_samples).fit_predict(features)
    ids, sizes = np.unique(labels[labels >= 0], return_counts=True)
    too_big = ids[sizes > max_cluster_size]
    return np.where(np.isin(labels, too_big), -1, labels)


def cqca_cfa_map(points_xyv: np.ndarray, eps: float = 0.4, min_samples: int = 10, max_cluster_size: int = 100,
                 map_h: int = 320, map_w: int = 320, resolution: float = 0.16, y_offset: float = 25.6,
                 vectorised: bool = False):
    """Upstream CQCA_cfa.generate_map for one scan: (map [3, H, W] float32, labels [N] int64).

    The steps as upstream runs them, not as GridDensityBEV reformulates them: sklearn DBSCAN on
    the three columns (x m, y m, v m/s) as they are; each point's "density" is the size of its
    cluster, counted by one ``torch.where`` over all labels per point (upstream's O(N^2) Python
    loop; ``vectorised`` counts with ``np.unique`` instead, DBSCAN's best case); clusters above
    ``max_cluster_size`` become noise; the points of clusters with id > 0 (upstream's
    ``labels > 0``, which also leaves out cluster 0) write (v, density, label) into cell
    (row int((y + y_offset) / res) - 1, column int(x / res) - 1), the last point written to a
    cell winning. Points whose cell falls outside the map are skipped here (upstream would
    index out of range or wrap around).
    """
    import torch

    xyv = torch.as_tensor(np.asarray(points_xyv, np.float32))
    labels = torch.as_tensor(DBSCAN(eps=eps, min_samples=min_samples).fit_predict(xyv.numpy()), dtype=torch.int64)
    density = torch.zeros(len(labels), dtype=torch.float32)
    if vectorised:
        ids, inverse, counts = np.unique(labels.numpy(), return_inverse=True, return_counts=True)
        density = torch.as_tensor(np.where(labels.numpy() >= 0, counts[inverse], 0), dtype=torch.float32)
    else:
        for i, label in enumerate(labels):
            if label != -1:
                density[i] = len(torch.where(labels == label)[0])
    labels = torch.where((density > max_cluster_size) & (labels != -1), torch.full_like(labels, -1), labels)
    keep = labels > 0
    cols = (xyv[keep, 0] / resolution).long() - 1
    rows = ((xyv[keep, 1] + y_offset) / resolution).long() - 1
    values = torch.stack([xyv[keep, 2], density[keep], labels[keep].float()], 1)
    inside = (cols >= 0) & (cols < map_w) & (rows >= 0) & (rows < map_h)
    bev = torch.zeros(map_h, map_w, 3)
    bev[rows[inside], cols[inside]] = values[inside]
    return bev.permute(2, 0, 1).contiguous(), labels
