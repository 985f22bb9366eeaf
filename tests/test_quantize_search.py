"""``radaredge quantize``: an int8 copy judged by the task metric on labelled data, and the search
for the layer groups to keep in fp32 (radaredge/quantizing/search.py)."""

from __future__ import annotations

import json
import shutil

import onnx
import pytest
from conftest import invoke

from radaredge import runtime
from radaredge.cards import load_card
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.node_scopes import module_names
from radaredge.quantizing import search


def test_layer_groups_partition_the_quantised_layers(maffnet_tiny_export):
    """Every quantised layer falls in exactly one group, and a module holding more than a third
    of the layers (the tiny card's fuser) is split into its children."""
    _, fp32 = maffnet_tiny_export
    model = onnx.load(str(fp32), load_external_data=False)
    groups = search.layer_groups(model)
    scopes = [module_names(n)[-1] for n in model.graph.node if n.op_type in ("Conv", "MatMul", "Gemm")]
    for scope in scopes:
        owners = [g for g in groups if scope == g or scope.startswith(g + ".")]
        assert len(owners) == 1, (scope, owners)
    assert "vfe" in groups and "fuser" not in groups and any(g.startswith("fuser.") for g in groups)


def _kept(graph) -> list[str]:
    """The modules an int8 graph kept in fp32 (none for the fp32 graph)."""
    props = {p.key: p.value for p in onnx.load(str(graph), load_external_data=False).metadata_props}
    q = props.get("radaredge.quantization")
    return json.loads(q)["keep_fp32"]["modules"] if q else []


def _labelled_copy(card, fp32, out, method=None):
    """Stands in for quantize_int8 where only the choice is tested: the fp32 graph, labelled with
    the modules the card keeps in fp32 as the int8 graph's metadata would be."""
    model = onnx.load(str(fp32))
    keep = card.get("quantization.keep_fp32", [])
    model.metadata_props.add(key="radaredge.quantization", value=json.dumps({"keep_fp32": {"modules": keep}}))
    onnx.save(model, str(out))
    return out


def test_search_keeps_the_most_sensitive_groups_until_the_copy_is_within_budget(
    maffnet_tiny_export, tmp_path, monkeypatch
):
    """With a judge whose int8 loss is the sum of fixed costs of the groups left quantised (plus
    0.2 that no group recovers), the search keeps the costliest group, then the next, and stops
    once within the budget; the copy it writes beside the fp32 graph is the chosen one."""
    card_path, exported = maffnet_tiny_export
    fp32 = tmp_path / exported.name
    shutil.copyfile(exported, fp32)
    groups = search.layer_groups(onnx.load(str(fp32), load_external_data=False))
    costs = {g: 0.1 for g in groups} | {"fuser.crossfusion": 3.0, "backbone_2d": 1.5}
    judged = []

    def fake_judge(card, inputs):
        def judge(graph):
            judged.append(graph)
            if "int8" not in graph.name:
                return {"Car": 50.0}
            return {"Car": 49.8 - sum(costs[g] for g in groups if g not in _kept(graph))}

        return judge

    monkeypatch.setitem(search.JUDGES, "detection", fake_judge)
    monkeypatch.setattr(search, "quantize_int8", _labelled_copy)  # quantisation itself: test_quantize.py
    from radaredge import api

    report = api.quantize(card_path, fp32, data="unused", search=True)
    assert report.start_step.worst == pytest.approx(sum(costs.values()) + 0.2)
    assert set(report.sensitivity) == set(groups)
    assert [s.keep_fp32 for s in report.steps] == [["fuser.crossfusion"], ["fuser.crossfusion", "backbone_2d"]]
    assert report and report.chosen.worst == pytest.approx(0.1 * (len(groups) - 2) + 0.2)
    assert _kept(tmp_path / "maffnet-tiny.int8.onnx") == ["fuser.crossfusion", "backbone_2d"]
    assert len(judged) == 1 + 1 + len(groups) + len(groups) - 1  # fp32, the card's copy, two rounds
    assert "chosen keep_fp32: ['fuser.crossfusion', 'backbone_2d'] (within the budget)" in "\n".join(report.lines())
    # a budget the search cannot meet: every recovering group joins, and the report says so
    costs["vfe"] = 5.0
    report = api.quantize(card_path, fp32, data="unused", search=True, budget=0.05)
    assert not report and len(report.steps) == len(groups)
    assert [len(r) for r in report.rounds] == list(range(len(groups), 0, -1))
    # started from every layer int8, a card's own keep_fp32 is a group like any other
    card = search.with_keep(load_card(card_path), ["backbone_2d"])
    report = api.quantize(card, fp32, data="unused", search=True, keep_fp32="none")
    assert report.start_step.keep_fp32 == [] and "backbone_2d" in report.sensitivity
    assert report.chosen.keep_fp32 == ["vfe", "fuser.crossfusion", "backbone_2d"]
    report = api.quantize(card, fp32, data="unused", search=True)
    assert report.start_step.keep_fp32 == ["backbone_2d"] and "backbone_2d" not in report.sensitivity
    assert report.chosen.keep_fp32 == ["backbone_2d", "vfe", "fuser.crossfusion"]


