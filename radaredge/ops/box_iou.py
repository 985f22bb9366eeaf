"""Rotated bird's-eye-view IoU of 3-D boxes, as OpenPCDet's ``boxes_iou_bev`` defines it.

Boxes are OpenPCDet's 7-vectors (x, y, z, dx, dy, dz, heading): centre in metres (radar/lidar
frame, x forward, y left, z up), size along the box's own x / y / z axes in metres, heading in
radians about z from the x axis. The BEV footprint is the rectangle of (x, y, dx, dy, heading);
IoU = overlap / max(area_a + area_b - overlap, 1e-8) (the CUDA kernel's EPS).

Export formulation (:func:`bev_iou_paired`): fixed-shape tensor ops, no sorting of polygon
vertices. The overlap area of two convex polygons is the boundary integral of A∩B, whose
boundary is made of the parts of A's edges inside B and the parts of B's edges inside A. Each
edge is clipped to the other rectangle with the Cyrus-Beck parameter test (4 half-planes) and
contributes cross(start, end) / 2 (shoelace). An edge parallel to a side of the other box and
within ``tol`` of its line (1e-5 m for float32, 1e-9 m for float64) lies on that side: it counts
as inside, except that B's copy of a side shared in the same direction (a side of A∩B that both
boxes have) is dropped so it counts once; sides shared in opposite directions (boxes touching
from outside) both count and cancel. The pairs run along the last axis ([4, 4, P] tensors, x and
y apart): onnxruntime's broadcasting elementwise kernels are fast over a long contiguous last
axis and slow over short ones such as a trailing 2.

Reference formulation (:func:`bev_iou_reference`): Sutherland-Hodgman clipping of A by B's four
edges, then the shoelace formula, in float64 with plain Python loops.
"""

from __future__ import annotations

import math

import numpy as np
import torch

EPS_UNION = 1e-8  # OpenPCDet iou3d_nms kernel: overlap / max(union, EPS)
EDGE_TOL = 1e-5  # m, float32 inputs; see the module docstring
EDGE_TOL_F64 = 1e-9  # m, float64 inputs


