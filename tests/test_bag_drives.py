"""ROS bag drives for training: radar scans from a point-cloud topic, positions from NavSatFix fixes
projected to UTM (against pyproj), NTU4DRadLM's topics and channels."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Transformer
from test_readers import ROS1, header, pointcloud, write_bag

from radaredge.data.bag_drives import BagSource, load_bag_sequence
from radaredge.data.geodesy import transverse_mercator, utm_from_latlon
from radaredge.errors import InputError
from radaredge.training.places import load_place_windows

FIX = "sensor_msgs/msg/NavSatFix"
LAT0, LON0 = 1.3483, 103.6831  # NTU, Singapore: UTM zone 48 N


@pytest.mark.parametrize("lat, lon", [(LAT0, LON0), (52.0116, 4.3571), (-33.9, 18.4), (60.0, 11.9), (40.5, -73.5)])
def test_utm_agrees_with_proj(lat, lon):
    e, n, zone, south = utm_from_latlon([lat], [lon])
    proj = Transformer.from_crs("EPSG:4326", f"EPSG:{(32700 if south else 32600) + zone}", always_xy=True)
    pe, pn = proj.transform(lon, lat)
    assert abs(e[0] - pe) < 1e-3 and abs(n[0] - pn) < 1e-3


def test_snyders_worked_example():
    """USGS PP 1395, p. 269: Clarke 1866, 40.5 N 73.5 W about 75 W -> x 127,106.5 m, y 4,484,124.4 m."""
    x, y = transverse_mercator(40.5, -73.5, -75.0, a=6378206.4, f=1 - np.sqrt(1 - 0.00676866))
    assert x == pytest.approx(127106.5, abs=0.05) and y == pytest.approx(4484124.4, abs=0.05)


def _fix(stamp, lat, lon, status=0):
    t = ROS1.types
    return t[FIX](header(ROS1, stamp), t["sensor_msgs/msg/NavSatStatus"](status, 1), lat, lon, 10.0, np.zeros(9), 0)


def _drive_bag(path, north_m: float, scans: int = 8, doppler: float = -8.0):
    """A drive heading north from NTU at 10 Hz: fixes at 5 Hz from 0.05 s, one with no fix;
    NTU4DRadLM-style PointCloud scans whose channel 0 is the Doppler and channel 2 the power."""
    fixes = [
        _fix((1700000000, int(5e7 + 2e8 * i)), LAT0 + (north_m + 2.0 * i) / 110574.0, LON0)
        for i in range(scans // 2 + 1)
    ]
    fixes.insert(2, _fix((1700000000, int(2.6e8)), 0.0, 0.0, status=-1))
    clouds = []
    for i in range(scans):
        xyz = np.array([[10.0 + i, 1.0, 0.5], [20.0, -2.0, 0.0]])
        clouds.append(
            pointcloud(
                ROS1,
                (1700000000, int(1e8 * i)),
                xyz,
                {"Doppler": [doppler, doppler], "Range": [10.0, 20.0], "Power": [30.0 + i, 20.0]},
            )
        )
    return write_bag(
        path, True, {"/radar_enhanced_pcl": ("sensor_msgs/msg/PointCloud", clouds), "/ublox/fix": (FIX, fixes)}
    )


def test_bag_drive_positions_are_interpolated_utm(tmp_path):
    bag = _drive_bag(tmp_path / "a.bag", north_m=0.0)
    seq = load_bag_sequence(bag, ["x", "y", "z", "v_r", "rcs"], BagSource(field_map={"v_r": 0, "rcs": 2}))
    # scan 0 (t = 0) precedes the first fix (t = 0.05 s) and is left out; the no-fix message is skipped
    assert len(seq) == 7 and seq.utm_zone == 48
    np.testing.assert_allclose(seq.timestamps - 1700000000, 0.1 * np.arange(1, 8), atol=1e-6)
    e0, n0, _, _ = utm_from_latlon([LAT0], [LON0])
    # 2 m north every 0.2 s from 0.05 s: scan at t is (t - 0.05) * 10 m north of the start
    np.testing.assert_allclose(seq.positions[:, 0] - n0[0], (seq.timestamps - 1700000000.05) * 10.0, atol=0.02)
    np.testing.assert_allclose(seq.positions[:, 1], e0[0], atol=0.02)
    scan = seq.scan(2, ["x", "v_r", "rcs"])
    np.testing.assert_allclose(scan, [[13.0, -8.0, 33.0], [20.0, -8.0, 20.0]])
    flipped = load_bag_sequence(
        bag, ["x", "y", "z", "v_r", "rcs"], BagSource(field_map={"v_r": 0, "rcs": 2}, doppler_sign=-1.0)
    )
    assert flipped.scan(2, ["v_r"]).ravel().tolist() == [8.0, 8.0]


def test_a_directory_of_bags_is_a_training_set(tmp_path):
    for i, north in enumerate((0.0, 0.5, 1.0)):
        _drive_bag(tmp_path / f"drive-{i}.bag", north)
    data = load_place_windows(
        tmp_path, 3, features=["x", "y", "z", "v_r", "rcs"], bag=BagSource(field_map={"v_r": "Doppler", "rcs": "Power"})
    )
    assert data.names == ["drive-0.bag", "drive-1.bag", "drive-2.bag"]
    assert data.validation.sum() == 5 and set(data.drive[data.validation]) == {2}
    scans, t = data.inputs(0, ["x", "y", "z", "v_r", "rcs"])
    assert len(scans) == 3 and t.tolist() == pytest.approx([0.0, 0.1, 0.2], abs=1e-6)


def test_bag_without_fixes_names_the_bag_and_topic(tmp_path):
    bag = write_bag(
        tmp_path / "nofix.bag",
        True,
        {
            "/radar_enhanced_pcl": (
                "sensor_msgs/msg/PointCloud",
                [pointcloud(ROS1, (1700000000, 0), np.zeros((1, 3)), {"Doppler": [0.0]})],
            )
        },
    )
    with pytest.raises(InputError, match=r"nofix\.bag: no GNSS topic '/ublox/fix'; the bag has: /radar_enhanced_pcl"):
        load_bag_sequence(bag, ["x", "y", "z", "v_r"])
    no_fix = write_bag(
        tmp_path / "bad.bag",
        True,
        {
            "/ublox/fix": (FIX, [_fix((1700000000, 0), 0.0, 0.0, -1)]),
            "/radar_enhanced_pcl": ("sensor_msgs/msg/PointCloud", []),
        },
    )
    with pytest.raises(InputError, match=r"bad\.bag: 0 valid GNSS fix"):
        load_bag_sequence(no_fix, ["x", "y", "z", "v_r"])
