"""radaredge.eval.localisation: localisation recall of an exported Des4Pos bundle over a map's described poses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import invoke

from radaredge.cards import load_card
from radaredge.data.text_city import make_city
from radaredge.errors import ConfigError, InputError
from radaredge.eval.localisation import evaluate_localization
from radaredge.models import create_model
from radaredge.runtime.cellmap import load_map
from radaredge.runtime.des4pos import Des4PosBundle, MapIndex

TINY = Path(__file__).parent / "cards" / "des4pos-tiny.yaml"


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("des4pos") / "bundle"
    res = invoke("export", "--model", "des4pos-tiny", "--config", TINY, "--output", d)
    assert res.exit_code == 0, res.output
    return d


@pytest.fixture
def city(tmp_path):
    """A small synthetic city in the tiny card's layout (6 slots of 32 points, at most 5 hints)."""
    return make_city(6, 32, seed=3, objects=30, poses=6, max_hints=5).save(tmp_path / "city.npz")


def test_recall_is_that_of_the_located_positions(bundle, city):
    loops = []
    report = evaluate_localization(bundle, city, progress=lambda desc: loops.append(desc) or iter)
    m = load_map(city)
    assert (report.model, report.cells, report.queries) == ("des4pos-tiny", len(m), 6)
    assert report.ks == (1, 5, 10) and report.thresholds == (5.0, 10.0, 15.0) and report.retrieval_ks == (1, 3, 5)
    assert loops == ["cells of city.npz", "poses"] and list(report.results) == ["onnxruntime"]
    # the same poses located one by one: recall at (k, t) is the share with a position within t m in the top k
    b = Des4PosBundle(bundle)
    index = MapIndex.build(b, city, cells=m)
    hits = [b.locate(str(t), index, top_k=10) for t in m.pose_text]
    pred = np.array([[h["position"] for h in row] for row in hits])
    dist = np.linalg.norm(pred - m.pose_w[:, None], axis=2)
    for k in report.ks:
        for t in report.thresholds:
            assert report.recall[k][t] == pytest.approx((dist[:, :k] <= t).any(1).mean())
    # Table II: the pose's best cell among the first k retrieved
    retrieved = np.array([[h["cell"] for h in row] for row in hits])
    for k in report.retrieval_ks:
        assert report.retrieval[k] == pytest.approx((retrieved[:, :k] == m.pose_cell[:, None]).any(1).mean())
    assert not report.from_cache
    again = evaluate_localization(bundle, city, top_k=(1, 3), thresholds=(30.0,), retrieval_ks=(2,))
    assert again.from_cache and list(again.recall) == [1, 3] and list(again.retrieval) == [2]
    assert again.recall[3][30.0] == pytest.approx((dist[:, :3] <= 30.0).any(1).mean())
    # without the fine stage: each retrieved cell's centre is the position
    centres = np.array(
        [[m.origins[list(m.ids).index(c)] + m.sizes[list(m.ids).index(c)] / 2 for c in row] for row in retrieved]
    )
    dist_c = np.linalg.norm(centres - m.pose_w[:, None], axis=2)
    res = report.results["onnxruntime"]
    for k in report.ks:
        for t in report.thresholds:
            assert report.centre_recall[k][t] == pytest.approx((dist_c[:, :k] <= t).any(1).mean())
            for key in ("localization", "localization_centre"):  # a 95 % bootstrap interval over queries
                low, high = res[key + "_interval"][k][t]
                assert 0.0 <= low <= res[key][k][t] <= high <= 1.0
            # the fine stage's gain: the same queries' difference, with its own (paired) interval
            gain = ((dist[:, :k] <= t).any(1).astype(float) - (dist_c[:, :k] <= t).any(1)).mean()
            assert res["localization_gain"][k][t] == pytest.approx(gain)
            low, high = res["localization_gain_interval"][k][t]
            assert -1.0 <= low <= gain <= high <= 1.0
    out = json.loads(json.dumps(report.to_dict()))
    res = out["results"]["onnxruntime"]
    assert out["queries"] == 6 and set(res["localization"]) == {"1", "5", "10"}
    assert set(res["localization"]["5"]) == {"5", "10", "15"} and set(res["retrieval"]) == {"1", "3", "5"}
    assert (
        set(res["localization_centre"]["10"]) == {"5", "10", "15"} and len(res["localization_interval"]["1"]["5"]) == 2
    )
    lines = report.lines()
    assert lines[1].startswith("Table I") and lines[3].split()[0] == "top-1" and "[" in lines[3]
    assert lines[6].startswith("Table I without the fine stage") and lines[11].startswith("The fine stage's gain")
    assert lines[16].startswith("Table II") and set(res["localization_gain_interval"]["5"]) == {"5", "10", "15"}


