"""`parity-check --data DIR`: the graph against the reference on the user's own recording.

Drives (scans/ + gps.csv, `make_pr_benchmark`), KITTI layouts (`make_detection_benchmark`) and
plain folders of .bin scans feed the same comparators as the synthetic cases; the report adds
the recording and a capacity summary; bad recordings are one error line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import MAFFNET_TINY_CARD, MAFFNET_TINY_FULL_DBSCAN_CARD, TINY_CARD, invoke, one_error_line

import radaredge
from radaredge.cards import load_card, parse_card
from radaredge.checking.capacity import point_counts
from radaredge.checking.recording import recorded_cases, spread
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.data.readers import read_scan
from radaredge.errors import ConfigError, InputError
from radaredge.models import model_spec
from radaredge.models.maffnet import rcnn
from radaredge.ops.pillars import PillarConfig, point_drops_reference

DES4POS_TINY = Path(__file__).parent / "cards" / "des4pos-tiny.yaml"


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """Two synthetic drives of 6 scans (TransLoc4D .npy, gps.csv at 10 Hz)."""
    root = tmp_path_factory.mktemp("drives")
    make_pr_benchmark(root, drives=2, frames_per_drive=6, seed=0)
    return root


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    """A labelled View-of-Delft layout: radar/ and radar_5frames/, 2 drives of 2 frames."""
    root = tmp_path_factory.mktemp("kitti")
    make_detection_benchmark(root, drives=2, frames=2, seed=0)
    return root


def _tj4d_folder(drive: Path, out: Path) -> Path:
    """The drive's scans as a plain folder of TJ4DRadSet .bin files (its training/velodyne/):
    X, Y, Z, V_r, Range, Power (the intensity), Alpha, Beta; no gps.csv."""
    out.mkdir()
    for p in sorted((drive / "scans").iterdir()):
        t = np.load(p)
        rows = np.zeros((len(t), 8), "<f4")
        rows[:, :4] = t[:, :4]
        rows[:, 4] = np.linalg.norm(t[:, :3], axis=1)
        rows[:, 5] = t[:, 4]
        rows.tofile(out / f"{p.stem}.bin")
    return out


def _summary_shape(report: dict) -> dict:
    """Per output its kind and tolerance: what says the same comparators judged it."""
    graph = next(iter(report["graphs"].values()))
    return {k: (v["kind"], json.dumps(v["tolerance"], sort_keys=True)) for k, v in graph["summary"].items()}


# ----------------------------------------------------------------------------- TDFANet windows


def test_tdfanet_windows_of_a_drive_pass_like_the_synthetic_cases(tiny_export, drives):
    _, _, onnx_path, _ = tiny_export
    drive = drives / "database" / "drive-00"
    res = invoke(
        "parity-check",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx_path,
        "--data",
        drive,
        "--frames",
        3,
        "--json",
    )
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    assert report["passed"]
    data = report["data"]
    assert data["kind"] == "drive" and data["unit"] == "window" and data["window"] == 3
    assert data["available"] == 4 and data["checked"] == 3 and data["timestamps"] == "gps.csv timestamps"
    # spread evenly, first and last window included
    assert list(data["files"]) == ["000000-000002", "000002-000004", "000003-000005"]
    graph = report["graphs"]["tdfanet"]
    assert [c["case"] for c in graph["cases"]] == list(data["files"])
    cap = graph["capacity"]["summary"]
    assert cap["cases"] == 3 and cap["frames"] == 9 and cap["points"] > 0
    assert cap["points_out_of_range"] > 0 and cap["input_flags"]["out_of_range"] == 9
    assert cap["ego_valid"]["frames"] == 9
    # the same comparators as the synthetic cases, output by output
    synthetic = invoke(
        "parity-check", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", onnx_path, "--cases", 2, "--json"
    )
    assert synthetic.exit_code == 0, synthetic.output
    assert _summary_shape(report) == _summary_shape(json.loads(synthetic.stdout))
    assert json.loads(synthetic.stdout)["data"] is None


def test_tdfanet_on_a_plain_folder_of_bin_scans_and_a_directory_of_drives(tiny_export, drives, tmp_path):
    card, model, onnx_path, _ = tiny_export
    folder = _tj4d_folder(drives / "database" / "drive-00", tmp_path / "velodyne")
    report = radaredge.parity(card, onnx_path, model=model, data=folder, frames=2)
    assert report.passed and report.data.kind == "folder" and report.data.fmt == "tj4d"
    assert "frame_rate, 10 Hz" in report.data.timestamps
    text = "\n".join(report.lines())
    assert "2 recorded windows" in text and "window times: the card's frame_rate" in text
    assert "capacity over the recording" in text and text.endswith("PASSED")
    # every drive under a directory (database/ and queries/), windows never across two drives
    many = radaredge.parity(card, onnx_path, model=model, data=drives, frames=3)
    assert many.passed and many.data.kind == "drives" and many.data.available == 8
    names = [c["case"] for c in many.graph().cases]
    assert names[0] == "database/drive-00/000000-000002" and names[-1] == "queries/drive-01/000003-000005"


def test_a_recorded_case_fails_through_the_same_comparators(tiny_export, drives, monkeypatch):
    """A graph whose descriptor is off is FAILED on the recording, naming the recording's window."""
    from radaredge.checking import check

    _, _, onnx_path, _ = tiny_export
    real = check.graph_runner

    def off(path, runtime="onnxruntime"):
        run = real(path, runtime)

        def perturbed(feeds):
            out = dict(run(feeds))
            if "descriptor" in out:
                out["descriptor"] = out["descriptor"] + 0.01
            return out

        return perturbed

    monkeypatch.setattr(check, "graph_runner", off)
    res = invoke(
        "parity-check",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx_path,
        "--data",
        drives / "database" / "drive-00",
        "--frames",
        2,
        "--json",
    )
    assert res.exit_code == 1, res.output
    summary = json.loads(res.stdout)["graphs"]["tdfanet"]["summary"]
    assert not summary["descriptor"]["passed"] and summary["descriptor"]["failed_cases"] == [
        "000000-000002",
        "000003-000005",
    ]
    assert summary["input_flags"]["passed"]


