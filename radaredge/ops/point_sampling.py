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

OpenPCDet's stack variants used by PV-RCNN-style second stages are here too: FPS over the valid
points of a masked set (:func:`farthest_point_sample_masked`) and the ball query with a candidate
mask, a strict ``<`` radius test and an empty-ball flag (:func:`ball_query_masked`, of which
:func:`ball_query` is the unmasked ``<=`` case).
"""

from __future__ import annotations

import numpy as np
import torch

from .loops import fixed_point_loop


def _sqdist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances between a [..., 3] and b [..., 3] (broadcast), dx*dx + dy*dy + dz*dz.
    Per coordinate, so the broadcast [..., 3] difference is never materialised (for the ROI-grid
    pooling of VoD that tensor alone would be 21600 x 1024 x 3 floats, 253 MB)."""
    dx, dy, dz = (a[..., i] - b[..., i] for i in range(3))
    return dx * dx + dy * dy + dz * dz


def _sqdist_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = (a - b).astype(np.float32)
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


# ----------------------------------------------------------------------------- FPS


def farthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """Export formulation. xyz [G, N, 3] float32 -> int64 [G, npoint] indices into N.

    A fixed loop of ``npoint`` - 1 argmax steps (unrolled when traced), start index 0.
    """
    g, n, _ = xyz.shape
    dev = xyz.device
    idx = torch.zeros(g, 1, dtype=torch.int64, device=dev)
    far = torch.zeros(g, dtype=torch.int64, device=dev)
    dist = torch.full((g, n), float("inf"), dtype=xyz.dtype, device=dev)
    chosen = [idx]
    for _ in range(npoint - 1):
        centre = torch.gather(xyz, 1, far.view(g, 1, 1).expand(g, 1, 3))  # [G, 1, 3]
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


def farthest_point_sample_masked(
    xyz: torch.Tensor, valid: torch.Tensor, npoint: int, picks: torch.Tensor | None = None
) -> torch.Tensor:
    """Export formulation of FPS over the valid points of one set. xyz [N, 3] (finite), valid [N]
    bool -> int64 [npoint] indices into N.

    Equals :func:`farthest_point_sample_reference` on the valid points compacted in index order
    (mapped back to N): start at the first valid point, pick the first index of the largest
    running minimum squared distance; invalid points carry distance -1 so they are never picked
    while a valid one exists. Slots past the number of valid points pick already chosen points
    (distance 0); a set without valid points gives index 0 everywhere. The picks run in
    :func:`radaredge.ops.loops.fixed_point_loop` (one ONNX Loop once exported), not unrolled.
    ``picks`` (a 0-d int64 tensor), when given, stops the loop after that many slots: the later
    slots hold the start index (callers that need fewer picks than ``npoint`` at run time).
    """
    n, dev = xyz.shape[0], xyz.device
    start = torch.argmax(torch.cat([valid, torch.zeros(1, dtype=torch.bool, device=dev)]).to(torch.int64))
    start = torch.where(start < n, start, 0)  # the first valid point (0 if none; N = 0 too)
    dist = torch.where(valid, torch.full((n,), float("inf"), device=dev), torch.full((n,), -1.0, device=dev))
    slots = torch.arange(npoint, dtype=torch.int64, device=dev)
    out = torch.zeros(npoint, dtype=torch.int64, device=dev) + start
    limit = torch.full((), npoint, dtype=torch.int64, device=dev) if picks is None else torch.clamp(picks, max=npoint)

    def not_done(i, far, dist, out, limit):
        return i < limit

    def step(i, far, dist, out, limit):
        centre = torch.index_select(xyz, 0, far.view(1))  # [1, 3]
        dist = torch.minimum(dist, _sqdist(xyz, centre))
        far = torch.argmax(dist)
        return i + 1, far, dist, torch.where(slots == i, far, out), limit.clone()

    state = (torch.ones((), dtype=torch.int64, device=dev), start, dist, out, limit)
    return fixed_point_loop(not_done, step, state)[3]


