"""The benchmark harness: backends (torch reference, torch export formulation, onnxruntime, ...)
timed in one run, alternating every iteration so machine drift hits all alike.

Numbers: warm-up runs are discarded; latency percentiles (ms) over the timed runs; FPS is
1000 / median latency. Threads are fixed (torch.set_num_threads, onnxruntime intra-op threads)
and the process is pinned to ``threads`` cores where the OS allows it. Each timed run starts
after a short idle pause (:data:`SETTLE_S`), so no backend is timed while the previous one's
worker threads still spin.
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..runtime.backends import cpu_model


@dataclass
class BackendResult:
    """One backend's row: latency percentiles over the timed runs (ms) and FPS (1000 / p50), or
    ``status`` ``error`` with the reason when the backend failed (its times are then None)."""

    backend: str
    runs: int
    p50_ms: float | None
    p90_ms: float | None
    p99_ms: float | None
    mean_ms: float | None
    fps: float | None
    status: str = "ok"
    error: str = ""

    def __bool__(self) -> bool:
        return self.status == "ok"


def pin_threads(threads: int) -> list[int] | None:
    """Pin this process to the first ``threads`` allowed cores and set torch's thread count
    (when torch is installed)."""
    try:
        # optional: torch's thread count is pinned too when torch is installed (the harness
        # also times torch-free backends)
        import torch

        torch.set_num_threads(threads)
    except ImportError:
        pass
    try:
        cores = sorted(os.sched_getaffinity(0))[:threads]
        os.sched_setaffinity(0, cores)
        return cores
    except (AttributeError, OSError):
        return None


@contextlib.contextmanager
def pinned(threads: int):
    """:func:`pin_threads` for the duration of a ``with`` block (yields the cores); the process's
    CPU affinity and torch's thread count are restored afterwards."""
    try:
        affinity = os.sched_getaffinity(0)
    except (AttributeError, OSError):
        affinity = None
    try:
        # optional: torch's thread count is pinned too when torch is installed (the harness
        # also times torch-free backends)
        import torch

        torch_threads = torch.get_num_threads()
    except ImportError:
        torch = None
    try:
        yield pin_threads(threads)
    finally:
        if affinity is not None:
            os.sched_setaffinity(0, affinity)
        if torch is not None:
            torch.set_num_threads(torch_threads)


def cpu_name() -> str:
    """The CPU model string (Linux /proc/cpuinfo, else platform)."""
    return cpu_model()


# /proc/cpuinfo flags (x86 "flags", Arm "Features") of int8 dot-product instructions, by name: where
# one is present onnxruntime's int8 kernels multiply four uint8 x int8 pairs per lane in one
# instruction; without, they widen through 16-bit products and int8 gains little over fp32.
INT8_DOT_PRODUCT_FLAGS = {
    "avx512_vnni": "AVX-512 VNNI",
    "avx_vnni": "AVX-VNNI",
    "amx_int8": "AMX-INT8",
    "asimddp": "Arm dot product",
}


def int8_dot_product(cpuinfo: str | None = None) -> list[str] | None:
    """The int8 dot-product instruction sets the CPU offers (names of
    :data:`INT8_DOT_PRODUCT_FLAGS`, in its order), read from ``cpuinfo`` (the text of Linux's
    /proc/cpuinfo; read from there when None): empty when it offers none, None when there is no
    /proc/cpuinfo to tell (not Linux)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return None
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            flags.update(value.split())
    return [name for flag, name in INT8_DOT_PRODUCT_FLAGS.items() if flag in flags]


def int8_dot_product_text(names: list[str] | None) -> str:
    """``names`` of :func:`int8_dot_product` as a report says them."""
    if names is None:
        return "int8 dot-product instructions not known"
    return f"int8 dot product: {', '.join(names)}" if names else "no int8 dot-product instructions"


def summarise(name: str, times_s: list[float]) -> BackendResult:
    """Percentiles of one backend's run times (s) as a row."""
    ms = np.asarray(times_s) * 1e3
    p50 = float(np.percentile(ms, 50))
    return BackendResult(
        name, len(ms), p50, float(np.percentile(ms, 90)), float(np.percentile(ms, 99)), float(ms.mean()), 1e3 / p50
    )


