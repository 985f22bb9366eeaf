"""A MAFF-Net card's test AP and speed over several training seeds: mean, spread and intervals.

Each ``--weights SEED=FILE`` is the best.pth of one ``radaredge train --seed SEED`` run of the
card, all on the same data with the same schedule. For every seed this script:

- exports the fp32 graph and its int8 copy (the card's int8 policy, synthetic calibration);
- scores both on the test split of ``--data`` (VoD's protocol, entire area): per class 3D and
  BEV AP with its 95 % bootstrap interval over frames, and int8's paired difference from fp32;
- times both graphs on ``--frames`` test frames in onnxruntime, 2 threads pinned, every seed's
  graphs in one alternating loop (medians, :func:`radaredge.benchmarking.timing.benchmark`).

Across the seeds, per backend and class: mean, sample standard deviation (the spread),
min..max and the 95 % interval of the mean over seeds (Student's t, n - 1 degrees of freedom):
how far another seed of the same command may land, which a one-run table cannot say. The
frame-bootstrap interval of each seed stays beside it. Writes
``benchmarks/results/detection-seeds-<card>-<date>.json`` with each checkpoint's sha256 and the
commands; benchmarks/render.py renders it.

    python benchmarks/detection_seeds.py --card maffnet-vod-edge --data set \\
        --weights 0=zoo/maffnet-vod-edge/weights.pth --weights 1=run-1/best.pth --weights 2=run-2/best.pth \\
        --command "radaredge make-benchmark --task detection --out set; radaredge train --model \\
maffnet-vod-edge --data set --epochs 12 --seed SEED --set val_frames=40 --output run-SEED"
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

import torch
import training_run
from maffnet_trained import frame_points
from result_file import RESULTS, save_result, sha256_of
from seed_stats import seed_summary

import radaredge
from radaredge import runtime
from radaredge.artifacts import INT8, copy_path
from radaredge.benchmarking.timing import benchmark, cpu_name, pinned, require_ok
from radaredge.cards import load_card
from radaredge.eval.detection import ORT, ORT_INT8, evaluate_detection
from radaredge.runtime.session import make_session, run_session
from zoo import AREA, detection_scores

CLASSES = ("Car", "Pedestrian", "Cyclist", "mAP")
BACKENDS = {ORT: "fp32", ORT_INT8: "int8"}


def parse_weights(items: list[str]) -> dict[int, Path]:
    """``SEED=FILE`` options -> seed -> checkpoint; SystemExit naming a malformed or missing one."""
    out = {}
    for item in items:
        seed, sep, file = item.partition("=")
        if not sep or not seed.strip().isdigit() or not Path(file).is_file():
            raise SystemExit(f"--weights {item!r}: expected SEED=FILE with an existing checkpoint")
        if int(seed) in out:
            raise SystemExit(f"--weights: seed {seed} given twice")
        out[int(seed)] = Path(file)
    return out


def score_seed(card, checkpoint: Path, data: Path, work: Path) -> tuple[dict, Path]:
    """(this checkpoint's test-split scores of the fp32 and int8 graphs with int8's paired
    difference; its fp32 graph)."""
    onnx = work / f"{card.name}.onnx"
    radaredge.export(card, onnx, checkpoint=checkpoint, quantize="int8")
    report = evaluate_detection(card, onnx, data, "test", checkpoint=checkpoint, reference=False, openvino=False)
    scores = detection_scores(report, list(BACKENDS))
    diff = {
        c: {
            "3d": scores[ORT_INT8][c]["3d"] - scores[ORT][c]["3d"],
            "3d_interval": report.delta_intervals[ORT_INT8][AREA][c]["3d"],
        }
        for c in CLASSES
    }
    saved = torch.load(checkpoint, map_location="cpu", weights_only=True)
    return {
        "checkpoint": str(checkpoint),
        "checkpoint_sha256": sha256_of(checkpoint),
        "weights_sha256": runtime.load(onnx).weights_sha256,
        "epoch": saved.get("epoch"),
        "frames": len(report.frames),
        "scores": scores,
        "int8_minus_fp32": diff,
    }, onnx


def time_seeds(card, graphs: dict[int, Path], data: Path, frames: int, passes: int) -> dict[int, dict]:
    """seed -> {fp32, int8: {p50_ms, p90_ms, fps}}: every seed's two graphs in one alternating
    loop over ``frames`` test frames (trained weights: the NMS sees real candidate counts)."""
    points, _ = frame_points(card, data, "test", frames)
    feeds = [runtime.load(next(iter(graphs.values())), threads=1).feeds([p]) for p in points]
    backends = {}
    for seed, fp32 in graphs.items():
        for name, path in (("fp32", fp32), ("int8", copy_path(fp32, INT8))):
            session = make_session(path, threads=training_run.THREADS)
            backends[f"{seed} {name}"] = lambda f, s=session: run_session(s, f)
    with pinned(training_run.THREADS):
        rows = {r.backend: r for r in require_ok(benchmark(backends, feeds, passes * len(feeds), warmup=2))}
    return {
        seed: {
            name: {k: getattr(rows[f"{seed} {name}"], k) for k in ("p50_ms", "p90_ms", "fps")}
            for name in ("fp32", "int8")
        }
        for seed in graphs
    }


def configuration(card) -> dict:
    """What sets the card's point on the trade-off curve: pillar size (m) and the BEV backbone's
    blocks per stage and channels per stage."""
    return {
        "voxel_size_m": card.get("pillars.voxel_size")[0],
        "layer_nums": card.get("backbone_2d.layer_nums"),
        "num_filters": card.get("backbone_2d.num_filters"),
    }


def summarise(seeds: list[dict]) -> dict:
    """backend -> class -> :func:`seed_summary` of its 3D AP; speed -> graph -> of its median ms;
    and int8's 3D AP difference from fp32 per class."""
    out = {BACKENDS[b]: {c: seed_summary([s["scores"][b][c]["3d"] for s in seeds]) for c in CLASSES} for b in BACKENDS}
    out["int8 - fp32"] = {c: seed_summary([s["int8_minus_fp32"][c]["3d"] for s in seeds]) for c in CLASSES}
    out["p50_ms"] = {g: seed_summary([s["speed"][g]["p50_ms"] for s in seeds]) for g in ("fp32", "int8")}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/detection_seeds.py", description=__doc__.splitlines()[0])
    ap.add_argument("--card", required=True, help="the card the runs trained (a name or a card file)")
    ap.add_argument("--data", type=Path, required=True, help="the labelled set they trained on (its test split)")
    ap.add_argument("--weights", action="append", required=True, metavar="SEED=FILE", help="one per training seed")
    ap.add_argument("--command", required=True, help="the commands that made the set and each run (SEED for the seed)")
    ap.add_argument("--frames", type=int, default=40, help="test frames timed per graph (evenly spaced)")
    ap.add_argument("--passes", type=int, default=3, help="timed passes over those frames")
    ap.add_argument("--tag", default="", help="appended to the result's name (e.g. the set's version)")
    ap.add_argument("--results", type=Path, default=RESULTS, help="where the result JSON goes")
    args = ap.parse_args(argv)
    weights = parse_weights(args.weights)
    torch.set_num_threads(training_run.THREADS)
    card = load_card(args.card)
    seeds, graphs = [], {}
    with tempfile.TemporaryDirectory(prefix="radaredge-seeds-") as tmp:
        for seed, checkpoint in sorted(weights.items()):
            print(f"seed {seed}: scoring {checkpoint} on the test split ...", flush=True)
            work = Path(tmp) / str(seed)
            work.mkdir()
            row, graphs[seed] = score_seed(card, checkpoint, args.data, work)
            seeds.append({"seed": seed, **row})
        print("timing every seed's fp32 and int8 graphs ...", flush=True)
        for row, speed in zip(seeds, time_seeds(card, graphs, args.data, args.frames, args.passes).values()):
            row["speed"] = speed
    doc = {
        "card": card.name,
        "configuration": configuration(card),
        "data": str(args.data),
        "split": "test",
        "area": AREA,
        "command": args.command,
        "score_command": "python benchmarks/detection_seeds.py " + shlex.join(sys.argv[1:] if argv is None else argv),
        "machine": {**training_run.machine(), "cpu": cpu_name()},
        "timing": {"frames": args.frames, "passes": args.passes, "threads": training_run.THREADS},
        "statistics": "per seed: 95 % percentile bootstrap over frames (radaredge eval); across seeds: mean, "
        "sample standard deviation, min..max and the 95 % Student-t interval of the mean",
        "seeds": seeds,
        "summary": summarise(seeds),
    }
    save_result(f"detection-seeds-{card.name}{args.tag}", doc, args.results, keep_same_day=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
