"""The 2-core benchmark harness: torch reference, torch export formulation and onnxruntime,
timed in one run, alternating backends every iteration so machine drift hits all alike.

Numbers: warm-up runs are discarded; latency percentiles (ms) over the timed runs; FPS is
1000 / median latency. Threads are fixed (torch.set_num_threads, onnxruntime intra-op threads)
and the process is pinned to ``threads`` cores where the OS allows it. Each timed run starts
after a short idle pause (:data:`SETTLE_S`), so no backend is timed while the previous one's
worker threads still spin.
"""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch


@dataclass
class BackendResult:
    backend: str
    runs: int
    p50_ms: float
    p90_ms: float
    p99_ms: float
    mean_ms: float
    fps: float


def pin_threads(threads: int) -> list[int] | None:
    """Pin this process to the first ``threads`` allowed cores and set torch's thread count."""
    torch.set_num_threads(threads)
    try:
        cores = sorted(os.sched_getaffinity(0))[:threads]
        os.sched_setaffinity(0, cores)
        return cores
    except (AttributeError, OSError):
        return None


def cpu_name() -> str:
    """The CPU model string (Linux /proc/cpuinfo, else platform)."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def summarise(name: str, times_s: list[float]) -> BackendResult:
    ms = np.asarray(times_s) * 1e3
    p50 = float(np.percentile(ms, 50))
    return BackendResult(name, len(ms), p50, float(np.percentile(ms, 90)), float(np.percentile(ms, 99)),
                         float(ms.mean()), 1e3 / p50)


# Idle time before each timed run, s. torch's OpenMP workers (GNU libgomp, OMP_WAIT_POLICY unset)
# busy-wait after every parallel region and took CPU from whatever ran next on 2 cores:
# tdfanet-edge (then C = 16) in onnxruntime took 43.3 ms right after the torch reference,
# 38.0 ms alone and 38.2 ms after a 50 ms pause (2026-11-24, medians of 12).
SETTLE_S = 0.05


def benchmark(backends: dict, cases: list[dict], runs: int, warmup: int = 3, progress=None) -> list[BackendResult]:
    """Time each callable in ``backends`` (name -> fn(feeds)) on ``cases``, interleaved per run,
    each timed call after :data:`SETTLE_S` seconds of idle."""
    for fn in backends.values():
        for i in range(warmup):
            fn(cases[i % len(cases)])
    times: dict[str, list[float]] = {n: [] for n in backends}
    order = list(backends)
    it = range(runs)
    for i in (progress(it) if progress else it):
        feeds = cases[i % len(cases)]
        for name in order[i % len(order):] + order[: i % len(order)]:   # rotate who goes first
            time.sleep(SETTLE_S)
            t0 = time.perf_counter()
            backends[name](feeds)
            times[name].append(time.perf_counter() - t0)
    return [summarise(n, times[n]) for n in backends]


def model_backends(card, model, onnx_path, threads: int, include_reference: bool = True, int8_path=None,
                   openvino: bool = False) -> dict:
    """name -> callable(feeds) for the torch reference, torch export formulation, onnxruntime fp32
    and, when ``int8_path`` is given, onnxruntime on the int8 graph; with ``openvino``, the same
    graph(s) in OpenVINO's CPU plugin too ("openvino", "openvino int8"). The sessions are never
    profiled: onnxruntime's profiler costs time in every node (tdfanet-edge: 1.15x the latency),
    so profiles come from a session of their own (:func:`profile_runs`)."""
    from .registry import model_spec
    from .runners import graph_runner

    spec = model_spec(card)

    def torch_export(feeds):
        with torch.no_grad():
            spec.run_export(model, {k: torch.from_numpy(v) for k, v in feeds.items()}, None)

    def torch_reference(feeds):
        with torch.no_grad():
            spec.run_reference(model, feeds)

    backends = {}
    if include_reference:
        backends["torch reference"] = torch_reference
    backends["torch export"] = torch_export
    backends["onnxruntime"] = graph_runner(onnx_path, "onnxruntime", threads)
    if int8_path is not None:
        backends["onnxruntime int8"] = graph_runner(int8_path, "onnxruntime", threads)
    if openvino:
        backends["openvino"] = graph_runner(onnx_path, "openvino", threads)
        if int8_path is not None:
            backends["openvino int8"] = graph_runner(int8_path, "openvino", threads)
    return backends


def output_differences(run_a, run_b, cases: list[dict]) -> dict[str, float]:
    """Largest absolute difference per output between two runners of one graph over ``cases``
    (outputs whose shapes differ count as inf): what a second runtime changes in the results."""
    worst: dict[str, float] = {}
    for feeds in cases:
        a, b = run_a(feeds), run_b(feeds)
        for name, x in a.items():
            y = np.asarray(b[name])
            d = (float(np.max(np.abs(x.astype(np.float64) - y.astype(np.float64)))) if x.size else 0.0) \
                if x.shape == y.shape else float("inf")
            worst[name] = max(worst.get(name, 0.0), d)
    return worst


def format_differences(diffs: dict[str, float]) -> str:
    """``output diff, ...`` for :func:`output_differences`' result."""
    return ", ".join(f"{k} {v:.2g}" if v != float("inf") else f"{k} (other shape)" for k, v in diffs.items())


