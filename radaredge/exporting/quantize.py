"""INT8 post-training quantisation of exported graphs: onnxruntime static QDQ (the default for
every graph of a model) and dynamic int8 (weights only, for a model that asks for it).

Only the network's heavy linear ops are quantised, Conv, MatMul and Gemm (a Relu after one folded
into it, :data:`FUSED_ACTIVATIONS`), with per-channel int8 weights and uint8 activations
calibrated on synthetic radar windows or on a recording of the user's sensor
(:mod:`radaredge.exporting.calibration`). Everything else stays fp32. That covers preprocessing
(range crop, pillar scatter indices), the ego-velocity RANSAC (float64 in the graph, never
touched), alignment and deformable-attention sampling
(GridSample) and the index math. A card can keep more in fp32: the Conv/MatMul/Gemm layers of
the modules it lists under ``quantization.keep_fp32`` (module names as in the state dict, ``*``
matching any run of characters, submodules included), for layers whose int8 error the model
cannot absorb. The radaredge metadata (card, features, weights hash) is copied over, the
quantisation settings are added under ``radaredge.quantization``, and the int8 graph records
its own content hash (``radaredge.content_sha256``).

The format is uint8 activations x int8 weights with the weights on a 7-bit range
(``quantization.reduce_range``, default true). On x86 CPUs without VNNI (AVX2 only)
onnxruntime multiplies uint8 by int8 with VPMADDUBSW, whose int16 sums of two products
saturate when full-range weights meet large activations; 7-bit weights cannot saturate, and on
tdfanet-edge they cut the int8 descriptor error several-fold. int8 activations with the same
weights were as accurate and slower on 2 cores. With VNNI a card can set ``reduce_range: false``
and get full 8-bit weights. Measurements: benchmarks/README.md.
"""

from __future__ import annotations

import contextlib
import fnmatch
import io
import json
import tempfile
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import onnx
import onnxruntime as ort
from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_dynamic, quantize_static
from onnxruntime.quantization.calibrate import TensorData, TensorsData, create_calibrator, save_tensors_data
from onnxruntime.quantization.shape_inference import quant_pre_process

from ..artifacts import INT8, copy_path
from ..cards import ModelCard
from ..errors import ConfigError, ExportError
from ..models.spec import GraphSpec, ModelSpec
from ..node_scopes import fused_from, module_names
from ..registry import model_spec
from ..runtime import FrameFeeds
from ..runtime.metadata import CONTENT_SHA256, QUANTIZATION
from .calibration import DEFAULT_WINDOWS, FeedList, recorded_feeds, synthetic_feeds
from .graphs import save_stamped

QUANTIZED_OPS = ("Conv", "MatMul", "Gemm")
# A Relu on a quantised layer's output is folded into that layer (its uint8 output range starts
# at 0): the layers then chain in uint8 and onnxruntime runs consecutive QLinearConvs in NHWC
# without a DequantizeLinear -> Relu -> QuantizeLinear between them. A Relu whose input stays
# fp32 (a keep_fp32 layer's) is left as it is.
FUSED_ACTIVATIONS = ("Relu",)
QUANTIZED_OP_TYPES = QUANTIZED_OPS + FUSED_ACTIVATIONS
# ``quantization.calibration`` / ``--calibration-method``: how activation ranges are set from the
# calibration windows (onnxruntime's calibrators).
CALIBRATION_METHODS = {
    "minmax": CalibrationMethod.MinMax,  # the lowest and highest value seen
    "percentile": CalibrationMethod.Percentile,  # both tails cut at quantization.percentile
    "entropy": CalibrationMethod.Entropy,  # the range whose int8 histogram keeps the most information (KL)
}
DEFAULT_PERCENTILE = 99.999


def carry_metadata(fp32_path: str | Path, out_path: str | Path, quantization: dict) -> None:
    """Give the quantised graph at ``out_path`` the fp32 graph's ``metadata_props`` (card, weights
    hash, ...) plus ``radaredge.quantization`` = ``quantization`` (JSON), and record the int8
    graph's own content hash (not the fp32 graph's: :func:`radaredge.exporting.graphs.save_stamped`)."""
    src = onnx.load(str(fp32_path), load_external_data=False)
    q = onnx.load(str(out_path))
    del q.metadata_props[:]
    for prop in src.metadata_props:
        if prop.key != CONTENT_SHA256:
            q.metadata_props.add(key=prop.key, value=prop.value)
    q.metadata_props.add(key=QUANTIZATION, value=json.dumps(quantization))
    save_stamped(q, out_path)


