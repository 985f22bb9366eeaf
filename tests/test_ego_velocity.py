"""Ego-velocity RANSAC: export formulation == numpy reference, accuracy, degenerate input, ONNX."""

import numpy as np
import pytest
import torch

from radaredge.errors import InputError
from radaredge.ops.ego_velocity import (
    EgoVelocityRansac,
    RansacConfig,
    estimate_ego_velocity,
    estimate_ego_velocity_reference,
    hypothesis_table,
    sample_ranks,
)
from radaredge.ops.scan_batch import concat_scans


def doppler_scan(n, dynamic_fraction, seed, v_ego=(8.0, 0.6, 0.1), noise=0.05):
    """Points on a forward FOV with v_r = -r.v_ego + noise; a fraction gets object motion."""
    rng = np.random.default_rng(seed)
    az, el, r = rng.uniform(-1.0, 1.0, n), rng.uniform(-0.25, 0.25, n), rng.uniform(2, 60, n)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    v_r = -d @ np.asarray(v_ego) + rng.normal(0, noise, n)
    dyn = rng.random(n) < dynamic_fraction
    v_obj = rng.uniform(2, 12, (n, 1)) * np.array([[1.0, 0.3, 0.0]]) * rng.choice([-1, 1], (n, 1))
    v_r[dyn] += (d[dyn] * v_obj[dyn]).sum(1)
    return (d * r[:, None]).astype(np.float32), v_r.astype(np.float32), dyn


def test_sample_ranks_are_distinct_and_in_range():
    table = hypothesis_table(500, 3)
    for n in (3, 4, 7, 100):
        r = sample_ranks(table, n)
        assert r.min() >= 0 and r.max() < n
        assert all(len(set(row)) == 3 for row in r.tolist())


def _mod_in_float32(a, b):
    """a mod b computed as a runtime without 64-bit integer kernels does: in float32."""
    a, b = np.float32(a), np.float32(b)
    return (a - np.floor(a / b) * b).astype(np.int64)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_samples_are_the_same_when_a_runtime_computes_mod_in_float32(seed):
    """OpenVINO's CPU plugin evaluates the graph's integer Mod in float32. The table keeps below
    2**24, so every value is exact there and the samples agree with int64 arithmetic for any
    point count (with the earlier 2**30 table most of them differed)."""
    table = hypothesis_table(64, seed)
    assert table.max() < 2**24
    for n in (3, 17, 300, 1186, 4999):
        exact = table % np.array([n, n - 1, n - 2])
        assert (_mod_in_float32(table, np.array([n, n - 1, n - 2])) == exact).all(), n


@pytest.mark.parametrize("dyn", [0.0, 0.2, 0.4])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_export_formulation_matches_reference(dyn, seed):
    xyz, v_r, _ = doppler_scan(300, dyn, seed)
    ref_v, ref_mask, ref_ok = estimate_ego_velocity_reference(xyz, v_r)
    v, mask, ok = estimate_ego_velocity(xyz, v_r)
    assert ok and ref_ok
    np.testing.assert_allclose(v, ref_v, atol=1e-4)
    assert (mask == ref_mask).mean() >= 0.995  # float32 vs float64 at the threshold edge only


def test_accuracy_on_doppler_scans():
    xyz, v_r, dyn = doppler_scan(400, 0.4, 7)
    v, static, ok = estimate_ego_velocity(xyz, v_r)
    assert ok
    assert np.abs(v - np.array([8.0, 0.6, 0.1])).max() < 0.1
    assert ((~static) == dyn).mean() >= 0.95


@pytest.mark.parametrize("n", [0, 1, 2, 3, 4])
def test_tiny_scans_are_flagged_invalid_not_nan(n):
    xyz, v_r, _ = doppler_scan(n, 0.0, 0)
    for fn in (estimate_ego_velocity, estimate_ego_velocity_reference):
        v, static, ok = fn(xyz, v_r)
        assert not ok and np.all(v == 0) and static.shape == (n,) and static.all()


def test_zero_velocity_scan_is_a_regular_result():
    xyz, _, _ = doppler_scan(100, 0.0, 0)
    v, static, ok = estimate_ego_velocity(xyz, np.zeros(100, np.float32))
    assert ok and np.abs(v).max() < 1e-6 and static.all()