def profile_runs(onnx_path, cases: list[dict], threads: int, runs: int) -> list[dict]:
    """Run ``onnx_path`` ``runs`` times over ``cases`` in a profiled onnxruntime session of its
    own; return onnxruntime's profile events. The JSON file onnxruntime writes them to (20-30 MB
    for a MAFF-Net bench) is read and deleted, so repeated benches do not fill the temp directory."""
    from .ort import make_session, run_session

    session = make_session(onnx_path, threads=threads, profile=True)
    for i in range(runs):
        run_session(session, cases[i % len(cases)])
    path = Path(session.end_profiling())
    try:
        return json.loads(path.read_text())
    finally:
        path.unlink(missing_ok=True)


def results_table(results: list[BackendResult], baseline: str = "torch reference") -> str:
    """A Markdown table with a speed-up column relative to ``baseline``."""
    base = next((r for r in results if r.backend == baseline), results[0])
    lines = ["| backend | p50 ms | p90 ms | p99 ms | FPS | x vs " + base.backend + " |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {r.backend} | {r.p50_ms:.1f} | {r.p90_ms:.1f} | {r.p99_ms:.1f} | {r.fps:.2f} | "
                     f"{base.p50_ms / r.p50_ms:.2f} |")
    return "\n".join(lines)


_RSS_CHILD = """
import resource, sys
import numpy as np
from radaredge.ort import make_session, run_session
session = make_session(sys.argv[1], threads=int(sys.argv[3]))
cases = np.load(sys.argv[2])
names = sorted({k.split("/", 1)[1] for k in cases.files})
count = len({k.split("/", 1)[0] for k in cases.files})
for i in range(count):
    run_session(session, {n: cases[f"{i}/{n}"] for n in names})
try:      # this process's own high-water mark; ru_maxrss can carry the parent's size across fork + exec
    print(next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:")))
except OSError:
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def onnxruntime_peak_rss_mb(onnx_path, cases: list[dict], threads: int) -> float:
    """Peak resident memory (MiB) of a fresh process that only loads ``onnx_path`` in onnxruntime
    (numpy + onnxruntime, no torch) and runs every case once: what an embedded app would need."""
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "cases.npz"
        np.savez(npz, **{f"{i}/{k}": v for i, feeds in enumerate(cases) for k, v in feeds.items()})
        done = subprocess.run([sys.executable, "-c", _RSS_CHILD, str(onnx_path), str(npz), str(threads)],
                              capture_output=True, text=True, check=True)
    return int(done.stdout.split()[-1]) / 1024.0          # VmHWM and Linux ru_maxrss are in KiB


def top_ops(events: list[dict], k: int = 10, runs: int = 1) -> list[tuple[str, float]]:
    """Top ``k`` op types by kernel time from the onnxruntime profile events of ``runs`` runs
    (:func:`profile_runs`), in ms per run."""
    tot: dict[str, float] = {}
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            op = e.get("args", {}).get("op_name", "?")
            tot[op] = tot.get(op, 0.0) + e.get("dur", 0) / 1e3 / runs
    return sorted(tot.items(), key=lambda kv: -kv[1])[:k]


def as_dicts(results: list[BackendResult]) -> list[dict]:
    return [asdict(r) for r in results]


def write_results_json(model: str, payload: dict) -> Path:
    """Write ``payload`` to benchmarks/results/<model>-<date>.json (cwd-relative); return the path."""
    import datetime
    out = Path("benchmarks/results")
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{model}-{datetime.date.today().isoformat()}.json"
    path.write_text(json.dumps(payload, indent=2))
    return path
