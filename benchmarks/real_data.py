"""Recorded radar in every card that takes scans: View-of-Delft's ``example_set`` (3 frames) and
TJ4DRadSet's ``Sample`` (41 consecutive frames), as published (docs/data.md says how to fetch them).

For each card, on its dataset's recording (MAFF-Net VoD cards: ``example_set/radar``, one scan a
frame; TJ4D cards: ``Sample``; TDFANet cards: windows of consecutive scans of ``Sample``'s
``training/velodyne``), fed as ``radaredge parity-check --data`` feeds them
(:func:`radaredge.checking.recording.recorded_cases`: the camera-view crop where the card asks):

- **points the card keeps**, on every frame: the share inside ``pillars.point_cloud_range`` and
  the share dropped by a full pillar (:func:`radaredge.checking.capacity.point_counts`);
- **time per frame and peak memory** of the fp32 graph in onnxruntime (2 threads, pinned),
  recorded frames against the synthetic cases ``radaredge bench`` times (4 cases, seed 1),
  interleaved in one run (:func:`radaredge.benchmarking.timing.benchmark`), so the ratio is like for
  like; peak memory is a fresh numpy + onnxruntime process running all the timed frames;
- **GridDensityBEV** (cards with ``cfa.grid``), on every frame: whether the card's
  ``cc_iterations`` max-pool steps reach the exact connected components, the steps each frame
  needs, and how many non-noise cells carry a partial label; and, where some frame does not
  converge, the graph exported with ``cc_mode: exact`` and with ``cc_iterations`` raised to the
  steps the recording needs: time per frame (interleaved with the card's own) and the boxes that
  change (top 20 by score, same class, BEV IoU >= 0.5:
  :func:`radaredge.eval.detection.unmatched_boxes`).

Weights are the cards' seeded initial weights, as in the speed suite: the clustering, the point
shares and the capacity figures do not depend on them; the boxes that change do, so that column
says whether the map the network sees changes, not what it costs a trained detector.

    .venv/bin/python benchmarks/real_data.py --real DIR     # DIR holds the two cloned repositories
    .venv/bin/python benchmarks/render.py                   # the "Recorded radar" section

Run it alone on the machine: the times and peak memory are the point.
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from result_file import save_result, utc_stamp

from radaredge import api
from radaredge.benchmarking.harness import BENCH_CASES, BENCH_SEED
from radaredge.benchmarking.profiling import onnxruntime_peak_rss_mb
from radaredge.benchmarking.timing import benchmark, cpu_name, pin_threads, require_ok
from radaredge.cards import ModelCard, load_card, parse_card
from radaredge.checking.capacity import point_counts
from radaredge.checking.recording import recorded_cases, spread
from radaredge.eval.detection import PICTURE_BOXES, unmatched_boxes
from radaredge.models import create_model, model_spec
from radaredge.ops.components import connected_components, propagate_labels
from radaredge.ops.pillars import PillarConfig
from radaredge.runtime.session import make_session, run_session

VOD, TJ4D = Path("view-of-delft-dataset/example_set"), Path("TJ4DRadSet/Sample")
# card -> its recording, relative to --real
CARDS = {
    "maffnet-vod": VOD / "radar",
    "maffnet-vod-edge": VOD / "radar",
    "maffnet-vod-full": VOD / "radar",
    "maffnet-vod-full-dbscan": VOD / "radar",
    "maffnet-tj4d": TJ4D,
    "maffnet-tj4d-full": TJ4D,
    "maffnet-tj4d-full-dbscan": TJ4D,
    "tdfanet-edge": TJ4D / "training" / "velodyne",
    "tdfanet": TJ4D / "training" / "velodyne",
}
MAX_STEPS = 4096  # max-pool steps tried before a frame's components count as never converging


# ----------------------------------------------------------------------------- measurements


def kept_points(card: ModelCard, frames: list[dict], inputs: list[str]) -> dict:
    """Over every scan fed: points, and the shares inside the range and over a pillar's cap."""
    pillars = card.section("pillars", PillarConfig)
    counts = [point_counts(feeds[name], card, pillars) for feeds in frames for name in inputs]
    points = sum(c["points"] for c in counts)
    outside = sum(c["out_of_range"] + c["implausible"] for c in counts)
    return {
        "scans": len(counts),
        "points_per_scan": points / max(len(counts), 1),
        "in_range_share": 1.0 - outside / max(points, 1),
        "over_pillar_cap_share": sum(c["over_pillar_cap"] for c in counts) / max(points, 1),
    }


