"""Whole-pipeline export: raw points in, result out, one self-contained graph + JSON sidecar
per graph; a multi-graph model writes its graphs, their shared files and the manifest into a
directory (the files of :mod:`radaredge.artifacts`).

The card, the feature columns, the input signature, the runtime checks, the package versions
and a hash of the weights travel inside each graph's ``metadata_props``
(:mod:`radaredge.runtime.metadata`), so an embedded app needs nothing else. Every graph written
(fp32, debug and int8 copies, each graph of a bundle) also records the hash of its own contents,
``radaredge.content_sha256`` (:mod:`radaredge.runtime.integrity`), which the runtime recomputes
when it loads the graph; a bundle's manifest records each part's.
"""

from __future__ import annotations

import collections
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import torch

from .. import artifacts
from ..atomic import Staging
from ..cards import ModelCard
from ..errors import ConfigError, ExportError
from ..models.factory import weights_hash
from ..models.spec import GraphSpec, ModelSpec
from ..runtime import RadarModel
from ..runtime.flags import BITS as FLAG_BITS
from ..runtime.flags import OUTPUT as FLAGS_OUTPUT
from ..runtime.flags import input_error_bits
from ..runtime.integrity import content_hash_of
from ..runtime.metadata import CONTENT_SHA256, GraphMetadata
from ..version import __version__
from .onnx_call import DEFAULT_OPSET, export_onnx

DEBUG_PREFIX = "debug."  # debug-export outputs are named debug.<intermediate>


def stamp_content_hash(proto: onnx.ModelProto) -> str:
    """Record ``proto``'s content hash (:mod:`radaredge.runtime.integrity`) in its metadata as
    ``radaredge.content_sha256``, replacing one recorded before (an int8 copy carries its fp32
    graph's metadata); return it. The last change to ``proto`` before it is saved."""
    kept = [(p.key, p.value) for p in proto.metadata_props if p.key != CONTENT_SHA256]
    del proto.metadata_props[:]
    for key, value in kept:
        proto.metadata_props.add(key=key, value=value)
    digest = content_hash_of(proto.SerializeToString()).computed
    proto.metadata_props.add(key=CONTENT_SHA256, value=digest)
    return digest


def save_stamped(proto: onnx.ModelProto, path: str | Path) -> str:
    """Save ``proto`` to ``path`` with its content hash recorded (:func:`stamp_content_hash`),
    checked by hashing the written file as the runtime will; return the hash. ExportError when
    the file does not verify (a serializer that wrote other bytes than it hashed)."""
    digest = stamp_content_hash(proto)
    onnx.save(proto, str(path))
    written = content_hash_of(Path(path).read_bytes())
    if written.status != "verified" or written.computed != digest:
        raise ExportError(f"{path}: the written graph hashes to {written.computed}, not the {digest} recorded in it")
    return digest


def require_same_weights(exported: RadarModel, model: torch.nn.Module, checkpoint=None) -> None:
    """ConfigError unless ``exported`` was exported from exactly ``model``'s weights."""
    if exported.weights_sha256 != weights_hash(model):
        source = f"checkpoint {checkpoint}" if checkpoint else "the seeded initialisation of this card"
        raise ConfigError(
            f"{exported.path} was exported with other weights than {source}; "
            f"pass the same --checkpoint/--config as at export"
        )


class _PipelineWrapper(torch.nn.Module):
    """Positional-input wrapper of one graph's export formulation; ``debug`` also returns the
    traced intermediates named in ``graph.trace_order(card)`` (for divergence reports)."""

    def __init__(self, module, graph: GraphSpec, card, debug: bool):
        super().__init__()
        self.model, self.graph, self.names, self.debug = module, graph, graph.input_names(card), debug
        self.out_names = graph.output_names(card)
        self.trace_names = graph.trace_order(card)

    def forward(self, *inputs):
        trace: dict | None = {} if self.debug else None
        out = self.graph.run_export(self.model, dict(zip(self.names, inputs)), trace)
        extra = tuple(trace[n] for n in self.trace_names) if self.debug else ()
        return tuple(out[n] for n in self.out_names) + extra


@dataclass
class GraphExport:
    """One written graph: the .onnx, its JSON sidecar, size, op histogram and metadata."""

    path: Path
    sidecar: Path
    size_bytes: int
    op_histogram: dict[str, int]
    metadata: GraphMetadata

    def to_dict(self) -> dict:
        return {
            "onnx": str(self.path),
            "sidecar": str(self.sidecar),
            "size_bytes": self.size_bytes,
            "op_histogram": self.op_histogram,
        }


