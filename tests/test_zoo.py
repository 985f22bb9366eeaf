"""The weights zoo (zoo/<card>/, written by benchmarks/zoo.py): each entry's files are the ones
its scores were measured on, and its exported graph still scores them. The last check is a
task-level regression net: a model-code change that keeps parity with itself but changes what
the trained network computes moves the AP or Recall@1 out of its recorded interval."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

import radaredge
from radaredge.cards import load_card
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.eval.detection import ORT, ORT_INT8, evaluate_detection

ZOO = Path(__file__).resolve().parent.parent / "zoo"
ENTRIES = sorted(ZOO.glob("*/entry.json"))
AREA = "entire_area"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_zoo_is_small_and_holds_the_edge_detector():
    assert "maffnet-vod-edge" in {p.parent.name for p in ENTRIES}
    assert sum(p.stat().st_size for p in ZOO.rglob("*")) < 16 * 2**20


@pytest.mark.parametrize("entry_path", ENTRIES, ids=[p.parent.name for p in ENTRIES])
def test_entry_files_are_the_measured_ones(entry_path):
    entry = json.loads(entry_path.read_text())
    home = entry_path.parent
    assert _sha256(home / entry["weights"]) == entry["weights_sha256"]
    assert _sha256(home / entry["card_file"]) == entry["card_sha256"]
    assert entry["command"] and entry["training_seed"] is not None and ORT_INT8 in entry["test"]["scores"]


def _rescore_detector(card, onnx, spec, tmp_path) -> dict:
    make_detection_benchmark(tmp_path / "set", spec["drives"], spec["frames"], spec["seed"], version=spec["version"])
    report = evaluate_detection(card, onnx, tmp_path / "set", spec["split"], reference=False, openvino=False)
    assert len(report.frames) == spec["frames_scored"]
    return {**{c: report.ap[ORT][AREA][c]["3d"] for c in report.classes}, "mAP": report.mean_ap(ORT, AREA)}


def _rescore_places(card, onnx, spec, tmp_path) -> dict:
    make_pr_benchmark(tmp_path / "town", spec["drives"], spec["frames"], spec["seed"])
    report = radaredge.evaluate(
        card, onnx, tmp_path / "town" / "database", tmp_path / "town" / "queries", reference=False
    )
    assert report.evaluated == spec["queries"]
    return {"R@1": report.recall(ORT)[1]}


@pytest.mark.parametrize("entry_path", ENTRIES, ids=[p.parent.name for p in ENTRIES])
def test_the_graph_still_scores_its_recorded_metric(entry_path, tmp_path):
    """The export of the zoo's weights scores, on the entry's regression set, within the 95 %
    interval recorded there; the interval's lower end is well above what a broken or untrained
    network scores, so a model-code change that breaks the trained function fails here."""
    entry = json.loads(entry_path.read_text())
    home, spec = entry_path.parent, entry["regression"]
    card = load_card(home / entry["card_file"])
    onnx = tmp_path / f"{card.name}.onnx"
    radaredge.export(card, onnx, checkpoint=home / entry["weights"])
    recorded = spec["scores"]
    if card.model == "maffnet":
        got = _rescore_detector(card, onnx, spec, tmp_path)
        bounds = {k: recorded[k]["3d_interval"] for k in got}
        assert bounds["mAP"][0] > 5.0
    else:
        got = _rescore_places(card, onnx, spec, tmp_path)
        bounds = {"R@1": recorded["recall_interval"]["1"]}
        assert bounds["R@1"][0] > 50.0
    for key, value in got.items():
        low, high = bounds[key]
        assert low <= value <= high, (key, value, (low, high))