def farthest_point_sample_masked_reference(xyz: np.ndarray, valid: np.ndarray, npoint: int) -> np.ndarray:
    """Reference of :func:`farthest_point_sample_masked`: compact the valid points, run the plain
    FPS loop, map back to the original indices; slots past the valid count repeat what the loop
    picks once every point is at distance 0 (the first valid point; 0 with no valid point)."""
    keep = np.flatnonzero(np.asarray(valid, bool))
    if len(keep) == 0:
        return np.zeros(npoint, np.int64)
    return keep[farthest_point_sample_reference(np.asarray(xyz, np.float32)[keep], npoint)]


# ----------------------------------------------------------------------------- ball query


def ball_query(xyz: torch.Tensor, centres: torch.Tensor, radius: float, nsample: int) -> torch.Tensor:
    """Export formulation. xyz [G, N, 3], centres [G, S, 3] -> int64 [G, S, nsample]: the
    PointNet++ convention of the module docstring (``<=``, every point a candidate); a centre
    with no point inside gets index 0 in every slot. See :func:`ball_query_masked`."""
    return ball_query_masked(xyz, None, centres, radius, nsample, strict=False)[0]


def ball_query_masked(
    xyz: torch.Tensor,
    valid: torch.Tensor | None,
    centres: torch.Tensor,
    radius: float,
    nsample: int,
    strict: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Export formulation of the general ball query. xyz [G, N, 3], valid [G, N] bool or None (all
    candidates), centres [G, S, 3] -> (idx int64 [G, S, nsample], empty bool [G, S]).

    A candidate is a hit when it is valid and its squared distance is < radius**2 (``strict``,
    OpenPCDet's stack ball query) or <= radius**2; idx holds the first ``nsample`` hits in index
    order, then the first hit repeated; a centre without hits is ``empty`` and gets index 0.
    Masked distances + TopK: hits get the key ``index``, the others ``N + index``, as float32
    (exact below 2**24 points, half the memory of int64 keys); the ``nsample`` smallest keys are
    the first hits in index order.
    """
    n = xyz.shape[1]
    d2 = _sqdist(centres.unsqueeze(2), xyz.unsqueeze(1))  # [G, S, N]
    hit = d2 < radius * radius if strict else d2 <= radius * radius
    if valid is not None:
        hit = hit & valid.unsqueeze(1)
    ar = torch.arange(n, dtype=torch.float32, device=xyz.device).view(1, 1, n)
    key = torch.where(hit, ar, ar + n)
    k = min(nsample, n)
    first = torch.topk(key, k, dim=2, largest=False, sorted=True).values.to(torch.int64)  # [G, S, k]
    empty = first[..., 0] >= n
    idx = torch.where(first >= n, first[..., :1], first)
    if k < nsample:  # fewer points than slots
        idx = torch.cat([idx, idx[..., :1].expand(-1, -1, nsample - k)], 2)
    return torch.where(idx >= n, idx - n, idx), empty


def ball_query_reference(xyz: np.ndarray, centres: np.ndarray, radius: float, nsample: int) -> np.ndarray:
    """Reference formulation on one set, one query at a time: the in-ball points of each centre
    in index order, cut at ``nsample`` and filled with the first. -> int64 [S, nsample]."""
    return ball_query_masked_reference(xyz, None, centres, radius, nsample, strict=False)[0]


def ball_query_masked_reference(
    xyz: np.ndarray, valid: np.ndarray | None, centres: np.ndarray, radius: float, nsample: int, strict: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Reference of :func:`ball_query_masked` on one set, one centre at a time: the valid
    candidates with d2 < r2 (or <=) in index order (the CUDA kernel's scan), cut at ``nsample``
    and filled with the first. -> (idx int64 [S, nsample], empty bool [S])."""
    xyz = np.asarray(xyz, np.float32)
    valid = np.ones(len(xyz), bool) if valid is None else np.asarray(valid, bool)
    out = np.zeros((len(centres), nsample), np.int64)
    empty = np.zeros(len(centres), bool)
    r2 = np.float32(radius * radius)  # the threshold torch compares against, rounded once
    for s, c in enumerate(np.asarray(centres, np.float32)):
        d2 = _sqdist_np(xyz, c)
        found = np.flatnonzero(valid & ((d2 < r2) if strict else (d2 <= r2)))[:nsample].tolist()
        empty[s] = not found
        first = found[0] if found else 0
        out[s] = found + [first] * (nsample - len(found))
    return out, empty


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