def steps_to_converge(keep: torch.Tensor, exact: torch.Tensor) -> int:
    """The fewest max-pool steps after which the labels of ``keep`` [1, H, W] equal the exact
    components ``exact``; MAX_STEPS + 1 when even MAX_STEPS fall short."""
    labels = connected_components(keep, "maxpool", 0)[0].to(torch.float32)
    target = exact.to(torch.float32)
    for steps in range(MAX_STEPS + 1):
        if torch.equal(labels, target):
            return steps
        labels = propagate_labels(labels, keep)
    return MAX_STEPS + 1


def grid_density_study(card: ModelCard, model, frames: list[dict], inputs: list[str]) -> dict:
    """On every frame: does GridDensityBEV's maxpool labelling converge at the card's
    ``cc_iterations``, the steps needed, and the non-noise cells with a partial label."""
    iterations = int(card.get("cfa.grid.cc_iterations"))
    rows = []
    for feeds in frames:
        points = torch.from_numpy(np.asarray(feeds[inputs[0]], np.float32))
        with torch.no_grad():
            _, bev, converged, _ = model.cfa_stage(points, reference=False)
        keep = (bev[1] > 0).unsqueeze(0)  # non-noise cells: density channel > 0
        exact = connected_components(keep, "exact")[0]
        partial = connected_components(keep, "maxpool", iterations)[0]
        rows.append(
            {
                "converged": bool(converged),
                "steps": steps_to_converge(keep, exact),
                "cells": int(keep.sum()),
                "partial_cells": int((partial != exact).sum()),
                "components": int(torch.unique(exact[exact > 0]).numel()),
                "labels": int(torch.unique(partial[partial > 0]).numel()),
            }
        )
    steps = [r["steps"] for r in rows]
    return {
        "cc_mode": card.get("cfa.grid.cc_mode"),
        "cc_iterations": iterations,
        "frames": len(rows),
        "converged": sum(r["converged"] for r in rows),
        "steps_max": max(steps),
        "steps_median": float(np.median(steps)),
        "partial_cell_share": sum(r["partial_cells"] for r in rows) / max(sum(r["cells"] for r in rows), 1),
        "components": sum(r["components"] for r in rows),
        "labels": sum(r["labels"] for r in rows),
        "per_frame": rows,
    }


def variant(card: ModelCard, **grid) -> ModelCard:
    """``card`` with its ``cfa.grid`` fields replaced by ``grid``."""
    data = copy.deepcopy(card.data)
    data["cfa"]["grid"].update(grid)
    return parse_card(data, card.path)


