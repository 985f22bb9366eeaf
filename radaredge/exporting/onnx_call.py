"""Trace a torch module to ONNX with named, optionally dynamic, axes.

This is the one place radaredge calls ``torch.onnx.export``; ops tests and the full-model
exporter (:mod:`radaredge.exporting.graphs`) both go through it, so every graph is built the same way.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import logging
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import onnx
import onnxscript.optimizer
import torch

from ..atomic import signals_held
from ..errors import ExportError

DEFAULT_OPSET = 18
INTERRUPT_NOTICE = "interrupted: stopping once torch has finished tracing this graph"


@contextlib.contextmanager
def _redirect_both(sink):
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        yield


def export_onnx(
    module: torch.nn.Module,
    args: tuple,
    path: str | Path,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_axes: Mapping[str, Mapping[int, str]] | None = None,
    opset: int = DEFAULT_OPSET,
    verbose: bool = False,
) -> Path:
    """Export ``module(*args)`` to ``path`` with torch's dynamo exporter.

    ``dynamic_axes`` maps an input name to ``{axis: symbolic_name}``; inputs sharing a symbolic
    name share one dimension. ExportError when the graph does not come out at ``opset`` (the
    exporter keeps its own opset when it cannot convert a model), so no file claims an opset it
    does not have. The exporter refuses code whose control flow depends on a dynamic
    size, which is what we want: a data-dependent branch must not be silently baked in.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dims: dict[str, torch.export.Dim] = {}
    dynamic_shapes = None
    if dynamic_axes:
        dynamic_shapes = []
        for name in input_names:
            axes = dynamic_axes.get(name)
            if not axes:
                dynamic_shapes.append(None)
                continue
            dynamic_shapes.append({ax: dims.setdefault(sym, torch.export.Dim.DYNAMIC) for ax, sym in axes.items()})
        dynamic_shapes = tuple(dynamic_shapes)
        params = inspect.signature(module.forward).parameters.values()
        if any(p.kind is inspect.Parameter.VAR_POSITIONAL for p in params):
            dynamic_shapes = (dynamic_shapes,)  # forward(*inputs): one nested entry
    module = module.eval()
    sink = io.StringIO()
    # The exporter and onnx_ir print progress and notes on stdout/stderr; failures still raise.
    quiet = contextlib.nullcontext() if verbose else _redirect_both(sink)
    logging.getLogger("torch.onnx").setLevel(logging.ERROR)
    # Ctrl-C waits for the tracer: a KeyboardInterrupt raised inside torch.export's dispatch
    # modes aborts the process (std::terminate) or is swallowed into an export error.
    try:
        with signals_held(INTERRUPT_NOTICE), quiet, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            program = torch.onnx.export(
                module,
                args,
                input_names=list(input_names),
                output_names=list(output_names),
                dynamic_shapes=dynamic_shapes,
                opset_version=opset,
                dynamo=True,
                external_data=False,
                verbose=False,
                optimize=False,
            )
            onnxscript.optimizer.fold_constants(program.model, should_fold=_fold_unless_generator)
            onnxscript.optimizer.remove_unused_nodes(program.model)
            program.save(str(path))
    except Exception as exc:  # torch raises many types; wrap them with context
        raise ExportError(f"exporting {type(module).__name__} to ONNX failed: {type(exc).__name__}: {exc}") from exc
    actual = next(
        (o.version for o in onnx.load(str(path), load_external_data=False).opset_import if o.domain in ("", "ai.onnx")),
        None,
    )
    if actual != opset:
        path.unlink(missing_ok=True)
        raise ExportError(
            f"opset {opset}: torch's exporter could not convert this graph to it and "
            f"kept opset {actual}; export with --opset {actual} (radaredge's default is {DEFAULT_OPSET})"
        )
    _finish(path, dynamic_axes or {})
    return path


_GENERATORS = frozenset({"ConstantOfShape", "Expand", "Tile"})
SMALL_FILL_ELEMENTS = 4096  # more than any layer's channel count in the cards (512)


