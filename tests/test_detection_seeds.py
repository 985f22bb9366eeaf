"""benchmarks/detection_seeds.py: a detector's test AP over training seeds, summarised as mean,
spread and the t-interval of the mean, and rendered by benchmarks/render.py."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

from radaredge.cards import load_card
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.models import create_model

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"


def _module(name: str):
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))  # the scripts import their neighbours by name
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_seed_summary_is_the_mean_with_its_student_t_interval():
    seeds = _module("detection_seeds")
    s = seeds.seed_summary([1.0, 2.0, 3.0])
    half = 4.303 / math.sqrt(3)  # t(0.975, 2 df) * std 1 / sqrt(3)
    assert (s["n"], s["mean"], s["std"], s["min"], s["max"]) == (3, 2.0, 1.0, 1.0, 3.0)
    assert s["interval"] == pytest.approx([2.0 - half, 2.0 + half])
    one = seeds.seed_summary([5.0])
    assert one["std"] is None and one["interval"] is None and one["mean"] == 5.0


def test_weights_arguments_name_what_is_wrong(tmp_path):
    seeds = _module("detection_seeds")
    ckpt = tmp_path / "best.pth"
    ckpt.write_bytes(b"x")
    assert seeds.parse_weights([f"0={ckpt}", f"3={ckpt}"]) == {0: ckpt, 3: ckpt}
    missing = f"0={tmp_path}/missing.pth"
    for bad, said in (([str(ckpt)], "SEED=FILE"), ([missing], "SEED=FILE"), ([f"1={ckpt}"] * 2, "twice")):
        with pytest.raises(SystemExit, match=said):
            seeds.parse_weights(bad)


def test_two_seeds_are_scored_timed_summarised_and_rendered(tmp_path):
    """Two checkpoints of the tiny card (seeded with different card seeds, standing in for two
    training seeds) on a small labelled set: every seed's scores and checkpoint hash are in the
    JSON, the summary is their mean, and render.py shows the table."""
    seeds = _module("detection_seeds")
    render = _module("render")
    card = load_card(ROOT / "tests" / "cards" / "maffnet-tiny.yaml")
    data = tmp_path / "set"
    make_detection_benchmark(data, drives=8, frames=1, seed=0)  # the test split: a few drives
    weights = []
    for seed in (0, 1):
        net, generator = create_model(card), torch.Generator().manual_seed(seed)
        with torch.no_grad():  # seed 1's weights differ from the card's seeded ones
            for p in net.parameters():
                p.add_(seed * 0.05 * torch.randn(p.shape, generator=generator))
        path = tmp_path / f"run-{seed}" / "best.pth"
        path.parent.mkdir()
        torch.save({"model_state": net.state_dict(), "card": card.data, "epoch": 1, "metrics": {}}, path)
        weights += ["--weights", f"{seed}={path}"]
    results = tmp_path / "results"
    args = ["--card", str(card.path), "--data", str(data), *weights, "--command", "train --seed SEED"]
    assert seeds.main([*args, "--frames", "2", "--passes", "1", "--results", str(results)]) == 0
    (written,) = results.glob("detection-seeds-maffnet-tiny-*.json")
    doc = json.loads(written.read_text())
    assert [s["seed"] for s in doc["seeds"]] == [0, 1]
    assert all(len(s["checkpoint_sha256"]) == 64 and s["frames"] > 0 for s in doc["seeds"])
    fp32 = [s["scores"]["onnxruntime"]["mAP"]["3d"] for s in doc["seeds"]]
    assert doc["summary"]["fp32"]["mAP"]["mean"] == pytest.approx(sum(fp32) / 2)
    assert doc["summary"]["p50_ms"]["int8"]["n"] == 2
    text = render.render(results, tmp_path / "no-zoo")
    assert "## MAFF-Net across training seeds: maffnet-tiny" in text
    assert "| seed | checkpoint sha256 | epoch |" in text and f"`{doc['seeds'][1]['checkpoint_sha256'][:12]}`" in text