def detections(out: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.asarray(out["boxes"]), np.asarray(out["scores"]), np.asarray(out["labels"])


# ----------------------------------------------------------------------------- one card


def measure_card(name: str, real: Path, timed: int, runs: int, threads: int, work: Path) -> dict:
    card = load_card(name)
    spec = model_spec(card)
    graph = spec.graphs[0]
    model = create_model(card, None, spec)
    path = work / f"{name}.onnx"
    api.export(card, path, model=model)
    inputs = graph.frame_inputs(card)
    everything = recorded_cases(card, graph, real / CARDS[name], frames=10**6)
    frames = [feeds for _, feeds in everything.cases]
    chosen = [frames[i] for i in spread(len(frames), timed)]
    synthetic = [feeds for _, feeds in graph.make_cases(card, BENCH_CASES, BENCH_SEED)]
    out = {
        "card": name,
        "recording": str(CARDS[name]),
        "unit": everything.unit,
        "available": everything.available,
        "timed": len(chosen),
        "notes": everything.notes,
        "points": kept_points(card, frames, inputs),
    }

    session = make_session(path, threads)
    backends = {
        "recording": lambda i: run_session(session, chosen[i % len(chosen)]),
        "synthetic": lambda i: run_session(session, synthetic[i % len(synthetic)]),
    }
    grid = card.get("cfa.grid") is not None and card.get("cfa.method", "grid_density") == "grid_density"
    if grid:
        out["grid_density"] = study = grid_density_study(card, model, frames, inputs)
        graph_converged = [bool(run_session(session, f)["cfa_converged"]) for f in chosen]
        chosen_rows = [study["per_frame"][i] for i in spread(len(frames), timed)]
        if graph_converged != [r["converged"] for r in chosen_rows]:
            raise RuntimeError(f"{name}: the graph's cfa_converged and GridDensityBEV's disagree on the timed frames")
        if study["converged"] < study["frames"]:
            needed = min(study["steps_max"], MAX_STEPS)
            base = [detections(run_session(session, f)) for f in chosen]
            out["variants"] = []
            for label, fields in (
                (f"cc_iterations {needed}", {"cc_iterations": needed}),
                ("cc_mode exact", {"cc_mode": "exact"}),
            ):
                other = variant(card, **fields)
                vpath = work / f"{name}-{len(out['variants'])}.onnx"
                api.export(other, vpath, model=create_model(other, None, spec))
                vsession = make_session(vpath, threads)
                outs = [run_session(vsession, f) for f in chosen]
                backends[label] = (lambda s: lambda i: run_session(s, chosen[i % len(chosen)]))(vsession)
                out["variants"].append(
                    {
                        "name": label,
                        "fields": fields,
                        "converged": sum(bool(o["cfa_converged"]) for o in outs),
                        "boxes": sum(len(b[0]) for b in base),
                        "boxes_compared": sum(min(len(b[0]), PICTURE_BOXES) for b in base),
                        "boxes_changed": sum(unmatched_boxes(b, detections(o)) for b, o in zip(base, outs)),
                    }
                )
    rows = require_ok(benchmark(backends, list(range(len(chosen) * len(synthetic))), runs, warmup=2))
    out["p50_ms"] = {r.backend: r.p50_ms for r in rows}
    out["peak_rss_mib"] = {
        "recording": onnxruntime_peak_rss_mb(path, chosen, threads),
        "synthetic": onnxruntime_peak_rss_mb(path, synthetic, threads),
    }
    print(
        f"{name}: recording {out['p50_ms']['recording']:.0f} ms, synthetic {out['p50_ms']['synthetic']:.0f} ms; "
        f"peak {out['peak_rss_mib']['recording']:.0f} / {out['peak_rss_mib']['synthetic']:.0f} MiB; "
        f"in range {100 * out['points']['in_range_share']:.0f} %",
        flush=True,
    )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--real", type=Path, required=True, help="directory holding the cloned view-of-delft-dataset and TJ4DRadSet"
    )
    ap.add_argument("--cards", nargs="+", default=list(CARDS), choices=list(CARDS))
    ap.add_argument("--frames", type=int, default=8, help="frames (windows) timed per card, spread evenly")
    ap.add_argument("--runs", type=int, default=16, help="timed runs per backend")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    for rel in (VOD, TJ4D):
        if not (args.real / rel).is_dir():
            ap.error(f"--real {args.real}: {rel} is missing (docs/data.md: the published samples)")
    cores = pin_threads(args.threads)
    torch.set_num_threads(args.threads)
    result = {
        "date": utc_stamp(),
        "cpu": cpu_name(),
        "threads": args.threads,
        "cores": cores,
        "runs": args.runs,
        "command": f"python benchmarks/real_data.py --real DIR --cards {' '.join(args.cards)} "
        f"--frames {args.frames} --runs {args.runs} --threads {args.threads}",
        "weights": "the cards' seeded initial weights",
        "cards": [],
    }
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cards:
            result["cards"].append(measure_card(name, args.real, args.frames, args.runs, args.threads, Path(tmp)))
    save_result("real-data", result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
