"""The published dataset samples as they are: View-of-Delft's devkit ``example_set/`` (radar/ with
the annotation tool's JSON labels, lidar/ with the KITTI .txt labels of the same objects, no
ImageSets) and TJ4DRadSet's ``Sample/training/`` (8-column scans, KITTI labels and calibration, no
images, no ImageSets). Each layout is a tiny synthetic copy written here as the devkits document it
(no real data is committed). And nothing silently wrong for the card: each thing read or dropped
without being asked is said once (a warning; one ``warning:`` line in the CLI), naming the card
field that decides it."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import MAFFNET_TINY_CARD, invoke

from radaredge.data.detection_benchmark import synthetic_calibration
from radaredge.data.kitti_detection import TJ4D, VOD, DetectionSet, list_frames, radar_boxes_to_labels, read_labels
from radaredge.data.readers import read_scan
from radaredge.data.synthetic import generate_scan
from radaredge.errors import CapacityError, InputError

VOD_FEATURES = ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"]
VOD_SIZE = (1936, 1216)
OCCLUSION = {0: "0-10%", 1: "41-80%", 2: "80-100%"}


def _png_header(width: int, height: int) -> bytes:
    """The start of a PNG: signature and IHDR, all radaredge reads of a camera image."""
    return (
        b"\x89PNG\r\n\x1a\n"
        + b"\x00\x00\x00\rIHDR"
        + width.to_bytes(4, "big")
        + height.to_bytes(4, "big")
        + b"\x08\x02\x00\x00\x00"
    )


def _calib_text(calib) -> str:
    row = lambda m: " ".join(f"{v:.12g}" for v in np.asarray(m).ravel())  # noqa: E731
    return (
        f"P0: {row(calib.P2)}\nP1: {row(calib.P2)}\nP2: {row(calib.P2)}\nP3: {row(calib.P2)}\n"
        f"R0_rect: {row(calib.R0)}\nTr_velo_to_cam: {row(calib.V2C)}\nTr_imu_to_velo: \n"
    )


def _quaternion_zyx(yaw: float, pitch: float, roll: float) -> dict[str, float]:
    """The unit quaternion {x, y, z, w} of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = (f(a / 2) for a in (yaw, pitch, roll) for f in (np.cos, np.sin))
    return {
        "x": sr * cp * cy - cr * sp * sy,
        "y": cr * sp * cy + sr * cp * sy,
        "z": cr * cp * sy - sr * sp * cy,
        "w": cr * cp * cy + sr * sp * sy,
    }


def _vod_objects(seed: int, calib):
    """(JSON objects as VoD's annotation tool writes them, the KITTI .txt lines of the same objects
    as the devkit's lidar/training/label_2 holds them) for the boxes of a synthetic scan.

    The JSON frame is the radar frame with y and z negated (what VoD's example_set holds): centre
    (x, -y, -z), yaw -heading, z down; the .txt is the devkit's KITTI line (camera frame, bottom
    centre, rotation_y = yaw - pi / 2, alpha from the location, 2D box clipped to the image,
    occluded from 'spatial occlusion', truncated 1 for moving objects, score 1)."""
    rng = np.random.default_rng(seed)
    scan = generate_scan(seed=seed)
    boxes = scan.boxes.astype(np.float64)
    keep = (boxes[:, 0] > 3) & (np.abs(boxes[:, 1]) < boxes[:, 0])  # in front of the camera
    boxes = boxes[keep][:8]
    kinds = [
        ("car", {}, "Car"),
        ("pedestrian", {}, "Pedestrian"),
        ("bicycle", {"has_rider": True}, "Cyclist"),
        ("bicycle", {"has_rider": False}, "bicycle"),
        ("rider", {}, "rider"),
        ("moped_scooter", {}, "moped_scooter"),
    ]
    objects, lines = [], []
    for i, b in enumerate(boxes):
        json_class, extra, kitti_class = kinds[i % len(kinds)]
        occluded = int(rng.integers(0, 3))
        moving = bool(rng.integers(0, 2))
        pitch, roll = rng.normal(0, 0.05, 2)  # the annotation tool's small tilts
        objects.append(
            {
                "id": f"box-{i}",
                "objectId": f"object-{i}",
                "className": json_class,
                "geometry": {
                    "size": {"height": b[5], "width": b[4], "length": b[3]},
                    "center": {"x": b[0], "y": -b[1], "z": -b[2]},
                    "quaternion": _quaternion_zyx(-b[6], pitch, roll),
                },
                "attributes": {
                    **extra,
                    "activity": "moving" if moving else "stopped",
                    "lightning occlusion": "0-10%",
                    "spatial occlusion": OCCLUSION[occluded],
                },
                "sensor": "LIDAR",
            }
        )
        label = radar_boxes_to_labels(b[None], np.zeros(1), np.array([kitti_class], dtype=object), calib, VOD_SIZE)
        loc = label.location[0]
        alpha = (label.rotation_y[0] - np.arctan2(loc[0], loc[2]) + np.pi) % (2 * np.pi) - np.pi
        h, w, length = b[5], b[4], b[3]
        lines.append(
            " ".join(
                str(v)
                for v in (
                    kitti_class,
                    int(moving),
                    occluded,
                    alpha,
                    *label.bbox[0],
                    h,
                    w,
                    length,
                    *loc,
                    label.rotation_y[0],
                    1,
                )
            )
        )
    return objects, lines


