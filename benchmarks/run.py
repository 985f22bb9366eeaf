"""The benchmark suite: every model card x {torch reference, torch export, onnxruntime fp32,
onnxruntime int8} on 2 cores, in one run, backends alternating every iteration; plus OpenVINO's
CPU plugin on the same fp32 and int8 graphs when openvino is installed.

Every card is exported and quantised afresh into export/ first, so the run times the current
code. Writes benchmarks/results/suite-<date>.json, the Markdown table in benchmarks/README.md and
a bar chart benchmarks/suite.png (log scale). Run it with ``make bench`` (or
``python benchmarks/run.py --help``).

Per row: median latency, FPS (1000 / median), GMACs per inference (radaredge.macs: matrix,
convolution, bilinear sampling and scatter work) and the achieved share of the machine's fp32
GEMM peak on the same threads, measured by this script. The int8 speed-up over fp32 is reported
with the share of onnxruntime fp32 time spent in the quantised op types, which bounds the
speed-up int8 can bring.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from pathlib import Path

import torch

from radaredge.bench import (benchmark, cpu_name, format_differences, model_backends, output_differences,
                             pin_threads, profile_runs, top_ops)
from radaredge.cards import load_card
from radaredge.export import build_model, export_model
from radaredge.macs import count_macs, gemm_peak_gflops
from radaredge.openvino_runtime import openvino_installed
from radaredge.quantize import QUANTIZED_OPS, quantize_int8
from radaredge.registry import model_spec

ROOT = Path(__file__).resolve().parent.parent
BACKENDS = ("torch reference", "torch export", "onnxruntime", "onnxruntime int8")
OPENVINO_BACKENDS = ("openvino", "openvino int8")
# The single-graph cards: TDFANet's two, MAFF-Net stage one for both datasets, and both stages on
# VoD with each clustering branch (the TJ4D two-stage cards differ from these only in grid size).
# des4pos is a three-graph bundle with its own query/cell benchmark (`radaredge bench --model des4pos`).
SUITE_MODELS = ("tdfanet", "tdfanet-edge", "maffnet-vod", "maffnet-tj4d", "maffnet-vod-full", "maffnet-vod-full-dbscan")


def export_both(card, model, export_dir: Path) -> tuple[Path, Path]:
    """Export ``card``'s fp32 graph and its int8 copy into ``export_dir`` from the current code:
    a graph left there by an earlier export may come from an older export formulation or
    quantisation setting with the same weights, so the suite never reuses one."""
    fp32 = export_dir / f"{card.name}.onnx"
    int8 = export_dir / f"{card.name}.int8.onnx"
    print(f"  exporting {fp32} and quantising {int8}", flush=True)
    export_model(card, fp32, model=model)
    quantize_int8(card, fp32, int8)
    return fp32, int8


def quantised_time_share(onnx_path: Path, cases: list[dict], threads: int, runs: int = 5) -> float:
    """Share of onnxruntime fp32 kernel time spent in the op types int8 quantises."""
    ops = dict(top_ops(profile_runs(onnx_path, cases, threads, runs), k=1000))
    total = sum(ops.values())
    return sum(v for k, v in ops.items() if k in QUANTIZED_OPS) / total if total else 0.0


def bench_card(name: str, runs: int, threads: int, peak: float, export_dir: Path, openvino: bool) -> dict:
    card = load_card(name)
    model = build_model(card)
    spec = model_spec(card)
    fp32, int8 = export_both(card, model, export_dir)
    cases = [feeds for _, feeds in spec.make_cases(card, 4, 1)]
    macs = count_macs(spec.run_export, model, {k: torch.from_numpy(v) for k, v in cases[0].items()})
    backends = model_backends(card, model, fp32, threads, True, int8_path=int8, openvino=openvino)
    results = benchmark(backends, cases, runs, warmup=3)
    rows = []
    for r in results:
        achieved = 2 * macs["total"] / (r.p50_ms / 1e3) / 1e9
        rows.append({**r.__dict__, "gmacs": macs["total"] / 1e9, "achieved_gflops": achieved,
                     "peak_fraction": achieved / peak})
    by = {r["backend"]: r for r in rows}
    out = {
        "model": name, "rows": rows, "macs_by_op": {k: v / 1e9 for k, v in macs.items()},
        "ort_vs_reference": by["torch reference"]["p50_ms"] / by["onnxruntime"]["p50_ms"],
        "int8_vs_fp32": by["onnxruntime"]["p50_ms"] / by["onnxruntime int8"]["p50_ms"],
        "quantised_op_time_share": quantised_time_share(fp32, cases, threads),
    }
    if openvino:
        out["openvino_vs_onnxruntime"] = by["onnxruntime"]["p50_ms"] / by["openvino"]["p50_ms"]
        out["openvino_max_abs_diff"] = output_differences(backends["openvino"], backends["onnxruntime"], cases)
    return out


def markdown(suite: dict) -> str:
    lines = [
        "# Benchmarks",
        "",
        f"Written by `make bench` (`python benchmarks/run.py`) on {suite['date']}: {suite['cpu']}, "
        f"{suite['threads']} threads pinned to cores {suite['cores']}, {suite['runs']} timed runs per backend after "
        f"3 warm-ups, backends alternating every run. Measured fp32 GEMM peak on these threads (best of 20 "
        f"1024 x 1024 products): "
        f"{suite['gemm_peak_gflops']:.1f} GFLOP/s. JSON: `{suite['json']}`; chart: `suite.png`.",
        "",
        "| model | backend | p50 ms | p90 ms | FPS | GMACs | % of fp32 GEMM peak |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for m in suite["models"]:
        for r in m["rows"]:
            lines.append(f"| {m['model']} | {r['backend']} | {r['p50_ms']:.1f} | {r['p90_ms']:.1f} | {r['fps']:.2f} | "
                         f"{r['gmacs']:.2f} | {100 * r['peak_fraction']:.1f} |")
    lines += ["", "| model | onnxruntime fp32 vs torch reference | int8 vs fp32 | fp32 time in quantised ops |",
              "|---|---:|---:|---:|"]
    for m in suite["models"]:
        lines.append(f"| {m['model']} | {m['ort_vs_reference']:.2f}x | {m['int8_vs_fp32']:.2f}x | "
                     f"{100 * m['quantised_op_time_share']:.0f} % |")
    with_openvino = [m for m in suite["models"] if "openvino_vs_onnxruntime" in m]
    if with_openvino:
        lines += ["", "| model | OpenVINO fp32 vs onnxruntime fp32 | largest output difference from onnxruntime |",
                  "|---|---:|---|"]
        for m in with_openvino:
            lines.append(f"| {m['model']} | {m['openvino_vs_onnxruntime']:.2f}x | "
                         f"{format_differences(m['openvino_max_abs_diff'])} |")
    lines += ["", "GMACs count matrix products and convolutions, plus bilinear sampling (4 MACs per sample "
              "and channel) and scatter updates (1 per element), which common counters report as zero; "
              "pointwise ops are not counted. The int8 row's share of the fp32 peak can exceed 100 %: "
              "int8 arithmetic is not bound by it. int8 quantises only " + ", ".join(QUANTIZED_OPS) +
              " (static QDQ, uint8 activations, per-channel int8 weights on 7 bits unless a card sets "
              "quantization.reduce_range: false). By Amdahl's law its speed-up cannot exceed "
              "1 / (1 - share + share / s) for a kernel speed-up s, so a low share of fp32 time in those ops "
              "explains a small int8 gain.", ""]
    return "\n".join(lines)


def chart(suite: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = [m["model"] for m in suite["models"]]
    fig, ax = plt.subplots(figsize=(8, 4))
    backends = [b for b in BACKENDS + OPENVINO_BACKENDS if all(any(r["backend"] == b for r in m["rows"])
                                                               for m in suite["models"])]
    width = 0.8 / len(backends)
    for i, backend in enumerate(backends):
        fps = [next(r["fps"] for r in m["rows"] if r["backend"] == backend) for m in suite["models"]]
        bars = ax.bar([j + i * width for j in range(len(models))], fps, width, label=backend)
        ax.bar_label(bars, fmt="%.2g", fontsize=7)
    ax.set_xticks([j + width * (len(backends) - 1) / 2 for j in range(len(models))], models)
    ax.set_yscale("log")                     # the cards span two orders of magnitude
    ax.set_ylabel("inferences per second (log)")
    ax.set_title(f"radaredge on {suite['threads']} cores, {suite['date']}\n"
                 "TDFANet: one K-frame window per inference; MAFF-Net: one scan", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=list(SUITE_MODELS))
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--export-dir", type=Path, default=ROOT / "export")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks")
    args = ap.parse_args(argv)
    if args.runs < 20:
        print("note: fewer than 20 timed runs; medians will be noisy", file=sys.stderr)
    cores = pin_threads(args.threads)
    peak = gemm_peak_gflops(args.threads)
    date = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    results_dir = args.out / "results"
    results_dir.mkdir(parents=True, exist_ok=True)
    json_path = results_dir / f"suite-{date[:10]}.json"
    openvino = openvino_installed()
    backends = BACKENDS + (OPENVINO_BACKENDS if openvino else ())
    suite = {"date": date, "cpu": cpu_name(), "threads": args.threads, "cores": cores, "runs": args.runs,
             "gemm_peak_gflops": peak, "json": str(json_path.relative_to(args.out)), "models": []}
    for name in args.models:
        print(f"{name}: benchmarking {', '.join(backends)}", flush=True)
        suite["models"].append(bench_card(name, args.runs, args.threads, peak, args.export_dir, openvino))
    json_path.write_text(json.dumps(suite, indent=2))
    (args.out / "README.md").write_text(markdown(suite))
    chart(suite, args.out / "suite.png")
    print(markdown(suite))
    print(f"wrote {json_path}, {args.out / 'README.md'}, {args.out / 'suite.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
