"""The benchmark suite: every model card x {torch reference, torch export, onnxruntime fp32,
onnxruntime int8} on 2 cores, in one run, backends alternating every iteration; plus OpenVINO's
CPU plugin on the same fp32 and int8 graphs when openvino is installed.

Every card is exported and quantised afresh into export/ first, so the run times the current
code. Writes benchmarks/results/suite-<date>.json, the Markdown table in benchmarks/README.md and
a bar chart benchmarks/suite.png (log scale). Run it with ``make bench`` (or
``python benchmarks/run.py --help``).

A card the repository's zoo holds (``zoo/<card>/``: maffnet-vod-edge, tdfanet-edge) is timed
with its trained weights and the card file they were trained with, since NMS and proposals take
work that depends on the scores; every other card with its seeded weights. Each card's entry says
which (``weights``, with the checkpoint's sha256).

Per row: median latency, FPS (1000 / median), GMACs per inference (radaredge.benchmarking.macs: matrix,
convolution, bilinear sampling and scatter work) and the achieved share of the machine's fp32
GEMM peak on the same threads, measured by this script. The int8 speed-up over fp32 is reported
with the share of onnxruntime fp32 time spent in the quantised op types, which bounds the
speed-up int8 can bring.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

import radaredge
from radaredge.artifacts import INT8, copy_path
from radaredge.benchmarking.harness import BenchOptions, pipeline_backends
from radaredge.benchmarking.macs import count_macs, gemm_peak_gflops
from radaredge.benchmarking.profiling import profile_runs, top_ops
from radaredge.benchmarking.timing import (
    benchmark,
    cpu_name,
    int8_dot_product,
    output_differences,
    pin_threads,
    require_ok,
)
from radaredge.cards import load_card
from radaredge.exporting.quantize import QUANTIZED_OPS
from radaredge.models import create_model, model_spec
from radaredge.runtime.openvino import openvino_installed

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling modules, also when loaded by path (tests)
from result_file import result_path, sha256_of, utc_stamp, write_result  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ZOO = ROOT / "zoo"
BACKENDS = ("torch reference", "torch export", "onnxruntime", "onnxruntime int8")
OPENVINO_BACKENDS = ("openvino", "openvino int8")
# The single-graph cards: TDFANet's two, MAFF-Net stage one for both datasets and its edge card, and
# both stages on VoD with each clustering branch (the TJ4D two-stage cards differ from these only in
# grid size).
# des4pos exports three graphs and has its own query/cell benchmark (`radaredge bench --model des4pos`).
SUITE_MODELS = (
    "tdfanet",
    "tdfanet-edge",
    "maffnet-vod",
    "maffnet-vod-edge",
    "maffnet-tj4d",
    "maffnet-vod-full",
    "maffnet-vod-full-dbscan",
)


def export_both(card, model, export_dir: Path) -> tuple[Path, Path]:
    """Export ``card``'s fp32 graph and its int8 copy into ``export_dir`` from the current code:
    a graph left there by an earlier export may come from an older export formulation or
    quantisation setting with the same weights, so the suite never reuses one."""
    fp32 = export_dir / f"{card.name}.onnx"
    int8 = copy_path(fp32, INT8)
    print(f"  exporting {fp32} and quantising {int8}", flush=True)
    radaredge.export(card, fp32, model=model, quantize="int8")
    return fp32, int8


def quantised_time_share(onnx_path: Path, cases: list[dict], threads: int, runs: int = 5) -> float:
    """Share of onnxruntime fp32 kernel time spent in the op types int8 quantises."""
    ops = dict(top_ops(profile_runs(onnx_path, cases, threads, runs), k=1000))
    total = sum(ops.values())
    return sum(v for k, v in ops.items() if k in QUANTIZED_OPS) / total if total else 0.0


def zoo_weights(name: str) -> Path | None:
    """The zoo's trained weights of card ``name`` (zoo/<name>/weights.pth, its card.yaml beside
    them), or None when the zoo does not hold the card."""
    weights = ZOO / name / "weights.pth"
    return weights if weights.is_file() else None


def bench_card(name: str, runs: int, threads: int, peak: float, export_dir: Path, openvino: bool) -> dict:
    weights = zoo_weights(name)
    card = load_card(name if weights is None else weights.with_name("card.yaml"))
    model = create_model(card, weights)
    graph = model_spec(card).graph()
    fp32, int8 = export_both(card, model, export_dir)
    cases = [feeds for _, feeds in graph.make_cases(card, 4, 1)]
    macs = count_macs(graph.run_export, model, {k: torch.from_numpy(v) for k, v in cases[0].items()})
    backends = pipeline_backends(card, graph, model, fp32, BenchOptions(threads=threads), int8, openvino)
    results = require_ok(benchmark(backends, cases, runs, warmup=3))
    rows = []
    for r in results:
        achieved = 2 * macs["total"] / (r.p50_ms / 1e3) / 1e9
        rows.append(
            {**r.__dict__, "gmacs": macs["total"] / 1e9, "achieved_gflops": achieved, "peak_fraction": achieved / peak}
        )
    by = {r["backend"]: r for r in rows}
    out = {
        "model": name,
        "weights": "seeded" if weights is None else str(weights.relative_to(ROOT)),
        **({} if weights is None else {"weights_sha256": sha256_of(weights)}),
        "rows": rows,
        "macs_by_op": {k: v / 1e9 for k, v in macs.items()},
        "ort_vs_reference": by["torch reference"]["p50_ms"] / by["onnxruntime"]["p50_ms"],
        "int8_vs_fp32": by["onnxruntime"]["p50_ms"] / by["onnxruntime int8"]["p50_ms"],
        "quantised_op_time_share": quantised_time_share(fp32, cases, threads),
    }
    if openvino:
        out["openvino_vs_onnxruntime"] = by["onnxruntime"]["p50_ms"] / by["openvino"]["p50_ms"]
        out["openvino_max_abs_diff"] = output_differences(backends["openvino"], backends["onnxruntime"], cases)
    return out


def chart(suite: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = [m["model"] for m in suite["models"]]
    fig, ax = plt.subplots(figsize=(8, 4))
    backends = [
        b
        for b in BACKENDS + OPENVINO_BACKENDS
        if all(any(r["backend"] == b for r in m["rows"]) for m in suite["models"])
    ]
    width = 0.8 / len(backends)
    for i, backend in enumerate(backends):
        fps = [next(r["fps"] for r in m["rows"] if r["backend"] == backend) for m in suite["models"]]
        bars = ax.bar([j + i * width for j in range(len(models))], fps, width, label=backend)
        ax.bar_label(bars, fmt="%.2g", fontsize=7)
    ax.set_xticks([j + width * (len(backends) - 1) / 2 for j in range(len(models))], models)
    ax.set_yscale("log")  # the cards span two orders of magnitude
    ax.set_ylabel("inferences per second (log)")
    ax.set_title(
        f"radaredge on {suite['threads']} cores, {suite['date']}\n"
        "TDFANet: one K-frame window per inference; MAFF-Net: one scan",
        fontsize=10,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _render_readme(results_dir: Path) -> str:
    """benchmarks/render.py's ``render(results_dir)``, loaded by path: this script also runs as an
    imported module (tests), where benchmarks/ is not on sys.path."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("benchmarks_render", Path(__file__).with_name("render.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.render(results_dir)


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
    date = utc_stamp()
    results_dir = args.out / "results"
    results_dir.mkdir(parents=True, exist_ok=True)
    json_path = result_path("suite", date, results_dir)
    openvino = openvino_installed()
    backends = BACKENDS + (OPENVINO_BACKENDS if openvino else ())
    suite = {
        "date": date,
        "cpu": cpu_name(),
        "int8_dot_product": int8_dot_product(),
        "threads": args.threads,
        "cores": cores,
        "runs": args.runs,
        "gemm_peak_gflops": peak,
        "json": str(json_path.relative_to(args.out)),
        "models": [],
    }
    for name in args.models:
        print(f"{name}: benchmarking {', '.join(backends)}", flush=True)
        suite["models"].append(bench_card(name, args.runs, args.threads, peak, args.export_dir, openvino))
    write_result(json_path, suite)
    (args.out / "README.md").write_text(_render_readme(results_dir))
    chart(suite, args.out / "suite.png")
    print(f"wrote {json_path}, {args.out / 'README.md'}, {args.out / 'suite.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
