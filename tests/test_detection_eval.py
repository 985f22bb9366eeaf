"""`radaredge make-benchmark --task detection` then `radaredge eval --data`: the torch reference,
the fp32 graph and its int8 copy scored with VoD's protocol in one table, the report directory,
the Python API verb, and int8 judged by AP in `parity-check --quantized`."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import yaml
from conftest import MAFFNET_TINY_CARD, invoke

import radaredge
from radaredge.cards import load_card
from radaredge.data.kitti_detection import VOD, DetectionSet, radar_boxes_to_labels
from radaredge.eval.detection import ORT, ORT_INT8, REFERENCE, card_points
from radaredge.eval.kitti_ap import ap_table, evaluate_frames


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
    res = invoke(
        "eval",
        "--model",
        "maffnet-tiny",
        "--config",
        card,
        "--onnx",
        onnx,
        "--data",
        labelled,
        "--report-dir",
        tmp_path / "report",
        "--report",
        tmp_path / "r.json",
    )
    assert res.exit_code == 0, res.output
    head = next(line for line in res.output.splitlines() if line.startswith("3D AP"))
    for backend in (REFERENCE, ORT, ORT_INT8):
        assert backend in head
    assert "corridor" in res.output and "frames per second" in res.output
    assert any(line.startswith("box errors") for line in res.output.splitlines())
    report = json.loads((tmp_path / "r.json").read_text())
    errors = report["box_errors"][REFERENCE]["Car"]
    assert errors["ground_truth"] >= report["ap"][REFERENCE]["entire_area"]["Car"]["num_gt"] > 0  # every label
    assert 0 <= errors["matched"] <= errors["ground_truth"]
    assert set(report["box_errors"]) == {"matching", *report["ap"]}
    assert report["frames"] == 4 and report["dataset"] == "vod" and report["reference"] == REFERENCE
    assert set(report["ap"]) >= {REFERENCE, ORT, ORT_INT8}
    assert set(report["ap"][ORT]) == {"entire_area", "corridor"}
    car = report["ap"][ORT]["entire_area"]["Car"]
    assert {"3d", "bev", "aos", "3d_r40", "num_gt"} <= set(car) and car["num_gt"] > 0
    delta = report["delta_ap_points"][ORT]["entire_area"]["Car"]["3d"]
    assert delta == pytest.approx(car["3d"] - report["ap"][REFERENCE]["entire_area"]["Car"]["3d"])
    # every AP and mAP with its bootstrap interval over frames, every difference with its paired one
    assert "bootstrap over frames" in report["protocol"]["interval"] and "[95 % interval" in res.output
    for backend in report["ap"]:
        for area in ("entire_area", "corridor"):
            for cls in ("Car", "Pedestrian", "Cyclist", "mAP"):
                for metric in ("3d", "bev"):
                    low, high = report["ap_interval"][backend][area][cls][metric]
                    assert 0.0 <= low <= high <= 100.0, (backend, area, cls, metric)
                    if backend != REFERENCE:
                        d_low, d_high = report["delta_ap_interval"][backend][area][cls][metric]
                        assert -100.0 <= d_low <= d_high <= 100.0
    low, high = report["ap_interval"][ORT]["entire_area"]["mAP"]["3d"]
    mean = report["map"][ORT]["entire_area"]["3d"]
    assert low - 1e-9 <= mean <= high + 1e-9
    assert REFERENCE not in report["delta_ap_interval"]
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
    res = invoke(
        "eval",
        "--model",
        "maffnet-tiny",
        "--config",
        card,
        "--onnx",
        onnx,
        "--data",
        labelled,
        "--radius",
        10,
        "--report-dir",
        tmp_path / "r",
    )
    assert res.exit_code == 2 and "--radius not used" in res.output
    res = invoke("eval", "--model", "maffnet-tiny", "--config", card, "--onnx", onnx, "--report-dir", tmp_path / "r")
    assert res.exit_code == 2 and "missing --data" in res.output
    res = invoke(
        "eval",
        "--model",
        "maffnet-tiny",
        "--config",
        card,
        "--onnx",
        onnx,
        "--data",
        labelled,
        "--split",
        "test",
        "--report-dir",
        tmp_path / "r",
    )
    assert res.exit_code == 2 and "val.txt" not in res.output and "lists no frames" in res.output


def test_parity_quantized_reports_ap_lost_per_class(maffnet_tiny_export):
    card, onnx = maffnet_tiny_export
    report = radaredge.parity(card, onnx, cases=2, quantized=True)
    task = report.to_dict()["task"]
    assert set(task["loss"]) == {"Car", "Pedestrian", "Cyclist"} and task["budget_ap_points"] == 1.0
    assert task["frames"] == 36  # every split of the 3-drive, 12-frame set, not its 12-frame val
    assert task["passed"] == all(v <= 1.0 for v in task["loss"].values())
    assert any(line.startswith("int8 by AP") for line in report.lines())


def test_a_tj4d_card_on_a_tj4d_layout(tmp_path):
    """A 4-class card on TJ4DRadSet's columns (x, y, z, v_r, snr), cropped to the camera's view,
    scored with TJ4D's protocol (Car, Pedestrian, Cyclist, Truck; entire area only)."""
    data = yaml.safe_load(MAFFNET_TINY_CARD.read_text())
    data.update(
        name="maffnet-tiny-tj4d",
        features=["x", "y", "z", "v_r", "snr"],
        classes=["Car", "Pedestrian", "Cyclist", "Truck"],
        input={"scans_accumulated": 1, "crop": "camera_fov"},
    )
    data["cfa"]["velocity_feature"] = "v_r"
    data["dense_head"]["anchors"].append(
        {**copy.deepcopy(data["dense_head"]["anchors"][0]), "class_name": "Truck", "anchor_sizes": [[8.0, 2.5, 3.0]]}
    )
    card = tmp_path / "maffnet-tiny-tj4d.yaml"
    card.write_text(yaml.safe_dump(data, sort_keys=False))
    radaredge.export(card, tmp_path / "tj.onnx")
    res = invoke(
        "make-benchmark",
        "--task",
        "detection",
        "--dataset",
        "tj4d",
        "--out",
        tmp_path / "tj4d",
        "--drives",
        2,
        "--frames",
        2,
    )
    assert res.exit_code == 0 and "TJ4DRadSet" in res.output, res.output
    report = radaredge.evaluate(card, tmp_path / "tj.onnx", data=tmp_path / "tj4d", reference=False)
    assert report.layout == "tj4d" and report.areas == ("entire_area",)
    assert report.classes == ["Car", "Pedestrian", "Cyclist", "Truck"]
    assert report.min_iou == {"Car": 0.5, "Pedestrian": 0.25, "Cyclist": 0.25, "Truck": 0.5}
    assert all(len(card_points(f, load_card(card))) <= len(f.points) for f in report.frames)


def test_make_benchmark_refuses_options_of_the_other_task(tmp_path):
    res = invoke("make-benchmark", "--out", tmp_path / "a", "--dataset", "tj4d")
    assert res.exit_code == 2 and "--dataset is for --task detection" in res.output
    res = invoke("make-benchmark", "--task", "detection", "--out", tmp_path / "b", "--towns", 2)
    assert res.exit_code == 2 and "--towns is for --task places" in res.output
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_eval_of_an_int8_copy_scores_it_beside_its_fp32_graph(labelled, maffnet_tiny_export):
    card, onnx = maffnet_tiny_export
    report = radaredge.evaluate(card, onnx.with_suffix(".int8.onnx"), data=labelled, reference=False)
    assert list(report.ap)[:2] == [ORT, ORT_INT8]