def keep_fp32_patterns(card: ModelCard) -> list[str]:
    """The card's ``quantization.keep_fp32`` module-name patterns (default none)."""
    patterns = card.get("quantization.keep_fp32", []) or []
    if not isinstance(patterns, list) or not all(isinstance(p, str) and p for p in patterns):
        raise ConfigError(
            f"card {card.name!r}: quantization.keep_fp32 must be a list of module names "
            f"(fnmatch patterns such as 'dfa.*.attn.value_proj'), got {patterns!r}"
        )
    return patterns


def fp32_node_names(fp32_model: onnx.ModelProto, patterns: list[str], card_name: str = "") -> set[str]:
    """Names of the Conv/MatMul/Gemm nodes of ``fp32_model`` (an export that still carries its
    module-scope metadata) traced inside a module matching one of ``patterns``: the module or
    one of its parents, since a module its grandparent calls, or one reached through a method
    other than ``forward``, is traced without its parent's scope (MAFF-Net's CFA convs carry
    ``image_backbone.conv.0`` alone, its VFE layer ``vfe.pfn_layers.0.linear``). ConfigError
    for a pattern that matches no quantisable node (a typo would silently quantise the layer)."""
    hits = {p: set() for p in patterns}
    for node in fp32_model.graph.node:
        if node.op_type not in QUANTIZED_OPS:
            continue
        scopes = {
            ".".join(parts[:k])
            for parts in (n.split(".") for n in module_names(node))
            for k in range(1, len(parts) + 1)
        }
        for name in scopes:
            for p in patterns:
                if fnmatch.fnmatchcase(name, p):
                    hits[p].add(node.name)
    missing = [p for p, names in hits.items() if not names]
    if missing:
        raise ConfigError(
            f"card {card_name!r}: quantization.keep_fp32 pattern(s) {missing} match no "
            f"Conv/MatMul/Gemm of the exported graph; module names look like "
            f"'backbone_2d.blocks.0' (the state dict's prefixes)"
        )
    return set().union(*hits.values())


def _optimised_names(pre: onnx.ModelProto, names: set[str]) -> list[str]:
    """The nodes of the pre-processed graph that came from ``names``: the optimiser keeps a
    node's name or extends it (:func:`radaredge.node_scopes.fused_from`). ExportError when one of
    ``names`` has no such node, since it would be quantised against the card's wish."""
    found = [n.name for n in pre.graph.node if n.op_type in QUANTIZED_OPS and fused_from(n.name) in names]
    lost = sorted(names - {fused_from(n) for n in found})
    if lost:
        raise ExportError(
            f"quantization.keep_fp32: onnxruntime's pre-processing renamed or fused {lost}; they cannot be kept in fp32"
        )
    return found


def optimise_without_folding(fp32_path: str | Path, out_path: str | Path) -> Path:
    """Write ``fp32_path`` after onnxruntime's basic graph optimisations (node fusions such as
    MatMul+Add -> Gemm, redundant-node removal, shared constants) but without constant folding,
    then ONNX shape inference, to ``out_path``: the graph quantize_static reads.

    onnxruntime's own pre-processing (``quant_pre_process``) folds constants too, and here that
    writes every shape-derived tensor of the export into the file: reference-point grids,
    scatter buffers sized by the point budget, which made the int8 graphs several times their
    fp32 size. Without folding, onnxruntime still folds them in
    memory when the session loads, and the file holds the weights alone, as int8."""
    tmp = Path(out_path).with_suffix(".basic.onnx")
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    options.optimized_model_filepath = str(tmp)
    options.log_severity_level = 3
    ort.InferenceSession(
        str(fp32_path), options, providers=["CPUExecutionProvider"], disabled_optimizers=["ConstantFolding"]
    )
    quant_pre_process(str(tmp), str(out_path), skip_optimization=True, skip_symbolic_shape=True)
    tmp.unlink()
    return Path(out_path)


def calibration_method_of(card: ModelCard, override: str | None = None) -> str:
    """``override`` (``--calibration-method``) or the card's ``quantization.calibration``
    (default minmax); ConfigError naming the card or option for an unknown method, or for the
    percentile method with an invalid ``quantization.percentile``."""
    where = "--calibration-method" if override is not None else f"card {card.name!r}: quantization.calibration"
    value = override if override is not None else card.get("quantization.calibration", "minmax")
    if value not in CALIBRATION_METHODS:
        raise ConfigError(f"{where} is {value!r}; expected one of {sorted(CALIBRATION_METHODS)}")
    if value == "percentile":
        percentile(card)  # its share is checked with it, before any export
    return value


