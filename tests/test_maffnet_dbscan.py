"""MAFF-Net with upstream's DBSCAN clustering map in the graph (``cfa.method: dbscan``).

The map is compared with tests/references/sklearn_cqca_cfa.py (sklearn's DBSCAN and a per-point
loop, written from upstream's CQCA_cfa.generate_map), on the scan points upstream's model sees.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_parses_in_tensorrt, export_with_cli, invoke, summary_of
from references.maffnet_upstream import upstream_scan_mask
from references.sklearn_cqca_cfa import upstream_map

from radaredge import runtime
from radaredge.cards import load_card
from radaredge.errors import CapacityError, ConfigError
from radaredge.models import create_model, model_spec
from radaredge.models.maffnet.spec import five_frame_points

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "cards" / "maffnet-tiny-full-dbscan.yaml"


def _sklearn_map(card, pts):
    d = card.get("cfa.dbscan")
    scan = upstream_scan_mask(pts, card.get("pillars.point_cloud_range")) & np.isfinite(pts).all(1)
    v = card.features.index(card.get("cfa.velocity_feature"))
    xyv = pts[scan][:, [0, 1, v]]
    bev, labels = upstream_map(
        xyv,
        None,
        d["eps"],
        d["min_samples"],
        d["map_rows"],
        d["map_cols"],
        d["resolution"],
        d["y_offset"],
        d["max_cluster_size"],
    )
    cluster = np.zeros(len(pts), bool)
    cluster[np.flatnonzero(scan)] = labels != -1
    return bev, cluster


@pytest.mark.parametrize("card_path, cases", [(TINY, 5), (ROOT / "models" / "maffnet-vod-full-dbscan.yaml", 5)])
def test_clustering_map_equals_sklearn(card_path, cases):
    card = load_card(card_path)
    model = create_model(card)
    seen = 0
    for name, feeds in model_spec(card).graph().make_cases(card, cases, 4):
        pts = feeds["points"]
        want_map, want_cluster = _sklearn_map(card, pts)
        for reference in (False, True):
            with torch.no_grad():
                _, bev, converged, cluster = model.cfa_stage(torch.from_numpy(pts), reference)
            np.testing.assert_array_equal(bev.numpy(), want_map, err_msg=f"{name} reference={reference}")
            np.testing.assert_array_equal(cluster.numpy(), want_cluster, err_msg=f"{name} reference={reference}")
            assert bool(converged), name
        seen += int((want_map[2] > 0).sum())
    assert seen > 20  # the cases do produce clusters on the map


def test_tiny_dbscan_export_parity_and_runtime(tmp_path):
    onnx_path = export_with_cli(tmp_path, "maffnet-tiny-full-dbscan", TINY)
    res = invoke(
        "parity-check",
        "--model",
        "maffnet-tiny-full-dbscan",
        "--config",
        TINY,
        "--onnx",
        onnx_path,
        "--cases",
        "5",
        "--json",
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    model = runtime.load(onnx_path)
    card = load_card(TINY)
    pts = five_frame_points(7, card)
    out = model.run(pts)
    assert bool(out["cfa_converged"]) and out["keypoint_valid"].all()
    # more scan points than cfa.dbscan.capacity: the card says error (not_converged defaults to error)
    many = np.concatenate([pts] * 3)
    inside = upstream_scan_mask(many, card.get("pillars.point_cloud_range")).sum()
    assert inside > card.get("cfa.dbscan.capacity")
    with pytest.raises(CapacityError, match="cfa.dbscan.capacity = 512"):
        model.run(many)


def test_runtime_warns_when_the_card_says_warn(tmp_path):
    data = load_card(TINY).data
    data["cfa"]["not_converged"] = "warn"
    data["cfa"]["dbscan"]["capacity"] = 16
    data["name"] = "maffnet-tiny-dbscan-warn"
    card = tmp_path / "warn.yaml"
    import yaml

    card.write_text(yaml.safe_dump(data))
    onnx_path = export_with_cli(tmp_path, "maffnet-tiny-dbscan-warn", card)
    pts = five_frame_points(7, load_card(card))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = runtime.load(onnx_path).run(pts)
    assert not bool(out["cfa_converged"])
    assert any("cfa.dbscan.capacity = 16" in str(w.message) for w in caught)


def test_card_names_one_clustering_method(tmp_path):
    import yaml

    data = load_card(TINY).data
    data["cfa"]["grid"] = {"map_h": 40, "map_w": 40}
    (tmp_path / "both.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="cfa.grid is set but cfa.method is 'dbscan'"):
        create_model(load_card(tmp_path / "both.yaml"))
    data = load_card(TINY).data
    data["cfa"]["method"] = "kmeans"
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="method must be one of"):
        create_model(load_card(tmp_path / "bad.yaml"))


def test_dense_five_frame_clouds_fit_the_vod_capacities():
    """The documented sizing (docs/models/maffnet.md): dense 5-frame clouds in the camera FOV stay
    below spa.capacity in non-empty pillars and below cfa.dbscan.capacity in scan points."""
    card = load_card(ROOT / "models" / "maffnet-vod-full-dbscan.yaml")
    model = create_model(card)
    r = card.get("pillars.point_cloud_range")
    for seed in (0, 2, 4):
        pts = five_frame_points(seed, card)
        with torch.no_grad():
            _, pillars, overflow = model.pillar_stage(torch.from_numpy(pts), reference=False)
        assert 800 < int(pillars) < card.get("spa.capacity") and not bool(overflow)
        assert upstream_scan_mask(pts, r).sum() < card.get("cfa.dbscan.capacity")


@pytest.mark.parametrize("model", ["maffnet-vod-full-dbscan", "maffnet-tj4d-full-dbscan"])
def test_full_dbscan_cards_export_and_parity(model, tmp_path):
    """Each shipped DBSCAN card, exported and parity-checked (VoD's cases include a dense 5-frame cloud)."""
    onnx_path = tmp_path / f"{model}.onnx"
    res = invoke("export", "--model", model, "--output", onnx_path)
    assert res.exit_code == 0, res.output
    assert_parses_in_tensorrt(onnx_path)
    cases = "5" if "vod" in model else "2"  # VoD's fifth case is the dense 5-frame cloud
    res = invoke("parity-check", "--model", model, "--onnx", onnx_path, "--cases", cases, "--json")
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert summary_of(report)["boxes"]["mismatches"] == 0
    assert summary_of(report)["keypoints"]["max_abs"] == 0
