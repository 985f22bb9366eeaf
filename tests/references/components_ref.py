"""Plain union-find 8-connected component labelling (numpy + Python, no scipy), and partition equality."""

from __future__ import annotations

import numpy as np


def union_find_labels(mask: np.ndarray) -> np.ndarray:
    """Label the 8-connected components of a 2-D bool mask with union-find.

    Returns int64 labels shaped like ``mask``: 0 on background, and for each component its
    largest linear index (row * W + column) + 1 -- the canonical ids of radaredge's op.
    """
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    parent = np.arange(h * w)

    def find(i: int) -> int:
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:  # path compression
            parent[i], i = root, parent[i]
        return root

    def union(a: int, b: int) -> None:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[min(ra, rb)] = max(ra, rb)  # the root is always the largest index

    rows, cols = np.nonzero(mask)
    for r, c in zip(rows.tolist(), cols.tolist()):
        # the four neighbours already visited in row-major order cover all 8-neighbour pairs
        for dr, dc in ((-1, -1), (-1, 0), (-1, 1), (0, -1)):
            rr, cc = r + dr, c + dc
            if 0 <= rr < h and 0 <= cc < w and mask[rr, cc]:
                union(r * w + c, rr * w + cc)
    labels = np.zeros(h * w, np.int64)
    for r, c in zip(rows.tolist(), cols.tolist()):
        labels[r * w + c] = find(r * w + c) + 1
    return labels.reshape(h, w)


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two label maps have the same background (0) and a bijection between their ids."""
    a = np.asarray(a).ravel()
    b = np.asarray(b).ravel()
    if a.shape != b.shape or not np.array_equal(a == 0, b == 0):
        return False
    pairs = np.unique(np.stack([a, b], 1), axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))
