"""GridDensityBEV: MAFF-Net's clustering-feature BEV map (CQCA_cfa) without DBSCAN.

What it computes, as the fthbng77/MAFF-Net fork's ``GridDensityBEV`` (pcdet/models/
backbones_image/CQCA_cfa.py) does for one scan, with points (x, y, velocity) in the radar
frame (x forward, y left; metres; velocity in m/s -- for VoD the ego-motion compensated radial
velocity ``v_r_comp``, the fork's DBSCAN_V column):

1. Grid. Cell (iy, ix) covers x in [x_min + ix*res, x_min + (ix+1)*res) and likewise y, with
   ix = floor((x - x_min) / res) in float32; the map is [H, W] = [rows = y cells, columns =
   x cells]. The VoD defaults (x_min 0, y_min -25.6, 320 x 320 cells of 0.16 m) cover the VoD
   point-cloud range [0, 51.2) x [-25.6, 25.6) m (the fork's ``x / res`` and
   ``(y + DBSCAN_Y) / res``).
2. Per cell: point count and mean velocity (scatter-add of the points and their velocities).
3. Density: count of points in the k x k cells around each cell (a fixed all-ones conv, zero
   padded), k = max(3, 2 * round(eps / res) + 1) as the fork derives it -- eps 0.4 m at 0.16 m
   gives k = 5 (Python rounds 2.5 to 2). This square window stands in for DBSCAN's eps disk.
4. Non-noise cells: min_density <= density <= max_density (the fork's DBSCAN_SAMPLE 10 and
   MAX_DENSITY 100, the latter mirroring CQCA_cfa's "clusters above 100 points are noise").
   Like the fork, this is a property of the cell's neighbourhood, so an empty cell next to a
   dense one is non-noise too and bridges clusters, as DBSCAN's eps-reach does.
5. Cluster ids: 8-connected components of the non-noise cells
   (:func:`radaredge.ops.components.connected_components`, ``cc_mode``), labelled by the
   component's largest linear index + 1; the ``converged`` output says whether they are final
   (always, in exact mode).
6. Map channels, all 0 on noise cells: ch0 mean velocity (m/s), ch1 density / max(density over
   the map, 1), ch2 label / max(label over the map, 1).
7. Point mask (the fork's ``cluster_points``): the point is valid, finite, inside the grid, and
   its cell is non-noise.

Deliberate differences from the fork, for a defined edge-deployment contract:
- points outside the grid are dropped (the fork clamps them into the border cells);
- points with a NaN/Inf coordinate or velocity, and points with ``valid`` False, are dropped
  (they count nowhere and are False in the point mask);
- ``cc_mode="exact"`` gives exact components in a proven, fixed number of rounds; the default
  ``"maxpool"`` with 20 iterations reproduces the fork's labels, which stay partial on
  clusters longer than 20 cells, and ``converged`` reports when that happened.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..config import card_ranges, positive
from .components import MODES, connected_components

MAX_MAP_CELLS = 2**20  # CFA map cells: 64 float32 channels of it make 256 MiB


@card_ranges(
    map_h=(1, 8192),
    map_w=(1, 8192),
    resolution=positive(100.0),
    x_min=(-1000.0, 1000.0),
    y_min=(-1000.0, 1000.0),
    eps=positive(100.0),
    min_density=(1, 1_000_000),
    max_density=(1, 1_000_000),
    cc_iterations=(1, 100_000),
)
@dataclass(frozen=True)
class GridDensityConfig:
    """Model-card section of GridDensityBEV (metres, cells, point counts); VoD values by default."""

    map_h: int = 320  # rows = y cells (upstream's DBSCAN_MAP_W: its first axis is y)
    map_w: int = 320  # columns = x cells (upstream's DBSCAN_MAP_H)
    resolution: float = 0.16  # m per cell (RESOLUTION)
    x_min: float = 0.0  # m, x of the first column's lower edge
    y_min: float = -25.6  # m, y of the first row's lower edge (-DBSCAN_Y)
    eps: float = 0.4  # m, DBSCAN radius the density window stands in for (DBSCAN_EPS)
    min_density: int = 10  # points in the window for a non-noise cell (DBSCAN_SAMPLE)
    max_density: int = 100  # more points than this is noise too (MAX_DENSITY)
    cc_mode: str = "maxpool"  # "maxpool" (the fork's labels) or "exact"
    cc_iterations: int = 20  # maxpool steps (CC_ITERATIONS); exact mode uses its proven bound

    def __post_init__(self):
        if self.map_h < 1 or self.map_w < 1:
            raise ValueError("map_h and map_w must be >= 1")
        if self.resolution <= 0 or self.eps <= 0:
            raise ValueError("resolution and eps must be > 0")
        if not 0 < self.min_density <= self.max_density:
            raise ValueError("need 0 < min_density <= max_density")
        if self.cc_mode not in MODES:
            raise ValueError(f"cc_mode must be one of {MODES}, got {self.cc_mode!r}")
        if self.cc_iterations < 0:
            raise ValueError("cc_iterations must be >= 0")
        if self.map_h * self.map_w > MAX_MAP_CELLS:
            raise ValueError(
                f"a {self.map_h} x {self.map_w} map is {self.map_h * self.map_w} cells; at most "
                f"{MAX_MAP_CELLS} (the CFA convolves it at 64 channels: 256 MiB)"
            )

    @property
    def kernel_size(self) -> int:
        """Side of the density window in cells: max(3, 2 * round(eps / resolution) + 1)."""
        return max(3, int(2 * round(self.eps / self.resolution) + 1))


class GridDensityBEV(nn.Module):
    """Export formulation for one scan and any N (dynamic axis, N = 0 included).

    forward(points_xyv [N, 3] float32 (x, y in m, velocity in m/s), valid [N] bool) ->
    (bev [3, H, W] float32, point_mask [N] bool, converged [] bool); see the module docstring.
    """

    def __init__(self, config: GridDensityConfig):
        super().__init__()
        self.config = config
        k = config.kernel_size
        self.register_buffer("density_kernel", torch.ones(1, 1, k, k), persistent=False)
        self.register_buffer(
            "origin", torch.tensor([config.x_min, config.y_min], dtype=torch.float32), persistent=False
        )
        self.register_buffer("cell", torch.tensor([config.resolution] * 2, dtype=torch.float32), persistent=False)
        self.register_buffer(
            "extent", torch.tensor([config.map_w, config.map_h], dtype=torch.float32), persistent=False
        )

    def forward(self, points_xyv: torch.Tensor, valid: torch.Tensor):
        cfg = self.config
        h, w = cfg.map_h, cfg.map_w
        finite = torch.isfinite(points_xyv).all(1)
        points = torch.where(finite.unsqueeze(1), points_xyv, 0.0)
        grid = torch.floor((points[:, :2] - self.origin) / self.cell)  # [N, 2] (ix, iy)
        inside = valid & finite & ((grid >= 0) & (grid < self.extent)).all(1)
        grid = torch.where(inside.unsqueeze(1), grid, 0.0).to(torch.int64)
        cell = torch.where(inside, grid[:, 1] * w + grid[:, 0], h * w)  # h*w = dropped

        weight = inside.to(torch.float32)
        zeros = torch.zeros(h * w + 1, device=cell.device)
        count = zeros.scatter_add(0, cell, weight)[: h * w].view(h, w)
        vel_sum = zeros.scatter_add(0, cell, points[:, 2] * weight)[: h * w].view(h, w)
        pad = cfg.kernel_size // 2
        density = F.conv2d(count.view(1, 1, h, w), self.density_kernel, padding=pad).view(h, w)
        keep = (density >= cfg.min_density) & (density <= cfg.max_density)

        iterations = cfg.cc_iterations if cfg.cc_mode == "maxpool" else None  # exact: proven bound
        labels, converged = connected_components(keep.unsqueeze(0), cfg.cc_mode, iterations)
        labels = labels[0].to(torch.float32)
        density = torch.where(keep, density, 0.0)
        bev = torch.stack(
            [
                torch.where(keep, vel_sum / torch.clamp(count, min=1.0), 0.0),
                density / torch.clamp(density.max(), min=1.0),
                labels / torch.clamp(labels.max(), min=1.0),
            ]
        )
        keep_flat = torch.cat([keep.reshape(-1), torch.zeros(1, dtype=torch.bool, device=keep.device)])
        point_mask = inside & keep_flat[cell]
        return bev, point_mask, converged[0]


# ----------------------------------------------------------------------------- reference


def grid_density_bev_reference(points_xyv, valid, config: GridDensityConfig):
    """Reference formulation: plain numpy loops over points and cells.

    Components by breadth-first search (``exact``, always converged) or by the fork's max-pool
    steps applied cell by cell (``maxpool``). Same contract as :class:`GridDensityBEV` (points
    (x, y, velocity) in the radar frame, m and m/s); returns numpy
    ``(bev [3, H, W] float32, point_mask [N] bool, converged bool)``.
    """
    cfg = config
    h, w, r = cfg.map_h, cfg.map_w, cfg.kernel_size // 2
    points = np.asarray(points_xyv, np.float32).reshape(-1, 3)
    valid = np.asarray(valid, bool).reshape(-1)
    count = np.zeros((h, w), np.float32)
    vel_sum = np.zeros((h, w), np.float32)
    cells: list[tuple[int, int] | None] = []
    for (x, y, v), ok in zip(points, valid):
        cell = _reference_cell(x, y, cfg) if ok and np.isfinite([x, y, v]).all() else None
        cells.append(cell)
        if cell is not None:
            count[cell] += 1
            vel_sum[cell] += v
    density = np.zeros((h, w), np.float32)
    for iy, ix in zip(*np.nonzero(count)):
        density[max(iy - r, 0) : iy + r + 1, max(ix - r, 0) : ix + r + 1] += count[iy, ix]
    keep = (density >= cfg.min_density) & (density <= cfg.max_density)

    if cfg.cc_mode == "exact":
        labels, converged = _bfs_labels(keep), True
    else:
        labels, converged = _maxpool_labels(keep, cfg.cc_iterations)
    labels = labels.astype(np.float32)
    density = np.where(keep, density, np.float32(0))
    bev = np.stack(
        [
            np.where(keep, vel_sum / np.maximum(count, np.float32(1)), np.float32(0)),
            density / max(density.max(), np.float32(1)),
            labels / max(labels.max(), np.float32(1)),
        ]
    ).astype(np.float32)
    point_mask = np.array([c is not None and bool(keep[c]) for c in cells], bool)
    return bev, point_mask, converged


def _reference_cell(x, y, cfg: GridDensityConfig):
    """(iy, ix) of a finite point in float32 arithmetic, or None outside the grid."""
    res = np.float32(cfg.resolution)
    ix = np.floor((np.float32(x) - np.float32(cfg.x_min)) / res)
    iy = np.floor((np.float32(y) - np.float32(cfg.y_min)) / res)
    if 0 <= ix < cfg.map_w and 0 <= iy < cfg.map_h:
        return int(iy), int(ix)
    return None


def _neighbours(keep: np.ndarray, iy: int, ix: int):
    """Non-noise 8-neighbours of cell (iy, ix), and the cell itself."""
    h, w = keep.shape
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            y, x = iy + dy, ix + dx
            if 0 <= y < h and 0 <= x < w and keep[y, x]:
                yield y, x


def _bfs_labels(keep: np.ndarray) -> np.ndarray:
    """Exact 8-connected components by breadth-first search; id = largest linear index + 1."""
    h, w = keep.shape
    labels = np.zeros((h, w), np.int64)
    for start in zip(*np.nonzero(keep)):
        if labels[start]:
            continue
        members, queue = [start], deque([start])
        labels[start] = -1
        while queue:
            for nb in _neighbours(keep, *queue.popleft()):
                if not labels[nb]:
                    labels[nb] = -1
                    members.append(nb)
                    queue.append(nb)
        top = max(y * w + x for y, x in members) + 1
        for cell in members:
            labels[cell] = top
    return labels


def _maxpool_labels(keep: np.ndarray, iterations: int):
    """The fork's scheme cell by cell: each step a non-noise cell takes its neighbourhood's max id."""
    h, w = keep.shape
    cells = list(zip(*np.nonzero(keep)))
    labels = {c: c[0] * w + c[1] + 1 for c in cells}

    def step(current):
        return {c: max(current[nb] for nb in _neighbours(keep, *c)) for c in cells}

    for _ in range(iterations):
        labels = step(labels)
    converged = step(labels) == labels
    out = np.zeros((h, w), np.int64)
    for c, value in labels.items():
        out[c] = value
    return out, converged
