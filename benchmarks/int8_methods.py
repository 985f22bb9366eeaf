"""int8 calibration methods side by side on trained weights: how much task accuracy each keeps.

For a MAFF-Net card and a checkpoint (the zoo's, or any ``radaredge train`` best.pth), this
exports the fp32 graph once, then one int8 copy per calibration method (``radaredge export
--quantize int8 --calibration-method M``: min/max, percentile, entropy; the card's keep_fp32
and reduce_range, synthetic calibration windows), and scores every copy against the fp32 graph
on the ``--split`` of the labelled set: per class 3D AP with its 95 % bootstrap interval over
frames, and int8's paired difference from fp32 with its interval (the same frames, so the
interval is far narrower than either AP's). A method meets the budget of
docs/quantization.md when no class's difference interval lies wholly below -1.0 point, and it is
*within* the budget when every class's difference is above -1.0. Writes
``benchmarks/results/int8-methods-<card>-<split>-<date>.json``; benchmarks/render.py renders it in
benchmarks/README.md and in docs/quantization.md.

``--qat-weights`` adds a row for a ``radaredge train --qat`` fine-tune of the same weights: its
int8 graph (the learned ranges, ``export --quantize int8 --checkpoint``) against the *original*
weights' fp32 graph, paired over the same frames, so the row says what a user deploying the
fine-tuned int8 graph gives up against the fp32 model they started from.

    python benchmarks/int8_methods.py --card zoo/maffnet-vod-edge/card.yaml \\
        --weights zoo/maffnet-vod-edge/weights.pth --data set [--qat-weights runs/qat/best.pth]
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import tempfile
from pathlib import Path

import torch
import training_run
from result_file import save_result, sha256_of, utc_stamp

import radaredge
from radaredge.artifacts import INT8, copy_path
from radaredge.cards import load_card
from radaredge.eval.detection import INT8_AP_BUDGET, ORT, ORT_INT8, ap_intervals, evaluate_detection
from radaredge.exporting.quantize import CALIBRATION_METHODS, quantize_int8
from zoo import AREA, detection_scores

CLASSES = ("Car", "Pedestrian", "Cyclist", "mAP")


def verdict(differences: dict) -> str:
    """ "within" when every class's int8 - fp32 3D AP is above -budget, "meets" when none's
    interval lies wholly below it (the loss is not resolved beyond the budget), else "fails"."""
    if all(d["3d"] > -INT8_AP_BUDGET for d in differences.values()):
        return "within"
    if all(d["3d_interval"][1] >= -INT8_AP_BUDGET for d in differences.values()):
        return "meets"
    return "fails"


def _row(report, fp32_scores: dict, int8_scores: dict, delta_intervals: dict, command: str) -> dict:
    differences = {
        c: {"3d": int8_scores[c]["3d"] - fp32_scores[c]["3d"], "3d_interval": delta_intervals[AREA][c]["3d"]}
        for c in CLASSES
    }
    return {
        "frames": len(report.frames),
        "fp32": fp32_scores,
        "int8": int8_scores,
        "int8_minus_fp32": differences,
        "verdict": verdict({c: d for c, d in differences.items() if c != "mAP"}),
        "export_command": command,
    }


def score_method(card, fp32: Path, method: str, data: Path, split: str, work: Path) -> tuple[dict, object]:
    """One method's int8 copy of ``fp32`` scored beside it: fp32 and int8 AP, and int8 - fp32
    per class with the paired interval; and the evaluation report."""
    home = work / method
    home.mkdir()
    graph = home / fp32.name
    os.link(fp32, graph)
    quantize_int8(card, graph, copy_path(graph, INT8), method=method)
    report = evaluate_detection(card, graph, data, split, reference=False, openvino=False)
    scores = detection_scores(report, [ORT, ORT_INT8])
    command = f"radaredge export --model {card.name} --checkpoint WEIGHTS --quantize int8 --calibration-method {method}"
    return _row(report, scores[ORT], scores[ORT_INT8], report.delta_intervals[ORT_INT8], command), report


def score_qat(card, weights: Path, baseline, data: Path, split: str, work: Path) -> dict:
    """The int8 graph of a --qat checkpoint (its learned ranges) against the original weights' fp32
    graph (``baseline``'s, an evaluation of the same frames), paired over the frames; its own fp32
    AP beside it."""
    home = work / "qat"
    home.mkdir()
    graph = home / f"{card.name}.onnx"
    radaredge.export(card, graph, checkpoint=weights, quantize="int8")
    report = evaluate_detection(card, graph, data, split, reference=False, openvino=False)
    if [f.frame_id for f in report.frames] != [f.frame_id for f in baseline.frames]:
        raise SystemExit("the --qat-weights evaluation saw other frames than the baseline's")
    curves = {ORT: baseline.curves[ORT], ORT_INT8: report.curves[ORT_INT8]}
    _, deltas = ap_intervals(curves, baseline.classes, baseline.areas, ORT)
    scores = detection_scores(report, [ORT, ORT_INT8])
    row = _row(
        report,
        detection_scores(baseline, [ORT])[ORT],
        scores[ORT_INT8],
        deltas[ORT_INT8],
        f"radaredge export --model {card.name} --checkpoint QAT_WEIGHTS --quantize int8",
    )
    return {**row, "qat_fp32": scores[ORT], "checkpoint": str(weights), "checkpoint_sha256": sha256_of(weights)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/int8_methods.py", description=__doc__.splitlines()[0])
    ap.add_argument("--card", required=True, help="a card name or file (the zoo's card.yaml for its weights)")
    ap.add_argument("--weights", type=Path, required=True, help="the trained checkpoint")
    ap.add_argument("--data", type=Path, required=True, help="the labelled set (its --split is scored)")
    ap.add_argument("--split", default="test", help="the split scored (default test)")
    ap.add_argument("--methods", nargs="+", default=list(CALIBRATION_METHODS), choices=list(CALIBRATION_METHODS))
    ap.add_argument("--qat-weights", type=Path, help="a `radaredge train --qat` fine-tune of --weights (best.pth)")
    ap.add_argument("--results", type=Path, default=training_run.ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    torch.set_num_threads(training_run.THREADS)
    card = load_card(args.card)
    rows = {}
    with tempfile.TemporaryDirectory(prefix="radaredge-int8-methods-") as tmp:
        fp32 = Path(tmp) / f"{card.name}.onnx"
        radaredge.export(card, fp32, checkpoint=args.weights)
        for method in args.methods:
            print(f"{method}: quantising and scoring on the {args.split} split ...", flush=True)
            rows[method], baseline = score_method(card, fp32, method, args.data, args.split, Path(tmp))
        if args.qat_weights:
            print(f"qat: exporting {args.qat_weights} with its learned ranges and scoring ...", flush=True)
            rows["qat"] = score_qat(card, args.qat_weights, baseline, args.data, args.split, Path(tmp))
    doc = {
        "date": utc_stamp(),
        "card": card.name,
        "checkpoint": str(args.weights),
        "checkpoint_sha256": sha256_of(args.weights),
        "data": str(args.data),
        "split": args.split,
        "area": AREA,
        "budget_ap_points": INT8_AP_BUDGET,
        "command": "python benchmarks/int8_methods.py " + shlex.join(sys.argv[1:] if argv is None else argv),
        "machine": training_run.machine(),
        "methods": rows,
    }
    save_result(f"int8-methods-{card.name}-{args.split}", doc, args.results, keep_same_day=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
