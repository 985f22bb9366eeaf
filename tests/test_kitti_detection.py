"""The KITTI-layout detection set: labels into the radar frame, the synthetic VoD set, and one
`error:` line naming the file and line for every malformed label, calibration or split file."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import invoke

from radaredge.data.detection_benchmark import make_detection_benchmark, synthetic_calibration
from radaredge.data.kitti_detection import (
    TJ4D,
    VOD,
    DetectionSet,
    camera_fov_mask,
    image_size,
    labels_to_radar_boxes,
    radar_boxes_to_labels,
    read_calibration,
    read_labels,
)
from radaredge.data.synthetic import generate_scan
from radaredge.errors import InputError


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("det") / "set"
    make_detection_benchmark(out, drives=3, frames=3, seed=1)
    return out


def test_labels_go_into_the_radar_frame_as_the_devkits_do():
    """Radar boxes -> camera labels -> radar boxes is the identity (headings modulo 2 pi), the
    label's location is the bottom centre and rotation_y = -(heading + pi / 2)."""
    calib = synthetic_calibration()
    scan = generate_scan(seed=3)
    boxes = scan.boxes.astype(np.float64)
    labels = radar_boxes_to_labels(
        boxes, np.zeros(len(boxes)), np.array(["Car"] * len(boxes), dtype=object), calib, (1936, 1216)
    )
    back = labels_to_radar_boxes(labels, calib)
    np.testing.assert_allclose(back[:, :6], boxes[:, :6], atol=1e-9)
    np.testing.assert_allclose(np.cos(back[:, 6] - boxes[:, 6]), 1.0, atol=1e-12)
    np.testing.assert_allclose(labels.rotation_y, -(boxes[:, 6] + np.pi / 2))
    bottom = boxes[:, :3] - np.column_stack([np.zeros((len(boxes), 2)), boxes[:, 5] / 2])
    np.testing.assert_allclose(labels.location, calib.radar_to_rect(bottom))


def test_camera_frame_axes_and_fov_crop():
    calib = synthetic_calibration()
    ahead = calib.radar_to_rect(np.array([[20.0, 0.0, 0.6]]))[0]  # 20 m ahead at camera height
    assert ahead[2] > 19.9 and abs(ahead[0]) < 1e-9  # z forward, no lateral offset
    left = calib.radar_to_rect(np.array([[20.0, 3.0, 0.0]]))[0]
    assert left[0] < 0  # radar y left = camera x negative
    pts = np.array([[20.0, 0.0, 0.0], [20.0, 20.0, 0.0], [-5.0, 0.0, 0.0], [20.0, -12.0, 0.0]])
    assert camera_fov_mask(pts, calib, (1936, 1216)).tolist() == [True, False, False, True]  # +-32.9 deg


def test_the_synthetic_set_reads_back(bench):
    ds = DetectionSet(bench, "val", VOD, scans_accumulated=5)
    assert ds.root.name == "radar_5frames" and len(ds) == 3
    frame = ds.frame(0, ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"])
    assert frame.points.shape[1] == 7
    # VoD's time is the scan index (0 the current scan, -1 the one before, ...), not seconds
    assert set(np.unique(frame.points[:, 6]).tolist()) == {-4.0, -3.0, -2.0, -1.0, 0.0}
    assert frame.image_size == (1936, 1216) and len(frame.labels) > 3
    assert set(frame.labels.name) <= {"Car", "Pedestrian", "Cyclist"}
    assert set(frame.labels.occluded.tolist()) <= {0, 1, 2}
    single = DetectionSet(bench / "radar", "val", VOD).frame(0, ["x", "y", "z"])
    assert (np.abs(single.points[:, 2]) < 50).all() and len(single.points) < len(frame.points)
    train = DetectionSet(bench, "train", VOD, 5)
    assert not set(train.frame_ids) & set(ds.frame_ids)  # split by drive


def test_tj4d_layout(tmp_path):
    make_detection_benchmark(tmp_path / "tj", drives=2, frames=2, seed=0, dataset="tj4d")
    ds = DetectionSet(tmp_path / "tj", "val", TJ4D)
    frame = ds.frame(0, ["x", "y", "z", "v_r", "snr"])
    assert frame.image_size == (1280, 960) and frame.points.shape[1] == 5


def test_image_size_from_png_and_jpeg_headers(tmp_path):
    png = tmp_path / "a.png"
    png.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + b"\x00\x00\x00\rIHDR"
        + (1936).to_bytes(4, "big")
        + (1216).to_bytes(4, "big")
        + b"\x08\x02\x00\x00\x00"
    )
    assert image_size(png) == (1936, 1216)
    jpg = tmp_path / "a.jpg"
    jpg.write_bytes(
        b"\xff\xd8"
        + b"\xff\xe0\x00\x04ab"
        + b"\xff\xc0\x00\x11\x08"
        + (960).to_bytes(2, "big")
        + (1280).to_bytes(2, "big")
        + b"\x03"
        + b"\x00" * 9
    )
    assert image_size(jpg) == (1280, 960)


# ----------------------------------------------------------------------------- bad input


def _copy(bench: Path, tmp_path: Path) -> Path:
    root = tmp_path / "set"
    shutil.copytree(bench / "radar", root)
    return root


