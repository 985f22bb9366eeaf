"""Train MAFF-Net stage one on the labelled synthetic set and score it on held-out frames.

The same steps as the commands in docs/models/maffnet.md ("Training"), through the library verbs:

1. the set: ``radaredge make-benchmark --task detection --out <work>/set`` (version 2: 16 train,
   4 val and 20 test drives, each in its own town);
2. ``radaredge train --model <card> --data <work>/set`` with ``--set`` options (validation AP on
   the ``val`` split picks the best epoch); with ``--run DIR`` an existing run directory of that
   command is read instead of training again;
3. ``radaredge export --checkpoint best.pth --quantize int8`` and the seeded network's export;
4. ``radaredge eval --split test``: 3D / BEV AP per class of the seeded graph, and of the trained
   torch reference, fp32 graph and int8 graph side by side, with each backend's frames per second
   and the matched boxes' errors (centre, height bias, size, heading).

Writes benchmarks/results/<card>-training-<date>.json (rendered by benchmarks/render.py).

    python benchmarks/maffnet_training.py --card maffnet-vod --set epochs=6 --set val_frames=40 --set precision=bf16
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import training_run
from result_file import save_result, sha256_of

import radaredge
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.eval.detection import ORT, ORT_INT8, REFERENCE


def _ap(report) -> dict:
    """backend -> area -> class -> {3d, bev} AP (%), frames per second, and backend -> class ->
    the matched boxes' errors (radaredge.eval.box_errors)."""
    return {
        "ap": {
            b: {
                area: {c: {"3d": v["3d"], "bev": v["bev"], "num_gt": v["num_gt"]} for c, v in per.items()}
                for area, per in areas.items()
            }
            for b, areas in report.ap.items()
        },
        "fps": report.fps,
        "frames": len(report.frames),
        "box_errors": {b: {c: e.to_dict() for c, e in per.items()} for b, per in report.box_errors.items()},
    }


def main(argv=None) -> int:
    ap = training_run.parser("python benchmarks/maffnet_training.py", __doc__, "maffnet-vod")
    ap.add_argument("--drives", type=int, help="drives of the set (default: the set version's)")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--set-version", type=int, default=2, choices=(1, 2), help="the detection set's version")
    ap.add_argument("--data", type=Path, help="an existing labelled set (default: <work>/set, written first)")
    ap.add_argument("--run", type=Path, help="an existing run directory of `radaredge train` to score")
    ap.add_argument("--command", help="the training command to record with --run")
    ap.add_argument("--no-reference", action="store_true", help="score the graphs only (not the torch reference)")
    args = ap.parse_args(argv)
    card, work, options, stamp = training_run.start(args)
    data = args.data or work / "set"
    if not data.exists():
        make_detection_benchmark(data, args.drives, args.frames, seed=0, version=args.set_version)
    run = args.run or work / "run"
    if args.run is None:
        t0 = time.perf_counter()
        radaredge.train(card, data, run, options=options, overwrite=True, log=lambda line: print(line, flush=True))
        print(f"trained in {(time.perf_counter() - t0) / 60:.1f} min", flush=True)
    log = json.loads((run / "train-log.json").read_text())
    best = run / "best.pth"
    graphs = work / "graphs"
    fp32 = graphs / f"{card.name}.onnx"
    radaredge.export(card, fp32, checkpoint=best, quantize="int8")
    seeded = graphs / f"{card.name}-seeded.onnx"
    radaredge.export(card, seeded)
    trained = radaredge.evaluate(card, fp32, data=data, split="test", checkpoint=best, reference=not args.no_reference)
    untrained = radaredge.evaluate(card, seeded, data=data, split="test", reference=False)
    for name, rep, backend in (
        ("seeded", untrained, ORT),
        ("trained reference", trained, REFERENCE),
        ("trained fp32", trained, ORT),
        ("trained int8", trained, ORT_INT8),
    ):
        if backend not in rep.ap:
            continue
        row = rep.ap[backend]["entire_area"]
        print(f"test split, {name}: 3D AP " + ", ".join(f"{c} {v['3d']:.2f}" for c, v in row.items()), flush=True)
    drives = f" --drives {args.drives}" if args.drives else ""
    command = args.command or (
        f"radaredge make-benchmark --task detection --out set --version {args.set_version}"
        f"{drives} --frames {args.frames}; radaredge train --model {card.name} --data set"
        + training_run.settings_text(options)
    )
    out = {
        "date": stamp,
        "card": card.name,
        "machine": training_run.machine(),
        "command": command,
        "checkpoint_sha256": sha256_of(best),
        "data": str(data),
        "train": log,
        "train_seconds": log.get("seconds"),
        "test_trained": _ap(trained),
        "test_seeded": _ap(untrained),
    }
    save_result(f"{card.name}-training", out, keep_same_day=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