# Idle time before each timed run, s. torch's OpenMP workers (GNU libgomp, OMP_WAIT_POLICY unset)
# busy-wait after every parallel region and take CPU from whatever runs next on 2 cores, which
# slowed the onnxruntime run right after a torch run; 50 ms of idle removes that.
SETTLE_S = 0.05


def benchmark(backends: dict, cases: list, runs: int, warmup: int = 3, progress=None) -> list[BackendResult]:
    """Time each callable in ``backends`` (name -> fn(case)) on ``cases``, interleaved per run,
    each timed call after :data:`SETTLE_S` seconds of idle. A backend that raises is a row with
    status ``error`` and the reason; the others are timed on."""
    failed: dict[str, str] = {}

    def attempt(name, case) -> bool:
        try:
            backends[name](case)
            return True
        except Exception as exc:  # a backend's own failure: reported in its row, the bench goes on
            failed[name] = f"{type(exc).__name__}: {exc}".splitlines()[0]
            return False

    for name in backends:
        for i in range(warmup):
            if not attempt(name, cases[i % len(cases)]):
                break
    times: dict[str, list[float]] = {n: [] for n in backends}
    order = list(backends)
    it = range(runs)
    for i in progress(it) if progress else it:
        case = cases[i % len(cases)]
        for name in order[i % len(order) :] + order[: i % len(order)]:  # rotate who goes first
            if name in failed:
                continue
            time.sleep(SETTLE_S)
            t0 = time.perf_counter()
            if attempt(name, case):
                times[name].append(time.perf_counter() - t0)
    return [
        BackendResult(n, len(times[n]), None, None, None, None, None, "error", failed[n])
        if n in failed
        else summarise(n, times[n])
        for n in backends
    ]


def require_ok(rows: list[BackendResult]) -> list[BackendResult]:
    """``rows`` when every backend ran; RuntimeError naming the first that failed and why (for
    scripts whose tables need every row)."""
    for r in rows:
        if not r:
            raise RuntimeError(f"backend {r.backend!r} failed: {r.error}")
    return rows


def output_differences(run_a, run_b, cases: list[dict]) -> dict[str, float]:
    """Largest absolute difference per output between two runners of one graph over ``cases``
    (outputs whose shapes differ count as inf): what a second runtime changes in the results."""
    worst: dict[str, float] = {}
    for feeds in cases:
        a, b = run_a(feeds), run_b(feeds)
        for name, x in a.items():
            y = np.asarray(b[name])
            d = (
                (float(np.max(np.abs(x.astype(np.float64) - y.astype(np.float64)))) if x.size else 0.0)
                if x.shape == y.shape
                else float("inf")
            )
            worst[name] = max(worst.get(name, 0.0), d)
    return worst


def format_differences(diffs: dict[str, float]) -> str:
    """``output diff, ...`` for :func:`output_differences`' result."""
    return ", ".join(f"{k} {v:.2g}" if v != float("inf") else f"{k} (other shape)" for k, v in diffs.items())


def results_table(
    results: list[BackendResult],
    baseline: str = "torch reference",
    items_per_case: int | None = None,
    item_unit: str = "",
) -> str:
    """A Markdown table with a speed-up column relative to ``baseline`` (the first working row
    when that failed) and, with ``items_per_case``, a throughput column; failed rows say why."""
    ok = [r for r in results if r]
    base = next((r for r in ok if r.backend == baseline), ok[0] if ok else None)
    extra = f" {item_unit}/s |" if items_per_case else ""
    lines = [
        f"| backend | p50 ms | p90 ms | p99 ms | FPS | x vs {base.backend if base else '-'} |{extra}",
        "|---|---:|---:|---:|---:|---:|" + ("---:|" if items_per_case else ""),
    ]
    for r in results:
        if not r:
            lines.append(f"| {r.backend} | error: {r.error} |")
            continue
        rate = f" {items_per_case * 1e3 / r.p50_ms:.1f} |" if items_per_case else ""
        lines.append(
            f"| {r.backend} | {r.p50_ms:.1f} | {r.p90_ms:.1f} | {r.p99_ms:.1f} | {r.fps:.2f} | "
            f"{base.p50_ms / r.p50_ms:.2f} |{rate}"
        )
    return "\n".join(lines)
