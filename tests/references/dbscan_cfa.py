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


def dbscan_cfa_labels(
    points_xyv: np.ndarray,
    eps: float = 0.4,
    min_samples: int = 10,
    max_cluster_size: int = 100,
    with_velocity: bool = False,
) -> np.ndarray:
    """Cluster id per point (>= 0), or -1 for noise; points_xyv [N, 3] = x, y (m), velocity (m/s)."""
    points = np.asarray(points_xyv, np.float64)
    features = points if with_velocity else points[:, :2]
    labels = DBSCAN(eps=eps, min_samples=min_samples).fit_predict(features)
    ids, sizes = np.unique(labels[labels >= 0], return_counts=True)
    too_big = ids[sizes > max_cluster_size]
    return np.where(np.isin(labels, too_big), -1, labels)