def write_vod_example_set(top: Path, frames=("00549", "01047", "01201")) -> Path:
    """VoD's devkit example_set as published: radar/training/{calib,image_2,label_2 (JSON),pose,velodyne}
    and lidar/training/{calib,image_2,label_2 (.txt),pose,velodyne}; no ImageSets."""
    example = top / "view-of-delft-dataset" / "example_set"
    calib = synthetic_calibration()
    for k, fid in enumerate(frames):
        objects, lines = _vod_objects(k + 3, calib)
        for sensor in ("radar", "lidar"):
            t = example / sensor / "training"
            for sub in ("calib", "image_2", "label_2", "pose", "velodyne"):
                (t / sub).mkdir(parents=True, exist_ok=True)
            (t / "calib" / f"{fid}.txt").write_text(_calib_text(calib))
            sof = b"\xff\xc0\x00\x11\x08" + VOD_SIZE[1].to_bytes(2, "big") + VOD_SIZE[0].to_bytes(2, "big")
            (t / "image_2" / f"{fid}.jpg").write_bytes(b"\xff\xd8" + sof + b"\x03" + b"\x00" * 9)
            identity = "[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]"
            (t / "pose" / f"{fid}.json").write_text(f'{{"odomToCamera": {identity}}}\n')
        scan = generate_scan(seed=k + 3)
        rows = np.column_stack(
            [scan.points[:, :3], scan.points[:, 4], scan.points[:, 3], scan.points[:, 3], np.zeros(len(scan.points))]
        ).astype("<f4")  # one scan: time 0
        rows.tofile(example / "radar" / "training" / "velodyne" / f"{fid}.bin")
        np.zeros((4, 4), "<f4").tofile(example / "lidar" / "training" / "velodyne" / f"{fid}.bin")
        (example / "radar" / "training" / "label_2" / f"{fid}.json").write_text(json.dumps(objects, indent=4))
        (example / "lidar" / "training" / "label_2" / f"{fid}.txt").write_text("\n".join(lines) + "\n")
    return example


