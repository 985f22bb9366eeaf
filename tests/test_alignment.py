"""Trajectory-guided BEV alignment (TDFANet eq. 4-5): grid_sample path == explicit bilinear
reference, exact integer shifts, the sign convention on a moving blob, ONNX round trip."""

import numpy as np
import pytest
import torch
from conftest import assert_close
from torch import nn

from radaredge.errors import ConfigError, InputError
from radaredge.ops.alignment import BevGrid, align_bev, align_bev_reference, grid_displacement

SMALL = BevGrid(x_min=0.0, y_min=-8.0, voxel_x=0.5, voxel_y=0.25, nx=24, ny=40)  # non-square cells
PAPER = BevGrid.from_range((0.0, -39.68, -3.0, 69.12, 39.68, 10.0), (0.32, 0.32, 13.0))


def random_case(grid, batch, seed):
    g = torch.Generator().manual_seed(seed)
    past = torch.rand(batch, 3, *grid.shape, generator=g)
    cells = (torch.rand(batch, 2, generator=g) - 0.5) * 12.0
    yaw = (torch.rand(batch, generator=g) - 0.5) * 0.6
    return past, cells, yaw


def render_blob(grid, centre, sigma=1.0):
    """[1, 1, H, W] Gaussian of peak 1 at ``centre`` (x, y) m, evaluated at the cell centres."""
    x = grid.x_min + (np.arange(grid.nx) + 0.5) * grid.voxel_x
    y = grid.y_min + (np.arange(grid.ny) + 0.5) * grid.voxel_y
    r2 = (x[None, :] - centre[0]) ** 2 + (y[:, None] - centre[1]) ** 2  # [ny, nx]
    return torch.from_numpy(np.exp(-0.5 * r2 / sigma**2)).float()[None, None]


def test_paper_grid_is_216_by_248():
    assert (PAPER.nx, PAPER.ny) == (216, 248) and PAPER.shape == (248, 216)  # maps are [C, ny, nx]
    assert PAPER.origin_cells() == pytest.approx((-0.5, 123.5))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_yaw", [False, True])
def test_export_matches_reference(seed, with_yaw):
    past, cells, yaw = random_case(SMALL, 3, seed)
    yaw = yaw if with_yaw else None
    got = align_bev(past, cells, yaw, grid=SMALL)
    assert_close(got, align_bev_reference(past, cells, yaw, grid=SMALL), 1e-5, "align_bev vs reference")


def test_export_matches_reference_on_paper_grid():
    # grid_sample works in float32 normalised coordinates; on a 248-cell axis that resolves a
    # position to ~2^-24 * 2 * 248 ~ 3e-5 cells, so values in [0, 1) agree to ~3e-5, not 1e-5.
    past, cells, yaw = random_case(PAPER, 2, 5)
    got = align_bev(past, cells, yaw, grid=PAPER)
    assert_close(got, align_bev_reference(past, cells, yaw, grid=PAPER), 1e-4, "paper grid")


@pytest.mark.parametrize("shift", [(3, -2), (-5, 7), (0, 0), (30, 0)])
def test_integer_shift_is_a_roll_with_zero_fill(shift):
    past, _, _ = random_case(SMALL, 1, 3)
    di, dj = shift  # cells along x (columns) and y (rows)
    expected = torch.zeros_like(past)
    h, w = SMALL.shape
    for row in range(h):
        for col in range(w):
            if 0 <= row + dj < h and 0 <= col + di < w:
                expected[..., row, col] = past[..., row + dj, col + di]
    cells = torch.tensor([[float(di), float(dj)]])
    assert torch.equal(align_bev_reference(past, cells, grid=SMALL), expected)
    assert_close(align_bev(past, cells, grid=SMALL), expected, 1e-6, "grid_sample roll")


def test_grid_displacement_follows_eq_4_and_5():
    v = torch.tensor([[10.0, 1.0, 0.3], [8.0, -2.0, 0.0], [5.0, 0.0, 0.0]])
    by_rate = grid_displacement(v, (0.5, 0.25), frame_interval=0.1)
    # frame 0 -> 2: (10 + 8) * 0.1 m = 1.8 m = 3.6 cells in x; (1 - 2) * 0.1 m = -0.4 cells in y
    expected = torch.tensor([[3.6, -0.4], [1.6, -0.8], [0.0, 0.0]])
    torch.testing.assert_close(by_rate, expected)
    by_time = grid_displacement(v, (0.5, 0.25), timestamps=torch.tensor([0.0, 0.2, 0.25], dtype=torch.float64))
    torch.testing.assert_close(by_time, torch.tensor([[4.8, 0.4], [0.8, -0.4], [0.0, 0.0]]))


