"""MAFF-Net training step: seconds per training scan, by pillar formulation, memory layout and precision.

One optimiser step of ``radaredge train`` (``--batch-size`` scans, each through the network and
its losses, one backward per scan, gradient clipping, AdamW) timed for:
- the pillar stage's export formulation on contiguous (NCHW) tensors: what training ran before
  the training formulation existed;
- the training formulation (radaredge.models.maffnet.model.MAFFNet.pillar_stage_training: the
  non-empty pillars only, the same values and gradients);
- the training formulation with channels-last weights and maps, as ``radaredge train`` runs now;
each in fp32 and under bf16 autocast (``--set precision=bf16``). Variants take turns step by
step, so a slow spell of a shared machine hits them alike; the table gives medians per scan.
The card's seeded weights (a training step's cost does not depend on the scores: stage one has
no NMS in training), the first training scans of ``--data``, augmented as in training.

    .venv/bin/python benchmarks/maffnet_train_step.py --data SET     # prints a table, writes JSON
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from result_file import RESULTS, save_result, utc_stamp

from radaredge.benchmarking.timing import cpu_name, pin_threads
from radaredge.cards import load_card
from radaredge.models import create_model
from radaredge.training import maffnet as tm

FORMULATIONS = {  # name -> (export pillars, memory format)
    "export pillars, NCHW": (True, torch.contiguous_format),
    "training pillars, NCHW": (False, torch.contiguous_format),
    "training pillars, channels last": (False, torch.channels_last),
}


def _variant(card, precision: str, export_pillars: bool, memory_format, lr: float):
    """(model, optimiser, loss setup) of one variant: the card's seeded network in train mode."""
    model = create_model(card).to(memory_format=memory_format)
    tm.set_train_mode(model, set())
    setup = tm.LossSetup(
        tm.anchor_classes(card, len(model.anchors)),
        tm.class_thresholds(card),
        None,
        tm.PRECISIONS[precision],
        export_pillars,
    )
    return model, torch.optim.AdamW(model.parameters(), lr=lr, betas=(0.95, 0.99), weight_decay=0.01), setup


def _step(model, opt, setup, batch: list[tuple]) -> float:
    """Seconds of one optimiser step over ``batch`` [(points, boxes, classes)], as radaredge train runs it."""
    start = time.perf_counter()
    opt.zero_grad()
    with tm.batch_norm_statistics(model, [points for points, _, _ in batch]):
        for points, boxes, classes in batch:
            (tm.scan_terms(model, points, boxes, classes, setup)["loss"] / len(batch)).backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
    opt.step()
    return time.perf_counter() - start


def run(card_name: str, data: Path, steps: int, warmup: int, batch_size: int, threads: int) -> dict:
    """Time every (precision, formulation) for ``steps`` steps of ``batch_size`` scans after
    ``warmup``, the variants interleaved step by step. Returns the JSON document: the host and
    one row per variant with the median and 90th percentile seconds per scan and the speed-up
    over the export formulation on NCHW in the same precision."""
    cores = pin_threads(threads)
    card = load_card(card_name)
    recipe = tm.DetectionRecipe()
    scans = tm.load_split(card, data, tm.TRAIN_SPLIT, None, batch_size * (steps + warmup))
    rng = np.random.default_rng(0)
    xyz = [card.features.index(c) for c in ("x", "y", "z")]
    pc_range = card.get("pillars.point_cloud_range")
    batches = []
    for first in range(0, len(scans), batch_size):
        batch = []
        for scan in scans[first : first + batch_size]:
            points, boxes = tm.augment(scan.points, scan.boxes, xyz, recipe, rng)
            keep = tm.boxes_in_range(boxes, pc_range)
            batch.append(
                (torch.from_numpy(points), torch.from_numpy(boxes[keep]), torch.from_numpy(scan.classes[keep]))
            )
        batches.append(batch)
    variants = {
        (p, name): _variant(card, p, *spec, recipe.lr / recipe.div_factor)
        for p in tm.PRECISIONS
        for name, spec in FORMULATIONS.items()
    }
    seconds: dict[tuple, list[float]] = {key: [] for key in variants}
    for k, batch in enumerate(batches):
        for key, (model, opt, setup) in variants.items():
            t = _step(model, opt, setup, batch)
            if k >= warmup:
                seconds[key].append(t / len(batch))
    rows = []
    for (precision, name), times in seconds.items():
        rows.append(
            {
                "precision": precision,
                "formulation": name,
                "median_s": statistics.median(times),
                "p90_s": float(np.percentile(times, 90)),
                "steps": len(times),
            }
        )
    base = {r["precision"]: r["median_s"] for r in rows if r["formulation"] == next(iter(FORMULATIONS))}
    for r in rows:
        r["speedup"] = base[r["precision"]] / r["median_s"]
    return {
        "card": card_name,
        "threads": threads,
        "cores": cores,
        "cpu": cpu_name(),
        "date": utc_stamp(),
        "batch_size": batch_size,
        "steps": steps,
        "warmup": warmup,
        "weights": f"seeded (card seed {card.get('seed', 0)})",
        "rows": rows,
    }


def table(result: dict) -> str:
    """The rows of :func:`run`'s result as a Markdown table."""
    lines = ["| precision | formulation | s per scan (median) | p90 | x |", "|---|---|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(
            f"| {r['precision']} | {r['formulation']} | {r['median_s']:.3f} | {r['p90_s']:.3f} | {r['speedup']:.2f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--data", type=Path, required=True, help="a labelled set (radaredge make-benchmark --task detection)"
    )
    ap.add_argument("--card", default="maffnet-vod")
    ap.add_argument("--steps", type=int, default=5, help="timed optimiser steps per variant")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--batch-size", type=int, default=4, help="scans per step (upstream's 4)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder of the JSON result")
    args = ap.parse_args(argv)
    result = run(args.card, args.data, args.steps, args.warmup, args.batch_size, args.threads)
    print(
        f"{args.card}: training step on {args.threads} thread(s), cores {result['cores']}, {result['cpu']}, "
        f"{args.steps} steps of {args.batch_size} scans, {result['date']}"
    )
    print(table(result))
    args.out.mkdir(parents=True, exist_ok=True)
    save_result("maffnet-train-step", result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
