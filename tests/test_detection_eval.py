"""`radaredge make-benchmark --task detection` then `radaredge eval --data`: the torch reference,
the fp32 graph and its int8 copy scored with VoD's protocol in one table, the report directory,
the Python API verb, and int8 judged by AP in `parity-check --quantized`."""

from __future__ import annotations

import json

import numpy as np
import pytest

import radaredge
from radaredge.data.kitti_detection import VOD, DetectionSet, radar_boxes_to_labels
from radaredge.eval.detection import REFERENCE, ORT, ORT_INT8, card_points
from radaredge.eval.kitti_ap import ap_table, evaluate_frames
from radaredge.cards import load_card
from conftest import invoke


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    out = tmp_path_factory.mktemp("labelled") / "set"
    res = invoke("make-benchmark", "--task", "detection", "--out", out, "--drives", 3, "--frames", 4, "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert summary["frames"] == {"train": 8, "val": 4, "test": 0} and summary["objects"]["val"]["Car"] > 0
    return out


def test_eval_scores_every_backend_in_one_table(labelled, maffnet_tiny_export, tmp_path):
    card, onnx = maffnet_tiny_export
    res = invoke("eval", "--model", "maffnet-tiny", "--config", card, "--onnx", onnx, "--data", labelled,
                 "--report-dir", tmp_path / "report", "--report", tmp_path / "r.json")
    assert res.exit_code == 0, res.output
    head = next(line for line in res.output.splitlines() if line.startswith("3D AP"))
    for backend in (REFERENCE, ORT, ORT_INT8):
        assert backend in head
    assert "corridor" in res.output and "frames per second" in res.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["frames"] == 4 and report["dataset"] == "vod" and report["reference"] == REFERENCE
    assert set(report["ap"]) >= {REFERENCE, ORT, ORT_INT8}
    assert set(report["ap"][ORT]) == {"entire_area", "corridor"}
    car = report["ap"][ORT]["entire_area"]["Car"]
    assert {"3d", "bev", "aos", "3d_r40", "num_gt"} <= set(car) and car["num_gt"] > 0
    delta = report["delta_ap_points"][ORT]["entire_area"]["Car"]["3d"]
    assert delta == pytest.approx(car["3d"] - report["ap"][REFERENCE]["entire_area"]["Car"]["3d"])
    files = sorted(p.name for p in (tmp_path / "report").iterdir())
    assert "report.json" in files and {"pr-Car.png", "pr-Pedestrian.png", "pr-Cyclist.png"} <= set(files)
    assert sum(f.startswith("bev-") for f in files) == 4


def test_the_api_verb_agrees_with_the_metric_on_the_graphs_detections(labelled, maffnet_tiny_export):
    """radaredge.evaluate's AP equals kitti_ap run directly on the onnxruntime graph's boxes; the
    fp32 graph and the reference detect the same (parity) so their AP agree closely."""
    card_path, onnx = maffnet_tiny_export
    report = radaredge.evaluate(card_path, onnx, data=labelled, split="val")
    card = load_card(card_path)
    model = radaredge.runtime.load(onnx)
    frames = [DetectionSet(labelled, "val", VOD).frame(i, card.features) for i in range(4)]
    dets = []
    for f in frames:
        out = model.run([card_points(f, card)])
        names = np.array([card.get("classes")[i - 1] for i in out["labels"]], dtype=object)
        dets.append(radar_boxes_to_labels(out["boxes"], out["scores"], names, f.calib, f.image_size))
    direct = ap_table(evaluate_frames([f.labels for f in frames], dets, VOD.eval_classes))
    for area in direct:
        for cls in direct[area]:
            assert report.ap[ORT][area][cls]["3d"] == pytest.approx(direct[area][cls]["3d"])
            assert abs(report.ap[ORT][area][cls]["bev"] - report.ap[REFERENCE][area][cls]["bev"]) < 5.0


def test_eval_refuses_options_of_other_tasks(labelled, maffnet_tiny_export, tmp_path):
    card, onnx = maffnet_tiny_export
    res = invoke("eval", "--model", "maffnet-tiny", "--config", card, "--onnx", onnx, "--data", labelled,
                 "--radius", 10, "--report-dir", tmp_path / "r")
    assert res.exit_code == 2 and "--radius not used" in res.output
    res = invoke("eval", "--model", "maffnet-tiny", "--config", card, "--onnx", onnx, "--report-dir", tmp_path / "r")
    assert res.exit_code == 2 and "missing --data" in res.output
    res = invoke("eval", "--model", "maffnet-tiny", "--config", card, "--onnx", onnx, "--data", labelled,
                 "--split", "test", "--report-dir", tmp_path / "r")
    assert res.exit_code == 2 and "val.txt" not in res.output and "lists no frames" in res.output


def test_parity_quantized_reports_ap_lost_per_class(maffnet_tiny_export):
    card, onnx = maffnet_tiny_export
    report = radaredge.parity(card, onnx, cases=2, quantized=True)
    task = report.to_dict()["task"]
    assert set(task["loss"]) == {"Car", "Pedestrian", "Cyclist"} and task["budget_ap_points"] == 1.0
    assert task["passed"] == all(v <= 1.0 for v in task["loss"].values())
    assert any(line.startswith("int8 by AP") for line in report.lines())