def test_grid_displacement_needs_one_time_base():
    v = torch.zeros(3, 3)
    with pytest.raises(ConfigError):
        grid_displacement(v, (0.5, 0.5))
    with pytest.raises(ConfigError):
        grid_displacement(v, (0.5, 0.5), frame_interval=0.1, timestamps=torch.zeros(3))


def test_static_blob_from_ego_velocity_lands_where_current_map_has_it():
    grid = BevGrid(0.0, -8.0, 0.25, 0.25, 96, 64)
    v_ego = torch.tensor([[9.0, 2.0, 0.0], [11.0, 1.0, 0.0], [0.0, 0.0, 0.0]])  # m/s; last unused
    cells = grid_displacement(v_ego, (grid.voxel_x, grid.voxel_y), frame_interval=0.1)
    d = (cells[0] * 0.25).numpy()  # (2.0, 0.3) m
    current_blob = np.array([9.125, 1.375])  # a current cell centre
    past = render_blob(grid, current_blob + d)  # the radar drove forward
    current = render_blob(grid, current_blob)
    for align in (align_bev, align_bev_reference):
        aligned = align(past, cells[:1], grid=grid)
        assert aligned.argmax() == current.argmax()
        assert_close(aligned, current, 0.02, f"{align.__name__} blob")
    wrong_sign = align_bev(past, -cells[:1], grid=grid)
    assert (wrong_sign - current).abs().max() > 0.9


def test_static_blob_with_yaw_rotates_about_the_radar_origin():
    grid = BevGrid(0.0, -10.0, 0.25, 0.5, 96, 40)  # anisotropic cells
    d, psi = np.array([1.2, -0.5]), 0.15  # m, rad (turned left)
    world = np.array([14.1, 3.3])  # blob in the past frame
    rot = np.array([[np.cos(psi), -np.sin(psi)], [np.sin(psi), np.cos(psi)]])
    current_blob = rot.T @ (world - d)  # p = R^T (p_past - d)
    past, current = render_blob(grid, world), render_blob(grid, current_blob)
    cells = torch.tensor([[d[0] / grid.voxel_x, d[1] / grid.voxel_y]], dtype=torch.float32)
    yaw = torch.tensor([psi], dtype=torch.float32)
    for align in (align_bev, align_bev_reference):
        assert_close(align(past, cells, yaw, grid=grid), current, 0.04, f"{align.__name__} yaw blob")
    assert (align_bev(past, cells, -yaw, grid=grid) - current).abs().max() > 0.5


def test_transposed_map_is_rejected_with_the_expected_layout():
    canvas = torch.zeros(1, 3, SMALL.nx, SMALL.ny)
    with pytest.raises(InputError, match=r"H=ny, W=nx"):
        align_bev(canvas, torch.zeros(1, 2), grid=SMALL)
    with pytest.raises(InputError, match="displacement_cells"):
        align_bev(torch.zeros(2, 3, *SMALL.shape), torch.zeros(1, 2), grid=SMALL)


class Align(nn.Module):
    def __init__(self, grid):
        super().__init__()
        self.grid = grid

    def forward(self, past_map, displacement_cells, yaw):
        return align_bev(past_map, displacement_cells, yaw, grid=self.grid)


def test_onnx_export_with_displacement_and_yaw_as_inputs(onnx_roundtrip):
    past, cells, yaw = random_case(SMALL, 2, 0)
    example = {"past_map": past, "displacement_cells": cells, "yaw": yaw}
    batch = {0: "B"}
    rt = onnx_roundtrip(
        Align(SMALL), example, ["aligned"], {"past_map": batch, "displacement_cells": batch, "yaw": batch}
    )
    for b, seed in [(2, 1), (4, 2), (1, 3)]:
        past, cells, yaw = random_case(SMALL, b, seed)
        ref, got = rt({"past_map": past, "displacement_cells": cells, "yaw": yaw})
        assert_close(got["aligned"], ref["aligned"], 1e-5, "onnxruntime vs torch")
