"""Thin onnxruntime helpers (numpy + onnxruntime only; safe to import without torch)."""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path
from typing import Mapping

import numpy as np
import onnxruntime as ort

from ..errors import ConfigError, InputError

THREADS_PER_CORE_MAX = 4  # more threads than this per usable core only slow a run down and cost memory


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS tells, else the CPU count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def checked_threads(threads) -> int:
    """``threads`` as an int in 1 .. :data:`THREADS_PER_CORE_MAX` x the usable cores; ConfigError
    outside it (a huge count exhausts memory creating threads), a RuntimeWarning above the core count."""
    cores = usable_cores()
    if (
        isinstance(threads, bool)
        or not isinstance(threads, (int, np.integer))
        or not 1 <= threads <= THREADS_PER_CORE_MAX * cores
    ):
        raise ConfigError(
            f"threads: expected an integer from 1 to {THREADS_PER_CORE_MAX * cores} "
            f"({THREADS_PER_CORE_MAX} x the {cores} usable cores), got {threads!r}"
        )
    if threads > cores:
        warnings.warn(
            f"threads = {threads} is more than the {cores} usable cores; runs will be slower, not faster",
            RuntimeWarning,
            stacklevel=3,
        )
    return int(threads)


def make_session(
    path: str | Path, threads: int = 2, profile: bool = False, graph_level: str = "all"
) -> ort.InferenceSession:
    """An onnxruntime CPU session with a fixed number of intra-op threads.

    ``graph_level`` is one of ``disable``, ``basic``, ``extended``, ``all``. The worker threads
    stop spinning when a run returns (``session.force_spinning_stop``): a radar app calls the
    model once per scan and needs the cores for its own work in between, and onnxruntime's
    default of spinning on after the run takes the cores from whatever runs next (on 2 cores, a
    second session run right after the first is slowed down). InputError when
    ``path`` is missing or onnxruntime cannot load it (not an ONNX model, truncated, an
    operator this onnxruntime lacks), with onnxruntime's reason.
    """
    threads = checked_threads(threads)
    if Path(path).is_dir():
        raise InputError(
            f"{path} is a directory; pass one graph's .onnx (a multi-graph export directory goes "
            f"to the commands that take one: inspect, parity-check, bench, eval, locate)"
        )
    if not Path(path).is_file():
        raise InputError(f"{path} does not exist; export one with `radaredge export --model NAME`")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.log_severity_level = 3
    opts.add_session_config_entry("session.force_spinning_stop", "1")
    opts.graph_optimization_level = {
        "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
        "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
        "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
    }[graph_level]
    if profile:
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(tempfile.gettempdir()) / "radaredge_ort_profile")
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime's own error types (InvalidArgument, Fail, ...)
        reason = str(exc).split(" : ")[-1].strip()
        raise InputError(
            f"{path}: onnxruntime cannot load it as a model ({type(exc).__name__}: {reason}); "
            f"pass an .onnx written by `radaredge export`"
        ) from None


def run_session(session: ort.InferenceSession, feeds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Run ``session`` and return its outputs by name."""
    names = [o.name for o in session.get_outputs()]
    return dict(zip(names, session.run(names, dict(feeds))))