def test_non_finite_points_are_masked_out():
    xyz, v_r, _ = doppler_scan(200, 0.1, 4)
    xyz[5, 0] = np.nan
    v_r[9] = np.inf
    v, static, ok = estimate_ego_velocity(xyz, v_r)
    ref_v, ref_static, _ = estimate_ego_velocity_reference(xyz, v_r)
    assert ok and np.isfinite(v).all()
    assert not static[5] and not static[9] and not ref_static[5] and not ref_static[9]
    np.testing.assert_allclose(v, ref_v, atol=1e-4)


def test_valid_mask_excludes_padding():
    xyz, v_r, _ = doppler_scan(150, 0.0, 5)
    padded_xyz = np.concatenate([xyz, np.full((20, 3), 3.0, np.float32)])
    padded_vr = np.concatenate([v_r, np.full(20, 50.0, np.float32)])
    valid = np.arange(170) < 150
    v, static, ok = estimate_ego_velocity(padded_xyz, padded_vr, valid=valid)
    v0, _, _ = estimate_ego_velocity(xyz, v_r)
    np.testing.assert_allclose(v, v0, atol=1e-6)
    assert not static[150:].any()


def test_bad_shapes_raise_input_error():
    with pytest.raises(InputError, match=r"\[N, 3\]"):
        estimate_ego_velocity(np.zeros((10, 4)), np.zeros(10))
    with pytest.raises(InputError, match="v_r"):
        estimate_ego_velocity_reference(np.zeros((10, 3)), np.zeros(9))


def test_config_rejects_nonsense():
    with pytest.raises(ValueError):
        RansacConfig(inlier_threshold=0)


def test_onnx_export_matches_torch(onnx_roundtrip):
    xyz, v_r, _ = doppler_scan(120, 0.3, 9)
    example = {"xyz": torch.from_numpy(xyz), "v_r": torch.from_numpy(v_r), "valid": torch.ones(120, dtype=torch.bool)}
    rt = onnx_roundtrip(
        EgoVelocityRansac(),
        example,
        ["v_ego", "static_mask", "valid_estimate"],
        {"xyz": {0: "N"}, "v_r": {0: "N"}, "valid": {0: "N"}},
    )
    for n, dyn, seed in [(300, 0.4, 1), (57, 0.1, 2), (2, 0.0, 3), (0, 0.0, 4)]:
        xyz, v_r, _ = doppler_scan(n, dyn, seed)
        ref, got = rt(
            {"xyz": torch.from_numpy(xyz), "v_r": torch.from_numpy(v_r), "valid": torch.ones(n, dtype=torch.bool)}
        )
        np.testing.assert_allclose(got["v_ego"], ref["v_ego"], atol=1e-5)
        assert np.array_equal(got["static_mask"], ref["static_mask"])
        assert bool(got["valid_estimate"]) == bool(ref["valid_estimate"])


@pytest.mark.parametrize("dynamic_fraction", [0.0, 0.2, 0.4])
def test_accuracy_on_synthetic_radar_scenes(dynamic_fraction):
    """Issue acceptance: < 0.1 m/s ego-velocity error and >= 95 % mask agreement with ground truth
    (dynamic points and multipath ghosts are the true outliers) on synthetic scans.

    The vertical component is the least observable one (a +-15 deg elevation FOV puts most
    points near the horizon): over 40 seeds per fraction the worst 3-D error seen was 0.107 m/s
    while the horizontal error, the part TDFANet's alignment uses, stayed below 0.025 m/s.
    """
    from radaredge.data.synthetic import generate_scan

    for seed in range(10):
        scan = generate_scan(seed=100 + seed, dynamic_fraction=dynamic_fraction)
        v, static, ok = estimate_ego_velocity(scan.points[:, :3], scan.points[:, 3])
        err = v - scan.ego_velocity
        assert ok
        assert np.linalg.norm(err[:2]) < 0.05, (seed, err)
        assert np.linalg.norm(err) < 0.1, (seed, err)
        assert ((~static) == (scan.dynamic | scan.ghost)).mean() >= 0.95, seed


