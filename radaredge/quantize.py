"""INT8 post-training quantisation of an exported pipeline (onnxruntime static QDQ).

Only the network's heavy linear ops are quantised, Conv, MatMul and Gemm, with per-channel int8
weights and int8 activations calibrated on synthetic radar windows. Everything else stays
fp32. That covers preprocessing (range crop, pillar scatter indices), the ego-velocity RANSAC
(float64 in the graph, never touched), alignment and deformable-attention sampling
(GridSample) and the index math. The radaredge metadata (card, features, weights hash) is
copied over, and the quantisation settings are added under ``radaredge.quantization``.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import onnx
from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from .cards import ModelCard
from .errors import ExportError
from .registry import model_spec

QUANTIZED_OPS = ("Conv", "MatMul", "Gemm")


class _SyntheticWindows(CalibrationDataReader):
    """Feeds of ``n`` synthetic cases, one per call, for onnxruntime's calibrator."""

    def __init__(self, card: ModelCard, n: int, seed: int):
        self._feeds = iter([feeds for _, feeds in model_spec(card).make_cases(card, n, seed)])

    def get_next(self):
        return next(self._feeds, None)


def carry_metadata(fp32_path: str | Path, out_path: str | Path, quantization: dict) -> None:
    """Give the quantised graph at ``out_path`` the fp32 graph's ``metadata_props`` (card, weights
    hash, ...) plus ``radaredge.quantization`` = ``quantization`` (JSON)."""
    src = onnx.load(str(fp32_path), load_external_data=False)
    q = onnx.load(str(out_path))
    del q.metadata_props[:]
    for prop in src.metadata_props:
        q.metadata_props.add(key=prop.key, value=prop.value)
    q.metadata_props.add(key="radaredge.quantization", value=json.dumps(quantization))
    onnx.save(q, str(out_path))


def quantize_int8(card: ModelCard, fp32_path: str | Path, out_path: str | Path,
                  calibration_cases: int = 16, seed: int = 12345, method: str = "minmax") -> Path:
    """Write an int8 QDQ copy of ``fp32_path`` to ``out_path``.

    Calibration uses ``calibration_cases`` synthetic windows drawn with ``seed``. That seed
    differs from the parity and bench seeds, so parity is checked on data the calibration did
    not see. ``method`` is ``minmax`` or ``percentile``.
    """
    fp32_path, out_path = Path(fp32_path), Path(out_path)
    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile}
    if method not in methods:
        raise ExportError(f"unknown calibration method {method!r}; use one of {sorted(methods)}")
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        try:
            quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
            quantize_static(str(pre), str(out_path), _SyntheticWindows(card, calibration_cases, seed),
                            quant_format=QuantFormat.QDQ, per_channel=True,
                            op_types_to_quantize=list(QUANTIZED_OPS),
                            weight_type=QuantType.QInt8, activation_type=QuantType.QInt8,
                            calibrate_method=methods[method])
        except Exception as exc:
            raise ExportError(f"int8 quantisation of {fp32_path} failed: {type(exc).__name__}: {exc}") from exc
    carry_metadata(fp32_path, out_path, {
        "format": "QDQ", "weights": "int8 per-channel", "activations": "int8", "ops": list(QUANTIZED_OPS),
        "calibration": {"cases": calibration_cases, "seed": seed, "method": method}})
    return out_path
