"""GridDensityBEV: export formulation == plain reference; agreement with CQCA_cfa's DBSCAN; ONNX."""

import numpy as np
import pytest
import torch
from sklearn.metrics import adjusted_rand_score

from radaredge.config import config_from_dict
from radaredge.errors import ConfigError
from radaredge.ops.grid_density import GridDensityBEV, GridDensityConfig, grid_density_bev_reference
from tests.conftest import assert_close
from tests.references.dbscan_cfa import dbscan_cfa_labels

VOD = GridDensityConfig()
WHERE = "maffnet-vod.yaml: image_backbone"


def radar_scan(seed: int, clutter: int = 150):
    """Radar-like scan in the VoD grid: 3 cars (60-80 points), 3 pedestrians (30-50), sparse clutter.

    Returns (points [N, 3] float32 as x, y in m and v_r_comp in m/s, object id per point, -1 = clutter).
    Objects are >= 5 m apart so that neither method should merge them.
    """
    rng = np.random.default_rng(seed)
    centres: list[np.ndarray] = []
    while len(centres) < 6:
        c = rng.uniform([3.0, -22.0], [48.0, 22.0])
        if all(np.hypot(*(c - d)) > 5.0 for d in centres):
            centres.append(c)
    points, ids = [], []
    for k, centre in enumerate(centres):
        car = k < 3
        n = int(rng.integers(60, 81) if car else rng.integers(30, 51))
        sigma = np.array([0.6, 0.3]) if car else np.array([0.15, 0.15])
        angle = rng.uniform(0.0, np.pi)
        rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        xy = centre + (rng.normal(0.0, 1.0, (n, 2)) * sigma) @ rot.T
        v = rng.uniform(-10.0, 10.0) + rng.normal(0.0, 0.2, n)
        points.append(np.c_[xy, v])
        ids += [k] * n
    points.append(np.c_[rng.uniform([0.0, -25.6], [51.2, 25.6], (clutter, 2)), rng.normal(0.0, 3.0, clutter)])
    ids += [-1] * clutter
    return np.concatenate(points).astype(np.float32), np.array(ids)


def hostile_scan(seed: int):
    """A radar scan plus points the contract must drop: outside the grid, NaN/Inf, invalid, on cell edges."""
    points, _ = radar_scan(seed)
    rng = np.random.default_rng(seed + 100)
    outside = np.array(
        [
            [-0.01, 0.0, 1.0],
            [51.2, 0.0, 1.0],
            [60.0, 3.0, 1.0],
            [10.0, 25.6, 1.0],
            [10.0, -25.61, 1.0],
            [1e30, -1e30, 2.0],
        ],
        np.float32,
    )
    blob_outside = np.c_[rng.normal(-0.5, 0.1, (20, 1)), rng.normal(5.0, 0.1, (20, 1)), np.ones((20, 1))]
    bad = np.array([[np.nan, 1.0, 0.0], [5.0, np.inf, 0.0], [5.0, 1.0, -np.inf]], np.float32)
    edges = np.c_[np.float32(0.16) * np.arange(40, 52), np.full(12, -25.6), np.linspace(-1, 1, 12)]
    ridge = np.c_[
        np.float32(0.16) * rng.integers(100, 110, (30, 1)),
        np.float32(0.16) * rng.integers(150, 160, (30, 1)),
        rng.normal(3.0, 0.5, (30, 1)),
    ]  # points exactly on cell corners
    points = np.concatenate([points, outside, blob_outside, bad, edges, ridge]).astype(np.float32)
    valid = rng.random(len(points)) > 0.05
    return points, valid


def run(module, points, valid=None):
    valid = np.ones(len(points), bool) if valid is None else valid
    with torch.no_grad():
        bev, mask, converged = module(torch.from_numpy(points), torch.from_numpy(valid))
    return bev.numpy(), mask.numpy(), bool(converged)


def point_clusters(points, bev, mask, config=VOD):
    """Cluster id per point from the label channel (its cell's component), -1 for noise."""
    res = np.float32(config.resolution)
    ix = np.floor((points[:, 0] - np.float32(config.x_min)) / res).astype(np.int64).clip(0, config.map_w - 1)
    iy = np.floor((points[:, 1] - np.float32(config.y_min)) / res).astype(np.int64).clip(0, config.map_h - 1)
    _, ids = np.unique(bev[2][iy, ix], return_inverse=True)
    return np.where(mask, ids, -1)


