"""Run one exported ``.onnx`` in a named runtime: onnxruntime, or OpenVINO's CPU plugin.

Parity checks and benches take the runtime by name and get back one callable, so both runtimes
go through the same code paths. Importing this module imports neither runtime; each is imported
when chosen.
"""

from __future__ import annotations

from ..errors import ConfigError

RUNTIMES = ("onnxruntime", "openvino")


def lazy_runner(onnx_path, runtime: str = "onnxruntime", threads: int = 2):
    """:func:`graph_runner` that loads the graph on its first call, so a graph that fails to load
    fails where the call is handled (a bench row), not where the runner is built."""
    loaded = []

    def run(feeds):
        if not loaded:
            loaded.append(graph_runner(onnx_path, runtime, threads))
        return loaded[0](feeds)

    return run


def graph_runner(onnx_path, runtime: str = "onnxruntime", threads: int = 2):
    """fn(feeds) -> {output name: array} running ``onnx_path`` in ``runtime`` (one of RUNTIMES)
    on ``threads`` threads; ConfigError for any other runtime name."""
    if runtime == "onnxruntime":
        # lazy: radaredge.cli imports RUNTIMES from here, and its light commands (list, --help)
        # must not load onnxruntime
        from .session import make_session, run_session

        session = make_session(onnx_path, threads=threads)
        return lambda feeds: run_session(session, feeds)
    if runtime == "openvino":
        # lazy: as above, and OpenVINO is an optional extra
        from .openvino import compile_openvino

        return compile_openvino(onnx_path, threads=threads).run
    raise ConfigError(f"unknown runtime {runtime!r}; choose one of {', '.join(RUNTIMES)}")
