"""Trajectory-guided alignment of past BEV maps into the current frame (TDFANet eq. 4-5).

BEV grid layout (the project-wide convention, OpenPCDet's pillar canvas, see
:mod:`radaredge.ops.pillars`): a map is [B, C, H, W] with H = ny rows along +y (left) and
W = nx columns along +x (forward); the paper's 216 x 248 grid (nx x ny) is a [B, C, 248, 216]
map. Cell (row j, column i) covers x in [x_min + i*sx, x_min + (i+1)*sx), y likewise with j.
Continuous cell coordinates (u along x, v along y) put cell centres at integers, so
u = (x - x_min)/sx - 0.5 and v = (y - y_min)/sy - 0.5.

Sign convention. Let d = (dx, dy) be the radar's displacement from the past frame to the current
frame and dpsi its yaw change (counter-clockwise about z, i.e. turning left, is positive), both
expressed in the past radar frame. The current radar pose in the past frame is then (R(dpsi), d),
so a static world point at position p in the current frame was at

    p_past = R(dpsi) p + d,      R(a) = [[cos a, -sin a], [sin a, cos a]],

in the past frame. Driving forward (dx > 0) a static object therefore sits further ahead in the
past map. The aligned map is A(p) = F_past(p_past), sampled bilinearly at cell centres with
zeros outside the past map. ``displacement_cells`` is d in cells: (dx / sx, dy / sy) (eq. 5).

Both formulations compute exactly this: :func:`align_bev` builds the sampling grid from tensors
(displacement and yaw may be computed in-graph) and calls ``grid_sample`` (bilinear, zero padding,
align_corners=False); :func:`align_bev_reference` interpolates the four corners explicitly.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import ConfigError, InputError


@dataclass(frozen=True)
class BevGrid:
    """Geometry of a BEV map: minimum corner (m), cell size (m) and cell counts along x and y."""

    x_min: float
    y_min: float
    voxel_x: float
    voxel_y: float
    nx: int
    ny: int

    def __post_init__(self):
        if self.voxel_x <= 0 or self.voxel_y <= 0 or self.nx < 1 or self.ny < 1:
            raise ConfigError(f"BevGrid needs positive cell sizes and counts, got {self}")

    @classmethod
    def from_range(cls, point_cloud_range, voxel_size) -> "BevGrid":
        """Grid of a model card's ``point_cloud_range`` (x_min, y_min, z_min, x_max, y_max, z_max)
        and ``voxel_size`` (sx, sy[, sz]), metres."""
        r, v = point_cloud_range, voxel_size
        return cls(
            float(r[0]),
            float(r[1]),
            float(v[0]),
            float(v[1]),
            int(round((r[3] - r[0]) / v[0])),
            int(round((r[4] - r[1]) / v[1])),
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) = (ny, nx) of a map on this grid."""
        return self.ny, self.nx

    def origin_cells(self) -> tuple[float, float]:
        """Continuous cell coordinates (u, v) of the radar origin, the centre of yaw rotations."""
        return -self.x_min / self.voxel_x - 0.5, -self.y_min / self.voxel_y - 0.5