# ----------------------------------------------------------------------------- MAFF-Net frames


def test_maffnet_frames_of_a_kitti_split(maffnet_tiny_export, kitti):
    card_path, onnx_path = maffnet_tiny_export
    res = invoke(
        "parity-check",
        "--model",
        "maffnet-tiny",
        "--config",
        card_path,
        "--onnx",
        onnx_path,
        "--data",
        kitti / "radar",
        "--split",
        "val",
        "--frames",
        1,
        "--json",
    )
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    data = report["data"]
    assert data["kind"] == "kitti" and data["split"] == "val" and data["unit"] == "frame"
    assert data["available"] == 2 and data["checked"] == 1 and data["timestamps"] is None
    graph = report["graphs"]["maffnet"]
    assert graph["summary"]["boxes"]["kind"] == "boxes" and graph["summary"]["boxes"]["passed"]
    cap = graph["capacity"]["summary"]
    assert cap["spa"]["capacity"] == 256 and 0 < cap["spa"]["max_pillars"] <= 256 and not cap["spa"]["overflow_cases"]
    assert cap["cfa"]["method"] == "grid_density" and cap["cfa"]["not_converged_cases"] == []
    assert "ego_valid" not in cap


def test_maffnet_on_a_plain_folder_and_a_frame_over_the_pillar_capacity(maffnet_tiny_export, kitti, tmp_path):
    """A scan with more non-empty pillars than spa.capacity: the graph flags it, the reference
    refuses it; it is listed, not compared, and counted in the capacity summary."""
    card_path, onnx_path = maffnet_tiny_export
    card = load_card(card_path)
    folder = tmp_path / "scans"
    folder.mkdir()
    shutil.copy(sorted((kitti / "radar" / "training" / "velodyne").iterdir())[0], folder / "000000.bin")
    rng = np.random.default_rng(0)
    dense = np.zeros((1201, 7), "<f4")  # 1201 points over 40 x 40 pillars: > 256 occupied
    dense[:, 0] = rng.uniform(0.1, 12.7, len(dense))
    dense[:, 1] = rng.uniform(-6.3, 6.3, len(dense))
    dense[:, 3] = rng.normal(0, 5, len(dense))
    dense.tofile(folder / "000001.bin")
    res = invoke(
        "parity-check", "--model", "maffnet-tiny", "--config", card_path, "--onnx", onnx_path, "--data", folder
    )
    assert res.exit_code == 0, res.output
    text = res.output
    assert "1 recorded frames" in text and "a folder of scan files" in text
    assert "not compared: 1 frame(s) the reference refuses" in text and "000001: scan has" in text
    assert "spa_overflow in 1 of 2: 000001" in text and "cfa grid_density" in text
    assert text.rstrip().endswith("PASSED")
    # the overflowing scan alone: nothing compared, FAILED
    (folder / "000000.bin").unlink()
    alone = radaredge.parity(card, onnx_path, data=folder)
    assert not alone.passed and alone.graph().skipped and "no frame could be compared" in "\n".join(alone.lines())


