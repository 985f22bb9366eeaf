"""Which deployment targets can run an exported graph: the ops, attributes and types each does
not support, checked against a table kept here with its sources (``radaredge inspect --targets``).

Targets and what the table records for them (the ops radaredge graphs use or might use):

- ``onnxruntime``: the CPU execution provider's kernels (microsoft/onnxruntime
  docs/OperatorKernels.md @ 001d12d2): GridSample has no float64 kernel before opset 20,
  NonZero, Resize and Conv none at all.
- ``tensorrt``: TensorRT 10's ONNX parser (onnx/onnx-tensorrt docs/operators.md and
  onnxOpImporters.cpp @ 6bde659, the 10.16 parser; NVIDIA/TensorRT include/NvInfer.h and
  plugin/scatterElementsPlugin @ 52399f55):
  ScatterND takes no ``reduction`` (10.0-10.8 refuse the attribute, 10.9+ accept only ``none``);
  ScatterElements with a reduction runs as TensorRT's ScatterElements plugin, which the parser
  finds only when the plugin library is initialised (``trt.init_libnvinfer_plugins``; trtexec
  does it) and which takes int64 indices only; TopK's K must be below 3840; GridSample is 4-D
  only; Unique, BitShift and the Bitwise ops are absent; Mod with ``fmod = 0`` takes integers
  only; ReduceMin/Max need constant axes; integer Einsum, CumSum, IsNaN, Round and Floor are
  refused; float64 tensors are cast to float32 (values clamped to +-FLT_MAX).
- ``openvino``: OpenVINO's ONNX frontend (openvinotoolkit/openvino
  src/frontends/onnx/docs/supported_ops.md and op/scatter_nd.cpp): ScatterND reductions other
  than ``none`` only from PR #36072 (2026-05); its CPU plugin computes float64 in float32 and
  int64 in int32.
- ``ort-mobile``: onnxruntime's reduced-operator mobile package (docs/reference/operators/
  mobile_package_op_type_support_1.17.md, the last published list; the package is deprecated in
  favour of onnxruntime-android / onnxruntime-c, which run every operator): opsets 12-15 only,
  float / int8 / uint8 data (int32 / int64 in shape and index ops), and no ScatterElements,
  GridSample, GatherElements, Mod, Einsum, LSTM, Trilu, Bitwise ops, IsNaN or IsInf.

A finding is ``unsupported`` (the target refuses the graph) or a ``note`` (it runs, with a
consequence to know: a plugin to load, a precision change, a run-time limit).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import onnx
from onnx import TensorProto

from .errors import ConfigError

TARGETS = ("onnxruntime", "tensorrt", "openvino", "ort-mobile")
TOPK_MAX_TENSORRT = 3840  # TensorRT: "K input must be less than 3840"

SOURCES = {
    "onnxruntime": "microsoft/onnxruntime docs/OperatorKernels.md @ 001d12d2 (CPU execution provider)",
    "tensorrt": "onnx/onnx-tensorrt docs/operators.md + onnxOpImporters.cpp @ 6bde659 (TensorRT 10.16); "
    "NVIDIA/TensorRT NvInfer.h, plugin/scatterElementsPlugin @ 52399f55",
    "openvino": "openvinotoolkit/openvino src/frontends/onnx/docs/supported_ops.md, op/scatter_nd.cpp; PR #36072; "
    "intel_cpu transformation_pipeline.cpp (precision conversion)",
    "ort-mobile": "microsoft/onnxruntime docs/reference/operators/mobile_package_op_type_support_1.17.md "
    "(last published list; deprecated package)",
}

MOBILE_OPSETS = (12, 15)
MOBILE_MISSING = {
    "ScatterElements",
    "GridSample",
    "GatherElements",
    "Mod",
    "Einsum",
    "LSTM",
    "Trilu",
    "BitwiseAnd",
    "BitwiseOr",
    "BitwiseXor",
    "BitwiseNot",
    "BitShift",
    "IsNaN",
    "IsInf",
}
MOBILE_TYPES = {TensorProto.FLOAT, TensorProto.INT8, TensorProto.UINT8}
MOBILE_INDEX_OPS = {
    "Shape",
    "Gather",
    "GatherND",
    "Reshape",
    "Unsqueeze",
    "Squeeze",
    "Slice",
    "Concat",
    "Expand",
    "ConstantOfShape",
    "Range",
    "Cast",
    "TopK",
    "ArgMax",
    "ArgMin",
    "NonZero",
    "ScatterND",
    "Where",
    "Equal",
    "Less",
    "Greater",
    "LessOrEqual",
    "GreaterOrEqual",
    "Add",
    "Sub",
    "Mul",
    "Div",
    "CumSum",
    "ReduceMin",
    "ReduceMax",
    "ReduceSum",
    "Tile",
    "Transpose",
    "Identity",
    "Not",
    "And",
    "Or",
    "Max",
    "Min",
    "Constant",
    "Split",
}
TENSORRT_MISSING = {"Unique", "BitShift", "BitwiseAnd", "BitwiseOr", "BitwiseXor", "BitwiseNot"}
TENSORRT_FLOAT_ONLY = {"Einsum", "CumSum", "IsNaN", "Round", "Floor"}
INTEGER_TYPES = {
    TensorProto.INT8,
    TensorProto.INT16,
    TensorProto.INT32,
    TensorProto.INT64,
    TensorProto.UINT8,
    TensorProto.UINT16,
    TensorProto.UINT32,
    TensorProto.UINT64,
    TensorProto.BOOL,
}


@dataclass(frozen=True)
class Finding:
    """One thing a target refuses (``unsupported``) or does differently (``note``)."""

    target: str
    level: str
    op: str
    count: int
    message: str

    def to_dict(self) -> dict:
        return {"target": self.target, "level": self.level, "op": self.op, "count": self.count, "message": self.message}


class _Graph:
    """The facts the rules read: every node (subgraphs included), tensor element types by name,
    constant values, and the default-domain opset."""

    def __init__(self, model: onnx.ModelProto):
        self.model = model
        self.opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 0)
        inferred = onnx.shape_inference.infer_shapes(model, strict_mode=False)
        self.types: dict[str, int] = {}
        self.ranks: dict[str, int] = {}
        self.constants: dict[str, onnx.TensorProto] = {}
        for graph in _graphs(inferred.graph):
            for info in list(graph.value_info) + list(graph.input) + list(graph.output):
                t = info.type.tensor_type
                if t.elem_type:
                    self.types[info.name] = t.elem_type
                if t.HasField("shape"):
                    self.ranks[info.name] = len(t.shape.dim)
            for init in graph.initializer:
                self.types[init.name] = init.data_type
                self.ranks[init.name] = len(init.dims)
                self.constants[init.name] = init
            for node in graph.node:
                if (
                    node.op_type == "Constant"
                    and node.attribute
                    and node.attribute[0].type == onnx.AttributeProto.TENSOR
                ):
                    self.constants[node.output[0]] = node.attribute[0].t
                    self.types[node.output[0]] = node.attribute[0].t.data_type
        self.nodes = [n for g in _graphs(model.graph) for n in g.node]

    def attr(self, node: onnx.NodeProto, name: str, default=None):
        for a in node.attribute:
            if a.name == name:
                return onnx.helper.get_attribute_value(a)
        return default

    def text(self, node: onnx.NodeProto, name: str, default: str | None = None) -> str | None:
        value = self.attr(node, name, default)
        return value.decode() if isinstance(value, bytes) else value

    def const(self, name: str):
        t = self.constants.get(name)
        return None if t is None else onnx.numpy_helper.to_array(t)


def _graphs(graph: onnx.GraphProto) -> Iterator[onnx.GraphProto]:
    yield graph
    for node in graph.node:
        for a in node.attribute:
            if a.type == onnx.AttributeProto.GRAPH:
                yield from _graphs(a.g)
            for sub in a.graphs:
                yield from _graphs(sub)


Rule = Callable[[_Graph], Iterator[tuple[str, str, str, onnx.NodeProto | None]]]  # (level, op, message, node)


def _name(t: int) -> str:
    return TensorProto.DataType.Name(t).lower()


def _onnxruntime(g: _Graph):
    for n in g.nodes:
        t = g.types.get(n.input[0]) if n.input else None
        if n.op_type == "GridSample" and t == TensorProto.DOUBLE and g.opset < 20:
            yield "unsupported", n.op_type, "no float64 kernel before opset 20", n
        if n.op_type in ("NonZero", "Resize", "Conv", "ConvTranspose") and t == TensorProto.DOUBLE:
            yield "unsupported", n.op_type, "no float64 kernel", n


def _tensorrt(g: _Graph):
    doubles = 0
    for n in g.nodes:
        op = n.op_type
        if op in TENSORRT_MISSING:
            yield "unsupported", op, "not in TensorRT's ONNX parser", n
        elif op == "ScatterND" and g.attr(n, "reduction") is not None:
            if g.text(n, "reduction") != "none":
                yield "unsupported", op, f"reduction '{g.text(n, 'reduction')}': TensorRT takes only 'none'", n
            else:
                yield "note", op, "an explicit reduction attribute, even 'none', is refused by TensorRT 10.0-10.8", n
        elif op == "ScatterElements" and g.text(n, "reduction", "none") != "none":
            red = g.text(n, "reduction")
            yield (
                "note",
                op,
                f"reduction '{red}' runs as TensorRT's ScatterElements plugin: initialise the plugin "
                f"library (trt.init_libnvinfer_plugins; trtexec does) before parsing; "
                f"int64 indices only",
                n,
            )
            if g.types.get(n.input[1]) not in (None, TensorProto.INT64):
                yield "unsupported", op, "the ScatterElements plugin takes int64 indices only", n
        elif op == "TopK":
            k = g.const(n.input[1]) if len(n.input) > 1 else None
            if k is None:
                yield (
                    "note",
                    op,
                    f"K is computed at run time; TensorRT fails a run whose K reaches {TOPK_MAX_TENSORRT}",
                    n,
                )
            elif int(k.reshape(-1)[0]) >= TOPK_MAX_TENSORRT:
                yield "unsupported", op, f"K = {int(k.reshape(-1)[0])}; TensorRT needs K < {TOPK_MAX_TENSORRT}", n
        elif op == "GridSample" and g.ranks.get(n.input[0], 4) != 4:
            yield "unsupported", op, "TensorRT's GridSample is 4-D only", n
        elif op == "Mod" and g.attr(n, "fmod", 0) == 0 and g.types.get(n.input[0]) not in INTEGER_TYPES | {None}:
            yield "unsupported", op, "fmod = 0 takes integer inputs only in TensorRT", n
        elif op in ("ReduceMin", "ReduceMax") and len(n.input) > 1 and n.input[1] and g.const(n.input[1]) is None:
            yield "unsupported", op, "TensorRT needs constant reduction axes", n
        elif op in TENSORRT_FLOAT_ONLY and g.types.get(n.input[0]) in INTEGER_TYPES:
            yield "unsupported", op, f"{_name(g.types[n.input[0]])} input: TensorRT takes float types only here", n
        if any(g.types.get(o) == TensorProto.DOUBLE for o in n.output):
            doubles += 1
    if doubles:
        yield (
            "note",
            "float64",
            f"{doubles} node(s) compute in float64; TensorRT casts float64 to float32 (clamped "
            f"to +-FLT_MAX), so those parts run in float32",
            None,
        )


def _openvino(g: _Graph):
    doubles = 0
    for n in g.nodes:
        if n.op_type == "ScatterND" and g.text(n, "reduction", "none") != "none":
            yield (
                "note",
                "ScatterND",
                "reductions other than 'none' need an OpenVINO whose ONNX frontend has "
                "PR #36072 (2026-05); older ones refuse the node",
                n,
            )
        if any(g.types.get(o) == TensorProto.DOUBLE for o in n.output):
            doubles += 1
    if doubles:
        yield (
            "note",
            "float64",
            f"{doubles} node(s) compute in float64; OpenVINO's CPU plugin runs them in float32",
            None,
        )


def _ort_mobile(g: _Graph):
    lo, hi = MOBILE_OPSETS
    if not lo <= g.opset <= hi:
        yield (
            "unsupported",
            "opset",
            f"opset {g.opset}; the mobile package's kernels cover opsets {lo}-{hi} "
            f"(onnxruntime-android / onnxruntime-c run every operator)",
            None,
        )
    for n in g.nodes:
        if n.op_type in MOBILE_MISSING:
            yield "unsupported", n.op_type, "not in the mobile package", n
        elif n.op_type not in MOBILE_INDEX_OPS and any(g.types.get(o) not in MOBILE_TYPES | {None} for o in n.output):
            bad = next(g.types[o] for o in n.output if g.types.get(o) not in MOBILE_TYPES | {None})
            yield "unsupported", n.op_type, f"{_name(bad)} data; the mobile package takes float, int8, uint8", n


RULES: dict[str, Rule] = {
    "onnxruntime": _onnxruntime,
    "tensorrt": _tensorrt,
    "openvino": _openvino,
    "ort-mobile": _ort_mobile,
}


def parse_targets(text: str | None) -> tuple[str, ...]:
    """``--targets`` as a tuple of target names ("all" for every one); ConfigError for an unknown name."""
    if text is None:
        return ()
    names = TARGETS if text.strip() == "all" else tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in names if t not in TARGETS]
    if unknown or not names:
        raise ConfigError(f"--targets: unknown target(s) {unknown or [text]}; choose from {', '.join(TARGETS)} or all")
    return names


def check_graph(path: str | Path, targets: tuple[str, ...] = TARGETS) -> dict[str, list[Finding]]:
    """{target: findings} for the graph at ``path``; identical findings are merged with a count."""
    g = _Graph(onnx.load(str(path)))
    out = {}
    for target in targets:
        merged: dict[tuple[str, str, str], int] = {}
        for level, op, message, _ in RULES[target](g):
            merged[(level, op, message)] = merged.get((level, op, message), 0) + 1
        out[target] = [Finding(target, level, op, count, message) for (level, op, message), count in merged.items()]
    return out


def unsupported(findings: dict[str, list[Finding]], target: str) -> list[Finding]:
    return [f for f in findings.get(target, []) if f.level == "unsupported"]