def graph_metadata(
    card: ModelCard,
    spec: ModelSpec,
    graph: GraphSpec,
    module: torch.nn.Module,
    opset: int,
    part: str | None = None,
    bundle_hash: str | None = None,
) -> GraphMetadata:
    """The metadata written into one graph (:mod:`radaredge.runtime.metadata`)."""
    flagged = FLAGS_OUTPUT in graph.output_names(card)
    return GraphMetadata(
        model=card.name,
        card_yaml=card.to_yaml(),
        features=card.features,
        input_names=graph.input_names(card),
        dynamic_axes={k: {str(a): s for a, s in v.items()} for k, v in graph.dynamic_axes(card).items()},
        frame_inputs=graph.frame_inputs(card),
        timestamps_input=graph.timestamps_input,
        output_names=graph.output_names(card),
        weights_sha256=weights_hash(module),
        versions={
            "radaredge": __version__,
            "torch": torch.__version__,
            "onnx": onnx.__version__,
            "onnxruntime": onnxruntime.__version__,
            "opset": opset,
        },
        checks=list(spec.runtime_checks(card)),
        part=part,
        bundle_weights_sha256=bundle_hash,
        input_flags={str(bit): text for bit, text in FLAG_BITS.items()} if flagged else None,
        input_errors=input_error_bits(card) if flagged else None,
    )


def export_example(card: ModelCard, graph: GraphSpec, candidates: int = 4) -> dict:
    """The inputs the export traces with: the first of the graph's first ``candidates`` parity
    cases whose dynamic axes are all at least 2 long (torch.export specialises a dimension of
    size 1, so a one-hint example would bake a single hint into the graph), else the first."""
    cases = [feeds for _, feeds in graph.make_cases(card, candidates, 0)]
    axes = graph.dynamic_axes(card)
    wide = [feeds for feeds in cases if all(np.shape(feeds[name])[d] >= 2 for name, dims in axes.items() for d in dims)]
    return (wide or cases)[0]


def check_finite_outputs(card: ModelCard, spec: ModelSpec, model: torch.nn.Module) -> None:
    """ExportError unless every graph's export formulation gives finite outputs on the example it
    is traced with: weights of the right shapes whose values overflow (a checkpoint of another
    model, or a diverged one that stayed finite) are refused before an export that would only
    ever output NaN or Inf."""
    for graph in spec.graphs:
        feeds = export_example(card, graph)
        with torch.no_grad():
            out = graph.run_export(graph.module(model), {k: torch.from_numpy(v) for k, v in feeds.items()})
        bad = [
            n
            for n in graph.output_names(card)
            if torch.is_tensor(out.get(n)) and out[n].is_floating_point() and not bool(torch.isfinite(out[n]).all())
        ]
        if bad:
            raise ExportError(
                f"{card.name}: with these weights, {', '.join(bad)} of graph {graph.name} are not finite "
                f"(NaN or Inf) on a synthetic {', '.join(feeds)} example; the checkpoint's values "
                f"overflow float32 in this network"
            )


def export_graph(
    card: ModelCard,
    spec: ModelSpec,
    graph: GraphSpec,
    module: torch.nn.Module,
    output: str | Path,
    opset: int = DEFAULT_OPSET,
    debug: bool = False,
    part: str | None = None,
    bundle_hash: str | None = None,
) -> GraphExport:
    """Export one graph of the card's model (``module`` = ``graph.module(model)``) to ``output``
    and write ``output`` with suffix .json beside it.

    ``debug`` adds the intermediate tensors of ``graph.trace_order(card)`` as extra outputs named
    ``debug.<name>``. ``part`` and ``bundle_hash`` mark a graph of a multi-graph model.
    """
    names = graph.input_names(card)
    example = export_example(card, graph)
    args = tuple(torch.from_numpy(example[n]) for n in names)
    wrapper = _PipelineWrapper(module, graph, card, debug)
    out_names = graph.output_names(card) + ([DEBUG_PREFIX + n for n in graph.trace_order(card)] if debug else [])
    path = Path(output)
    export_onnx(wrapper, args, path, names, out_names, graph.dynamic_axes(card), opset=opset)
    proto = onnx.load(str(path))
    meta = graph_metadata(card, spec, graph, module, opset, part, bundle_hash)
    actual = [o.name for o in proto.graph.output]
    if not debug and actual != meta.output_names:
        raise ExportError(f"the exported graph's outputs are {actual}, not {meta.output_names}")
    meta.output_names = actual  # a debug graph: the outputs plus debug.<intermediate> (an intermediate
    # that is also an output keeps one name, its debug one)
    del proto.metadata_props[:]
    for k, v in meta.to_props().items():
        proto.metadata_props.add(key=k, value=v)
    proto.doc_string = f"radaredge export of {card.name}: {card.description}"
    try:
        onnx.checker.check_model(proto, full_check=True)
    except onnx.checker.ValidationError as exc:
        raise ExportError(f"onnx.checker rejected the exported graph: {exc}") from exc
    meta.content_sha256 = save_stamped(proto, path)
    hist = dict(sorted(collections.Counter(n.op_type for n in proto.graph.node).items(), key=lambda kv: -kv[1]))
    custom = sorted({n.domain for n in proto.graph.node if n.domain not in ("", "ai.onnx")})
    if custom:
        raise ExportError(f"exported graph uses custom op domains {custom}; radaredge graphs must not")
    sidecar = artifacts.copy_path(path, artifacts.SIDECAR)
    result = GraphExport(path, sidecar, path.stat().st_size, hist, meta)
    sidecar.write_text(
        json.dumps(
            {
                "model": card.name,
                "onnx": path.name,
                "size_bytes": result.size_bytes,
                "opset": opset,
                "debug_outputs": list(graph.trace_order(card)) if debug else [],
                "inputs": [{"name": i.name, "shape": _shape(i)} for i in proto.graph.input],
                "outputs": [{"name": o.name, "shape": _shape(o)} for o in proto.graph.output],
                "op_histogram": hist,
                "weights_sha256": meta.weights_sha256,
                "content_sha256": meta.content_sha256,
                "versions": meta.versions,
            },
            indent=2,
        )
    )
    return result