def test_bootstrap_intervals_are_those_of_the_per_query_hits():
    """localization_hits gives per query what localization_recall averages; the interval is the
    percentile bootstrap of those hits (recall_stats.bootstrap_interval), in fractions."""
    from radaredge.eval.localisation import _intervals, localization_hits
    from radaredge.eval.places import localization_recall
    from radaredge.eval.recall_stats import bootstrap_interval

    rng = np.random.default_rng(0)
    pred, pose = rng.uniform(0, 40, (200, 10, 2)), rng.uniform(0, 40, (200, 2))
    same = rng.random((200, 10)) > 0.2
    hits = localization_hits(pred, pose, (1, 5, 10), (5.0, 10.0), same)
    recall = localization_recall(pred, pose, (1, 5, 10), (5.0, 10.0), same_scene=same)
    for k in (1, 5, 10):
        for t in (5.0, 10.0):
            assert hits[k][t].mean() == pytest.approx(recall[k][t])
    low, high = _intervals(hits)[5][10.0]
    assert (100 * low, 100 * high) == pytest.approx(bootstrap_interval(hits[5][10.0]))
    assert low < recall[5][10.0] < high


def test_the_torch_reference_agrees_and_the_database_spans_maps(bundle, city, tmp_path):
    """Two maps are one database (cells of both, poses of both); the torch reference formulation
    with the bundle's weights retrieves the same cells and lands within float noise."""
    d = tmp_path / "maps"
    d.mkdir()
    for seed in (3, 4):
        make_city(6, 32, seed=seed, objects=30, poses=5, max_hints=5).save(d / f"city-{seed}.npz")
    report = evaluate_localization(bundle, d, reference=True)
    assert report.cells == sum(len(load_map(p)) for p in sorted(d.glob("city-?.npz"))) and report.queries == 10
    assert list(report.results) == ["onnxruntime", "torch reference"]
    onnx, ref = report.results["onnxruntime"], report.results["torch reference"]
    assert onnx["retrieval"] == ref["retrieval"] and onnx["localization"] == ref["localization"]
    assert onnx["localization_centre"] == ref["localization_centre"]
    assert "recall (torch reference)" in report.retrieval_table()
    again = evaluate_localization(bundle, d)  # the caches beside the maps are not maps
    assert again.from_cache and again.cells == report.cells
    model = create_model(load_card(TINY))
    with torch.no_grad():
        model.fine.offset[0].bias.add_(1.0)
    torch.save(model.state_dict(), tmp_path / "other.pth")
    with pytest.raises(ConfigError, match="exported with other weights than checkpoint"):
        evaluate_localization(bundle, d, reference=True, checkpoint=tmp_path / "other.pth")


