"""The synthetic scenes' radar physics (radaredge.data.radar_physics) and the version-2 detection
set built on it: each effect against a plain formulation, and the scenes that use them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from radaredge.data import radar_physics as rp
from radaredge.data.detection_benchmark import PHYSICS_V2, make_detection_benchmark, split_drives
from radaredge.data.kitti_detection import VOD, DetectionSet
from radaredge.data.synthetic import generate_sequence, vod_table

CAR = [10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]


def _hidden_by_sampling(points, boxes, own, shrink, margin, steps=4000):
    """The path from the origin to each point, sampled finely, tested against each shrunk box in
    its own frame (the plain formulation of radar_physics.hidden_by_boxes)."""
    out = []
    for n, p in enumerate(points):
        t = np.linspace(0.0, 1.0 - margin / np.linalg.norm(p), steps)[:, None] * p
        hidden = False
        for m, b in enumerate(boxes):
            if own[n] == m:
                continue
            c, s = np.cos(-b[6]), np.sin(-b[6])
            d = t - b[:3]
            local = np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]])
            hidden |= bool((np.abs(local) <= shrink * np.asarray(b[3:6]) / 2).all(1).any())
        out.append(hidden)
    return np.array(out)


def test_line_of_sight_in_azimuth_and_elevation():
    boxes = np.array([CAR])
    points = np.array(
        [
            [20.0, 0.0, 0.0],  # behind the car: hidden
            [20.0, 5.0, 0.0],  # beside it (azimuth): seen
            [20.0, 0.0, 3.0],  # above its roof line (elevation): seen
            [20.0, 0.0, 1.0],  # just below it: hidden
            [5.0, 0.0, 0.0],  # in front of it: seen
            [11.0, 0.0, 0.0],
        ]
    )  # on the car itself: never hidden by its own box
    own = np.array([-1, -1, -1, -1, -1, 0])
    assert rp.hidden_by_boxes(points, boxes, own).tolist() == [True, False, False, True, False, False]


def test_line_of_sight_matches_sampling_the_path():
    rng = np.random.default_rng(0)
    boxes = np.column_stack(
        [
            rng.uniform(5, 30, 12),
            rng.uniform(-10, 10, 12),
            rng.uniform(-0.5, 0.5, 12),
            rng.uniform(0.5, 4.5, 12),
            rng.uniform(0.5, 2.0, 12),
            rng.uniform(1.0, 1.8, 12),
            rng.uniform(-np.pi, np.pi, 12),
        ]
    )
    points = np.column_stack([rng.uniform(2, 45, 300), rng.uniform(-20, 20, 300), rng.uniform(-1.5, 2.0, 300)])
    own = np.where(rng.random(300) < 0.2, rng.integers(0, 12, 300), -1)
    fast = rp.hidden_by_boxes(points, boxes, own)
    # decided the same way by boxes a hair smaller and larger: away from the edges, where sampling is exact
    inner = _hidden_by_sampling(points, boxes, own, rp.OCCLUDER_SHRINK * 0.98, rp.OCCLUSION_MARGIN)
    outer = _hidden_by_sampling(points, boxes, own, rp.OCCLUDER_SHRINK * 1.02, rp.OCCLUSION_MARGIN)
    clear = inner == outer
    assert clear.mean() > 0.9 and 20 < fast.sum() < 280
    np.testing.assert_array_equal(fast[clear], inner[clear])


def test_occluded_share_of_labels():
    alone = rp.occluded_share(np.array([CAR]))
    behind = rp.occluded_share(np.array([CAR, [20.0, 0.0, 0.0, 0.6, 0.6, 1.2, 0.0]]))
    half = rp.occluded_share(np.array([CAR, [20.0, 1.6, 0.0, 4.0, 2.0, 1.5, 0.0]]))
    assert alone.tolist() == [0.0] and behind[0] == 0.0 and behind[1] == 1.0
    assert 0.1 < half[1] < 0.9


def test_points_fall_with_range_and_depend_on_class_and_aspect():
    names = ["car", "car", "car", "pedestrian"]
    boxes = np.array(
        [
            CAR,
            [40.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
            [10.0, 0.0, 0.0, 4.0, 2.0, 1.5, np.pi / 2],
            [10.0, 0.0, 0.0, 0.6, 0.6, 1.7, 0.0],
        ]
    )
    rcs = np.array([8.0, 8.0, 8.0, -6.0])
    near, far, broadside, walker = rp.expected_object_points(boxes, names, rcs)
    assert near > 4 * far and broadside > 1.5 * near and near > walker > 3
    assert rp.detection_probability(-6.0, 40.0) < 0.2 < rp.detection_probability(-6.0, 15.0)


def test_elevation_noise_exceeds_azimuth_noise():
    rng = np.random.default_rng(1)
    xyz = np.tile([[30.0, 0.0, 0.0]], (4000, 1))
    noisy = rp.spherical_noise(rng, xyz, 0.05, np.radians(0.3), np.radians(1.0))
    assert 2.5 < noisy[:, 2].std() / noisy[:, 1].std() < 4.0
    assert abs(np.linalg.norm(noisy, axis=1).std() - 0.05) < 0.005


def test_micro_doppler_moves_limbs_and_wheels_only():
    rng = np.random.default_rng(2)
    names = ["pedestrian"] * 500 + ["cyclist"] * 500 + ["car"] * 100
    share = np.r_[np.linspace(0, 1, 500), np.linspace(0, 1, 500), np.linspace(0, 1, 100)]
    factor = rp.micro_doppler_factor(rng, names, share, 1.0)
    legs, torso = factor[:250], factor[250:500]
    wheels = factor[500 : 500 + 200]
    assert legs.min() < 0.2 and legs.max() > 1.8 and np.all(torso == 1.0)
    assert wheels.min() < 0.1 and wheels.max() > 1.9 and np.all(factor[1000:] == 1.0)


def test_occlusion_removes_the_shadowed_points():
    quiet = dict(
        position_noise=0.0, ghost_fraction=0.0, num_cars=10, num_pedestrians=6, num_cyclists=4, points_model="radar"
    )
    shares = {}
    for occlusion in (False, True):
        hidden = []
        for scan in generate_sequence(4, seed=4, occlusion=occlusion, **quiet):
            real = ~scan.ghost
            hidden.append(rp.hidden_by_boxes(scan.points[real, :3], scan.boxes, scan.object_index[real]).mean())
        shares[occlusion] = float(np.mean(hidden))
    assert shares[True] < 0.01 < shares[False]


def test_manoeuvres_and_mounting_stay_consistent():
    """Speeds change and some road users cross the road; with a mounting error, the ego velocity
    still explains every static point's Doppler (VoD's compensated velocity about 0)."""
    scans = generate_sequence(
        60,
        seed=6,
        road_curvature=0.0,
        doppler_noise=0.0,
        **{**PHYSICS_V2, "clutter_points": 0.0, "ghost_fraction": 0.0, "vru_crossing": 0.5},
        num_pedestrians=12,
        mount_pitch_deg=0.8,
        mount_roll_deg=-0.6,
        mount_yaw_deg=0.9,
    )
    first, last = scans[0], scans[-1]
    speed = [
        dict(zip(s.box_ids[s.box_dynamic].tolist(), np.linalg.norm(s.box_velocities[s.box_dynamic], axis=1)))
        for s in (first, last)
    ]
    both = set(speed[0]) & set(speed[1])
    assert both and max(abs(speed[0][i] - speed[1][i]) for i in both) > 0.3
    walkers = np.concatenate([s.box_velocities[(s.box_labels == 1)] for s in scans])
    assert (np.abs(walkers[:, 1]) > 2 * np.abs(walkers[:, 0])).any()  # crossing, not along the road
    table = vod_table(last)
    static = ~last.dynamic & ~last.ghost
    assert np.abs(table[static, 5]).max() < 0.05


def test_version_two_set(tmp_path):
    assert {k: len(v) for k, v in split_drives(40, 2).items()} == {"train": 16, "val": 4, "test": 20}
    out = tmp_path / "set"
    result = make_detection_benchmark(out, drives=4, frames=3, seed=3)
    doc = json.loads((out / "benchmark.json").read_text())
    assert doc["version"] == 2 and doc["frame_stride_scans"] == 5 and doc["physics"]["occlusion"] is True
    towns = [set(v) for v in doc["towns_per_split"].values()]
    assert sum(len(t) for t in towns) == len(set().union(*towns)) == 4  # no town in two splits
    assert len({json.dumps(m) for m in doc["mounts"]}) == 4
    calibs = {(out / "radar" / "training" / "calib" / f"{d:02d}000.txt").read_text() for d in range(4)}
    assert len(calibs) == 4  # per-drive mounting
    for split in ("train", "val", "test"):
        for name, n in result.objects[split].items():
            assert 0 < result.distinct[split][name] <= n or n == 0
    ds = DetectionSet(out, "test", VOD, scans_accumulated=5)
    frame = ds.frame(0, ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"])
    assert set(np.unique(frame.points[:, 6]).tolist()) == {-4.0, -3.0, -2.0, -1.0, 0.0}
    assert set(frame.labels.occluded.tolist()) <= {0, 1, 2}


@pytest.mark.parametrize("bad", [dict(points_model="lidar"), dict(occlusion="yes"), dict(mount_pitch_deg=9.0)])
def test_physics_fields_are_checked(bad):
    from radaredge.data.synthetic import SceneConfig
    from radaredge.errors import ConfigError

    with pytest.raises(ConfigError, match=next(iter(bad))):
        SceneConfig(**bad)
