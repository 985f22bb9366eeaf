"""benchmarks/int8_methods.py on a place recogniser: every calibration method's int8 graph, a
--qat fine-tune's and its fp32 control's, and the one quantize --search chooses on another town,
scored against the fp32 graph over the same queries, with paired Recall@N differences, written to
a result file that benchmarks/render.py renders."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY_CARD, benchmark_module

from radaredge.cards import load_card
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.models import create_model, model_spec
from radaredge.models.factory import save_checkpoint
from radaredge.training.qat import FakeQuantizedLayers


def _qat_checkpoint(card, model, path: Path) -> Path:
    """A best.pth as `radaredge train --qat` writes it: ``model``'s weights and the ranges its
    fake-quantised layers observed on a few synthetic windows."""
    fq = FakeQuantizedLayers(model, card)
    with torch.no_grad(), fq.observing():
        for _, feeds in model_spec(card).graph().make_cases(card, 4, 11):
            model(*(torch.from_numpy(v) for v in feeds.values()))
    torch.save({"model_state": model.state_dict(), "qat": fq.checkpoint_entry()}, path)
    fq.remove()
    return path


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    root = tmp_path_factory.mktemp("int8-methods")
    town = root / "town-7"
    make_pr_benchmark(town, drives=3, frames_per_drive=20, seed=7)
    held_out = root / "town-8"
    make_pr_benchmark(held_out, drives=3, frames_per_drive=20, seed=8)
    card = load_card(TINY_CARD)
    model = create_model(card)
    weights = save_checkpoint(model, root / "weights.pth")
    control = copy.deepcopy(model)
    with torch.no_grad():
        for p in control.parameters():
            p.mul_(1.01)
    control_weights = save_checkpoint(control, root / "control.pth")
    qat = _qat_checkpoint(card, copy.deepcopy(model).eval(), root / "qat.pth")
    methods = benchmark_module("int8_methods")
    argv = [
        "--card",
        str(TINY_CARD),
        "--weights",
        str(weights),
        "--database",
        str(town / "database"),
        "--queries",
        str(town / "queries"),
        "--methods",
        "minmax",
        "--qat-weights",
        str(qat),
        "--control-weights",
        str(control_weights),
        "--search",
        "--search-database",
        str(held_out / "database"),
        "--search-queries",
        str(held_out / "queries"),
        "--results",
        str(root / "results"),
    ]
    assert methods.main(argv) == 0
    (path,) = (root / "results").glob("int8-methods-tdfanet-tiny-town-7-*.json")
    return path, json.loads(path.read_text())


def test_each_row_pairs_int8_with_fp32_over_the_same_queries(scored):
    _, doc = scored
    assert doc["task"] == "place recognition" and doc["budget_recall_points"] == 1.0
    minmax, qat, searched = doc["methods"]["minmax"], doc["methods"]["qat"], doc["methods"]["search"]
    for row in (minmax, qat, searched):
        assert row["queries"] > 0 and row["fp32"] == minmax["fp32"]  # the original weights' fp32 graph
        for n, d in row["int8_minus_fp32"].items():
            assert d["value"] == pytest.approx(row["int8"]["recall"][n] - row["fp32"]["recall"][n])
            low, high = d["interval"]
            assert low <= d["value"] + 1e-9 and d["value"] <= high + 1e-9
        worst = row["int8_minus_fp32"]["1"]
        assert row["verdict"] == (
            "within" if worst["value"] > -1.0 else "meets" if worst["interval"][1] >= -1.0 else "fails"
        )
    control = qat["control"]
    versus = control["qat_int8_minus_control_fp32"]["1"]
    assert versus["value"] == pytest.approx(qat["int8"]["recall"]["1"] - control["fp32"]["recall"]["1"])
    gained = control["fp32_minus_original_fp32"]["1"]["value"]
    assert gained == pytest.approx(control["fp32"]["recall"]["1"] - minmax["fp32"]["recall"]["1"])
    assert np.isfinite(doc["no_learning"]["recall"]["1"])
    # the search chose on the other town, from every layer int8, and the row scores what it chose
    assert "town-8" in searched["search"]["data"] and searched["search"]["start_keep_fp32"]["keep_fp32"] == []
    assert searched["keep_fp32"] == searched["search"]["keep_fp32"]
    assert "--keep-fp32 none --search" in searched["export_command"]


def test_the_search_must_choose_on_other_data_than_it_is_scored_on(scored, tmp_path):
    path, _ = scored
    town = path.parent.parent / "town-7"
    argv = ["--card", str(TINY_CARD), "--weights", "w.pth", "--database", str(town / "database")]
    argv += ["--queries", str(town / "queries"), "--search", "--results", str(tmp_path)]
    methods = benchmark_module("int8_methods")
    with pytest.raises(SystemExit):
        methods.main(argv)  # no held-out drives
    with pytest.raises(SystemExit):
        methods.main([*argv, "--search-database", str(town / "database"), "--search-queries", str(town / "queries")])
    assert not list(tmp_path.iterdir())


def test_the_place_rows_render_as_recall_differences(scored):
    path, doc = scored
    render = benchmark_module("render")
    lines = render.int8_methods_lines(render.Result(path))
    assert lines[0].startswith("`tdfanet-tiny`, weights") and "no learning (polar occupancy) @1" in lines[0]
    header = next(line for line in lines if line.startswith("| method |"))
    assert header.startswith("| method | R@1 | R@5 | R@10 | verdict | command |")
    minmax = next(line for line in lines if line.startswith("| `minmax` |"))
    assert f"{doc['methods']['minmax']['int8_minus_fp32']['1']['value']:+.2f}" in minmax
    assert any(line.startswith("| control: fp32 fine-tune") and "| (fp32) |" in line for line in lines)
    assert any(line.startswith("| `train --qat` int8 vs the control's fp32") for line in lines)
    assert any(line.startswith("| `quantize --search` from every layer int8 (kept fp32: ") for line in lines)


def test_a_method_measured_later_joins_the_file_only_over_the_same_fp32_graph(scored, tmp_path):
    """--into adds a run's rows to an earlier result of the same weights and data, paired with the
    same fp32 scores, and lists the run; other weights, a row it has, or an fp32 graph that scores
    otherwise are refused."""
    path, doc = scored
    methods = benchmark_module("int8_methods")
    root = path.parent.parent
    town = root / "town-7"
    base = ["--card", str(TINY_CARD), "--database", str(town / "database"), "--queries", str(town / "queries")]
    out = ["--results", str(tmp_path)]
    with pytest.raises(SystemExit, match="checkpoint_sha256"):
        methods.main(
            [*base, "--weights", str(root / "control.pth"), "--methods", "percentile", "--into", str(path), *out]
        )
    with pytest.raises(SystemExit, match=r"already has the rows \['minmax'\]"):
        methods.main([*base, "--weights", str(root / "weights.pth"), "--methods", "minmax", "--into", str(path), *out])
    assert not list(tmp_path.iterdir())  # both refused before scoring anything
    assert (
        methods.main(
            [*base, "--weights", str(root / "weights.pth"), "--methods", "percentile", "--into", str(path), *out]
        )
        == 0
    )
    (merged,) = tmp_path.glob("int8-methods-tdfanet-tiny-town-7-*.json")
    both = json.loads(merged.read_text())
    assert list(both["methods"]) == ["minmax", "qat", "search", "percentile"]
    assert both["methods"]["percentile"]["fp32"] == doc["methods"]["minmax"]["fp32"]
    assert [run["methods"] for run in both["added"]] == [["percentile"]] and both["command"] == doc["command"]
    render = benchmark_module("render")
    lines = render.int8_methods_lines(render.Result(merged))
    assert any(line.startswith("The `percentile` row added by `python benchmarks/int8_methods.py") for line in lines)
    shifted = copy.deepcopy(doc)
    for row in shifted["methods"].values():
        row["fp32"]["recall"]["1"] += 0.5
    other = tmp_path / "shifted.json"
    other.write_text(json.dumps(shifted))
    # a run's scores hold tuples where the file, read back from JSON, holds lists
    assert (
        methods._max_abs_difference({"Car": {"3d_interval": (1.0, 2.0)}}, {"Car": {"3d_interval": [1.0, 2.5]}}) == 0.5
    )
    with pytest.raises(SystemExit, match="fp32 graph scores up to 0.5 points away"):
        methods.main(
            [*base, "--weights", str(root / "weights.pth"), "--methods", "entropy", "--into", str(other), *out]
        )
