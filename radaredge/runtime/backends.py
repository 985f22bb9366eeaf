"""Which runtime executes a loaded graph: onnxruntime, OpenVINO's CPU plugin, or the faster of the two.

``auto`` times both runtimes on the graph's first real input (:data:`TRIAL_RUNS` runs each, after
one warm-up, the median compared) and remembers the winner per graph weights hash, CPU model and
thread count in ``$RADAREDGE_CACHE/backends.json`` (default ``~/.cache/radaredge``), so the trial
runs once per graph and machine. Without OpenVINO installed, ``auto`` is onnxruntime.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from .. import atomic
from ..errors import ConfigError
from .openvino import compile_openvino, openvino_installed

BACKENDS = ("onnxruntime", "openvino", "auto")
TRIAL_RUNS = 3
Runner = Callable[[Mapping[str, np.ndarray]], dict]


def check_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    return backend


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``'s first ``model name``, else the platform's)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cache_path() -> Path:
    return Path(os.environ.get("RADAREDGE_CACHE") or Path.home() / ".cache" / "radaredge") / "backends.json"


def _cache_key(weights_sha256: str, threads: int) -> str:
    return f"{weights_sha256}|{cpu_model()}|{threads} threads"


def cached_choice(weights_sha256: str, threads: int) -> str | None:
    """The runtime ``auto`` chose before for this graph, CPU and thread count, if any."""
    try:
        entry = json.loads(cache_path().read_text()).get(_cache_key(weights_sha256, threads))
    except (OSError, ValueError, AttributeError):
        return None
    return entry.get("backend") if isinstance(entry, dict) and entry.get("backend") in BACKENDS[:2] else None


def _median_seconds(run: Runner, feeds, runs: int) -> float:
    run(feeds)  # warm-up: first-run allocations
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        run(feeds)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def choose(weights_sha256: str, threads: int, runners: dict[str, Runner], feeds) -> str:
    """The faster of ``runners`` (name -> runner) on ``feeds``, by median of :data:`TRIAL_RUNS`
    timed runs each, remembered in the cache with the timings."""
    timings = {name: _median_seconds(run, feeds, TRIAL_RUNS) for name, run in runners.items()}
    best = min(timings, key=timings.get)
    path = cache_path()
    try:
        cache = json.loads(path.read_text()) if path.exists() else {}
        if not isinstance(cache, dict):
            cache = {}
    except (OSError, ValueError):
        cache = {}
    cache[_cache_key(weights_sha256, threads)] = {"backend": best, "median_s": timings}
    try:
        atomic.write_json(path, cache)
    except OSError:  # a read-only home: the choice holds for this process
        pass
    return best


def openvino_runner(path, threads: int) -> Runner:
    return compile_openvino(path, threads=threads).run


def auto_available() -> bool:
    return openvino_installed()
