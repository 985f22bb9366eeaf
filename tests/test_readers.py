"""Scan readers: VoD / TJ4D .bin, TransLoc4D-style .npy and ROS 1 / ROS 2 bags into named columns; malformed input."""

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from radaredge.data.readers import (
    FORMATS,
    TJ4D_COLUMNS,
    VOD_COLUMNS,
    iter_rosbag,
    read_rosbag,
    read_scan,
    read_tj4d_bin,
    read_vod_bin,
)
from radaredge.data.synthetic import (
    generate_scan,
    generate_sequence,
    vod_accumulated_table,
    write_tj4d_bin,
    write_vod_bin,
)
from radaredge.errors import InputError

CARD = ["x", "y", "z", "v_r", "rcs"]


def labelled_table(n: int, columns: int) -> np.ndarray:
    """Row i, column j holds 100 j + i: every value says where it came from."""
    return (100.0 * np.arange(columns) + np.arange(n)[:, None]).astype(np.float32)


def write_bin(path, table):
    np.ascontiguousarray(table, dtype="<f4").tofile(path)
    return path


# ----------------------------------------------------------------------------- scan files


def test_formats():
    assert FORMATS == ("vod", "tj4d", "transloc", "rosbag")


def test_vod_columns_land_in_their_named_features(tmp_path):
    table = labelled_table(3, 7)  # 84 bytes: a whole number of 7-column rows only, so vod is inferred
    path = write_bin(tmp_path / "00000.bin", table)
    features = ["x", "y", "z", "v_r", "rcs", "v_r_comp", "time"]
    for fmt in ("vod", None):
        scan = read_scan(path, features, fmt)
        assert scan.dtype == np.float32 and scan.shape == (3, 7)
        order = [VOD_COLUMNS.index(c) for c in ("x", "y", "z", "v_r", "rcs", "v_r_compensated", "time")]
        np.testing.assert_array_equal(scan, table[:, order])
    np.testing.assert_array_equal(read_vod_bin(path), table)


def test_tj4d_columns_and_power_as_rcs(tmp_path):
    table = labelled_table(3, 8)  # not TJ4D content (Range is no distance): the format is named
    path = write_bin(tmp_path / "000000.bin", table)
    scan = read_scan(path, ["x", "y", "z", "v_r", "rcs", "range", "power", "alpha", "beta"], "tj4d")
    col = {name: table[:, i] for i, name in enumerate(TJ4D_COLUMNS)}
    expected = ["X", "Y", "Z", "V_r", "Power", "Range", "Power", "Alpha", "Beta"]
    np.testing.assert_array_equal(scan, np.column_stack([col[c] for c in expected]))
    np.testing.assert_array_equal(read_tj4d_bin(path), table)


def test_bin_format_is_inferred_from_size_and_content(tmp_path):
    scan = generate_scan(seed=2)
    tj4d = write_tj4d_bin(tmp_path / "t.bin", scan)
    vod = write_vod_bin(tmp_path / "v.bin", scan)
    np.testing.assert_array_equal(read_scan(tj4d, CARD), scan.points)
    np.testing.assert_array_equal(read_scan(vod, CARD), scan.points)


def test_a_truncated_file_that_fits_the_other_layout_is_refused(tmp_path):
    """A VoD file cut to 2,784 bytes fits 87 TJ4D rows; a TJ4D file cut to a multiple of 28
    bytes fits VoD rows. Neither is read as the other layout (rcs would be served as v_r)."""
    scan = generate_scan(seed=2, static_points=400)
    data = write_vod_bin(tmp_path / "full.bin", scan).read_bytes()
    (tmp_path / "cut_vod.bin").write_bytes(data[:2784])
    with pytest.raises(InputError, match="fit the tj4d layout, but its Range column.*fmt='vod'"):
        read_scan(tmp_path / "cut_vod.bin", CARD)
    data = write_tj4d_bin(tmp_path / "full.bin", scan).read_bytes()
    (tmp_path / "cut_tj4d.bin").write_bytes(data[: 28 * 50])
    with pytest.raises(InputError, match="fit the vod layout, but its first rows read as TJ4DRadSet rows"):
        read_scan(tmp_path / "cut_tj4d.bin", CARD)
    assert read_scan(tmp_path / "cut_tj4d.bin", CARD, "vod").shape == (50, 5)  # named: read as told


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_transloc_npy_columns_and_intensity_as_rcs(tmp_path, dtype):
    table = labelled_table(4, 5).astype(dtype)
    np.save(tmp_path / "scan.npy", table)
    scan = read_scan(tmp_path / "scan.npy", ["rcs", "x", "y", "z", "v_r", "intensity"])
    assert scan.dtype == np.float32
    np.testing.assert_array_equal(scan, table[:, [4, 0, 1, 2, 3, 4]].astype(np.float32))


