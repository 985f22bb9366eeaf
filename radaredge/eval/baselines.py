"""A place descriptor without learning: the floor a learned one has to clear.

:func:`polar_occupancy` is a ScanContext-style descriptor (Kim and Kim, IROS 2018) of a
K-frame window: the points of all K scans, each in its own radar frame (no alignment, no
learning), binned into ``rings`` range rings of equal width out to ``max_range`` m and
``sectors`` azimuth sectors around the radar (x forward, y left); a cell holds log(1 + the
number of points in it), and the matrix, flattened ring by ring, is L2-normalised. ScanContext
keeps each cell's highest point; a 4D radar's elevation is too coarse for that, so occupancy
replaces height. Retrieval is the same exact L2 search as for the learned descriptors.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import InputError

RINGS, SECTORS, MAX_RANGE = 20, 60, 70.0


def polar_occupancy(
    frames: Sequence[np.ndarray],
    x_column: int = 0,
    y_column: int = 1,
    rings: int = RINGS,
    sectors: int = SECTORS,
    max_range: float = MAX_RANGE,
) -> np.ndarray:
    """float32 [rings * sectors]: the window's polar occupancy descriptor (module docstring) of
    ``frames`` (float32 [N_k, F] each, metres in columns ``x_column`` and ``y_column``)."""
    points = np.concatenate([np.asarray(f, dtype=np.float64)[:, [x_column, y_column]] for f in frames])
    if points.ndim != 2 or not np.isfinite(points).all():
        raise InputError("the window's x and y columns must be finite numbers (m)")
    r = np.hypot(points[:, 0], points[:, 1])
    keep = r < max_range
    ring = (r[keep] / max_range * rings).astype(np.int64)
    sector = ((np.arctan2(points[keep, 1], points[keep, 0]) + np.pi) / (2 * np.pi) * sectors).astype(np.int64) % sectors
    grid = np.log1p(np.bincount(ring * sectors + sector, minlength=rings * sectors)).astype(np.float32)
    norm = float(np.linalg.norm(grid))
    return grid / norm if norm > 0 else grid
