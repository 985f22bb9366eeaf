"""Put a trained run into the repository's weights zoo (zoo/<card>/) with its scores.

Given the run directory of ``radaredge train`` and the data it trained on, this writes:

- zoo/<card>/weights.pth: the run's best.pth (weights, card, epoch and validation metrics);
- zoo/<card>/card.yaml: the card it was trained with (the export and the regression test read it);
- zoo/<card>/entry.json: sha256 of both, the commands that made them, the training seed, the
  task metric of the torch reference, the fp32 graph, the int8 graph and the seeded (untrained)
  network's graph, with 95 % intervals, on
  held-out data (MAFF-Net: 3D / BEV AP per class on the test split of the labelled set;
  TDFANet: Recall@1/5/10 on a held-out street-network town, ``make-benchmark --layout network
  --route-km 2.2 --seed 1000``, where chance is below 1 %), and the regression set (a small
  fixed synthetic set no training drive is in) with the fp32 graph's metric and interval there,
  which tests/test_zoo.py checks on every run of ``make test``.

    python benchmarks/zoo.py --card maffnet-vod-edge --run runs/maffnet-vod-edge --data set --seed 0 \
        --command "radaredge make-benchmark --task detection --out set; radaredge train ..."

``--name`` files a second entry of a card under another directory (zoo/maffnet-vod-edge-qat/ for
a ``radaredge train --qat`` fine-tune of zoo/maffnet-vod-edge/; its int8 graph is exported with
the ranges the fine-tune learned, and the entry says ``qat``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import torch
import training_run
import yaml
from result_file import sha256_of, write_result

import radaredge
from radaredge.api import make_benchmark
from radaredge.cards import load_card
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.eval.detection import ORT, ORT_INT8, REFERENCE, evaluate_detection

ZOO = training_run.ROOT / "zoo"
DETECTION_REGRESSION = {"version": 2, "drives": 8, "frames": 10, "seed": 11, "split": "test"}  # 40 frames
PLACES_TEST = {"layout": "network", "route_km": 2.2, "seed": 1000}  # a street network no training town shares
PLACES_REGRESSION = {"drives": 2, "frames": 40, "seed": 5}
AREA = "entire_area"


def detection_scores(report, backends) -> dict:
    """backend -> class (and "mAP") -> {3d, bev, 3d_interval, bev_interval} on the entire area."""
    out = {}
    for backend in backends:
        if backend not in report.ap:
            continue
        row = {c: {"3d": v["3d"], "bev": v["bev"], "num_gt": v["num_gt"]} for c, v in report.ap[backend][AREA].items()}
        row["mAP"] = {m: report.mean_ap(backend, AREA, m) for m in ("3d", "bev")}
        for cls, values in row.items():
            for metric in ("3d", "bev"):
                values[f"{metric}_interval"] = report.intervals[backend][AREA][cls][metric]
        out[backend] = row
    return out


def place_scores(report, backends) -> dict:
    """backend -> {recall: {N: %}, recall_interval: {N: [low, high]}} over the queries."""
    return {
        b: {
            "recall": {str(n): r for n, r in report.recall(b).items()},
            "recall_interval": {str(n): list(ci) for n, ci in report.interval(b).items()},
        }
        for b in backends
        if b in report.results
    }


def score_detector(card, weights: Path, data: Path, work: Path) -> tuple[dict, dict]:
    """(test-split scores of the reference, fp32 and int8 graphs; the fp32 graph's regression-set scores)."""
    onnx = work / f"{card.name}.onnx"
    radaredge.export(card, onnx, checkpoint=weights, quantize="int8")
    report = evaluate_detection(card, onnx, data, "test", checkpoint=weights, reference=True, openvino=False)
    seeded = work / f"{card.name}-seeded.onnx"
    radaredge.export(card, seeded)
    untrained = evaluate_detection(card, seeded, data, "test", reference=False, openvino=False)
    test = {
        "frames": len(report.frames),
        "scores": detection_scores(report, [REFERENCE, ORT, ORT_INT8]),
        "seeded": detection_scores(untrained, [ORT])[ORT],
    }  # speed: the benchmarks, measured alone
    spec = DETECTION_REGRESSION
    make_detection_benchmark(work / "regression", spec["drives"], spec["frames"], spec["seed"], version=spec["version"])
    fp32 = work / f"{card.name}-fp32.onnx"
    radaredge.export(card, fp32, checkpoint=weights)
    reg = evaluate_detection(card, fp32, work / "regression", spec["split"], reference=False, openvino=False)
    return test, {**spec, "frames_scored": len(reg.frames), "scores": detection_scores(reg, [ORT])[ORT]}


def score_places(card, weights: Path, work: Path) -> tuple[dict, dict]:
    """(held-out town scores of the reference, fp32 and int8 graphs; the fp32 graph's regression-town scores)."""
    onnx = work / f"{card.name}.onnx"
    exported = radaredge.export(card, onnx, checkpoint=weights, quantize="int8")
    town, reg_town = work / "town", work / "regression"
    chance = make_benchmark(town, **PLACES_TEST).chance["."]["5"]["recall_at_1"]
    make_pr_benchmark(reg_town, PLACES_REGRESSION["drives"], PLACES_REGRESSION["frames"], PLACES_REGRESSION["seed"])
    fp32 = radaredge.evaluate(card, onnx, town / "database", town / "queries", checkpoint=weights)
    int8 = radaredge.evaluate(
        card,
        next(iter(exported.int8.values())),
        town / "database",
        town / "queries",
        checkpoint=weights,
        reference=False,
    )
    scores = {**place_scores(fp32, fp32.results), **{ORT_INT8: place_scores(int8, [ORT])[ORT]}}
    seeded = work / f"{card.name}-seeded.onnx"
    radaredge.export(card, seeded)
    untrained = radaredge.evaluate(card, seeded, town / "database", town / "queries", reference=False)
    test = {
        **PLACES_TEST,
        "queries": fp32.evaluated,
        "chance_recall_1": chance,
        "scores": scores,
        "seeded": place_scores(untrained, [ORT])[ORT],
    }
    reg = radaredge.evaluate(card, onnx, reg_town / "database", reg_town / "queries", reference=False)
    return test, {**PLACES_REGRESSION, "queries": reg.evaluated, "scores": place_scores(reg, [ORT])[ORT]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/zoo.py", description=__doc__.splitlines()[0])
    ap.add_argument("--card", required=True)
    ap.add_argument("--run", type=Path, required=True, help="the run directory of `radaredge train` (best.pth)")
    ap.add_argument("--data", type=Path, help="MAFF-Net: the labelled set it trained on (its test split scores)")
    ap.add_argument("--command", required=True, help="the commands that made the set and the run")
    ap.add_argument("--seed", type=int, required=True, help="the training seed (`radaredge train --seed`)")
    ap.add_argument("--name", help="the entry's directory under zoo/ (default: the card's name)")
    args = ap.parse_args(argv)
    torch.set_num_threads(training_run.THREADS)
    card = load_card(args.card)
    home = ZOO / (args.name or card.name)
    home.mkdir(parents=True, exist_ok=True)
    weights, card_path = home / "weights.pth", home / "card.yaml"
    shutil.copyfile(args.run / "best.pth", weights)
    log = torch.load(weights, weights_only=True)
    card_path.write_text(yaml.safe_dump(log["card"], sort_keys=False))
    trained = load_card(card_path)
    with tempfile.TemporaryDirectory(prefix="radaredge-zoo-") as tmp:
        if trained.model == "maffnet":
            test, regression = score_detector(trained, weights, args.data, Path(tmp))
        else:
            test, regression = score_places(trained, weights, Path(tmp))
    entry = {
        "name": home.name,
        "card": card.name,
        "weights": "weights.pth",
        "weights_sha256": sha256_of(weights),
        "card_file": "card.yaml",
        "card_sha256": sha256_of(card_path),
        "epoch": log["epoch"],
        "validation": log["metrics"],
        "training_seed": args.seed,
        "command": args.command,
        "score_command": f"python benchmarks/zoo.py --card {card.name} --run RUN --data set --seed {args.seed} "
        + (f"--name {args.name} " if args.name else "")
        + "--command ...",
        "qat": "qat" in log,
        "machine": training_run.machine(),
        "test": test,
        "regression": regression,
        "knows": "synthetic scenes only (radaredge make-benchmark)",
    }
    write_result(home / "entry.json", entry)
    print(json.dumps({"test": test["scores"], "regression": regression["scores"]}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