def test_files_written_by_the_synthetic_generator_read_back_as_the_card_columns(tmp_path):
    scan = generate_scan(seed=1)
    for write, fmt in ((write_vod_bin, "vod"), (write_tj4d_bin, "tj4d")):
        np.testing.assert_array_equal(read_scan(write(tmp_path / f"{fmt}.bin", scan), CARD, fmt), scan.points)


def test_vod_radar_5frames_layout_reads_into_the_maffnet_vod_columns(tmp_path):
    """VoD's radar_5frames files (5 scans in the newest scan's frame, time the scan index 0 .. -4) have the
    single-scan layout; they read into MAFF-Net's VoD features unchanged, time column included."""
    table = vod_accumulated_table(generate_sequence(5, seed=1), fov_deg=32.9)
    table.astype("<f4").tofile(tmp_path / "00042.bin")
    pts = read_scan(tmp_path / "00042.bin", ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"])
    np.testing.assert_array_equal(pts, table)
    assert np.unique(pts[:, 6]).tolist() == [-4.0, -3.0, -2.0, -1.0, 0.0]
    assert (np.abs(np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))) <= 32.9).all()


def test_empty_scan_is_zero_rows(tmp_path):
    np.save(tmp_path / "empty.npy", np.zeros((0, 5), np.float32))
    assert read_scan(tmp_path / "empty.npy", CARD).shape == (0, 5)


def test_feature_the_format_lacks_names_feature_format_and_what_it_provides(tmp_path):
    path = write_bin(tmp_path / "a.bin", labelled_table(2, 8))
    with pytest.raises(InputError, match=r"'tj4d'.*\['v_r_comp'\].*provides \['alpha', 'beta', 'power'"):
        read_scan(path, ["x", "v_r_comp"], "tj4d")
    np.save(tmp_path / "a.npy", labelled_table(2, 5))
    with pytest.raises(InputError, match="'transloc'.*'time'"):
        read_scan(tmp_path / "a.npy", ["x", "time"])
    with pytest.raises(InputError, match="non-empty list"):
        read_scan(path, "xyz", "tj4d")


@pytest.mark.parametrize("size, detail", [(224, "fit both"), (30, "fit neither"), (0, "fit both")])
def test_bin_format_inference_refuses_ambiguous_sizes(tmp_path, size, detail):
    path = tmp_path / "scan.bin"
    path.write_bytes(bytes(size))
    with pytest.raises(InputError, match=f"{size} bytes {detail}.*fmt='vod' or fmt='tj4d'"):
        read_scan(path, CARD)


def test_unknown_suffix_or_format(tmp_path):
    path = tmp_path / "scan.pcd"
    path.write_bytes(bytes(28))
    with pytest.raises(InputError, match="suffix '.pcd'"):
        read_scan(path, CARD)
    with pytest.raises(InputError, match="iter_rosbag"):
        read_scan(path, CARD, "rosbag")
    with pytest.raises(InputError, match="unknown scan format 'kitti'"):
        read_scan(path, CARD, "kitti")


def test_truncated_bin_says_how_many_bytes_and_what_was_expected(tmp_path):
    path = tmp_path / "cut.bin"
    path.write_bytes(labelled_table(2, 7).astype("<f4").tobytes()[:-3])
    with pytest.raises(InputError, match=r"cut.bin: 53 bytes .*7 float32 columns.*multiple of 28 bytes"):
        read_scan(path, CARD, "vod")
    with pytest.raises(InputError, match="53 bytes .*multiple of 32 bytes"):
        read_scan(path, CARD, "tj4d")