def test_errors_name_the_map_and_pose(bundle, city, tmp_path):
    with pytest.raises(ConfigError, match="thresholds must be positive"):
        evaluate_localization(bundle, city, thresholds=(0.0,))
    small = make_city(6, 32, seed=3, world=40.0, objects=10, poses=3, max_hints=5).save(tmp_path / "small.npz")
    with pytest.raises(ConfigError, match="top-10 recall needs at least 10 database cells; .*small.npz has 4"):
        evaluate_localization(bundle, small)  # not silently recall over the 4 cells there are
    bare = make_city(6, 32, seed=3, objects=30, poses=0).save(tmp_path / "bare.npz")
    with pytest.raises(InputError, match="bare.npz: no described pose; make maps with poses"):
        evaluate_localization(bundle, bare)
    m = load_map(city)
    m.pose_text[2] = "A. B. C. D. E. F."
    with pytest.raises(InputError, match=r"long.npz: pose 2 has 6 hint sentence\(s\); the card takes 1 to 5"):
        evaluate_localization(bundle, m.save(tmp_path / "long.npz"))
    m = load_map(city)
    m.pose_cell[0] = "elsewhere"
    with pytest.raises(InputError, match="lost.npz: pose 0's best cell elsewhere is not a cell of the map"):
        evaluate_localization(bundle, m.save(tmp_path / "lost.npz"))


def test_eval_command_runs_the_models_own_metric(bundle, tmp_path):
    """`radaredge eval` on des4pos is localisation recall over a map made by `radaredge make-city`
    with the card's hint limit; place-recognition inputs are refused by name."""
    city = tmp_path / "city.npz"
    res = invoke(
        "make-city", "--model", "des4pos-tiny", "--config", TINY, "--out", city, "--poses", 5, "--objects", 30, "--json"
    )
    assert res.exit_code == 0, res.output
    res = invoke("eval", "--model", "des4pos-tiny", "--config", TINY, "--onnx", bundle, "--map", city, "--json")
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["queries"] == 5 and list(out["results"]) == ["onnxruntime", "torch reference"]
    assert set(out["results"]["torch reference"]["retrieval"]) == {"1", "3", "5"}
    assert json.loads(bundle.with_name("bundle.eval.json").read_text()) == out
    res = invoke(
        "eval", "--model", "des4pos-tiny", "--config", TINY, "--onnx", bundle, "--map", city, "--database", tmp_path
    )
    assert res.exit_code == 2 and "evaluated by localisation recall on --map; --database not used" in res.output


def test_locate_without_an_int8_text_encoder_says_how_to_make_one(bundle, city):
    res = invoke(
        "locate", "--onnx-dir", bundle, "--map", city, "--text", "The pose is north of a red car.", "--int8-text"
    )
    assert res.exit_code == 2 and "text_encoder.int8.onnx does not exist" in res.output
    assert "--quantize int8" in res.output


def test_a_bad_or_unwritable_cell_cache_is_rebuilt_not_trusted(bundle, city, monkeypatch):
    """The cache beside the map is written atomically with a hash of its arrays: a truncated or
    tampered cache is rebuilt with a warning (same positions as a fresh encoding), and a map
    directory that cannot be written costs the cache, not the result."""
    import tempfile

    b = Des4PosBundle(bundle)
    fresh = MapIndex.build(b, city, cache=True)
    assert fresh.cache is not None and fresh.cache.is_file() and not fresh.from_cache
    assert not [p for p in city.parent.iterdir() if p.name.endswith(".tmp")]
    assert MapIndex.build(b, city).from_cache
    data = fresh.cache.read_bytes()
    for damaged in (data[: len(data) // 2], data.replace(b"descriptors", b"descriptorz")):
        fresh.cache.write_bytes(damaged)
        with pytest.warns(RuntimeWarning, match="ignoring the cell cache"):
            again = MapIndex.build(b, city)
        assert not again.from_cache and np.array_equal(again.descriptors, fresh.descriptors)
    with np.load(fresh.cache) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["descriptors"] = arrays["descriptors"] + 1.0  # tampered values, old hash
    np.savez(fresh.cache, **arrays)
    with pytest.warns(RuntimeWarning, match="do not match the map or their hash"):
        assert not MapIndex.build(b, city).from_cache
    fresh.cache.unlink()

    def read_only(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(city.parent))

    monkeypatch.setattr(tempfile, "mkstemp", read_only)  # a read-only map directory
    with pytest.warns(RuntimeWarning, match="cannot write the cell cache"):
        index = MapIndex.build(b, city)
    assert index.cache is None and np.array_equal(index.descriptors, fresh.descriptors)