def grid_displacement(
    ego_velocities: torch.Tensor,
    voxel_size,
    *,
    frame_interval: float | None = None,
    timestamps: torch.Tensor | None = None,
) -> torch.Tensor:
    """Grid displacement from each frame to the current (last) one, [K, 2] cells (eq. 4-5).

    ``ego_velocities`` [K, 3] m/s is the radar's velocity w.r.t. the world in each frame's radar
    frame, oldest frame first. Between frames k-1 and k the radar moves s = v_{k-1} * dt (eq. 4;
    dt = ``frame_interval`` = 1/f_r in seconds, or the differences of ``timestamps`` [K] s); the
    displacement of frame k is the sum of the steps from k to K-1, divided by the cell size
    ``voxel_size`` (sx, sy) m (eq. 5). Rotation between frames is ignored, as in the paper, so
    the steps are summed as if all frames shared one orientation. Row k is (dx, dy) in cells
    along +x and +y, the ``displacement_cells`` of :func:`align_bev`; the last row is zero.
    """
    if (frame_interval is None) == (timestamps is None):
        raise ConfigError("grid_displacement needs exactly one of frame_interval (s) or timestamps [K] (s)")
    if ego_velocities.dim() != 2 or ego_velocities.shape[1] != 3:
        raise InputError(f"ego_velocities must be [K, 3] m/s, got {list(ego_velocities.shape)}")
    if timestamps is None:
        dt = torch.full_like(ego_velocities[1:, 0], frame_interval)
    else:
        dt = (timestamps[1:] - timestamps[:-1]).to(ego_velocities.dtype)
    steps = ego_velocities[:-1, :2] * dt.unsqueeze(1)  # [K-1, 2] m
    to_current = torch.flip(torch.cumsum(torch.flip(steps, [0]), 0), [0])  # sum_{j >= k} steps_j
    metres = torch.cat([to_current, torch.zeros_like(steps[:1])], 0)
    return metres / torch.tensor([voxel_size[0], voxel_size[1]], dtype=metres.dtype, device=metres.device)


def _check_inputs(past_map: torch.Tensor, displacement_cells: torch.Tensor, yaw, grid: BevGrid) -> None:
    if past_map.dim() != 4 or tuple(past_map.shape[2:]) != grid.shape:
        raise InputError(
            f"past_map must be [B, C, H=ny, W=nx] = [B, C, {grid.ny}, {grid.nx}] for this grid, got "
            f"{list(past_map.shape)}"
        )
    if tuple(displacement_cells.shape) != (past_map.shape[0], 2):
        raise InputError(
            f"displacement_cells must be [B, 2] = [{past_map.shape[0]}, 2] (dx, dy cells), "
            f"got {list(displacement_cells.shape)}"
        )
    if yaw is not None and tuple(yaw.shape) != (past_map.shape[0],):
        raise InputError(f"yaw must be [B] = [{past_map.shape[0]}] rad, got {list(yaw.shape)}")


def _index_map(displacement_cells: torch.Tensor, yaw, grid: BevGrid):
    """Past-map cell coordinates (u', v') of every current cell (u, v), broadcastable to [B, H, W].

    In cell units p_past = R p + d becomes u' = c + A (u - c) + delta with A = S^-1 R S,
    S = diag(sx, sy), c the radar origin in cell coordinates and delta = ``displacement_cells``.
    """
    dtype, dev = displacement_cells.dtype, displacement_cells.device
    u = torch.arange(grid.nx, dtype=dtype, device=dev).view(1, 1, -1)
    v = torch.arange(grid.ny, dtype=dtype, device=dev).view(1, -1, 1)
    du = displacement_cells[:, 0].view(-1, 1, 1)
    dv = displacement_cells[:, 1].view(-1, 1, 1)
    if yaw is None:
        return u + du, v + dv
    cu, cv = grid.origin_cells()
    cos = torch.cos(yaw).to(dtype).view(-1, 1, 1)
    sin = torch.sin(yaw).to(dtype).view(-1, 1, 1)
    ratio = grid.voxel_y / grid.voxel_x
    return (cu + cos * (u - cu) - sin * ratio * (v - cv) + du, cv + sin / ratio * (u - cu) + cos * (v - cv) + dv)