@pytest.mark.parametrize(
    "array, detail",
    [
        (np.zeros((4, 4), np.float32), r"4 columns, expected a numeric \[N, 5\]"),
        (np.zeros((2, 4, 5), np.float32), r"shape \(2, 4, 5\) is not 2-D"),
        (np.zeros(5, np.float32), r"shape \(5,\) is not 2-D"),
        (np.array([["a"] * 5]), "dtype <U1 is not numeric"),
        (np.zeros((2, 5), np.complex64), "dtype complex64 is not numeric"),
        (np.array([[{"x": 1}] * 5], dtype=object), "pickled object array"),
    ],
)
def test_malformed_npy(tmp_path, array, detail):
    path = tmp_path / "bad.npy"
    np.save(path, array, allow_pickle=True)
    with pytest.raises(InputError, match=detail) as info:
        read_scan(path, CARD)
    assert "bad.npy" in str(info.value)


def test_not_a_npy_file_or_a_truncated_one(tmp_path):
    path = tmp_path / "text.npy"
    path.write_text("x,y,z\n")
    with pytest.raises(InputError, match="text.npy: not a readable .npy file"):
        read_scan(path, CARD)
    np.save(tmp_path / "cut.npy", np.zeros((10, 5), np.float32))
    (tmp_path / "cut.npy").write_bytes((tmp_path / "cut.npy").read_bytes()[:-7])
    with pytest.raises(InputError, match="cut.npy: not a readable .npy file: .*50 elements"):
        read_scan(tmp_path / "cut.npy", CARD)


def test_missing_file_names_the_path(tmp_path):
    for fmt in (None, "vod", "transloc"):
        with pytest.raises(InputError, match="nope.npy: no such"):
            read_scan(tmp_path / "nope.npy", CARD, fmt)


# ----------------------------------------------------------------------------- ROS bags

ROS1 = get_typestore(Stores.ROS1_NOETIC)
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
PCL2, PCL = "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/PointCloud"
STAMPS = [(1700000000, 250000000), (1700000000, 350000000)]  # (sec, nanosec)


def header(store, stamp):
    sec, nanosec = stamp
    extra = {"seq": 0} if store is ROS1 else {}
    return store.types["std_msgs/msg/Header"](
        **extra, stamp=store.types["builtin_interfaces/msg/Time"](sec, nanosec), frame_id="radar"
    )


def pointcloud2(store, stamp, columns: dict, *, big_endian=False, height=1, pad=0):
    """A PointCloud2 whose float32 fields are ``columns`` (name -> [P]); ``pad`` bytes after each
    point and 3 after each row, plus an unused uint16 field, exercise point_step and row_step."""
    names = list(columns)
    n = len(next(iter(columns.values())))
    order = ">" if big_endian else "<"
    dtype = np.dtype(
        {
            "names": names + ["ring"],
            "formats": [order + "f4"] * len(names) + [order + "u2"],
            "offsets": [4 * i for i in range(len(names))] + [4 * len(names)],
            "itemsize": 4 * len(names) + 2 + pad,
        }
    )
    points = np.zeros(n, dtype)
    for name in names:
        points[name] = columns[name]
    width = n // height
    rows = points.tobytes()
    row_bytes = width * dtype.itemsize
    data = b"".join(rows[r * row_bytes : (r + 1) * row_bytes] + b"\xff" * 3 for r in range(height))
    PointField = store.types["sensor_msgs/msg/PointField"]
    fields = [PointField(name, 4 * i, 7, 1) for i, name in enumerate(names)]  # 7: FLOAT32
    fields.append(PointField("ring", 4 * len(names), 4, 1))  # 4: UINT16
    return store.types[PCL2](
        header(store, stamp),
        height,
        width,
        fields,
        big_endian,
        dtype.itemsize,
        row_bytes + 3,
        np.frombuffer(data, np.uint8),
        True,
    )


def pointcloud(store, stamp, xyz, channels: dict):
    Point32 = store.types["geometry_msgs/msg/Point32"]
    Channel = store.types["sensor_msgs/msg/ChannelFloat32"]
    return store.types[PCL](
        header(store, stamp),
        [Point32(*map(float, p)) for p in xyz],
        [Channel(name, np.asarray(v, np.float32)) for name, v in channels.items()],
    )