def write_tj4d_sample(top: Path, first: int = 70070, count: int = 5) -> Path:
    """TJ4DRadSet's Sample as published: Sample/training/{calib,label_2,velodyne} (8 columns X, Y, Z,
    V_r, Range, Power, Alpha, Beta), 3dbox_to_cloud.py beside them; no image_2, no ImageSets."""
    sample = top / "TJ4DRadSet" / "Sample"
    t = sample / "training"
    for sub in ("calib", "label_2", "velodyne"):
        (t / sub).mkdir(parents=True, exist_ok=True)
    (t / "3dbox_to_cloud.py").write_text("# the sample's viewer\n")
    calib = synthetic_calibration()
    for k in range(count):
        fid = f"{first + k:06d}"
        scan = generate_scan(seed=20 + k)
        p = scan.points
        rng = np.linalg.norm(p[:, :3], axis=1)
        rows = np.column_stack(
            [
                p[:, :3],
                p[:, 3],
                rng,
                5 + np.abs(p[:, 4]),
                np.arctan2(p[:, 1], p[:, 0]),
                np.arcsin(p[:, 2] / np.maximum(rng, 1e-6)),
            ]
        ).astype("<f4")
        rows.tofile(t / "velodyne" / f"{fid}.bin")
        (t / "calib" / f"{fid}.txt").write_text(_calib_text(calib) + f"Tr_imu_to_cam: {' '.join(['0'] * 12)}\n")
        boxes = scan.boxes.astype(np.float64)[:3]
        names = np.array(["Car", "Other", "Truck"][: len(boxes)], dtype=object)
        lab = radar_boxes_to_labels(boxes, np.zeros(len(boxes)), names, calib, (1280, 960))
        (t / "label_2" / f"{fid}.txt").write_text(
            "".join(
                f"{n} 0 0 0 {' '.join(map(str, bb))} {d[1]} {d[2]} {d[0]} {' '.join(map(str, loc))} {ry}\n"
                for n, bb, d, loc, ry in zip(lab.name, lab.bbox, lab.dimensions, lab.location, lab.rotation_y)
            )
        )
    return sample


def _said(caught, needle: str) -> list[str]:
    return [str(w.message) for w in caught if needle in str(w.message)]


# ----------------------------------------------------------------------------- item 1: the samples as they are