def align_bev(
    past_map: torch.Tensor, displacement_cells: torch.Tensor, yaw: torch.Tensor | None = None, *, grid: BevGrid
) -> torch.Tensor:
    """Export formulation: warp past maps [B, C, H=ny, W=nx] into the current frame.

    ``displacement_cells`` [B, 2] is the radar displacement past -> current in cells (dx/sx, dy/sy),
    ``yaw`` [B] the yaw change past -> current in rad (None: no rotation), both expressed in the
    past radar frame (module docstring). Returns the aligned maps [B, C, H, W]; cells whose source
    lies outside the past map blend towards zero (bilinear with zero padding).
    """
    _check_inputs(past_map, displacement_cells, yaw, grid)
    u, v = _index_map(displacement_cells, yaw, grid)
    # grid_sample, align_corners=False: pixel k of n spans normalised [2k/n - 1, 2(k+1)/n - 1].
    gx = (2.0 * u + 1.0) / grid.nx - 1.0  # width axis = x cells
    gy = (2.0 * v + 1.0) / grid.ny - 1.0  # height axis = y cells
    sample_grid = torch.stack(torch.broadcast_tensors(gx, gy), -1).to(past_map.dtype)
    return F.grid_sample(past_map, sample_grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def bilinear_sample_reference(image: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``image`` [B, C, H, W] at continuous pixel coordinates [B, Q] -> [B, C, Q].

    Pixel (r, c) has its centre at integer (r, c). Each sample blends its four neighbouring
    pixels (floor/floor+1 on both axes) with the usual bilinear weights; a neighbour outside the
    image contributes zero. Computed in float64 and returned in ``image``'s dtype.
    """
    b, c, h, w = image.shape
    flat = image.double().reshape(b, c, h * w)
    rows, cols = rows.double(), cols.double()
    r0, c0 = torch.floor(rows), torch.floor(cols)
    fr, fc = rows - r0, cols - c0
    out = torch.zeros(b, c, rows.shape[1], dtype=torch.float64)
    for dr, wr in ((0, 1.0 - fr), (1, fr)):
        for dc, wc in ((0, 1.0 - fc), (1, fc)):
            r, col = (r0 + dr).long(), (c0 + dc).long()
            inside = (r >= 0) & (r < h) & (col >= 0) & (col < w)
            index = (r.clamp(0, h - 1) * w + col.clamp(0, w - 1)).unsqueeze(1).expand(b, c, -1)
            weight = torch.where(inside, wr * wc, torch.zeros_like(wr)).unsqueeze(1)
            out += weight * torch.gather(flat, 2, index)
    return out.to(image.dtype)


def align_bev_reference(
    past_map: torch.Tensor, displacement_cells: torch.Tensor, yaw: torch.Tensor | None = None, *, grid: BevGrid
) -> torch.Tensor:
    """Reference formulation of :func:`align_bev`, derived in metres and sampled explicitly.

    For every current cell centre p (m): p_past = R(yaw) p + d with d = ``displacement_cells``
    times the cell size, then the past map is sampled bilinearly at p_past's continuous cell
    coordinates (float64 throughout).
    """
    _check_inputs(past_map, displacement_cells, yaw, grid)
    b = past_map.shape[0]
    x = grid.x_min + (torch.arange(grid.nx, dtype=torch.float64) + 0.5) * grid.voxel_x
    y = grid.y_min + (torch.arange(grid.ny, dtype=torch.float64) + 0.5) * grid.voxel_y
    py, px = (t.reshape(1, -1) for t in torch.meshgrid(y, x, indexing="ij"))  # [1, H*W]
    d = displacement_cells.double() * torch.tensor([grid.voxel_x, grid.voxel_y], dtype=torch.float64)
    psi = torch.zeros(b, dtype=torch.float64) if yaw is None else yaw.double()
    cos, sin = torch.cos(psi).unsqueeze(1), torch.sin(psi).unsqueeze(1)
    past_x = cos * px - sin * py + d[:, :1]
    past_y = sin * px + cos * py + d[:, 1:]
    rows = (past_y - grid.y_min) / grid.voxel_y - 0.5
    cols = (past_x - grid.x_min) / grid.voxel_x - 0.5
    out = bilinear_sample_reference(past_map, rows, cols)
    return out.reshape(past_map.shape)