def _fid(root: Path) -> str:
    return (root / "ImageSets" / "val.txt").read_text().split()[0]


@pytest.mark.parametrize(
    "case, expect",
    [
        ("missing label", "label file missing"),
        ("column count", ":2: 12 fields"),
        ("unknown class", ":1: unknown class 'Tank'"),
        ("not a number", ":1: a field after the class is not a number"),
        ("missing calib", "calibration file missing"),
        ("calib values", ":6: Tr_velo_to_cam must hold 12 finite numbers, got 11"),
        ("singular calib", ":6: Tr_velo_to_cam's 3 x 3 rotation part cannot be inverted"),
        ("no Tr line", "no Tr_velo_to_cam line"),
    ],
)
def test_bad_labels_and_calibration_name_the_file_and_line(bench, tmp_path, case, expect):
    root = _copy(bench, tmp_path)
    fid = _fid(root)
    label, calib = root / "training" / "label_2" / f"{fid}.txt", root / "training" / "calib" / f"{fid}.txt"
    lines, cal = label.read_text().splitlines(), calib.read_text().splitlines()
    if case == "missing label":
        label.unlink()
    elif case == "column count":
        label.write_text("\n".join([lines[0], " ".join(lines[1].split()[:12])]) + "\n")
    elif case == "unknown class":
        label.write_text("Tank" + lines[0][lines[0].index(" ") :] + "\n")
    elif case == "not a number":
        label.write_text(lines[0].replace(" 0 ", " x ", 1) + "\n")
    elif case == "missing calib":
        calib.unlink()
    elif case == "calib values":
        cal[5] = " ".join(cal[5].split()[:-1])
        calib.write_text("\n".join(cal) + "\n")
    elif case == "singular calib":
        cal[5] = "Tr_velo_to_cam: " + " ".join(["0"] * 12)
        calib.write_text("\n".join(cal) + "\n")
    elif case == "no Tr line":
        calib.write_text("\n".join(c for c in cal if not c.startswith("Tr_velo")) + "\n")
    with pytest.raises(InputError) as err:
        DetectionSet(root, "val", VOD).frame(0, ["x", "y", "z"])
    where = label if "label" in case or case in ("column count", "unknown class", "not a number") else calib
    assert str(where) in str(err.value) and expect in str(err.value)


@pytest.mark.parametrize(
    "case, expect",
    [
        ("missing split", "ImageSets/val.txt: split file missing; ImageSets has ['test', 'train']"),
        ("frame without scan", "val.txt:2: frame 99999 is listed but"),
        ("bad id", "val.txt:1: 'a b' is not a frame id"),
        ("empty split", "val.txt: lists no frames"),
        ("not a set", "no training/ folder"),
    ],
)
def test_bad_image_sets(bench, tmp_path, case, expect):
    root = _copy(bench, tmp_path)
    split = root / "ImageSets" / "val.txt"
    if case == "missing split":
        split.unlink()
    elif case == "frame without scan":
        split.write_text(f"{_fid(root)}\n99999\n")
    elif case == "bad id":
        split.write_text("a b\n")
    elif case == "empty split":
        split.write_text("\n")
    elif case == "not a set":
        root = root / "training" / "calib"
    with pytest.raises(InputError) as err:
        DetectionSet(root, "val", VOD)
    assert expect in str(err.value)


def test_the_command_line_says_one_error_line(bench, tmp_path, maffnet_tiny_export):
    root = _copy(bench, tmp_path)
    fid = _fid(root)
    (root / "training" / "label_2" / f"{fid}.txt").write_text("Car 0 0\n")
    card, onnx = maffnet_tiny_export
    res = invoke(
        "eval",
        "--model",
        "maffnet-tiny",
        "--config",
        card,
        "--onnx",
        onnx,
        "--data",
        root,
        "--no-reference",
        "--report-dir",
        tmp_path / "r",
    )
    assert res.exit_code == 2
    errors = [line for line in res.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and f"label_2/{fid}.txt:1: 3 fields" in errors[0], res.output


def test_read_labels_accepts_scores_and_dont_care(tmp_path):
    f = tmp_path / "l.txt"
    f.write_text(
        "DontCare -1 -1 -10 100 200 150 260 -1 -1 -1 -1000 -1000 -1000 -10\n"
        "Car 0 1 0.1 1 2 3 4 1.5 1.8 4.2 1 1.2 20 0.3 0.9\n\n"
    )
    labels = read_labels(f, VOD.label_classes)
    assert list(labels.name) == ["DontCare", "Car"] and labels.score.tolist() == [0.0, 0.9]
    np.testing.assert_allclose(labels.dimensions[1], [4.2, 1.5, 1.8])  # (l, h, w) from h, w, l


def test_a_missing_r0_rect_is_the_identity(tmp_path):
    f = tmp_path / "c.txt"
    f.write_text("P2: 1000 0 500 0 0 1000 400 0 0 0 1 0\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n")
    calib = read_calibration(f)
    np.testing.assert_allclose(calib.R0, np.eye(3))
    np.testing.assert_allclose(calib.rect_to_radar(calib.radar_to_rect(np.array([[5.0, 1.0, -1.0]]))), [[5, 1, -1]])