def percentile(card: ModelCard) -> float:
    """The card's ``quantization.percentile`` (default 99.999): the share of an activation's values,
    in percent, that the percentile method's range keeps."""
    value = card.get("quantization.percentile", DEFAULT_PERCENTILE)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 50 < value <= 100:
        raise ConfigError(f"card {card.name!r}: quantization.percentile must be a number in (50, 100], got {value!r}")
    return float(value)


def activation_ranges(pre: Path, feeds: list, method: str, kept_percentile: float, work: Path) -> TensorsData:
    """The activation range of every tensor onnxruntime quantises in the graph at ``pre``, from
    ``feeds`` by ``method`` (:data:`CALIBRATION_METHODS`). Windows are collected one at a time:
    a radar graph's point-count dependent tensors change shape from window to window, which
    onnxruntime's histogram calibrators cannot stack. Percentile keeps ``kept_percentile`` % of
    the values of both signs (asymmetric, as the uint8 activations are)."""
    options = {"symmetric": False, "percentile": kept_percentile}
    calibrator = create_calibrator(
        pre,
        list(QUANTIZED_OP_TYPES),
        augmented_model_path=str(work / "augmented.onnx"),
        calibrate_method=CALIBRATION_METHODS[method],
        extra_options=options,
    )
    with contextlib.redirect_stdout(io.StringIO()):  # the histogram calibrators print their progress
        for feed in feeds:
            calibrator.collect_data(FeedList([feed]))
        return calibrator.compute_data()


def check_qat_settings(card: ModelCard, qat: dict, checkpoint: str) -> None:
    """ConfigError when ``card``'s int8 settings (weight range, fp32 layers) are not those the
    ``--qat`` checkpoint ``checkpoint`` was fine-tuned for (:func:`radaredge.models.checkpoints.read_qat_entry`)."""
    mine = {"reduce_range": reduce_range(card), "keep_fp32": keep_fp32_patterns(card)}
    differ = [k for k, v in mine.items() if qat[k] != v]
    if differ:
        raise ConfigError(
            f"--checkpoint {checkpoint} was fine-tuned with fake quantisation for "
            + ", ".join(f"quantization.{k} = {qat[k]!r}" for k in differ)
            + f"; card {card.name!r} says "
            + ", ".join(f"{mine[k]!r}" for k in differ)
            + ": export with the card it was trained with, or fine-tune again"
        )


def learned_tensor_ranges(pre: onnx.ModelProto, fp32: onnx.ModelProto, learned: dict) -> dict[str, list[float]]:
    """The activation ranges a ``--qat`` checkpoint learned (``learned``: layer name -> "input" /
    "output" [min, max], :mod:`radaredge.training.qat`) as tensor name -> [min, max] of the
    pre-processed graph ``pre``: a quantised node made from an exported node traced inside a
    learned layer (``fp32``'s module scopes) takes the layer's input range for its first input,
    and a Conv its output range for its output and for the output of a Relu that follows it (the
    tensor whose range the folded Relu quantises with)."""
    scopes = {n.name: module_names(n) for n in fp32.graph.node if n.op_type in QUANTIZED_OPS}
    consumers = defaultdict(list)
    for node in pre.graph.node:
        for name in node.input:
            consumers[name].append(node)
    out: dict[str, list[float]] = {}
    for node in pre.graph.node:
        if node.op_type not in QUANTIZED_OPS:
            continue
        layer = next((n for n in reversed(scopes.get(fused_from(node.name), [])) if n in learned), None)
        if layer is None:
            continue
        ranges = learned[layer]
        if "input" in ranges:
            out[node.input[0]] = ranges["input"]
        if "output" in ranges and node.op_type == "Conv":
            out[node.output[0]] = ranges["output"]
            out.update({c.output[0]: ranges["output"] for c in consumers[node.output[0]] if c.op_type == "Relu"})
    return out


def override_ranges(data: TensorsData, learned: dict[str, list[float]]) -> int:
    """Replace the calibrated ranges of ``data`` by the ``learned`` ones (tensor name -> [min,
    max]) for the tensors it holds; the number replaced."""
    hits = [name for name in learned if name in data]
    for name in hits:
        lo, hi = learned[name]
        data.data[name] = TensorData(lowest=np.float32(lo), highest=np.float32(hi))
    return len(hits)


