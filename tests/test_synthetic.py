"""Synthetic radar scenes: determinism, Doppler physics, FOV, counts, sequences, file layouts, config errors."""

import subprocess
import sys

import numpy as np
import pytest

from radaredge.config import config_from_dict
from radaredge.data.readers import TJ4D_COLUMNS, VOD_COLUMNS, read_tj4d_bin, read_vod_bin
from radaredge.data.synthetic import (
    CLASS_NAMES,
    COLUMNS,
    RadarScan,
    SceneConfig,
    generate_scan,
    generate_sequence,
    write_tj4d_bin,
    write_vod_bin,
)
from radaredge.errors import ConfigError, InputError

SEEDS = range(6)
NOISE = SceneConfig().doppler_noise


def unit(xyz):
    xyz = np.asarray(xyz, dtype=np.float64)
    return xyz / np.linalg.norm(xyz, axis=1, keepdims=True)


def static_residual(scan: RadarScan) -> np.ndarray:
    """v_r + r̂·v_ego per point (m/s): 0 up to Doppler noise for points on the static world."""
    return scan.column("v_r") + unit(scan.points[:, :3]) @ scan.ego_velocity


def assert_same(a: RadarScan, b: RadarScan):
    for name, value in vars(a).items():
        np.testing.assert_array_equal(value, getattr(b, name), err_msg=name)