def test_vod_json_labels_give_the_lidar_txt_labels(tmp_path):
    """example_set/radar/training/label_2/<id>.json (the annotation tool's objects) read into the
    same KITTI labels as example_set/lidar/training/label_2/<id>.txt: class (a bicycle with a rider
    is a Cyclist), bottom centre, size, rotation_y, alpha, 2D box, occluded and truncated."""
    example = write_vod_example_set(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = DetectionSet(example / "radar", "val", VOD)
    assert ds.frame_ids == ["00549", "01047", "01201"]
    for i, fid in enumerate(ds.frame_ids):
        got = ds.frame(i, VOD_FEATURES).labels
        want = read_labels(example / "lidar" / "training" / "label_2" / f"{fid}.txt", VOD.label_classes)
        assert len(got) == len(want) > 3
        assert list(got.name) == list(want.name) and "Cyclist" in list(got.name) and "bicycle" in list(got.name)
        np.testing.assert_allclose(got.location, want.location, atol=1e-6)
        np.testing.assert_allclose(got.dimensions, want.dimensions, atol=1e-9)
        np.testing.assert_allclose(np.cos(got.rotation_y - want.rotation_y), 1.0, atol=1e-12)
        np.testing.assert_allclose(got.alpha, want.alpha, atol=1e-6)
        np.testing.assert_allclose(got.bbox, want.bbox, atol=1e-4)
        assert got.occluded.tolist() == want.occluded.tolist() and got.truncated.tolist() == want.truncated.tolist()


def test_vod_json_label_problems_point_at_the_txt_labels(tmp_path):
    example = write_vod_example_set(tmp_path, frames=("00549",))
    label = example / "radar" / "training" / "label_2" / "00549.json"
    objects = json.loads(label.read_text())
    objects[1]["className"] = "hovercraft"
    label.write_text(json.dumps(objects))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = DetectionSet(example, "val", VOD)
    unknown = r"00549.json: object 1: unknown className 'hovercraft'.*lidar/training/label_2"
    with pytest.raises(InputError, match=unknown):
        ds.frame(0, VOD_FEATURES)
    del objects[1]["className"]
    label.write_text(json.dumps(objects))
    with pytest.raises(InputError, match=r"object 1: expected className and geometry"):
        ds.frame(0, VOD_FEATURES)


def test_the_vod_example_set_reads_as_published_and_says_what_it_read(tmp_path):
    """--data example_set for a 5-scan card: radar/ is read (no radar_5frames there), every
    labelled frame is the split (no ImageSets), and both are said once, naming how many frames,
    which folder and input.scans_accumulated."""
    example = write_vod_example_set(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = DetectionSet(example, "val", VOD, scans_accumulated=5)
    assert ds.root == example / "radar" and len(ds) == 3 and ds.scans_per_frame == 1
    assert len(caught) == 3, [str(w.message) for w in caught]
    assert len(_said(caught, "no radar_5frames/ or radar_5_scans/")) == 1
    assert len(_said(caught, "read radar/ (single scans) instead")) == 1
    assert len(_said(caught, "no ImageSets/ folder, so split 'val' is every labelled frame")) == 1
    assert len(_said(caught, ": 3 frames")) == 1
    assert len(_said(caught, "holds single scans (its name: radar/), but the card's input.scans_accumulated is 5")) == 1
    frame = ds.frame(0, VOD_FEATURES)
    assert frame.image_size == VOD_SIZE and (frame.points[:, 6] == 0).all()
    listed = list_frames(example, "val", VOD, 5)  # the plain function other verbs use
    assert listed.frame_ids == ds.frame_ids and listed.split_file is None and listed.notes == ds.notes
    with warnings.catch_warnings(record=True) as caught:  # a card of single scans: nothing about scans
        warnings.simplefilter("always")
        DetectionSet(example, "val", VOD, scans_accumulated=1)
    assert not _said(caught, "scans") and len(caught) == 1


@pytest.mark.parametrize("folder, scans", [("radar_5_scans", 5), ("radar_3_scans", 3), ("radar_5frames", 5)])
def test_the_devkits_accumulated_folder_names(tmp_path, folder, scans):
    """The devkit's docs name the accumulated folders radar_3_scans/ and radar_5_scans/, the
    dataset radar_3frames/ and radar_5frames/: both are the card's folder, and a folder that holds
    other scans than the card takes is said (from its time column when its name does not say)."""
    example = write_vod_example_set(tmp_path, frames=("00549",))
    (example / "radar").rename(example / folder)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = DetectionSet(example, "val", VOD, scans_accumulated=scans)
    assert ds.root == example / folder and not _said(caught, "scans_accumulated")
    renamed = example.parent / "my_copy"
    (example / folder).rename(renamed)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        DetectionSet(renamed, "val", VOD, scans_accumulated=scans)
    assert (
        len(
            _said(
                caught,
                f"holds single scans (distinct values of its time column), but the card's "
                f"input.scans_accumulated is {scans}",
            )
        )
        == 1
    )


def test_an_image_sets_folder_without_the_split_is_still_an_error(tmp_path):
    example = write_vod_example_set(tmp_path, frames=("00549",))
    (example / "radar" / "ImageSets").mkdir()
    (example / "radar" / "ImageSets" / "train.txt").write_text("00549\n")
    with pytest.raises(InputError, match=r"val.txt: split file missing; ImageSets has \['train'\]"):
        DetectionSet(example / "radar", "val", VOD)


def test_the_tj4d_sample_reads_as_published_and_says_the_image_size(tmp_path):
    """Sample/ of TJ4DRadSet: no ImageSets (every labelled frame, said with the count), no
    image_2 (the image size is TJ4D's camera or the card's input.image_size, said once with the
    calibration's principal point), the README's 'Other' class."""
    sample = write_tj4d_sample(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = DetectionSet(sample, "val", TJ4D)
    assert ds.frame_ids == [f"{70070 + k:06d}" for k in range(5)]
    assert len(_said(caught, "every labelled frame")) == 1 and len(_said(caught, ": 5 frames")) == 1
    size = _said(caught, "have no camera image")
    assert (
        len(size) == 1
        and "1280 x 960 px (TJ4DRadSet's camera, radaredge's default; the card has no input.image_size)" in size[0]
        and "P2's principal point" in size[0]
    )
    frame = ds.frame(0, ["x", "y", "z", "v_r", "snr"])
    assert frame.image_size == (1280, 960) and "Other" in list(frame.labels.name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = DetectionSet(sample, "val", TJ4D, image_size=[1250, 924])
    assert len(_said(caught, "1250 x 924 px (the card's input.image_size)")) == 1
    assert ds.frame(0, ["x", "y", "z"]).image_size == (1250, 924)
    with pytest.raises(InputError, match="input.image_size"):
        DetectionSet(sample, "val", TJ4D, image_size=[1250])


def test_a_make_benchmark_set_says_nothing(tmp_path):
    """radaredge's own labelled set: ImageSets, the dataset's camera (benchmark.json), the card's
    folder: nothing read unasked; a copy of its radar/ without benchmark.json says the image size."""
    from radaredge.data.detection_benchmark import make_detection_benchmark

    make_detection_benchmark(tmp_path / "set", drives=2, frames=2, seed=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        DetectionSet(tmp_path / "set", "val", VOD, 5)
        DetectionSet(tmp_path / "set" / "radar", "val", VOD, 1)
    assert not caught, [str(w.message) for w in caught]
    (tmp_path / "set" / "radar").rename(tmp_path / "copy")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        DetectionSet(tmp_path / "copy", "val", VOD, 1)
    assert len(_said(caught, "1936 x 1216 px (View-of-Delft's camera")) == 1


def test_times_in_seconds_are_said(tmp_path):
    """VoD's time column is the scan index (0, -1, ..., -4); radaredge's set writes it so, and a
    radar_5frames folder written with times in seconds (-0.1 s a scan) is said once, with the value."""
    from radaredge.data.detection_benchmark import make_detection_benchmark

    make_detection_benchmark(tmp_path / "set", drives=2, frames=2, seed=0)
    for path in (tmp_path / "set" / "radar_5frames" / "training" / "velodyne").glob("*.bin"):
        table = np.fromfile(path, "<f4").reshape(-1, 7)
        assert set(np.unique(table[:, 6]).tolist()) == {-4.0, -3.0, -2.0, -1.0, 0.0}
        table[:, 6] *= 0.1
        table.tofile(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        DetectionSet(tmp_path / "set", "val", VOD, 5)
    assert len(_said(caught, "not a whole number: View-of-Delft's time is the scan index")) == 1


# ----------------------------------------------------------------------------- item 4: said once


def test_tj4d_power_served_as_rcs_is_said_once_per_run(tmp_path):
    sample = write_tj4d_sample(tmp_path, count=3)
    files = sorted((sample / "training" / "velodyne").glob("*.bin"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")  # as the CLI and Python's default say them
        for f in files:
            read_scan(f, ["x", "y", "z", "v_r", "rcs"])
        for f in files:
            read_scan(f, ["x", "y", "z", "v_r", "snr"])  # SNR is what TJ4D's Power is: nothing to say
    said = [str(w.message) for w in caught]
    assert len(said) == 1 and "'rcs'" in said[0] and "Power column" in said[0] and "features" in said[0]


@pytest.fixture(scope="module")
def tiny_graph(maffnet_tiny_export):
    from radaredge import runtime
    from radaredge.cards import load_card

    return runtime.load(maffnet_tiny_export[1]), load_card(MAFFNET_TINY_CARD)


def _crowded_scan(card, outside: int = 5) -> np.ndarray:
    """20 points in one pillar (the card keeps 16), 30 spread ones, ``outside`` beyond the range."""
    rng = np.random.default_rng(0)
    pile = np.column_stack([np.full(20, 5.0), np.full(20, 0.5), np.linspace(-1, 0, 20)])
    spread = np.column_stack([rng.uniform(1, 12, 30), rng.uniform(-6, 6, 30), rng.uniform(-1, 1, 30)])
    far = np.column_stack([np.full(outside, 40.0), np.zeros(outside), np.zeros(outside)])
    xyz = np.concatenate([pile, spread, far])
    pts = np.zeros((len(xyz), len(card.features)), np.float32)
    pts[:, :3] = xyz
    return pts


def test_the_runtime_says_pillar_cap_and_range_drops_once_per_graph(tiny_graph):
    """input_flags bit 8 (points beyond pillars.max_points_per_pillar dropped) and bit 4 (points
    outside pillars.point_cloud_range, with their share) said the first time each is set on a
    loaded graph, counted every run in flag_tally."""
    from radaredge import runtime

    model, card = tiny_graph
    model = runtime.load(model.path)
    pts = _crowded_scan(card)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            out = model.run([pts])
    assert int(out["input_flags"][0]) & 8 and int(out["input_flags"][0]) & 4
    cap = _said(caught, "pillars.max_points_per_pillar = 16")
    rng = _said(caught, "pillars.point_cloud_range")
    assert len(cap) == 1 and "input_flags bit 8" in cap[0] and "dropped" in cap[0]
    assert len(rng) == 1 and f"5 of the {len(pts)} points fed (9.1%)" in rng[0]
    t = model.flag_tally
    assert (t.runs, t.capacity, t.out_of_range, t.points, t.outside) == (3, 3, 3, 3 * len(pts), 15)


def test_eval_on_the_example_set_layout_says_each_note_once(tmp_path, maffnet_tiny_export):
    """`radaredge eval --data example_set` (no ImageSets, JSON labels) runs with no file edited,
    and says each note once: the split of every labelled frame, the frames whose pillars
    overflowed, the share of points outside the range."""
    example = write_vod_example_set(tmp_path)
    card, onnx = maffnet_tiny_export
    for fid in ("00549", "01047", "01201"):  # crowd one pillar of every scan
        scan = example / "radar" / "training" / "velodyne" / f"{fid}.bin"
        rows = np.fromfile(scan, "<f4").reshape(-1, 7)
        pile = np.zeros((20, 7), "<f4")
        pile[:, 0], pile[:, 1], pile[:, 2] = 5.0, 0.5, np.linspace(-1, 0, 20)
        np.concatenate([rows, pile]).tofile(scan)
    res = invoke(
        "eval",
        "--model",
        "maffnet-tiny",
        "--config",
        card,
        "--onnx",
        onnx,
        "--data",
        example,
        "--no-reference",
        "--report",
        tmp_path / "r.json",
    )
    assert res.exit_code == 0, res.output
    warned = [ln for ln in res.output.splitlines() if ln.startswith("warning:")]
    assert len([w for w in warned if "every labelled frame" in w and ": 3 frames" in w]) == 1, res.output
    assert (
        len(
            [
                w
                for w in warned
                if "input_flags bit 8 (capacity) in 3 of 3 frames" in w and "pillars.max_points_per_pillar = 16" in w
            ]
        )
        == 1
    ), res.output
    assert len([w for w in warned if "pillars.point_cloud_range" in w and "frames) lie outside" in w]) == 1, res.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["frames"] == 3 and any("every labelled frame" in n for n in report["notes"])


def test_the_dbscan_capacity_error_gives_the_count(tmp_path):
    """More scan points than cfa.dbscan.capacity: the error names how many, as the SPA one names
    the pillars."""
    import radaredge
    from radaredge import runtime
    from radaredge.cards import load_card

    data = yaml.safe_load(MAFFNET_TINY_CARD.read_text())
    data["name"] = "maffnet-tiny-dbscan"
    data["cfa"] = {
        "velocity_feature": "v_r_comp",
        "method": "dbscan",
        "dbscan": {
            "eps": 1.0,
            "min_samples": 4,
            "max_cluster_size": 100,
            "capacity": 16,
            "map_rows": 40,
            "map_cols": 40,
            "resolution": 0.32,
            "y_offset": 6.4,
        },
    }
    path = tmp_path / "maffnet-tiny-dbscan.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    radaredge.export(path, tmp_path / "g.onnx")
    card = load_card(path)
    pts = _crowded_scan(card, outside=4)
    pts[-1, :2] = (12.8, 6.4)  # on the range's x, y bounds: a scan point
    with pytest.raises(CapacityError, match=r"the scan has 51 points inside the range .* cfa.dbscan.capacity = 16"):
        runtime.load(tmp_path / "g.onnx").run([pts])