def reduce_range(card: ModelCard) -> bool:
    """The card's ``quantization.reduce_range``: quantise weights to 7 bits (default true)."""
    value = card.get("quantization.reduce_range", True)
    if not isinstance(value, bool):
        raise ConfigError(f"card {card.name!r}: quantization.reduce_range must be true or false, got {value!r}")
    return value


def quantize_int8(
    card: ModelCard,
    fp32_path: str | Path,
    out_path: str | Path,
    calibration_cases: int | None = None,
    seed: int = 12345,
    calibration_dir: str | Path | None = None,
    calibration_format: str | None = None,
    graph: GraphSpec | None = None,
    method: str | None = None,
    qat: dict | None = None,
) -> Path:
    """Write an int8 QDQ copy of ``fp32_path`` to ``out_path``.

    Calibration uses ``calibration_cases`` windows (default ``DEFAULT_WINDOWS``): synthetic ones
    drawn with ``seed``, or with ``calibration_dir`` windows of that recording
    (:mod:`radaredge.exporting.calibration`; its scan format ``calibration_format`` or inferred). The seed
    differs from the parity and bench seeds, so parity is checked on data the calibration did
    not see. Activation ranges come from ``method`` (default the card's
    ``quantization.calibration``, min/max unless it says otherwise; :func:`activation_ranges`),
    which the int8 graph's metadata records. The layers of the card's
    ``quantization.keep_fp32`` modules stay fp32; ``quantization.reduce_range`` is the module
    docstring's weight range. ``graph`` is the graph's spec (default: the card's only graph).
    ``qat``, a ``--qat`` checkpoint's entry (:func:`radaredge.models.checkpoints.read_qat_entry`),
    gives the ranges fake-quantised training learned, which replace the calibrated ones of
    their tensors (:func:`learned_tensor_ranges`); the metadata says how many.
    """
    fp32_path, out_path = Path(fp32_path), Path(out_path)
    patterns, seven_bit = keep_fp32_patterns(card), reduce_range(card)
    method = calibration_method_of(card, method)
    kept = percentile(card)
    fp32_model = onnx.load(str(fp32_path), load_external_data=False)
    keep = fp32_node_names(fp32_model, patterns, card.name)
    calibration_cases = DEFAULT_WINDOWS if calibration_cases is None else calibration_cases
    if calibration_dir is None:
        feeds = synthetic_feeds(card, calibration_cases, seed, graph)
        source = {"data": "synthetic", "cases": calibration_cases, "seed": seed}
    else:
        if graph is None:
            graph = model_spec(card).graph()
        inputs = FrameFeeds.of_card(card, graph.frame_inputs(card), graph.timestamps_input, str(fp32_path))
        feeds, source = recorded_feeds(inputs, calibration_dir, calibration_cases, calibration_format)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        try:
            optimise_without_folding(fp32_path, pre)
            pre_model = onnx.load(str(pre), load_external_data=False)
            excluded = _optimised_names(pre_model, keep)
            ranges = Path(tmp) / "ranges.json"
            data = activation_ranges(pre, feeds, method, kept, Path(tmp))
            learned = override_ranges(data, learned_tensor_ranges(pre_model, fp32_model, qat["ranges"])) if qat else 0
            calibrated = len(data.data) - learned
            save_tensors_data(data, ranges)
            quantize_static(
                str(pre),
                str(out_path),
                None,
                calibration_cache_path=ranges,
                quant_format=QuantFormat.QDQ,
                per_channel=True,
                op_types_to_quantize=list(QUANTIZED_OP_TYPES),
                weight_type=QuantType.QInt8,
                activation_type=QuantType.QUInt8,
                reduce_range=seven_bit,
                calibrate_method=CALIBRATION_METHODS[method],
                nodes_to_exclude=excluded,
            )
        except Exception as exc:
            raise ExportError(f"int8 quantisation of {fp32_path} failed: {type(exc).__name__}: {exc}") from exc
    carry_metadata(
        fp32_path,
        out_path,
        {
            "format": "QDQ",
            "weights": "int8 per-channel, 7-bit range" if seven_bit else "int8 per-channel",
            "activations": "uint8",
            "ops": list(QUANTIZED_OPS),
            "fused_activations": list(FUSED_ACTIVATIONS),
            "keep_fp32": {"modules": patterns, "nodes": len(excluded)},
            "calibration": {**source, "method": method, **({"percentile": kept} if method == "percentile" else {})},
            **({"qat": {"layers": len(qat["ranges"]), "tensors": learned, "calibrated": calibrated}} if qat else {}),
        },
    )
    return out_path