def bev_corners(boxes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Counter-clockwise BEV corners of boxes [P, 7]: (x [4, P], y [4, P]) in metres, pairs last
    (onnxruntime broadcasts fastest over a long contiguous last axis)."""
    b = boxes.t()  # [7, P]
    sx = torch.tensor([[1.0], [-1.0], [-1.0], [1.0]], dtype=boxes.dtype, device=boxes.device)
    sy = torch.tensor([[1.0], [1.0], [-1.0], [-1.0]], dtype=boxes.dtype, device=boxes.device)
    lx, ly = sx * (b[3] / 2), sy * (b[4] / 2)  # [4, P]
    c, s = torch.cos(b[6]), torch.sin(b[6])
    return c * lx - s * ly + b[0], s * lx + c * ly + b[1]


def _next_corner(corner: torch.Tensor) -> torch.Tensor:
    """One coordinate of the corners [4, P] -> that of the corner after each (k -> k + 1 mod 4)."""
    return torch.cat([corner[1:], corner[:1]])


def _clipped_boundary_area(
    px: torch.Tensor,
    py: torch.Tensor,
    p_len: torch.Tensor,
    qx: torch.Tensor,
    qy: torch.Tensor,
    q_len: torch.Tensor,
    tol: float,
    skip_shared: torch.Tensor,
) -> torch.Tensor:
    """Sum over the edges of polygon p (corners ``px``, ``py`` [4, P]) of cross(start, end)/2 of
    the part of the edge inside polygon q (``qx``, ``qy`` [4, P]); both counter-clockwise,
    ``*_len`` [4, P] the edge lengths. An edge parallel to a side of q and within ``tol`` of its
    line lies on it: inside, unless ``skip_shared`` [P] (bool) is set and the two run the same way.
    Returns [P]. Axes: k = p's edge, l = q's side, pairs last."""
    dx, dy = _next_corner(px) - px, _next_corner(py) - py  # edge k: p[k] -> p[k+1]
    ex, ey = (_next_corner(qx) - qx).unsqueeze(0), (_next_corner(qy) - qy).unsqueeze(0)  # [1, 4l, P]
    e_len, d_len = q_len.unsqueeze(0), p_len.unsqueeze(1)  # [1, 4l, P], [4k, 1, P]
    # inside side l: cross(e_l, x - q_l) >= 0 for x = p_k + t d_k, i.e. num + t den >= 0
    num = ex * (py.unsqueeze(1) - qy.unsqueeze(0)) - ey * (px.unsqueeze(1) - qx.unsqueeze(0))  # [4k, 4l, P]
    den = ex * dy.unsqueeze(1) - ey * dx.unsqueeze(1)
    parallel = den.abs() <= (1e-5 if px.dtype == torch.float32 else 1e-12) * e_len * d_len
    on_line = parallel & (num.abs() <= tol * e_len)
    outside = parallel & ~on_line & (num < 0)
    shared = on_line & (ex * dx.unsqueeze(1) + ey * dy.unsqueeze(1) > 0)
    outside = outside | (shared & skip_shared)
    den = torch.where(parallel, torch.zeros_like(den), den)
    t = -num / torch.where(parallel, torch.ones_like(den), den)
    inf = torch.full_like(t, math.inf)
    t_lo = torch.clamp(torch.where(den > 0, t, -inf).amax(1), min=0.0)  # [4k, P]
    t_hi = torch.clamp(torch.where(den < 0, t, inf).amin(1), max=1.0)
    ok = (t_hi > t_lo) & ~outside.any(1)
    ax, ay = px + t_lo * dx, py + t_lo * dy
    bx, by = px + t_hi * dx, py + t_hi * dy
    return torch.where(ok, ax * by - ay * bx, torch.zeros_like(t_lo)).sum(0) / 2


def bev_overlap_paired(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """Export formulation: BEV overlap area (m^2) of row i of boxes_a [P, 7] with row i of boxes_b.
    float64 boxes are computed in float64 with a 1e-9 m edge tolerance. A's edges clipped to B and
    B's edges clipped to A run as one batch of 2P pairs (half the graph nodes of two calls)."""
    tol = EDGE_TOL_F64 if boxes_a.dtype == torch.float64 else EDGE_TOL
    p = boxes_a.shape[0]
    ax, ay = bev_corners(boxes_a)
    bx, by = bev_corners(boxes_b)
    ox, oy = boxes_a[:, 0], boxes_a[:, 1]  # cross products about A's centre
    ax, ay, bx, by = ax - ox, ay - oy, bx - ox, by - oy
    la, lb = boxes_a[:, 3:5].t().repeat(2, 1), boxes_b[:, 3:5].t().repeat(2, 1)  # [4, P], edge lengths
    skip = torch.cat(
        [
            torch.zeros(p, dtype=torch.bool, device=boxes_a.device),
            torch.ones(p, dtype=torch.bool, device=boxes_a.device),
        ]
    )
    parts = _clipped_boundary_area(
        torch.cat([ax, bx], 1),
        torch.cat([ay, by], 1),
        torch.cat([la, lb], 1),
        torch.cat([bx, ax], 1),
        torch.cat([by, ay], 1),
        torch.cat([lb, la], 1),
        tol,
        skip,
    )
    return torch.clamp(parts[:p] + parts[p:], min=0.0)


def bev_iou_paired(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """Export formulation: rotated BEV IoU [P] of row i of boxes_a [P, 7] with row i of boxes_b."""
    overlap = bev_overlap_paired(boxes_a, boxes_b)
    union = boxes_a[:, 3] * boxes_a[:, 4] + boxes_b[:, 3] * boxes_b[:, 4] - overlap
    return overlap / torch.clamp(union, min=EPS_UNION)


def bev_half_extents(boxes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Half extents (m) along x and along y [...] of the axis-aligned rectangle that bounds each
    box's BEV footprint (boxes [..., 7])."""
    c, s = torch.cos(boxes[..., 6]).abs(), torch.sin(boxes[..., 6]).abs()
    return 0.5 * (boxes[..., 3] * c + boxes[..., 4] * s), 0.5 * (boxes[..., 3] * s + boxes[..., 4] * c)


def bev_iou_upper_bound(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """An upper bound [P] of :func:`bev_iou_paired` of row i of boxes_a [P, 7] with row i of
    boxes_b, from a few ops a pair: a footprint lies inside its bounding rectangle, so the overlap
    is at most the area u of the two rectangles' intersection and at most the smaller footprint,
    and IoU = overlap / (area_a + area_b - overlap) rises with the overlap, so IoU <= u / (area_a +
    area_b - u). It equals the IoU for two axis-aligned boxes and is 0 for disjoint rectangles."""
    exa, eya = bev_half_extents(boxes_a)
    exb, eyb = bev_half_extents(boxes_b)
    ix = torch.minimum(boxes_a[:, 0] + exa, boxes_b[:, 0] + exb) - torch.maximum(
        boxes_a[:, 0] - exa, boxes_b[:, 0] - exb
    )
    iy = torch.minimum(boxes_a[:, 1] + eya, boxes_b[:, 1] + eyb) - torch.maximum(
        boxes_a[:, 1] - eya, boxes_b[:, 1] - eyb
    )
    area_a, area_b = boxes_a[:, 3] * boxes_a[:, 4], boxes_b[:, 3] * boxes_b[:, 4]
    u = torch.minimum(torch.clamp(ix, min=0.0) * torch.clamp(iy, min=0.0), torch.minimum(area_a, area_b))
    return u / torch.clamp(area_a + area_b - u, min=EPS_UNION)


def boxes_iou3d(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """3-D IoU [N, M] of every box of boxes_a [N, 7] with every box of boxes_b [M, 7], as
    OpenPCDet's boxes_iou3d_gpu: rotated BEV overlap times the overlap of the z extents (z is the
    box centre), over max(volume_a + volume_b - intersection, 1e-6). Training-time (target
    assignment), not exported."""
    n, m = len(boxes_a), len(boxes_b)
    if n == 0 or m == 0:
        return boxes_a.new_zeros((n, m))
    bev = bev_overlap_paired(boxes_a.repeat_interleave(m, 0), boxes_b.repeat(n, 1)).reshape(n, m)
    top = torch.minimum(boxes_a[:, None, 2] + boxes_a[:, None, 5] / 2, boxes_b[None, :, 2] + boxes_b[None, :, 5] / 2)
    bottom = torch.maximum(boxes_a[:, None, 2] - boxes_a[:, None, 5] / 2, boxes_b[None, :, 2] - boxes_b[None, :, 5] / 2)
    inter = bev * torch.clamp(top - bottom, min=0.0)
    vol_a = (boxes_a[:, 3] * boxes_a[:, 4] * boxes_a[:, 5])[:, None]
    vol_b = (boxes_b[:, 3] * boxes_b[:, 4] * boxes_b[:, 5])[None, :]
    return inter / torch.clamp(vol_a + vol_b - inter, min=1e-6)


# ----------------------------------------------------------------------------- reference


def _corners_reference(box) -> list[tuple[float, float]]:
    x, y, _, dx, dy, _, h = (float(v) for v in box[:7])
    c, s = math.cos(h), math.sin(h)
    local = [(dx / 2, dy / 2), (-dx / 2, dy / 2), (-dx / 2, -dy / 2), (dx / 2, -dy / 2)]
    return [(x + c * u - s * v, y + s * u + c * v) for u, v in local]


def _clip(polygon, a, b):
    """Part of ``polygon`` left of the directed line a -> b (Sutherland-Hodgman step)."""

    def side(p):
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])

    out = []
    for i, p in enumerate(polygon):
        q = polygon[(i + 1) % len(polygon)]
        sp, sq = side(p), side(q)
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            t = sp / (sp - sq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _shoelace(polygon) -> float:
    return 0.5 * sum(p[0] * q[1] - q[0] * p[1] for p, q in zip(polygon, polygon[1:] + polygon[:1]))


def bev_iou_reference(box_a, box_b) -> float:
    """Reference formulation: rotated BEV IoU of two boxes (7-vectors), float64, plain Python."""
    poly = _corners_reference(box_a)
    clip = _corners_reference(box_b)
    for i in range(4):
        if not poly:
            break
        poly = _clip(poly, clip[i], clip[(i + 1) % 4])
    overlap = max(_shoelace(poly), 0.0) if len(poly) >= 3 else 0.0
    union = float(box_a[3]) * float(box_a[4]) + float(box_b[3]) * float(box_b[4]) - overlap
    return overlap / max(union, EPS_UNION)


def bev_iou_matrix_reference(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Reference IoU of every box of boxes_a [N, 7] with every box of boxes_b [M, 7] -> [N, M]."""
    return np.array([[bev_iou_reference(a, b) for b in boxes_b] for a in boxes_a], np.float64).reshape(
        len(boxes_a), len(boxes_b)
    )