class _ScansAtOnce(torch.nn.Module):
    """EgoVelocityRansac.estimate_frames over scans given as separate inputs, for export."""

    def __init__(self, count):
        super().__init__()
        self.ransac, self.count = EgoVelocityRansac(), count

    def forward(self, *xyz_vr):
        xyz, frame = concat_scans(list(xyz_vr[0::2]))
        v_r = torch.cat(xyz_vr[1::2])
        return self.ransac.estimate_frames(xyz, v_r, torch.ones(xyz.shape[0], dtype=torch.bool), frame, self.count)


# Scans of different sizes and kinds: a plain one, an empty one, one too small to estimate, a
# static one with the ego standing still, one with 40 % dynamic points.
_MIXED = [(150, 0.1, 11), (0, 0.0, 12), (2, 0.0, 13), (80, 0.0, 14), (300, 0.4, 15)]


def _mixed_scans():
    scans = [doppler_scan(n, d, s)[:2] for n, d, s in _MIXED]
    scans[3] = (scans[3][0], np.zeros(len(scans[3][1]), np.float32))
    return scans


def test_scans_at_once_equal_scans_alone():
    """frames(): each scan's ego velocity, static mask and validity are those of the scan alone."""
    scans = _mixed_scans()
    with torch.no_grad():
        v, static, ok = _ScansAtOnce(len(scans))(*[torch.from_numpy(a) for s in scans for a in s])
    start = 0
    for k, (xyz, v_r) in enumerate(scans):
        v1, s1, ok1 = estimate_ego_velocity(xyz, v_r)
        np.testing.assert_allclose(v[k].numpy(), v1, atol=1e-6, err_msg=f"scan {k}")
        assert np.array_equal(static[start : start + len(xyz)].numpy(), s1), f"scan {k}"
        assert bool(ok[k]) == ok1, f"scan {k}"
        start += len(xyz)
    assert [bool(o) for o in ok] == [True, False, False, True, True]


def test_scans_at_once_onnx_matches_torch(onnx_roundtrip):
    scans = _mixed_scans()[:3]
    names = [f"{a}_{k}" for k in range(3) for a in ("xyz", "v_r")]
    example = dict(zip(names, [torch.from_numpy(a) for s in scans for a in s]))
    rt = onnx_roundtrip(
        _ScansAtOnce(3), example, ["v_ego", "static_mask", "valid_estimate"], {n: {0: f"N_{n}"} for n in names}
    )
    for sizes in [(300, 57, 120), (0, 4, 200), (90, 0, 0)]:
        scans = [doppler_scan(n, 0.3, n + 1)[:2] for n in sizes]
        ref, got = rt(dict(zip(names, [torch.from_numpy(a) for s in scans for a in s])))
        np.testing.assert_allclose(got["v_ego"], ref["v_ego"], atol=1e-5)
        assert np.array_equal(got["static_mask"], ref["static_mask"])
        assert np.array_equal(got["valid_estimate"], ref["valid_estimate"])


def test_a_scan_without_a_static_world_is_not_a_valid_estimate():
    """Doppler that fits no common ego motion (a swapped rcs column, a scan of movers only): the
    best 3-point fit explains few points and is flagged invalid by the inlier ratio."""
    rng = np.random.default_rng(3)
    for seed in range(20):
        xyz, _, _ = doppler_scan(300, 0.0, seed)
        rcs_as_doppler = rng.uniform(-20.0, 40.0, len(xyz))
        for v, static, ok in (
            estimate_ego_velocity_reference(xyz, rcs_as_doppler),
            estimate_ego_velocity(xyz, rcs_as_doppler),
        ):
            assert not ok and np.all(np.asarray(v) == 0) and np.all(static)


def test_an_implausible_speed_is_not_a_valid_estimate():
    """A perfect static world seen at 90 m/s fits, but exceeds max_speed (70 m/s by default)."""
    xyz, v_r, _ = doppler_scan(300, 0.0, 0, v_ego=(90.0, 0.0, 0.0), noise=0.0)
    for cfg, expect in ((RansacConfig(), False), (RansacConfig(max_speed=100.0), True)):
        v_ref, _, ok_ref = estimate_ego_velocity_reference(xyz, v_r, cfg)
        v_exp, _, ok_exp = estimate_ego_velocity(xyz, v_r, cfg)
        assert ok_ref == ok_exp == expect
        assert np.allclose(v_ref, v_exp, atol=1e-4)
