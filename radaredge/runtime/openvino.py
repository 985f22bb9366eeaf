"""OpenVINO's CPU plugin as a second runtime for radaredge's ``.onnx`` graphs (optional).

``pip install 'radaredge[openvino]'`` adds it; radaredge works without it. OpenVINO reads the
ONNX file itself (no conversion step) and compiles it for the CPU. The same graph then runs in
``radaredge bench`` beside onnxruntime and in ``radaredge parity-check --runtime openvino``
against the torch reference.

What differs from onnxruntime: OpenVINO's CPU plugin has no float64 or int64 kernels (its CPU
inference precisions are f32/bf16/f16, i32, u8/i8). float64 runs in float32, so the TDFANet
RANSAC's ego velocity can miss its 1e-4 m/s tolerance against the float64 reference, which
onnxruntime meets bit-equal (`parity-check --runtime openvino` shows by how much). An integer Mod
runs in float32 too, which is why the RANSAC's hypothesis table keeps below 2**24
(:mod:`radaredge.ops.ego_velocity`). Numpy + openvino only: no torch.
"""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import ConfigError, InputError
from .session import checked_threads

INSTALL_HINT = "pip install 'radaredge[openvino]'"


def openvino_installed() -> bool:
    """True when the ``openvino`` package can be imported."""
    return importlib.util.find_spec("openvino") is not None


class OpenVinoModel:
    """One ``.onnx`` compiled by OpenVINO for the CPU, run one request at a time."""

    def __init__(self, path: Path, compiled, output_names: list[str]):
        self.path = path
        self._request = compiled.create_infer_request()
        self.output_names = output_names  # the graph's names, in order: compilation may merge
        self._outputs = list(compiled.outputs)  # the names of outputs that share a tensor

    def run(self, feeds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run on ``feeds`` (input name -> array) and return every output by name (copies:
        the request reuses its buffers on the next run)."""
        result = self._request.infer(dict(feeds))
        return {name: np.array(result[o]) for name, o in zip(self.output_names, self._outputs)}


@functools.cache
def _core():
    """The process's one ``openvino.Core``. OpenVINO's CPU plugin, created with each Core,
    points the calling thread's signal stack (sigaltstack) at a buffer of its own and, as it
    goes, back at the one it found: two Cores with overlapping lives leave the thread's signal
    stack on the first one's freed buffer, and the next signal with a Python handler (Ctrl-C,
    SIGTERM) kills the process with SIGSEGV. One Core for the process's life makes one plugin."""
    # optional: OpenVINO is the openvino extra
    import openvino as ov

    return ov.Core()


def compile_openvino(path: str | Path, threads: int = 2) -> OpenVinoModel:
    """Read ``path`` and compile it for OpenVINO's CPU plugin with ``threads`` inference threads,
    one stream, the latency hint and float32 inference precision (a CPU with bf16 would otherwise
    run in bf16 and no longer match the reference). ConfigError when openvino is not installed;
    InputError when ``path`` is missing or OpenVINO cannot read or compile it, with its reason."""
    if not openvino_installed():
        raise ConfigError(f"OpenVINO is not installed; {INSTALL_HINT}")
    # optional: OpenVINO is the openvino extra
    from openvino.frontend import FrontEndManager

    threads = checked_threads(threads)
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path} does not exist; export one with `radaredge export --model NAME`")
    try:
        # The ONNX frontend by name: Core.read_model would also probe other formats (TensorFlow's
        # prints parse errors of its own for a file that is not ONNX).
        frontend = FrontEndManager().load_by_framework("onnx")
        model = frontend.convert(frontend.load(str(path)))
        names = [o.get_any_name() for o in model.outputs]
        compiled = _core().compile_model(
            model,
            "CPU",
            {
                "INFERENCE_NUM_THREADS": threads,
                "NUM_STREAMS": 1,
                "PERFORMANCE_HINT": "LATENCY",
                "INFERENCE_PRECISION_HINT": "f32",
            },
        )
    except Exception as exc:  # OpenVINO's errors end with the reason, after where it was raised
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        raise InputError(
            f"{path}: OpenVINO cannot compile it for the CPU ({lines[-1] if lines else type(exc).__name__})"
        ) from None
    return OpenVinoModel(path, compiled, names)
