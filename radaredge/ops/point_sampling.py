"""PointNet++ point sampling and grouping: farthest point sampling, ball query, grouping.

Each op exists twice (DESIGN.md):

- the **export** formulation works on a batch of G point sets of a fixed size N at once and is
  built from fixed-shape tensor ops only (ArgMax, Min, TopK, Gather, Where), so it traces to
  ONNX opset 18 without custom ops;
- the **reference** formulation is the plain loop of the PointNet++ paper / CUDA kernels, on one
  point set (numpy), written for clarity.

Conventions shared by both (they decide the exact indices, and the tests hold them bit-equal):

* Squared distances are computed as ``dx*dx + dy*dy + dz*dz`` in float32, in that order, so
  the two formulations round identically.
* FPS starts from point 0 (deterministic, as the PointNet++ CUDA kernel does), keeps every
  point's minimum squared distance to the selected set and picks the first index of the
  maximum (ArgMax / ``np.argmax`` semantics) ``npoint`` - 1 more times. A set with fewer
  distinct points than ``npoint`` repeats index 0 once every point is at distance 0.
* Ball query returns, for each centre, the first ``nsample`` point indices (in index order)
  whose squared distance is <= radius**2; when fewer lie inside, the first one found fills the
  remaining slots (the PointNet++ ``query_ball_point`` convention). A centre drawn from the set
  always finds itself, so a slot is never empty.
"""

from __future__ import annotations

import numpy as np
import torch


def _sqdist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances between a [..., 3] and b [..., 3] (broadcast), dx*dx + dy*dy + dz*dz."""
    d = a - b
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def _sqdist_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = (a - b).astype(np.float32)
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


# ----------------------------------------------------------------------------- FPS


def farthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """Export formulation. xyz [G, N, 3] float32 -> int64 [G, npoint] indices into N.

    A fixed loop of ``npoint`` - 1 argmax steps (unrolled when traced), start index 0.
    """
    g, n, _ = xyz.shape
    idx = torch.zeros(g, 1, dtype=torch.int64)
    far = torch.zeros(g, dtype=torch.int64)
    dist = torch.full((g, n), float("inf"), dtype=xyz.dtype)
    chosen = [idx]
    for _ in range(npoint - 1):
        centre = torch.gather(xyz, 1, far.view(g, 1, 1).expand(g, 1, 3))        # [G, 1, 3]
        dist = torch.minimum(dist, _sqdist(xyz, centre))
        far = torch.argmax(dist, dim=1)
        chosen.append(far.view(g, 1))
    return torch.cat(chosen, 1)


def farthest_point_sample_reference(xyz: np.ndarray, npoint: int) -> np.ndarray:
    """Reference formulation on one set. xyz [N, 3] -> int64 [npoint]: a Python loop over the
    picks, each updating the running minimum distance of every point (numpy over N)."""
    xyz = np.asarray(xyz, np.float32)
    dist = np.full(len(xyz), np.inf, np.float32)
    out = [0]
    far = 0
    for _ in range(npoint - 1):
        dist = np.minimum(dist, _sqdist_np(xyz, xyz[far]))
        far = int(np.argmax(dist))
        out.append(far)
    return np.array(out, np.int64)


# ----------------------------------------------------------------------------- ball query


def ball_query(xyz: torch.Tensor, centres: torch.Tensor, radius: float, nsample: int) -> torch.Tensor:
    """Export formulation. xyz [G, N, 3], centres [G, S, 3] -> int64 [G, S, nsample].

    Masked distances + TopK: points inside the ball get the key ``index``, the others
    ``N + index``; the ``nsample`` smallest keys are the first in-ball indices in index order,
    and slots past the in-ball count are filled with the first one.
    """
    n = xyz.shape[1]
    d2 = _sqdist(centres.unsqueeze(2), xyz.unsqueeze(1))                     # [G, S, N]
    ar = torch.arange(n, dtype=torch.int64).view(1, 1, n)
    key = torch.where(d2 <= radius * radius, ar, ar + n)
    k = min(nsample, n)
    first = torch.topk(key, k, dim=2, largest=False, sorted=True).values    # [G, S, k]
    idx = torch.where(first >= n, first[..., :1], first)
    if k < nsample:                                                          # fewer points than slots
        idx = torch.cat([idx, idx[..., :1].expand(-1, -1, nsample - k)], 2)
    return torch.where(idx >= n, idx - n, idx)


def ball_query_reference(xyz: np.ndarray, centres: np.ndarray, radius: float, nsample: int) -> np.ndarray:
    """Reference formulation on one set, one query at a time: the in-ball points of each centre
    in index order, cut at ``nsample`` and filled with the first. -> int64 [S, nsample]."""
    xyz = np.asarray(xyz, np.float32)
    out = np.zeros((len(centres), nsample), np.int64)
    r2 = np.float32(radius * radius)        # the threshold torch compares against, rounded once
    for s, c in enumerate(np.asarray(centres, np.float32)):
        found = np.flatnonzero(_sqdist_np(xyz, c) <= r2)[:nsample].tolist()
        first = found[0] if found else 0
        out[s] = found + [first] * (nsample - len(found))
    return out


# ----------------------------------------------------------------------------- grouping


def group_points(features: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Export formulation. features [G, N, C], idx [G, S, K] -> [G, S, K, C] (one Gather)."""
    g, n, c = features.shape
    _, s, k = idx.shape
    flat = idx.reshape(g, s * k, 1).expand(g, s * k, c)
    return torch.gather(features, 1, flat).reshape(g, s, k, c)


def group_points_reference(features: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Reference formulation on one set. features [N, C], idx [S, K] -> [S, K, C], loops."""
    s, k = idx.shape
    out = np.zeros((s, k, features.shape[1]), features.dtype)
    for i in range(s):
        for j in range(k):
            out[i, j] = features[idx[i, j]]
    return out
