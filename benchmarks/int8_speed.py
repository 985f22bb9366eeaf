"""Where int8 wins or loses its speed: each zoo card's fp32 graph and its int8 copy timed side by
side (onnxruntime, and OpenVINO when installed) on the zoo's trained weights, with onnxruntime's
profile of both: kernel ms per op type and the heaviest nodes.

For every card named (default: every card in ``zoo/``) this exports the fp32 graph with the zoo's
weights and its int8 copy (``radaredge export --quantize int8``: the card's calibration method,
keep_fp32 and reduce_range), then runs ``radaredge bench --int8 --profile`` on them: the backends
alternate every run on the same pinned cores, so the int8/fp32 ratio is one run's. Writes
``benchmarks/results/int8-speed[-<first int8 dot-product set>]-<date>.json``; benchmarks/render.py
renders it in docs/quantization.md.

    python benchmarks/int8_speed.py [--card maffnet-vod-edge] [--runs 30]
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
import tempfile
from pathlib import Path

import training_run
from result_file import save_result, sha256_of, utc_stamp

import radaredge
from radaredge import runtime
from radaredge.artifacts import INT8, copy_path
from radaredge.cards import load_card

ZOO = training_run.ROOT / "zoo"
TOP_NODES = 3


def card_speed(name: str, runs: int) -> dict:
    """One zoo card: its fp32 and int8 rows (median ms), the int8/fp32 ratio and the profiles."""
    entry = ZOO / name
    card, weights = load_card(entry / "card.yaml"), entry / "weights.pth"
    with tempfile.TemporaryDirectory(prefix="radaredge-int8-speed-") as tmp:
        fp32 = Path(tmp) / f"{card.name}.onnx"
        radaredge.export(card, fp32, checkpoint=weights, quantize="int8")
        report = radaredge.bench(card, fp32, checkpoint=weights, runs=runs, reference=False, profile=True)
        int8_metadata = runtime.load(copy_path(fp32, INT8), threads=1).info.quantization
    task = next(iter(report.tasks.values()))
    graph = next(iter(report.graphs.values()))
    rows = {r.backend: round(r.p50_ms, 2) for r in task.rows if r}
    return {
        "checkpoint": str(weights),
        "checkpoint_sha256": sha256_of(weights),
        "median_ms": rows,
        "int8_vs_fp32": task.int8_vs_fp32,
        "openvino_int8_vs_fp32": (
            rows["openvino"] / rows["openvino int8"] if {"openvino", "openvino int8"} <= set(rows) else None
        ),
        "quantization": int8_metadata,
        "profiled_runs": graph.profiled_runs,
        "fp32_ops_ms": dict(graph.top_ops),
        "int8_ops_ms": dict(graph.int8_top_ops),
        "fp32_heaviest_nodes": [list(n) for n in graph.top_nodes[:TOP_NODES]],
        "int8_heaviest_nodes": [list(n) for n in graph.int8_top_nodes[:TOP_NODES]],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/int8_speed.py", description=__doc__.splitlines()[0])
    ap.add_argument("--card", action="append", help="a zoo card (repeat; default every card in zoo/)")
    ap.add_argument("--runs", type=int, default=30, help="timed runs per backend (default 30)")
    ap.add_argument("--results", type=Path, default=training_run.ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    names = args.card or sorted(p.name for p in ZOO.iterdir() if (p / "weights.pth").is_file())
    missing = [n for n in names if not (ZOO / n / "weights.pth").is_file()]
    if missing:
        raise SystemExit(f"no zoo entry (zoo/<card>/weights.pth) for {missing}")
    cards = {}
    for name in names:
        print(f"{name}: exporting, quantising and timing ...", flush=True)
        cards[name] = card_speed(name, args.runs)
    doc = {
        "date": utc_stamp(),
        "command": " ".join(
            ["python benchmarks/int8_speed.py", shlex.join(sys.argv[1:] if argv is None else argv)]
        ).strip(),
        "machine": training_run.machine(),
        "runs": args.runs,
        "cards": cards,
    }
    isa = doc["machine"]["int8_dot_product"]
    if isa is None:  # no /proc/cpuinfo to tell: a study of its own
        suffix = "-unknown-cpu"
    else:
        suffix = f"-{re.sub('[^a-z0-9]+', '-', isa[0].lower())}" if isa else ""
    save_result(f"int8-speed{suffix}", doc, args.results, keep_same_day=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
