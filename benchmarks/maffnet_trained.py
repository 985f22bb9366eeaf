"""MAFF-Net speed on trained weights, with the stage split, NMS's share and the worst case.

Seeded weights score nearly every anchor just above the threshold, so their frames fill all
pre-NMS slots and time the NMS, not the detector. This script times a *trained* checkpoint
(`radaredge train --model M --data SET`) on real frames of a labelled set (the ``test`` split by
default, cropped as the graph takes them), in onnxruntime on 2 cores:

- ``fp32`` and ``int8``: the graph exported with the checkpoint, and its int8 copy;
- ``worst case``: the same weights with every anchor's class logit raised by 30, so every anchor
  scores above the threshold and the NMS gets ``post_processing.pre_max`` candidates on every
  frame: the bound a real-time user plans with.

All three run in one alternating loop (:func:`radaredge.benchmarking.timing.benchmark`), medians over
``--passes`` passes over the frames. Each graph is then profiled (median over 3 passes) and its
kernel time split by the card's stages (VFE+SPA, CFA, CAF, backbone+head, NMS); not the int8
copy, whose quantised nodes lose the module scopes the split reads. Also counted per
frame: the anchors above the score threshold (NMS candidates) and the detections. Writes
``benchmarks/results/maffnet-trained-<card>-<date>.json``, which benchmarks/render.py renders.

    python benchmarks/maffnet_trained.py --model maffnet-vod --checkpoint runs/maffnet-vod/best.pth \\
        --data bench-detection
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import statistics
import sys
from pathlib import Path

import numpy as np
import onnx
import torch
from result_file import RESULTS, save_result

import radaredge
from radaredge import runtime
from radaredge.artifacts import INT8, copy_path
from radaredge.benchmarking.profiling import profile_runs, stage_times_from_profile
from radaredge.benchmarking.timing import benchmark, cpu_name, pin_threads, require_ok
from radaredge.cards import load_card
from radaredge.data.kitti_detection import DetectionSet
from radaredge.eval.detection import card_points, layout_for_card
from radaredge.models import create_model, model_spec
from radaredge.runtime.session import make_session, run_session

ROOT = Path(__file__).resolve().parent.parent
WORST_LOGIT_SHIFT = 30.0  # added to every class bias: sigmoid(logit + 30) > 0.999 for any logit > -23


def frame_points(card, data: Path, split: str, frames: int) -> tuple[list[np.ndarray], list[str]]:
    """Up to ``frames`` frames of ``split``, evenly spaced, as the graph takes them."""
    the_set = DetectionSet(data, split, layout_for_card(card), int(card.get("input.scans_accumulated", 1)))
    idx = sorted({int(i) for i in np.linspace(0, len(the_set) - 1, min(frames, len(the_set))).round()})
    got = [the_set.frame(i, card.features) for i in idx]
    return [card_points(f, card) for f in got], [f.frame_id for f in got]


def export_graphs(card, checkpoint: Path, export_dir: Path) -> dict[str, Path]:
    """fp32 + int8 graphs of the checkpoint, and the fp32 worst-case graph (class bias + 30)."""
    export_dir.mkdir(parents=True, exist_ok=True)
    net = create_model(card, checkpoint)
    fp32 = export_dir / f"{card.name}-trained.onnx"
    radaredge.export(card, fp32, model=net, quantize="int8")
    worst_net = copy.deepcopy(net)
    with torch.no_grad():
        worst_net.dense_head.conv_cls.bias += WORST_LOGIT_SHIFT
    worst = export_dir / f"{card.name}-worst-case.onnx"
    radaredge.export(card, worst, model=worst_net)
    return {"fp32": fp32, "int8": copy_path(fp32, INT8), "worst case": worst}


def candidates(out: dict, threshold: float) -> int:
    """Anchors whose best class score reaches the threshold: what the NMS is given (before pre_max)."""
    return int((np.asarray(out["anchor_scores"]).max(-1) >= threshold).sum())


def bench_trained(
    model: str,
    checkpoint: Path,
    data: Path,
    split: str,
    frames: int,
    passes: int,
    threads: int,
    export_dir: Path,
    rounds: int = 3,
) -> dict:
    card = load_card(model)
    spec = model_spec(card).graph()
    points, ids = frame_points(card, data, split, frames)
    graphs = export_graphs(card, checkpoint, export_dir)
    loaded = runtime.load(graphs["fp32"], threads=threads)
    cases = [loaded.feeds([p]) for p in points]
    sessions = {name: make_session(path, threads=threads) for name, path in graphs.items()}
    backends = {name: (lambda feeds, s=s: run_session(s, feeds)) for name, s in sessions.items()}
    results = {r.backend: r for r in require_ok(benchmark(backends, cases, passes * len(cases), warmup=2))}
    threshold = float(card.get("post_processing.score_thresh"))
    stages, counts = {}, {}
    for name, path in graphs.items():
        outs = [run_session(sessions[name], c) for c in cases]
        counts[name] = {
            "candidates": [candidates(o, threshold) for o in outs],
            "detections": [int(len(o["scores"])) for o in outs],
        }
        if name == "int8":  # quantised nodes lose their module scopes: no stage split
            continue
        model_proto = onnx.load(str(path), load_external_data=False)
        profiled = [
            stage_times_from_profile(
                profile_runs(path, cases, threads, len(cases)),
                model_proto,
                list(spec.onnx_stages),
                spec.onnx_post_outputs,
                len(cases),
            )
            for _ in range(rounds)
        ]
        stages[name] = {
            k: statistics.median(p.get(k, 0.0) for p in profiled) for k in dict.fromkeys(k for p in profiled for k in p)
        }
    rows = []
    for name in graphs:
        r = results[name]
        per_stage = stages.get(name, {})
        total = sum(per_stage.values())
        rows.append(
            {
                "graph": name,
                "p50_ms": r.p50_ms,
                "p90_ms": r.p90_ms,
                "fps": r.fps,
                "stage_ms": per_stage,
                "nms_share": per_stage.get("NMS", 0.0) / total if total else None,
                "candidates_median": float(np.median(counts[name]["candidates"])),
                "candidates_max": int(max(counts[name]["candidates"])),
                "detections_median": float(np.median(counts[name]["detections"])),
            }
        )
    digest = hashlib.sha256(Path(checkpoint).read_bytes()).hexdigest()
    return {
        "model": card.name,
        "checkpoint": str(checkpoint),
        "checkpoint_sha256": digest,
        "weights_sha256": loaded.weights_sha256,
        "data": str(data),
        "split": split,
        "frames": ids,
        "points_median": float(np.median([len(p) for p in points])),
        "passes": passes,
        "threads": threads,
        "score_thresh": threshold,
        "pre_max": int(card.get("post_processing.pre_max")),
        "worst_logit_shift": WORST_LOGIT_SHIFT,
        "rows": rows,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="maffnet-vod")
    ap.add_argument("--checkpoint", type=Path, required=True, help="A trained checkpoint (radaredge train's best.pth).")
    ap.add_argument(
        "--data", type=Path, required=True, help="A labelled set (radaredge make-benchmark --task detection)."
    )
    ap.add_argument("--split", default="test")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--passes", type=int, default=3, help="Timed passes over the frames (medians over all).")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--export-dir", type=Path, default=ROOT / "export")
    ap.add_argument("--note", default="", help="Which weights these are, for the table (e.g. the training command).")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    cores = pin_threads(args.threads)
    result = bench_trained(
        args.model, args.checkpoint, args.data, args.split, args.frames, args.passes, args.threads, args.export_dir
    )
    result.update(cpu=cpu_name(), cores=cores, note=args.note)
    save_result(f"maffnet-trained-{result['model']}", result, args.out)
    for row in result["rows"]:
        split = ", ".join(f"{k} {v:.1f}" for k, v in row["stage_ms"].items())
        share = "-" if row["nms_share"] is None else f"{100 * row['nms_share']:.1f} %"
        print(
            f"{row['graph']:<11} p50 {row['p50_ms']:7.1f} ms  {row['fps']:5.1f} FPS  NMS {share}"
            f"  candidates {row['candidates_median']:.0f} (max {row['candidates_max']})  [{split}]"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