# ----------------------------------------------------------------------------- reading recordings


def _card_with(path: Path, **changes):
    data = yaml.safe_load(Path(path).read_text())
    for key, value in changes.items():
        node = data
        *parents, last = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    return parse_card(data, Path(path))


def test_kitti_roots_and_the_camera_crop(kitti, tmp_path):
    card = _card_with(MAFFNET_TINY_CARD, **{"input.crop": "camera_fov"})
    graph = model_spec(card).graph()
    # VoD's top folder: the card's accumulated scans (1: radar/); every frame without --split
    rec = recorded_cases(card, graph, kitti, frames=10)
    assert rec.kind == "kitti" and rec.available == 4 and rec.directory == str(kitti)
    assert any("camera_fov: each scan cropped" in n for n in rec.notes)
    name, feeds = rec.cases[0]
    raw = read_scan(kitti / "radar" / "training" / "velodyne" / f"{name}.bin", card.features)
    assert 0 < len(feeds["points"]) < len(raw)
    five = recorded_cases(_card_with(MAFFNET_TINY_CARD, **{"input.scans_accumulated": 5}), graph, kitti, frames=1)
    assert Path(rec.files[rec.cases[0][0]][0]).parts[-4] == "radar"
    assert Path(five.files[five.cases[0][0]][0]).parts[-4] == "radar_5frames"
    # a single-scan folder for a 5-scan card: checked, with a note; a top folder without it: refused
    single = recorded_cases(
        _card_with(MAFFNET_TINY_CARD, **{"input.scans_accumulated": 5}), graph, kitti / "radar", frames=1
    )
    assert any("holds 1 accumulated scan(s)" in n for n in single.notes)
    top = tmp_path / "example_set"
    shutil.copytree(kitti / "radar", top / "radar")
    with pytest.raises(InputError, match="takes 5 accumulated scan.*radar/"):
        recorded_cases(_card_with(MAFFNET_TINY_CARD, **{"input.scans_accumulated": 5}), graph, top)
    # no calib/: fed whole, and said so
    shutil.rmtree(top / "radar" / "training" / "calib")
    whole = recorded_cases(card, graph, top / "radar", frames=1)
    assert any("not applied" in n for n in whole.notes)


def test_spread_takes_first_and_last():
    assert spread(3, 20).tolist() == [0, 1, 2]
    assert spread(10, 4).tolist() == [0, 3, 6, 9]
    assert spread(5, 1).tolist() == [0]


