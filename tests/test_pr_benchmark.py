"""The synthetic place-recognition benchmark (one town, several days) and `radaredge eval` on it."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import TINY_CARD

from radaredge.cards import load_card
from radaredge.cli import main
from radaredge.data.pr_benchmark import DAY_S, make_pr_benchmark, plan_drives
from radaredge.data.sequences import load_sequence
from radaredge.data.synthetic import SceneConfig
from radaredge.errors import ConfigError
from radaredge.eval.places import evaluate


def world_points(scan, mask):
    """World xyz [M, 3] m of the scan's points selected by ``mask``."""
    return scan.points[mask, :3].astype(np.float64) @ scan.pose[:3, :3].T + scan.pose[:3, 3]


def share_near(points, reference, tol=0.5):
    """Fraction of ``points`` within ``tol`` m of some point of ``reference``."""
    if len(points) == 0 or len(reference) == 0:
        return 0.0
    return float(np.mean([np.linalg.norm(reference - p, axis=1).min() <= tol for p in points]))


def static(scan):
    return ~scan.dynamic & ~scan.ghost


def test_layout_positions_and_times(tmp_path):
    plan = make_pr_benchmark(tmp_path, drives=3, frames_per_drive=6, seed=1)
    assert [d.subdir for d in plan] == ["database/drive-00", "queries/drive-01", "queries/drive-02"]
    assert sorted(p.name for p in (tmp_path / "queries").iterdir()) == ["drive-01", "drive-02"]
    for d, drive in enumerate(plan):
        seq = load_sequence(tmp_path / drive.subdir)
        scans = drive.scans()
        assert len(seq) == 6 and seq.scan_paths[0].suffix == ".npy"
        np.testing.assert_allclose(seq.timestamps, d * DAY_S + np.arange(6) / 10.0)
        np.testing.assert_allclose(seq.positions[:, 0], [s.pose[1, 3] for s in scans])  # northing = world y
        # easting = world x + 10 km x seed
        np.testing.assert_allclose(seq.positions[:, 1], [s.pose[0, 3] + 10_000.0 for s in scans])
        np.testing.assert_array_equal(seq.scan(2, ["x", "y", "z", "v_r", "rcs"]), scans[2].points)
    speeds = [d.config.ego_speed_max for d in plan]
    assert speeds[0] == 10.0 and all(7.0 <= v <= 10.0 for v in speeds) and len(set(speeds)) == 3


def test_days_share_the_static_world_but_not_the_traffic():
    """The same place on two days: the query's static points lie on the database day's static
    map, its moving-object points are elsewhere than the database day's at the same time; a
    town of another seed does not match."""
    database, query = (d.scans() for d in plan_drives(2, 20, seed=0))
    other_town = plan_drives(2, 20, seed=7)[0].scans()
    static_map = np.concatenate([world_points(s, static(s)) for s in database])
    here = world_points(query[10], static(query[10]))
    assert share_near(here, static_map) > 0.85
    assert share_near(here, np.concatenate([world_points(s, static(s)) for s in other_town])) < 0.5
    moving = [share_near(world_points(q, q.dynamic), world_points(b, b.dynamic)) for q, b in zip(query, database)]
    assert np.mean(moving) < 0.15


def test_query_days_move_some_parked_cars():
    """Database parked cars reappear on the query day at the same place (to float32 rounding),
    shifted by 0.3-0.8 m, or not at all."""
    database, query = (d.scans() for d in plan_drives(2, 20, seed=1))

    def parked(scans):
        centres = [s.boxes[~s.box_dynamic, :3].astype(np.float64) @ s.pose[:3, :3].T + s.pose[:3, 3] for s in scans]
        return np.unique(np.concatenate(centres).round(2), axis=0)

    there = parked(query)
    moved = np.array([np.linalg.norm(there - c, axis=1).min() for c in parked(database)])
    assert (moved < 0.05).sum() >= 3 and (moved > 0.25).any()
    assert not ((moved > 0.05) & (moved < 0.25)).any()


@pytest.mark.parametrize(
    "field, value", [("world_seed", -1), ("world_seed", 1.5), ("road_curvature", 0.02), ("parked_change", 1.2)]
)
def test_scene_knobs_are_validated(field, value):
    with pytest.raises(ConfigError, match=f"SceneConfig.{field}"):
        SceneConfig(**{field: value})