def write_bag(path, ros1: bool, topics: dict, storage=StoragePlugin.SQLITE3):
    """A ROS 1 ``.bag`` or ROS 2 bag directory with ``topics``: name -> (msgtype, [messages])."""
    store = ROS1 if ros1 else ROS2
    writer = Writer1(path) if ros1 else Writer2(path, version=9, storage_plugin=storage)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    with writer:
        for topic, (msgtype, messages) in topics.items():
            connection = writer.add_connection(topic, msgtype, typestore=store)
            for i, msg in enumerate(messages):
                writer.write(connection, 1000 + i, serialize(msg, msgtype))
    return path


def radar_points(seed: int, n: int = 6) -> dict:
    rng = np.random.default_rng(seed)
    return {name: rng.normal(size=n).astype(np.float32) for name in ("x", "y", "z", "Doppler", "RCS")}


@pytest.mark.parametrize("ros1, storage", [(True, None), (False, StoragePlugin.SQLITE3), (False, StoragePlugin.MCAP)])
def test_pointcloud2_bag_round_trip(tmp_path, ros1, storage):
    store = ROS1 if ros1 else ROS2
    clouds = [radar_points(0), radar_points(1)]
    msgs = [
        pointcloud2(store, STAMPS[0], clouds[0]),
        pointcloud2(store, STAMPS[1], clouds[1], big_endian=True, height=2, pad=5),
    ]
    path = write_bag(
        tmp_path / ("drive.bag" if ros1 else "drive"), ros1, {"/radar": (PCL2, msgs)}, storage or StoragePlugin.SQLITE3
    )
    scans = read_rosbag(path, "/radar", ["x", "y", "z", "v_r", "rcs"])
    assert [t for t, _ in scans] == pytest.approx([1700000000.25, 1700000000.35], abs=1e-6)
    for (_, scan), cloud in zip(scans, clouds):
        assert scan.dtype == np.float32
        np.testing.assert_array_equal(scan, np.column_stack([cloud[c] for c in ("x", "y", "z", "Doppler", "RCS")]))


def test_pointcloud2_field_map_by_name_and_index(tmp_path):
    cloud = {"x": [1, 2], "y": [3, 4], "z": [5, 6], "vel_rad": [7, 8], "pwr": [9, 10]}
    path = write_bag(tmp_path / "a.bag", True, {"/r": (PCL2, [pointcloud2(ROS1, STAMPS[0], cloud)])})
    [(_, scan)] = read_rosbag(path, "/r", ["x", "v_r", "rcs"], field_map={"v_r": "vel_rad", "rcs": 4})
    np.testing.assert_array_equal(scan, [[1, 7, 9], [2, 8, 10]])


@pytest.mark.parametrize("ros1", [True, False])
def test_pointcloud_channels_ntu4dradlm_style(tmp_path, ros1):
    """NTU4DRadLM /radar_enhanced_pcl: PointCloud, Doppler in channel 0, power in channel 2."""
    store = ROS1 if ros1 else ROS2
    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    channels = {"Doppler": [0.5, -1.0, 2.0, 0.0], "Range": [1, 2, 3, 4], "Power": [10, 20, 30, 40]}
    path = write_bag(
        tmp_path / ("ntu.bag" if ros1 else "ntu"),
        ros1,
        {"/radar_enhanced_pcl": (PCL, [pointcloud(store, STAMPS[1], xyz, channels)])},
    )
    [(stamp, scan)] = read_rosbag(path, "/radar_enhanced_pcl", CARD, field_map={"v_r": 0, "rcs": 2})
    assert stamp == pytest.approx(1700000000.35, abs=1e-6)
    np.testing.assert_array_equal(scan, np.column_stack([xyz, channels["Doppler"], channels["Power"]]))
    # the default names find the same channels (doppler -> v_r, power -> rcs)
    [(_, default)] = read_rosbag(path, "/radar_enhanced_pcl", CARD)
    np.testing.assert_array_equal(default, scan)