def test_scan_layout_and_dtypes():
    scan = generate_scan(seed=0)
    n, m = len(scan.points), len(scan.boxes)
    assert COLUMNS == ("x", "y", "z", "v_r", "rcs")
    assert scan.points.dtype == np.float32 and scan.points.shape == (n, 5)
    for mask in (scan.dynamic, scan.ghost):
        assert mask.dtype == bool and mask.shape == (n,)
    assert not (scan.dynamic & scan.ghost).any()
    assert scan.object_index.shape == (n,) and scan.object_index.min() >= -1 and scan.object_index.max() < m
    assert (scan.object_index[scan.ghost] == -1).all() and (scan.object_index[scan.dynamic] >= 0).all()
    assert scan.boxes.dtype == np.float32 and scan.boxes.shape == (m, 7)
    assert scan.box_velocities.shape == (m, 3) and scan.box_dynamic.shape == (m,)
    assert set(scan.box_labels.tolist()) <= set(range(len(CLASS_NAMES)))
    np.testing.assert_array_equal(
        scan.box_num_points, np.bincount(scan.object_index[scan.object_index >= 0], minlength=m)
    )
    assert scan.ego_velocity.shape == (3,) and scan.pose.shape == (4, 4) and scan.timestamp == 0.0
    np.testing.assert_allclose(scan.pose[:3, :3] @ scan.pose[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_array_equal(scan.column("v_r"), scan.points[:, 3])
    with pytest.raises(InputError, match="v_x"):
        scan.column("v_x")


def test_same_seed_same_scene_and_other_seed_another():
    assert_same(generate_scan(seed=5), generate_scan(seed=5))
    assert_same(generate_scan(SceneConfig(seed=5)), generate_sequence(3, seed=5)[0])
    for a, b in zip(generate_sequence(3, seed=5), generate_sequence(3, seed=5)):
        assert_same(a, b)
    a, b = generate_scan(seed=5), generate_scan(seed=6)
    assert a.points.shape != b.points.shape or not np.array_equal(a.points, b.points)
    assert not np.allclose(a.ego_velocity, b.ego_velocity)


@pytest.mark.parametrize("seed", SEEDS)
def test_static_points_are_consistent_with_ego_velocity(seed):
    scan = generate_scan(seed=seed, dynamic_fraction=0.3)
    static = ~scan.dynamic & ~scan.ghost
    assert static.sum() > 100
    assert np.abs(static_residual(scan)[static]).max() < 5 * NOISE
    assert abs(static_residual(scan)[static].std() - NOISE) < 0.3 * NOISE


@pytest.mark.parametrize("seed", SEEDS)
def test_dynamic_points_follow_their_box_velocity(seed):
    scan = generate_scan(seed=seed, dynamic_fraction=0.3)
    dyn = scan.dynamic
    assert dyn.sum() > 50
    rows = scan.object_index[dyn]
    assert scan.box_dynamic[rows].all()
    expected = np.einsum("ij,ij->i", unit(scan.points[dyn, :3]), scan.box_velocities[rows] - scan.ego_velocity)
    assert np.abs(scan.column("v_r")[dyn] - expected).max() < 5 * NOISE + 1e-4
    # ... and they really move: most are far from the static-world relation
    assert np.median(np.abs(static_residual(scan)[dyn])) > 1.0
    # points lie on (the noisy surface of) their box
    box = scan.boxes[rows]
    local = scan.points[dyn, :2] - box[:, :2]
    c, s = np.cos(box[:, 6]), np.sin(box[:, 6])
    along, across = c * local[:, 0] + s * local[:, 1], -s * local[:, 0] + c * local[:, 1]
    assert (np.abs(along) <= box[:, 3] / 2 + 0.5).all() and (np.abs(across) <= box[:, 4] / 2 + 0.5).all()


def test_parked_cars_are_static_boxes_with_zero_velocity():
    scans = [generate_scan(seed=s) for s in SEEDS]
    parked = np.concatenate([s.box_velocities[~s.box_dynamic] for s in scans])
    assert len(parked) > 0 and np.all(parked == 0)
    moving = np.concatenate([s.box_velocities[s.box_dynamic] for s in scans])
    assert np.linalg.norm(moving, axis=1).min() > 0.5


@pytest.mark.parametrize("seed", SEEDS)
def test_ghosts_are_flagged_and_inconsistent_with_the_static_world(seed):
    scan = generate_scan(seed=seed)
    assert 0 < scan.ghost.sum() < 0.08 * len(scan.points)
    assert np.abs(static_residual(scan)[scan.ghost]).min() > 0.5 - 5 * NOISE
    assert generate_scan(seed=seed, ghost_fraction=0.0).ghost.sum() == 0


@pytest.mark.parametrize(
    "fov", [{}, {"max_range": 40.0, "max_azimuth_deg": 45.0, "max_elevation_deg": 10.0, "min_range": 3.0}]
)
def test_all_points_and_listed_box_centres_are_inside_the_fov(fov):
    config = SceneConfig(**fov)
    for seed in SEEDS:
        scan = generate_scan(config, seed=seed)
        xyz = scan.points[:, :3].astype(np.float64)
        r = np.linalg.norm(xyz, axis=1)
        azimuth = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
        elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
        eps = 1e-3
        assert r.min() >= config.min_range - eps and r.max() <= config.max_range + eps
        assert np.abs(azimuth).max() <= config.max_azimuth_deg + eps
        assert np.abs(elevation).max() <= config.max_elevation_deg + eps
        empty = scan.box_num_points == 0  # boxes without points are listed because their centre is in view
        assert (np.linalg.norm(scan.boxes[empty, :3], axis=1) <= config.max_range + eps).all()


def test_point_count_is_a_sparse_radar_scan():
    counts = [len(s.points) for seed in range(4) for s in generate_sequence(3, seed=seed)]
    assert 150 <= min(counts) and max(counts) <= 600


@pytest.mark.parametrize("fraction, low, high", [(0.0, 0.0, 0.0), (0.2, 0.13, 0.27), (0.4, 0.3, 0.5)])
def test_dynamic_fraction_is_honoured(fraction, low, high):
    for seed in SEEDS:
        scan = generate_scan(seed=seed, dynamic_fraction=fraction)
        share = scan.dynamic.mean()
        assert low <= share <= high, f"seed {seed}: dynamic share {share:.3f} for dynamic_fraction={fraction}"


def test_sequence_timestamps_poses_and_velocities_agree():
    rate = 10.0
    seq = generate_sequence(20, seed=3, frame_rate=rate, max_yaw_rate=0.05)
    dt = 1.0 / rate
    np.testing.assert_allclose([s.timestamp for s in seq], np.arange(20) / rate)
    np.testing.assert_allclose(seq[0].pose[:3, 3], [0.0, 0.0, SceneConfig().mount_height], atol=1e-9)
    for a, b in zip(seq, seq[1:]):
        np.testing.assert_array_equal(a.ego_velocity, b.ego_velocity)
        step = a.pose[:3, :3].T @ (b.pose[:3, 3] - a.pose[:3, 3])  # displacement in a's radar frame
        np.testing.assert_allclose(step, a.ego_velocity * dt, atol=0.02)
        yaw = lambda p: np.arctan2(p[1, 0], p[0, 0])  # noqa: E731
        assert abs(yaw(b.pose) - yaw(a.pose) - a.yaw_rate * dt) < 1e-9


def test_static_world_is_the_same_in_every_frame():
    """Parked cars seen from different frames sit at the same world position."""
    seq = generate_sequence(30, seed=2)
    centres = np.concatenate(
        [(s.pose[:3, :3] @ s.boxes[~s.box_dynamic, :3].T.astype(np.float64)).T + s.pose[:3, 3] for s in seq]
    )
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    assert ((d < 1e-3) | (d > 1.0)).all()
    assert ((d < 1e-3).sum(1) > 1).mean() > 0.9  # nearly every parked car is seen more than once


def test_frame_does_not_depend_on_sequence_length():
    assert_same(generate_sequence(8, seed=1)[5], generate_sequence(6, seed=1)[5])


def test_robust_estimator_recovers_ego_velocity():
    from radaredge.ops.ego_velocity import estimate_ego_velocity_reference

    for seed in SEEDS:
        scan = generate_scan(seed=seed, dynamic_fraction=0.4)
        v, static, ok = estimate_ego_velocity_reference(scan.points[:, :3], scan.column("v_r"))
        assert ok
        assert np.linalg.norm(v - scan.ego_velocity) < 0.1
        assert ((~static) == (scan.dynamic | scan.ghost)).mean() > 0.97


def test_vod_file_round_trip(tmp_path):
    scan = generate_scan(seed=4)
    path = write_vod_bin(tmp_path / "00000.bin", scan)
    assert path.stat().st_size == len(scan.points) * 7 * 4
    table = read_vod_bin(path)
    assert table.dtype == np.float32 and table.shape == (len(scan.points), len(VOD_COLUMNS))
    col = {name: table[:, i] for i, name in enumerate(VOD_COLUMNS)}
    for name in ("x", "y", "z", "v_r", "rcs"):
        np.testing.assert_array_equal(col[name], scan.column(name))
    static = ~scan.dynamic & ~scan.ghost
    assert np.abs(col["v_r_compensated"][static]).max() < 5 * NOISE
    assert np.abs(col["v_r_compensated"][scan.dynamic]).max() > 1.0
    assert (col["time"] == 0).all()
    # the layout is plain little-endian float32 rows of 7
    np.testing.assert_array_equal(np.fromfile(path, dtype="<f4").reshape(-1, 7), table)


def test_tj4d_file_round_trip(tmp_path):
    scan = generate_scan(seed=4)
    table = read_tj4d_bin(write_tj4d_bin(tmp_path / "000000.bin", scan))
    assert table.dtype == np.float32 and table.shape == (len(scan.points), len(TJ4D_COLUMNS))
    col = {name: table[:, i].astype(np.float64) for i, name in enumerate(TJ4D_COLUMNS)}
    xyz = scan.points[:, :3].astype(np.float64)
    np.testing.assert_array_equal(table[:, :3], scan.points[:, :3])
    np.testing.assert_array_equal(col["V_r"], scan.column("v_r"))
    np.testing.assert_allclose(col["Range"], np.linalg.norm(xyz, axis=1), rtol=1e-6)
    np.testing.assert_array_equal(col["Power"], scan.column("rcs"))
    np.testing.assert_allclose(col["Alpha"], np.arctan2(xyz[:, 1], xyz[:, 0]), atol=1e-6)
    np.testing.assert_allclose(col["Beta"], np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])), atol=1e-6)