def _shape(value_info) -> list:
    dims = value_info.type.tensor_type.shape.dim
    return [d.dim_param or d.dim_value for d in dims]


def export_graphs(
    card: ModelCard,
    spec: ModelSpec,
    model: torch.nn.Module,
    bundle: artifacts.Bundle,
    opset: int = DEFAULT_OPSET,
    debug: bool = False,
    progress=None,
) -> dict[str, GraphExport]:
    """Export every graph of the card's model to its file in ``bundle`` (``debug``: each graph's
    debug copy beside it); a bundle of several graphs also gets the model's shared files
    (``spec.files``) and the manifest. Writes in place: :func:`write_export` is the atomic form."""
    paths = bundle.graph_files()
    bundle_hash = weights_hash(model) if bundle.multi else None
    graphs = list(spec.graphs)
    done = {}
    for g in progress(graphs) if progress else graphs:
        module = g.module(model)
        part = g.name if bundle.multi else None
        done[g.name] = export_graph(card, spec, g, module, paths[g.name], opset, part=part, bundle_hash=bundle_hash)
        if debug:
            export_graph(
                card,
                spec,
                g,
                module,
                artifacts.copy_path(paths[g.name], artifacts.DEBUG),
                opset,
                debug=True,
                part=part,
                bundle_hash=bundle_hash,
            )
    if bundle.multi:
        write_manifest(card, spec, bundle, done, opset, bundle_hash)
    return done


def _moved(path: Path, stage: Staging, dest: Path) -> Path:
    return dest / path.relative_to(stage.dir) if path.is_relative_to(stage.dir) else path


def write_export(
    card: ModelCard,
    spec: ModelSpec,
    model: torch.nn.Module,
    bundle: artifacts.Bundle,
    opset: int = DEFAULT_OPSET,
    debug: bool = False,
    int8=None,
    progress=None,
) -> tuple[dict[str, GraphExport], dict[str, Path]]:
    """:func:`export_graphs` (and ``int8(paths)`` -> {graph: int8 path}, the model's int8 hook
    applied to the fp32 graphs) into a staging directory, then every file moved into place at
    once (:class:`radaredge.atomic.Staging`): a failed or interrupted export leaves the previous
    files of ``bundle`` as they were and no partial file. Returns the graphs and int8 copies at
    their final paths."""
    check_finite_outputs(card, spec, model)
    root = bundle.root
    with Staging(root) as stage:
        staged = bundle.moved(stage.dir)
        graphs = export_graphs(card, spec, model, staged, opset, debug, progress)
        int8_paths = int8(staged.graph_files()) if int8 is not None else {}
        stage.commit()
    for g in graphs.values():
        g.path, g.sidecar = _moved(g.path, stage, root), _moved(g.sidecar, stage, root)
    return graphs, {n: _moved(p, stage, root) for n, p in int8_paths.items()}


def write_manifest(
    card: ModelCard,
    spec: ModelSpec,
    bundle: artifacts.Bundle,
    graphs: dict[str, GraphExport],
    opset: int,
    bundle_hash: str,
) -> Path:
    """Copy the model's shared files into the bundle's directory and write its manifest: the
    graphs with their hashes (weights, and contents as recorded in each graph), the files and the
    card."""
    files = {}
    for fname, src in spec.files(card).items():
        shutil.copyfile(src, bundle.root / fname)
        files[fname] = str(fname)
    manifest = bundle.manifest
    manifest.write_text(
        json.dumps(
            {
                "model": card.name,
                "family": card.model,
                "opset": opset,
                "weights_sha256": bundle_hash,
                "parts": {
                    n: {
                        "onnx": r.path.name,
                        "sidecar": r.sidecar.name,
                        "size_bytes": r.size_bytes,
                        "weights_sha256": r.metadata.weights_sha256,
                        "content_sha256": r.metadata.content_sha256,
                    }
                    for n, r in graphs.items()
                },
                "files": files,
                "card": card.data,
            },
            indent=2,
        )
    )
    return manifest
