"""The DBSCAN path of MAFF-Net's clustering features as upstream runs it (CQCA_cfa with sklearn)
and the speed-up script that times it against GridDensityBEV."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from radaredge.ops.dbscan import VOD, cqca_cfa_map_reference, cqca_cfa_map_sklearn

ROOT = Path(__file__).resolve().parents[1]


def _blob(rng, centre, n, v):
    xy = centre + rng.uniform(-0.15, 0.15, (n, 2))
    return np.c_[xy, np.full(n, v)].astype(np.float32)


def test_cqca_cfa_map_follows_upstream_rules():
    rng = np.random.default_rng(0)
    first = _blob(rng, (10.0, 0.0), 12, 1.0)  # DBSCAN cluster 0: upstream's labels > 0 leaves it out
    second = _blob(rng, (20.0, 5.0), 15, -2.0)  # cluster 1: written with density 15
    big = _blob(rng, (30.0, -5.0), 120, 0.5)  # cluster 2, above 100 points: noise
    lone = np.array([[40.0, 10.0, 3.0]], np.float32)  # noise
    pts = np.concatenate([first, second, big, lone])
    bev, labels = cqca_cfa_map_sklearn(pts)
    assert bev.shape == (3, 320, 320)
    assert labels.tolist() == [0] * 12 + [1] * 15 + [-1] * 121
    written = torch.nonzero(bev[1]).tolist()
    cells = {(int((y + 25.6) / 0.16) - 1, int(x / 0.16) - 1) for x, y, _ in second}
    assert {tuple(c) for c in written} == cells
    r, c = next(iter(cells))
    assert bev[:, r, c].tolist() == pytest.approx([-2.0, 15.0, 1.0])
    vec, vec_labels = cqca_cfa_map_sklearn(pts, vectorised=True)
    assert torch.equal(vec, bev) and torch.equal(vec_labels, labels)
    ref, ref_points, _ = cqca_cfa_map_reference(pts, np.ones(len(pts), bool), VOD)
    np.testing.assert_array_equal(bev.numpy(), ref)
    np.testing.assert_array_equal(labels.numpy() != -1, ref_points)


def test_speedup_script_measures_every_backend(tmp_path):
    res = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "cfa_speedup.py"),
            "--runs",
            "1",
            "--warmup",
            "0",
            "--threads",
            "1",
            "--clouds",
            "1",
            "--scans",
            "1",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    [path] = tmp_path.glob("cfa-speedup-*.json")
    rows = json.loads(path.read_text())["rows"]
    assert {(r["part"], r["backend"]) for r in rows} == {
        (part, b)
        for part in ("map", "map + CNN")
        for b in (
            "CQCA_cfa: DBSCAN + per-point loop (upstream)",
            "CQCA_cfa: DBSCAN + np.unique counts",
            "GridDensityBEV, torch",
            "GridDensityBEV, onnxruntime",
        )
    }
    assert all(r["scans"] == 1 and r["p50_ms"] > 0 and r["points"] > 100 for r in rows)
    assert "| 1 scan," in res.stdout