def test_readers_reject_truncated_or_missing_files(tmp_path):
    path = tmp_path / "bad.bin"
    np.zeros(10, dtype="<f4").tofile(path)
    with pytest.raises(InputError, match="7 float32 columns"):
        read_vod_bin(path)
    with pytest.raises(InputError, match="8 float32 columns"):
        read_tj4d_bin(path)
    with pytest.raises(InputError, match="no such"):
        read_vod_bin(tmp_path / "missing.bin")


@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"frame_rate": -10.0}, "frame_rate"),
        ({"frame_rate": 0}, "frame_rate"),
        ({"dynamic_fraction": 0.95}, "dynamic_fraction"),
        ({"dynamic_fraction": -0.1}, "dynamic_fraction"),
        ({"doppler_noise": -0.01}, "doppler_noise"),
        ({"ghost_fraction": 0.7}, "ghost_fraction"),
        ({"static_points": -5}, "static_points"),
        ({"num_cars": 2.5}, "num_cars"),
        ({"max_azimuth_deg": 120.0}, "max_azimuth_deg"),
        ({"max_range": 0.5}, "min_range"),
        ({"ego_speed_min": 10.0, "ego_speed_max": 5.0}, "ego_speed_min"),
        ({"frame_rate": "fast"}, "frame_rate"),
        ({"seed": -1}, "seed"),
        ({"rcs_dbsm": {"tree": (0.0, 1.0)}}, "rcs_dbsm"),
        ({"rcs_dbsm": {"car": (8.0, -1.0)}}, "rcs_dbsm.car"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_bad_config_raises_config_error_naming_the_field(overrides, field):
    with pytest.raises(ConfigError, match=field):
        generate_scan(**overrides)


def test_config_sources():
    with pytest.raises(ConfigError, match="dynamic_fraction"):
        SceneConfig(dynamic_fraction=1.0)
    with pytest.raises(ConfigError, match="n_frames"):
        generate_sequence(0)
    config = config_from_dict(SceneConfig, {"dynamic_fraction": 0.2, "rcs_dbsm": {"car": [10, 3]}}, "demo.yaml: scene")
    assert config.rcs_dbsm["car"] == (10.0, 3.0) and config.rcs_dbsm["wall"] == SceneConfig().rcs_dbsm["wall"]
    with pytest.raises(ConfigError, match="demo.yaml: scene.*dynamic_fraction"):
        config_from_dict(SceneConfig, {"dynamic_fraction": 2.0}, "demo.yaml: scene")


def test_module_needs_only_numpy():
    code = "import sys, radaredge.data.synthetic; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