def test_bad_options_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="drives"):
        make_pr_benchmark(tmp_path, drives=1)
    with pytest.raises(ConfigError, match="speed"):
        plan_drives(speed=(5.0, 2.0))


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def small_benchmark(tmp_path_factory):
    out = tmp_path_factory.mktemp("pr-benchmark")
    res = invoke("make-benchmark", "--out", out, "--drives", 3, "--frames", 20, "--seed", 0, "--json")
    assert res.exit_code == 0, res.output
    assert [d["role"] for d in json.loads(res.stdout)["drives"]] == ["database", "query", "query"]
    return out


def test_eval_on_the_benchmark_agrees_with_the_reference(tiny_export, small_benchmark, tmp_path):
    _, _, onnx, _ = tiny_export
    report_path, plot_path = tmp_path / "report.json", tmp_path / "report.png"
    res = invoke(
        "eval",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx,
        "--database",
        small_benchmark / "database",
        "--queries",
        small_benchmark / "queries",
        "--report",
        report_path,
        "--plot",
        plot_path,
    )
    assert res.exit_code == 0, res.output
    assert "R@1" in res.output and "top-1 agreement" in res.output
    report = json.loads(report_path.read_text())
    assert plot_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert report["database"]["windows"] == 18 and report["queries"]["windows"] == 36
    assert report["evaluated"] + report["skipped"] == 36 and report["evaluated"] > 30
    assert set(report["recall"]) == {"onnxruntime", "torch_reference", "polar_occupancy"}
    low, high = report["recall_interval_95"]["onnxruntime"]["1"]
    assert low <= report["recall"]["onnxruntime"]["1"] <= high
    assert "no learning" in res.output and "95 % interval" in res.output
    assert set(report["recall"]["onnxruntime"]) == {"1", "5", "10"}
    assert len(report["recall_curve"]["onnxruntime"]) == 25
    assert report["top1_agreement"] >= 0.995
    assert report["top1_place_agreement"] >= report["top1_agreement"]
    assert "within 5 m of each other" in res.output
    assert len(report["per_query"]) == 36 and report["per_query"][0]["drive"] == "drive-01"


def test_eval_json_without_reference(tiny_export, small_benchmark):
    _, _, onnx, _ = tiny_export
    res = invoke(
        "eval",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx,
        "--no-reference",
        "--database",
        small_benchmark / "database/drive-00",
        "--queries",
        small_benchmark / "queries/drive-02",
        "--json",
    )
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    assert set(report["recall"]) == {"onnxruntime", "polar_occupancy"} and report["top1_agreement"] is None
    assert report["top1_place_agreement"] is None
    assert report["queries"]["drives"] == {"drive-02": 18}
    card = load_card(TINY_CARD)
    database, queries = small_benchmark / "database/drive-00", small_benchmark / "queries/drive-02"
    alone = evaluate(card, onnx, database, queries, reference=False, baseline=False)
    assert set(alone.results) == {"onnxruntime"}  # the no-learning descriptor left out
    assert alone.recall("onnxruntime") == {int(n): r for n, r in report["recall"]["onnxruntime"].items()}


def test_eval_errors_are_one_clear_line(tiny_export, small_benchmark, tmp_path):
    _, _, onnx, _ = tiny_export
    db, queries = small_benchmark / "database", small_benchmark / "queries"
    tiny = ("--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", onnx, "--no-reference")
    (tmp_path / "empty").mkdir()
    res = invoke("eval", *tiny, "--database", tmp_path / "empty", "--queries", queries)
    assert res.exit_code == 2 and "no drives found" in res.output
    make_pr_benchmark(tmp_path / "short", drives=2, frames_per_drive=2)
    res = invoke("eval", *tiny, "--database", db, "--queries", tmp_path / "short/queries")
    assert res.exit_code == 2 and "drive-01 (2)" in res.output and "K = 3" in res.output
    res = invoke("eval", "--model", "tdfanet-edge", "--onnx", onnx, "--database", db, "--queries", queries)
    assert res.exit_code == 2 and "export of card 'tdfanet-tiny', not 'tdfanet-edge'" in res.output
    res = invoke("eval", *tiny, "--database", db, "--queries", queries, "--radius", 0)
    assert res.exit_code == 2 and "radius" in res.output