def quantize_dynamic_int8(fp32_path: str | Path, out_path: str | Path, seven_bit: bool = True) -> Path:
    """onnxruntime dynamic quantisation: per-channel int8 weights of MatMul/Gemm (on a 7-bit range
    when ``seven_bit``, the card's ``quantization.reduce_range``: the module docstring says why),
    activations quantised at run time (no calibration). Per-tensor weights, full-range or 7-bit,
    missed the text descriptor's cosine budget on an AVX2 CPU without VNNI. Metadata is copied
    and ``radaredge.quantization`` added."""
    fp32_path, out_path = Path(fp32_path), Path(out_path)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            # the exporter's intermediate value_info carries shapes that onnx's re-inference rejects
            # after quantisation rewrites the graph; drop it and let the quantiser infer afresh
            clean = onnx.load(str(fp32_path))
            del clean.graph.value_info[:]
            pre = Path(tmp) / "pre.onnx"
            onnx.save(clean, str(pre))
            quantize_dynamic(
                str(pre),
                str(out_path),
                weight_type=QuantType.QInt8,
                per_channel=True,
                reduce_range=seven_bit,
                op_types_to_quantize=["MatMul", "Gemm"],
            )
    except Exception as exc:
        raise ExportError(f"dynamic int8 quantisation of {fp32_path} failed: {type(exc).__name__}: {exc}") from exc
    carry_metadata(
        fp32_path,
        out_path,
        {
            "format": "dynamic",
            "weights": "int8",
            "activations": "uint8 at run time",
            "ops": ["MatMul", "Gemm"],
            "per_channel": True,
            "reduce_range": seven_bit,
        },
    )
    return out_path


@dataclass(frozen=True)
class Int8Options:
    """``export --quantize int8`` settings: calibration windows (default ``DEFAULT_WINDOWS``),
    to calibrate on a recording instead of synthetic scenes its directory and format, the
    calibration method (default the card's, :func:`calibration_method_of`) and a ``--qat``
    checkpoint's learned ranges."""

    windows: int | None = None
    calibration_dir: str | Path | None = None
    calibration_format: str | None = None
    method: str | None = None
    qat: dict | None = None  # a --qat checkpoint's entry: its learned ranges replace calibrated ones


def static_int8(card: ModelCard, spec: ModelSpec, paths: dict[str, Path], options: Int8Options) -> dict[str, Path]:
    """Static QDQ int8 copies, beside them, of the graphs the spec's int8 plan names (calibrated
    on ``options``' recording or on synthetic scenes)."""
    return {
        g.name: quantize_int8(
            card,
            paths[g.name],
            copy_path(paths[g.name], INT8),
            options.windows,
            calibration_dir=options.calibration_dir,
            calibration_format=options.calibration_format,
            graph=g,
            method=options.method,
            qat=options.qat,
        )
        for g in spec.graphs
        if spec.int8.quantises(g.name)
    }


def dynamic_int8(card: ModelCard, spec: ModelSpec, paths: dict[str, Path], options: Int8Options) -> dict[str, Path]:
    """Dynamically quantised copies, beside them, of the graphs the spec's int8 plan names (int8
    MatMul/Gemm weights at the card's reduce_range, no calibration)."""
    return {
        g.name: quantize_dynamic_int8(paths[g.name], copy_path(paths[g.name], INT8), reduce_range(card))
        for g in spec.graphs
        if spec.int8.quantises(g.name)
    }


# Int8Plan.method -> how its copies are made
INT8_METHODS: dict[str, Callable] = {"static": static_int8, "dynamic": dynamic_int8}


def make_int8_copies(card: ModelCard, spec: ModelSpec, paths: dict[str, Path], options: Int8Options) -> dict[str, Path]:
    """The int8 copies of the graphs at ``paths`` that ``spec.int8`` asks for: graph name -> path."""
    try:
        make = INT8_METHODS[spec.int8.method]
    except KeyError:
        raise ConfigError(
            f"{card.name}: its spec asks for int8 method {spec.int8.method!r}; known: {sorted(INT8_METHODS)}"
        ) from None
    return make(card, spec, paths, options)
