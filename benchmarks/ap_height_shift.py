"""How far does a detector's 3D AP move when its boxes move up or down by a few millimetres?

A 3D AP measured at IoU 0.5 on boxes that already sit off in height can turn on millimetres: when
many detections overlap their labels at just about the IoU threshold, a shift far below anything a
user would call a different detector moves the AP by points. This script scores the detections
of an exported graph (and of its ``.int8.onnx`` copy beside it, when there is one) on a labelled
split as ``radaredge eval`` does, then again with every detected box's centre moved by ``dz``
metres along z (radar frame, z up), for each ``--shifts`` value. Read an int8 graph's AP loss
against the fp32 graph's own AP at a shift the size of the int8 graph's change in height bias
(``radaredge eval``'s box errors, ``dz``): when fp32 moved by that much loses as much, the loss is
the metric's edge, not a worse detector. Writes
``benchmarks/results/ap-height-shift-<card>-<date>.json``.

    python benchmarks/ap_height_shift.py --model maffnet-vod-edge --onnx export/maffnet-vod-edge.onnx \\
        --data bench-detection
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from result_file import RESULTS, save_result, sha256_of

from radaredge.benchmarking.timing import cpu_name
from radaredge.cards import load_card
from radaredge.eval.detection import ap_table, as_labels, evaluate_detection, evaluate_frames, layout_for_card

SHIFTS = (-0.2, -0.1, -0.05, -0.01, -0.004, 0.0, 0.004, 0.01, 0.05)  # m, along z


def shifted_ap(model: str, onnx: Path, data: Path, split: str, shifts=SHIFTS) -> dict:
    """backend -> {"dz_bias": the matched boxes' mean height error per class (m), "ap": {dz (m, as
    a string) -> class -> {"3d", "bev"} AP (%), entire area}}."""
    card = load_card(model)
    report = evaluate_detection(card, onnx, data, split=split, reference=False, openvino=False)
    layout = layout_for_card(card)
    eval_classes = tuple(layout.eval_class(c) for c in report.classes)
    labels = [f.labels for f in report.frames]
    out = {}
    for backend, found in report.detections.items():
        per_shift = {}
        for dz in shifts:
            step = np.array([0.0, 0.0, dz, 0.0, 0.0, 0.0, 0.0])
            moved = [
                as_labels((boxes + step, scores, classes), frame, card.get("classes"))
                for (boxes, scores, classes), frame in zip(found, report.frames)
            ]
            table = ap_table(evaluate_frames(labels, moved, eval_classes, ("entire_area",)))["entire_area"]
            per_shift[f"{dz:+.3f}"] = {c: {"3d": table[c]["3d"], "bev": table[c]["bev"]} for c in report.classes}
        out[backend] = {
            "dz_bias": {c: e.to_dict()["dz"] for c, e in report.box_errors[backend].items()},
            "ap": per_shift,
        }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--onnx", type=Path, required=True, help="The fp32 graph; its .int8.onnx beside it is scored too.")
    ap.add_argument(
        "--data", type=Path, required=True, help="A labelled set (radaredge make-benchmark --task detection)."
    )
    ap.add_argument("--split", default="test")
    ap.add_argument("--shifts", default=",".join(str(s) for s in SHIFTS), help="Comma-separated z shifts in metres.")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    shifts = tuple(float(s) for s in args.shifts.split(","))
    result = shifted_ap(args.model, args.onnx, args.data, args.split, shifts)
    for backend, r in result.items():
        for dz, per in r["ap"].items():
            print(
                f"{backend:18s} dz {dz} m: "
                + ", ".join(f"{c} {v['3d']:.2f} (BEV {v['bev']:.2f})" for c, v in per.items())
            )
    doc = {
        "model": args.model,
        "onnx": str(args.onnx),
        "onnx_sha256": sha256_of(args.onnx),
        "data": str(args.data),
        "split": args.split,
        "shifts_m": list(shifts),
        "backends": result,
        "cpu": cpu_name(),
    }
    save_result(f"ap-height-shift-{args.model}", doc, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