def _fold_unless_generator(node) -> bool | None:
    """Constant-folding policy: ops that build a large tensor from a small one (the zero canvas
    of a pillar scatter, a bias spread over every query, a reference-point grid) stay in the
    graph, and onnxruntime folds them when the session starts; folded here, the file would
    store their whole output (up to the optimiser's 262144 elements each). A small fill folds:
    one value spread over at most SMALL_FILL_ELEMENTS elements. That is the zero bias the
    exporter writes as Expand(0, [C]) for a layer built with ``bias=False``, which must reach
    onnxruntime's Conv+BatchNorm fusion and the int8 quantiser as a constant. Everything else
    folds as the optimiser decides. The optimiser asks only about nodes whose inputs are all
    constant."""
    if node.op_type not in _GENERATORS:
        return None
    size = _fill_size(node)
    return size is not None and size <= SMALL_FILL_ELEMENTS


def _fill_size(node) -> int | None:
    """Elements a generator with constant inputs writes when it spreads one value (Expand or
    Tile of a one-element tensor, ConstantOfShape); None for any other generator. Computed from
    the inputs: the optimiser has not inferred the output shape when it asks."""
    try:
        values = [v.const_value.numpy() for v in node.inputs]
        if node.op_type == "ConstantOfShape":
            return int(np.prod(values[0]))
        if values[0].size != 1:
            return None
        if node.op_type == "Expand":
            return int(np.prod(np.broadcast_shapes(values[0].shape, tuple(int(d) for d in values[1]))))
        return int(np.prod(values[1]))  # Tile of one element: the product of repeats
    except (AttributeError, TypeError, ValueError, IndexError):
        return None


def _finish(path: Path, dynamic_axes: Mapping[str, Mapping[int, str]]) -> None:
    """Rewrite the saved graph: our names for the dynamic dimensions, and no provenance."""
    proto = onnx.load(str(path))
    _name_dynamic_dims(proto, dynamic_axes)
    strip_provenance(proto.graph)
    onnx.save(proto, str(path))


KEPT_NODE_METADATA = ("pkg.torch.onnx.name_scopes",)  # module paths: profiling and int8 read them


def strip_provenance(graph: onnx.GraphProto) -> None:
    """Drop what the exporter records about where each node came from (torch's stack traces
    with the absolute paths of the installed sources, FX node text, class hierarchies), in
    subgraphs too, and value and initializer metadata and doc strings. Each node keeps only its
    module scopes (:data:`KEPT_NODE_METADATA`, e.g. ``model.dfa.0.attn``), which the per-stage
    profile and int8's ``keep_fp32`` patterns read. The graph computes the same; exports of one
    card and checkpoint become byte-identical wherever radaredge is installed."""
    for node in graph.node:
        kept = [(p.key, p.value) for p in node.metadata_props if p.key in KEPT_NODE_METADATA]
        del node.metadata_props[:]
        for key, value in kept:
            node.metadata_props.add(key=key, value=value)
        node.doc_string = ""
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                strip_provenance(attr.g)
            for sub in attr.graphs:
                strip_provenance(sub)
    for info in list(graph.value_info) + list(graph.input) + list(graph.output):
        del info.metadata_props[:]
        info.doc_string = ""
    for init in graph.initializer:
        del init.metadata_props[:]
        init.doc_string = ""
    del graph.metadata_props[:]


def _name_dynamic_dims(proto: onnx.ModelProto, dynamic_axes: Mapping[str, Mapping[int, str]]) -> None:
    """Replace the exporter's generic symbols (s0, s1, ...) by our names (num_points_0, ...)
    everywhere in the graph, so the signature reads as the card documents it."""
    rename: dict[str, str] = {}
    for inp in proto.graph.input:
        dims = inp.type.tensor_type.shape.dim
        for axis, name in dynamic_axes.get(inp.name, {}).items():
            if dims[axis].dim_param:
                rename[dims[axis].dim_param] = name
    for info in list(proto.graph.input) + list(proto.graph.output) + list(proto.graph.value_info):
        for dim in info.type.tensor_type.shape.dim:
            if dim.dim_param in rename:
                dim.dim_param = rename[dim.dim_param]
