"""Recorded radar, end to end: the public View-of-Delft ``example_set`` and TJ4DRadSet ``Sample``
frames read as published, every MAFF-Net card and tdfanet-edge checked against the reference on
them (``parity-check --data``), their capacity margins, and the ego velocity along the TJ4D
sequence.

Gated like the upstream-config tests: set ``RADAREDGE_REAL_DATA`` to a directory holding the two
repositories as cloned (``view-of-delft-dataset/example_set``, ``TJ4DRadSet/Sample``;
docs/data.md says how); skipped otherwise. The recordings are never part of this repository.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import invoke

from radaredge.data.kitti_detection import LAYOUTS, list_frames
from radaredge.data.readers import read_scan

REAL = os.environ.get("RADAREDGE_REAL_DATA")
pytestmark = pytest.mark.skipif(
    not REAL,
    reason="set RADAREDGE_REAL_DATA to a directory with the cloned view-of-delft-dataset and TJ4DRadSet (docs/data.md)",
)
ROOT = Path(REAL or ".")
VOD = ROOT / "view-of-delft-dataset" / "example_set"
TJ4D = ROOT / "TJ4DRadSet" / "Sample"
FRAMES = int(os.environ.get("RADAREDGE_REAL_FRAMES", "5"))  # TJ4D frames per MAFF-Net card (of 41)


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    return tmp_path_factory.mktemp("real-exports")


def _export(exports: Path, card: str) -> Path:
    path = exports / f"{card}.onnx"
    if not path.exists():
        res = invoke("export", "--model", card, "--output", path)
        assert res.exit_code == 0, res.output
    return path


def test_the_samples_read_as_published():
    vod = list_frames(VOD / "radar", "val", LAYOUTS["vod"], 1, None)
    tj4d = list_frames(TJ4D, "val", LAYOUTS["tj4d"], 1, None)
    assert len(vod.frame_ids) == 3 and len(tj4d.frame_ids) == 41, (vod.frame_ids, len(tj4d.frame_ids))
    assert vod.split_file is None and tj4d.split_file is None  # no ImageSets: every labelled frame
    assert any("image size" in n for n in tj4d.notes), tj4d.notes


# (card, recording, frames): every MAFF-Net card on the recording of its dataset
CARDS = [
    ("maffnet-vod", VOD / "radar", 3),
    ("maffnet-vod-edge", VOD / "radar", 3),
    ("maffnet-vod-full", VOD / "radar", 3),
    ("maffnet-vod-full-dbscan", VOD / "radar", 3),
    ("maffnet-tj4d", TJ4D, FRAMES),
    ("maffnet-tj4d-full", TJ4D, FRAMES),
    ("maffnet-tj4d-full-dbscan", TJ4D, FRAMES),
    ("tdfanet-edge", TJ4D / "training" / "velodyne", 39),
]


@pytest.mark.parametrize("card, data, frames", CARDS, ids=[c[0] for c in CARDS])
def test_parity_and_capacity_on_the_recordings(exports, card, data, frames):
    onnx = _export(exports, card)
    res = invoke("parity-check", "--model", card, "--onnx", onnx, "--data", data, "--frames", frames, "--json")
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    for graph in report["graphs"].values():
        s = graph["capacity"]["summary"]
        assert s["cases"] >= min(frames, 3)
        spa = s.get("spa")
        if spa and spa["enabled"]:  # the sparse attention's pillars: at most half full
            assert not spa["overflow_cases"] and spa["max_pillars"] <= 0.5 * spa["capacity"], spa
        cfa = s.get("cfa")
        if cfa and cfa["method"] == "dbscan":  # the clustering's points: at most half its capacity
            assert cfa["max_scan_points"] <= 0.5 * cfa["capacity"], cfa


@pytest.mark.parametrize("card, data", [("maffnet-vod-edge", VOD), ("maffnet-tj4d", TJ4D)], ids=["vod", "tj4d"])
def test_eval_runs_on_the_samples_as_published(exports, card, data, tmp_path):
    """`radaredge eval` on each sample as cloned (no ImageSets, VoD's JSON labels, TJ4D without
    images): every labelled frame scored, each AP with its interval, the notes said."""
    onnx = _export(exports, card)
    res = invoke(
        "eval",
        "--model",
        card,
        "--onnx",
        onnx,
        "--data",
        data,
        "--no-reference",
        "--report",
        tmp_path / "r.json",
        "--report-dir",
        tmp_path / "report",
    )
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["frames"] == (3 if data == VOD else 41), report["frames"]
    assert report["ap"] and report["ap_interval"]
    assert any("every labelled frame" in note for note in report["notes"]), report["notes"]


def test_the_ego_velocity_is_steady_along_the_tj4d_sequence(exports):
    """tdfanet-edge's in-graph RANSAC against a least-squares fit of the Doppler equation over the
    static points: forward speed steady along the 41 consecutive frames (the car drives straight)."""
    from radaredge import runtime

    model = runtime.load(_export(exports, "tdfanet-edge"), threads=2)
    scans = sorted((TJ4D / "training" / "velodyne").glob("*.bin"))
    frames = [read_scan(p, model.features, "tj4d") for p in scans]
    times = np.arange(model.frames, dtype=np.float32) / np.float32(model.card.data.get("frame_rate", 10.0))
    speeds, fits = [], []
    for k in range(len(frames) - model.frames + 1):
        window = frames[k : k + model.frames]
        out = model.run(window, times)
        assert bool(np.asarray(out["ego_valid"]).all())
        v = np.asarray(out["ego_velocity"])[-1]
        speeds.append(float(v[0]))
        pts = window[-1]
        xyz, vr = pts[:, :3].astype(np.float64), pts[:, model.features.index("v_r")].astype(np.float64)
        u = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
        fit = np.linalg.lstsq(u, -vr, rcond=None)[0]  # v_r = -u . v_ego for static points
        for _ in range(3):  # drop the movers, refit
            keep = np.abs(u @ fit + vr) < 0.3
            fit = np.linalg.lstsq(u[keep], -vr[keep], rcond=None)[0]
        fits.append(float(fit[0]))
    speeds, fits = np.array(speeds), np.array(fits)
    assert np.ptp(speeds) < 1.5, speeds
    assert np.abs(speeds - fits).max() < 0.1, np.abs(speeds - fits).max()