def test_iter_rosbag_yields_in_recording_order(tmp_path):
    msgs = [pointcloud2(ROS1, (s, 0), radar_points(s)) for s in range(3)]
    path = write_bag(tmp_path / "a.bag", True, {"/radar": (PCL2, msgs)})
    assert [t for t, _ in iter_rosbag(path, "/radar", ["x"])] == [0.0, 1.0, 2.0]


def test_missing_topic_lists_the_topics_present_with_types(tmp_path):
    note = ROS1.types["std_msgs/msg/String"]("hi")
    path = write_bag(
        tmp_path / "a.bag",
        True,
        {"/radar": (PCL2, [pointcloud2(ROS1, STAMPS[0], radar_points(0))]), "/note": ("std_msgs/msg/String", [note])},
    )
    with pytest.raises(
        InputError,
        match=r"no topic '/lidar'; the bag has: /note \(std_msgs/msg/String\), "
        r"/radar \(sensor_msgs/msg/PointCloud2\)",
    ):
        read_rosbag(path, "/lidar", CARD)
    with pytest.raises(InputError, match="'/note' carries std_msgs/msg/String; expected sensor_msgs/msg/PointCloud2"):
        read_rosbag(path, "/note", CARD)


def test_unmappable_field_names_it_and_lists_the_fields(tmp_path):
    cloud = {"x": [1.0], "y": [2.0], "z": [3.0], "foo": [4.0]}
    path = write_bag(tmp_path / "a.bag", True, {"/r": (PCL2, [pointcloud2(ROS1, STAMPS[0], cloud)])})
    with pytest.raises(
        InputError,
        match=r"cannot map feature 'v_r': the message's fields are "
        r"\['x', 'y', 'z', 'foo', 'ring'\].*field_map",
    ):
        read_rosbag(path, "/r", CARD)
    with pytest.raises(InputError, match="maps 'rcs' to field 'power', which the message lacks"):
        read_rosbag(path, "/r", ["x", "rcs"], field_map={"rcs": "power"})
    with pytest.raises(InputError, match="maps 'rcs' to field index 9, but the message has 5 fields"):
        read_rosbag(path, "/r", ["x", "rcs"], field_map={"rcs": 9})
    with pytest.raises(InputError, match=r"field_map key\(s\) \['vr'\] are not among the requested features"):
        read_rosbag(path, "/r", CARD, field_map={"vr": "foo"})


def test_unmappable_channel_lists_the_channels(tmp_path):
    msg = pointcloud(ROS1, STAMPS[0], np.zeros((2, 3)), {"speed": [1, 2]})
    path = write_bag(tmp_path / "a.bag", True, {"/r": (PCL, [msg])})
    with pytest.raises(InputError, match=r"x, y, z from points.*'v_r': the message's channels are \['speed'\]"):
        read_rosbag(path, "/r", CARD)


def test_bad_pointcloud2_layout(tmp_path):
    msg = pointcloud2(ROS1, STAMPS[0], radar_points(0))
    msg.row_step = 5  # shorter than width x point_step
    path = write_bag(tmp_path / "a.bag", True, {"/r": (PCL2, [msg])})
    with pytest.raises(InputError, match="row_step >= width 6 x point_step 22"):
        read_rosbag(path, "/r", CARD)


def test_missing_or_unreadable_bag(tmp_path):
    with pytest.raises(InputError, match="none.bag: no such ROS bag"):
        read_rosbag(tmp_path / "none.bag", "/r", CARD)
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    with pytest.raises(InputError, match="junk.bag: cannot read the ROS bag"):
        read_rosbag(tmp_path / "junk.bag", "/r", CARD)


def test_npy_header_claiming_more_than_the_file_holds_is_refused_before_allocating(tmp_path):
    """A header saying 5e11 rows over an 80-byte body would make numpy allocate terabytes."""
    path = tmp_path / "lie.npy"
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (500000000000, 5), }"
    body = (header + " " * (118 - len(header)) + "\n").encode()
    path.write_bytes(b"\x93NUMPY\x01\x00" + len(body).to_bytes(2, "little") + body + bytes(80))
    with pytest.raises(
        InputError,
        match=r"lie.npy: its header claims shape \(500000000000, 5\) of float32 "
        r"\(1e\+13 bytes\) but the file holds 209 bytes",
    ):
        read_scan(path, ["x", "y", "z", "v_r", "rcs"], "transloc")