def test_each_round_rescores_the_groups_on_top_of_those_kept(maffnet_tiny_export, tmp_path, monkeypatch):
    """Groups interact: here ``vfe`` in fp32 recovers nothing while ``backbone_2d`` is int8 (its
    error dominates) but everything once it is fp32, and ``fuser.crossfusion`` recovers a little
    either way. Ranking by sensitivity alone would keep it before ``vfe``; re-scoring each round
    keeps ``backbone_2d`` and then ``vfe``."""
    card_path, exported = maffnet_tiny_export
    fp32 = tmp_path / exported.name
    shutil.copyfile(exported, fp32)

    def loss(kept: list[str]) -> float:
        if "backbone_2d" not in kept:
            return 9.0 if "fuser.crossfusion" in kept else 10.0
        return 0.1 if "vfe" in kept else 2.0 if "fuser.crossfusion" not in kept else 1.9

    def fake_judge(card, inputs):
        return lambda graph: {"Car": 50.0 - (loss(_kept(graph)) if "int8" in graph.name else 0.0)}

    monkeypatch.setitem(search.JUDGES, "detection", fake_judge)
    monkeypatch.setattr(search, "quantize_int8", _labelled_copy)
    from radaredge import api

    report = api.quantize(card_path, fp32, data="unused", search=True)
    assert report.sensitivity["vfe"].worst == pytest.approx(10.0)
    assert report.sensitivity["fuser.crossfusion"].worst < report.sensitivity["vfe"].worst
    assert report and report.chosen.keep_fp32 == ["backbone_2d", "vfe"]
    assert report.rounds[1]["vfe"].worst == pytest.approx(0.1)


def test_quantize_judges_int8_by_ap_on_a_labelled_split(maffnet_tiny_export, tmp_path):
    """The command end to end: the tiny detector's fp32 graph and its int8 copy scored by 3D AP on
    a labelled split, the copy written beside the graph with the method asked for."""
    card_path, exported = maffnet_tiny_export
    fp32 = tmp_path / exported.name
    shutil.copyfile(exported, fp32)
    make_detection_benchmark(tmp_path / "set", drives=3, frames=2, seed=1)
    res = invoke(
        "quantize", "--model", "maffnet-tiny", "--config", card_path, "--onnx", fp32, "--data", tmp_path / "set",
        "--method", "percentile", "--json",
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert set(doc["fp32"]) == {"Car", "Pedestrian", "Cyclist"} and doc["within_budget"] is True
    assert doc["method"] == "percentile" and doc["keep_fp32"] == [] and doc["steps"] == []
    int8 = tmp_path / "maffnet-tiny.int8.onnx"
    assert json.loads(runtime.load(int8).metadata["radaredge.quantization"])["calibration"]["method"] == "percentile"


def test_quantize_judges_a_place_recogniser_by_recall_at_1(tiny_export, tmp_path):
    """TDFANet's copy is judged by Recall@1 over query drives against database drives."""
    from radaredge import api
    from radaredge.data.pr_benchmark import make_pr_benchmark

    card, _, exported, _ = tiny_export
    fp32 = tmp_path / exported.name
    shutil.copyfile(exported, fp32)
    make_pr_benchmark(tmp_path / "town", 2, 12, 0)
    report = api.quantize(card, fp32, database=tmp_path / "town" / "database", queries=tmp_path / "town" / "queries")
    assert set(report.fp32) == {"Recall@1"} and 0 <= report.start_step.int8["Recall@1"] <= 100
    assert (tmp_path / "tdfanet-tiny.int8.onnx").is_file() and "Recall@1" in "\n".join(report.lines())


@pytest.mark.parametrize(
    "args, message",
    [
        (["--onnx", "INT8", "--data", "."], "is a copy of"),
        (["--onnx", "MISSING", "--data", "."], "expected an exported fp32 .onnx file"),
        (["--onnx", "FP32", "--data", ".", "--budget", "0"], "--budget 0.0: expected a positive number"),
        (["--onnx", "FP32", "--database", ".", "--queries", "."], "is evaluated by 3D-detection AP on --data"),
    ],
)
def test_quantize_refuses_what_it_cannot_judge(maffnet_tiny_export, tmp_path, args, message):
    card_path, exported = maffnet_tiny_export
    fp32 = tmp_path / exported.name
    shutil.copyfile(exported, fp32)
    paths = {"FP32": fp32, "INT8": exported.with_name("maffnet-tiny.int8.onnx"), "MISSING": tmp_path / "x.onnx"}
    res = invoke("quantize", "--model", "maffnet-tiny", "--config", card_path, *[paths.get(a, a) for a in args])
    assert res.exit_code == 2 and message in res.output, res.output
    assert not (tmp_path / "maffnet-tiny.int8.onnx").exists()


def test_quantize_refuses_a_dynamically_quantised_model(tmp_path):
    res = invoke("quantize", "--model", "des4pos", "--onnx", tmp_path / "x.onnx", "--data", tmp_path)
    assert res.exit_code == 2 and "quantised dynamically" in res.output