def guardrail():
    """A 15 m dense line of points along x: one component ~95 cells long."""
    x = np.repeat(np.arange(5.0, 20.0, 0.05), 2)
    return np.c_[x, np.full_like(x, 3.0), np.zeros_like(x)].astype(np.float32)


# ----------------------------------------------------------------------------- config


def test_config_from_model_card():
    cfg = config_from_dict(GridDensityConfig, {"map_h": 160, "cc_mode": "exact", "min_density": 8}, WHERE)
    assert (cfg.map_h, cfg.map_w, cfg.cc_mode, cfg.min_density) == (160, 320, "exact", 8)
    assert VOD.kernel_size == 5  # eps 0.4 / 0.16 = 2.5 -> round 2
    assert GridDensityConfig(eps=0.32).kernel_size == 5
    assert GridDensityConfig(eps=0.05).kernel_size == 3
    for bad in ({"cc_mode": "bfs"}, {"resolution": -0.1}, {"min_density": 200}, {"radius": 1.0}):
        with pytest.raises(ConfigError, match="image_backbone"):
            config_from_dict(GridDensityConfig, bad, WHERE)


# ----------------------------------------------------------------------------- semantics


def test_min_density_threshold_and_channels():
    """10 points in one cell make its 5 x 5 window one cluster; 9 points are noise."""
    cell = np.array([10 * 0.16 + 0.08, -25.6 + 20 * 0.16 + 0.08], np.float32)  # centre of (iy 20, ix 10)
    v = np.arange(10, dtype=np.float32)
    points = np.c_[np.repeat(cell[None], 10, 0), v].astype(np.float32)
    bev, mask, converged = run(GridDensityBEV(VOD), points)
    assert mask.all() and converged
    window = np.zeros((VOD.map_h, VOD.map_w), bool)
    window[18:23, 8:13] = True
    np.testing.assert_array_equal(bev[1] > 0, window)
    np.testing.assert_allclose(bev[0][20, 10], v.mean(), atol=1e-6)
    assert bev[0][window].sum() == pytest.approx(v.mean())  # empty cells of the window hold 0 m/s
    np.testing.assert_array_equal(bev[1][window], 1.0)  # density 10 everywhere, / max
    np.testing.assert_array_equal(bev[2][window], 1.0)  # the only component, / its own id
    bev, mask, _ = run(GridDensityBEV(VOD), points[:9])
    assert not mask.any() and not bev.any()


def test_max_density_marks_crowds_as_noise():
    points = np.tile(np.array([[20.0, 0.0, 1.0]], np.float32), (101, 1))
    bev, mask, _ = run(GridDensityBEV(VOD), points)
    assert not mask.any() and not bev.any()
    bev, mask, _ = run(GridDensityBEV(VOD), points[:100])
    assert mask.all()


def test_outside_and_non_finite_points_are_dropped_not_wrapped():
    points, _ = radar_scan(3)
    base = run(GridDensityBEV(VOD), points)
    hostile, _ = hostile_scan(3)
    extra = hostile[len(points) :]
    outside = extra[:29]  # outside rows, outside blob, NaN/Inf rows
    bev, mask, _ = run(GridDensityBEV(VOD), np.concatenate([points, outside]))
    np.testing.assert_array_equal(bev, base[0])
    np.testing.assert_array_equal(mask[: len(points)], base[1])
    assert not mask[len(points) :].any()


def test_empty_scan():
    for cfg in (VOD, GridDensityConfig(cc_mode="exact")):
        bev, mask, converged = run(GridDensityBEV(cfg), np.zeros((0, 3), np.float32))
        assert bev.shape == (3, 320, 320) and not bev.any()
        assert mask.shape == (0,) and converged


def test_maxpool_mode_reports_a_long_cluster_unconverged():
    points = guardrail()
    bev_max, mask_max, conv_max = run(GridDensityBEV(VOD), points)
    bev_exact, mask_exact, conv_exact = run(GridDensityBEV(GridDensityConfig(cc_mode="exact")), points)
    assert conv_exact and not conv_max
    np.testing.assert_array_equal(mask_max, mask_exact)
    assert len(np.unique(bev_exact[2][bev_exact[2] > 0])) == 1
    assert len(np.unique(bev_max[2][bev_max[2] > 0])) > 1  # the fork's labels split the rail