def test_point_counts_match_the_reference_drops():
    card = load_card(MAFFNET_TINY_FULL_DBSCAN_CARD)
    pillars = card.section("pillars", PillarConfig)
    rng = np.random.default_rng(1)
    pts = np.zeros((600, len(card.features)), np.float32)
    pts[:, 0] = rng.uniform(-2, 15, len(pts))
    pts[:, 1] = rng.uniform(-8, 8, len(pts))
    pts[:, 2] = rng.uniform(-4, 3, len(pts))
    pts[:200, :2] = rng.uniform(1.0, 1.5, (200, 2))  # a crowded corner: full pillars
    counts = point_counts(pts, card, pillars)
    outside, full = point_drops_reference(pts, pillars)
    assert counts["out_of_range"] == outside.sum() and counts["over_pillar_cap"] == full.sum() > 0
    import torch

    assert counts["scan_points"] == int(rcnn.scan_points(torch.from_numpy(pts), pillars.point_cloud_range)[2].sum())


# ----------------------------------------------------------------------------- bad input


def _bad(tmp_path, onnx_path, *args, card=TINY_CARD, model="tdfanet-tiny"):
    return invoke("parity-check", "--model", model, "--config", card, "--onnx", onnx_path, *args)


def test_bad_recordings_are_one_error_line(tiny_export, drives, tmp_path):
    _, _, onnx_path, _ = tiny_export
    empty = tmp_path / "empty"
    empty.mkdir()
    npy4 = tmp_path / "npy4"
    npy4.mkdir()
    for i in range(3):
        np.save(npy4 / f"{i:06d}.npy", np.zeros((10, 4), np.float32))
    bin6 = tmp_path / "bin6"
    bin6.mkdir()
    for i in range(3):
        np.zeros((5, 6), "<f4").tofile(bin6 / f"{i:06d}.bin")  # 120 bytes: neither 28- nor 32-byte rows
    short = tmp_path / "short"
    short.mkdir()
    for p in sorted((drives / "database" / "drive-00" / "scans").iterdir())[:2]:
        shutil.copy(p, short / p.name)
    drive = drives / "database" / "drive-00"
    cases = [
        (("--data", tmp_path / "nowhere"), ("nowhere: no such directory",)),
        (("--data", drive / "gps.csv"), ("is a file, not a directory",)),
        (("--data", empty), ("no scan files", "a KITTI layout")),
        (("--data", npy4), ("000000.npy: 4 columns",)),
        (("--data", bin6), ("fit neither", "--format")),
        (("--data", short), ("takes 3 consecutive scans",)),
        (("--data", drive, "--frames", 0), ("frames: expected an integer from 1",)),
        (("--data", drive, "--cases", 4), ("--cases draw(s) synthetic cases", "--frames")),
        (("--data", drive, "--split", "val"), ("--split picks labelled frames", "windows of 3")),
        (("--frames", 2), ("--frames: choose(s) the frames of a recording; add --data",)),
    ]
    for args, needles in cases:
        one_error_line(_bad(tmp_path, onnx_path, *args), *needles)


def test_models_without_scans_and_splits_without_imagesets_are_refused(maffnet_tiny_export, kitti, tmp_path):
    one_error_line(
        invoke(
            "parity-check", "--model", "des4pos-tiny", "--config", DES4POS_TINY, "--onnx", tmp_path, "--data", kitti
        ),
        "des4pos-tiny takes no radar scans",
        "drop --data",
    )
    card_path, onnx_path = maffnet_tiny_export
    no_sets = tmp_path / "no-sets"
    shutil.copytree(kitti / "radar", no_sets)
    shutil.rmtree(no_sets / "ImageSets")
    one_error_line(
        _bad(tmp_path, onnx_path, "--data", no_sets, "--split", "val", card=card_path, model="maffnet-tiny"),
        "--split val",
        "drop --split to check every frame",
    )
    one_error_line(
        _bad(tmp_path, onnx_path, "--data", kitti / "radar", "--split", "nope", card=card_path, model="maffnet-tiny"),
        "ImageSets has ['test', 'train', 'val']",
    )
    with pytest.raises(ConfigError, match="takes no radar scans"):
        radaredge.parity(DES4POS_TINY, tmp_path, data=kitti)