# ----------------------------------------------------------------------------- reference


@pytest.mark.parametrize("mode", ["maxpool", "exact"])
@pytest.mark.parametrize("scan", ["radar_0", "radar_1", "hostile_2", "hostile_5", "guardrail"])
def test_export_formulation_matches_reference(mode, scan):
    if scan == "guardrail":
        points, valid = guardrail(), None
    elif scan.startswith("radar"):
        points, valid = radar_scan(int(scan[-1]))[0], None
    else:
        points, valid = hostile_scan(int(scan[-1]))
    valid = np.ones(len(points), bool) if valid is None else valid
    cfg = GridDensityConfig(cc_mode=mode)
    bev, mask, converged = run(GridDensityBEV(cfg), points, valid)
    ref_bev, ref_mask, ref_converged = grid_density_bev_reference(points, valid, cfg)
    assert_close(bev, ref_bev, 1e-5, "bev")
    np.testing.assert_array_equal(bev[2], ref_bev[2])
    np.testing.assert_array_equal(mask, ref_mask)
    assert converged == ref_converged


# ----------------------------------------------------------------------------- DBSCAN (CQCA_cfa)


@pytest.mark.parametrize("mode", ["maxpool", "exact"])
def test_clusters_agree_with_dbscan(mode):
    """Adjusted Rand index between GridDensityBEV's point clusters and CQCA_cfa's DBSCAN.

    Noise is one class in both labelings. On these scans the objects map one-to-one between the
    two methods (checked below); they disagree only at cluster borders, where a 5 x 5 window of
    0.16 m cells (0.64 m^2, quantised to the cell) replaces DBSCAN's 0.4 m disk (0.50 m^2) and
    its border-point rule: about 4-7 % of the points flip between noise and cluster, which
    alone puts the ARI near 0.8 (we measured 0.79-0.89). The floor 0.7 allows roughly twice that
    border loss and fails on a broken noise rule, label channel or cell mapping.
    """
    module = GridDensityBEV(GridDensityConfig(cc_mode=mode))
    scores = []
    for seed in range(8):
        points, _ = radar_scan(seed)
        bev, mask, converged = run(module, points)
        grid = point_clusters(points, bev, mask)
        dbscan = dbscan_cfa_labels(points)
        both = (grid >= 0) & (dbscan >= 0)
        pairs = np.unique(np.c_[dbscan[both], grid[both]], axis=0)
        assert len(pairs) == len(np.unique(dbscan[dbscan >= 0])) == len(np.unique(grid[grid >= 0])) == 6
        score = adjusted_rand_score(dbscan, grid)
        upstream = adjusted_rand_score(dbscan_cfa_labels(points, with_velocity=True), grid)
        print(
            f"{mode} seed {seed}: ARI vs DBSCAN(x, y) {score:.3f}, vs DBSCAN(x, y, v) {upstream:.3f}, "
            f"converged {converged}"
        )
        scores.append(score)
    print(f"{mode}: ARI min {min(scores):.3f} mean {np.mean(scores):.3f}")
    assert min(scores) >= 0.7


# ----------------------------------------------------------------------------- ONNX


@pytest.mark.parametrize("mode", ["maxpool", "exact"])
def test_onnx_export_dynamic_n(onnx_roundtrip, mode):
    points, valid = hostile_scan(0)
    example = {"points_xyv": torch.from_numpy(points), "valid": torch.from_numpy(valid)}
    rt = onnx_roundtrip(
        GridDensityBEV(GridDensityConfig(cc_mode=mode)),
        example,
        ["bev", "point_mask", "converged"],
        {"points_xyv": {0: "num_points"}, "valid": {0: "num_points"}},
    )
    scans = [
        radar_scan(4)[0],
        hostile_scan(7)[0],
        guardrail(),
        radar_scan(1)[0][:1],
        radar_scan(1)[0][:3],
        np.zeros((0, 3), np.float32),
    ]
    for pts in scans:
        ref, got = rt({"points_xyv": torch.from_numpy(pts), "valid": torch.ones(len(pts), dtype=torch.bool)})
        assert_close(got["bev"], ref["bev"], 1e-5, f"bev (N={len(pts)})")
        np.testing.assert_array_equal(got["point_mask"], ref["point_mask"])
        np.testing.assert_array_equal(got["converged"], ref["converged"])
