"""Per-stage time inside onnxruntime: its node profile attributed to the model's pipeline stages.

onnxruntime's profiler times each node of the *optimised* graph. This module maps those nodes
back to the stages a model spec names (``ModelSpec.onnx_stages``, e.g. MAFF-Net's VFE+SPA, CFA,
CAF, backbone+head, NMS):

1. a node traced inside a stage's module (the exporter's ``pkg.torch.onnx.name_scopes``
   metadata, e.g. ``model.backbone_2d.blocks.2``) belongs to that stage;
2. a node outside every module that (transitively) consumes one of the spec's ``post`` graph
   outputs (the dense head's per-anchor outputs) belongs to the last stage (post-processing);
3. any other node outside the modules (index math, scatters, box decoding) takes the latest
   stage among its ancestors, or, when it has none (preprocessing of the raw points), the
   earliest stage among its consumers.

onnxruntime renames some nodes when it optimises (``X/GatherSliceToSplitFusion``,
``relu_6_nchwc``); those map back to the node ``X`` or to the node producing ``relu_6``. The
layout reorders it inserts for its NCHWc convolutions map to no node and are reported as their
own row, so the split never hides time. Nodes inside a Loop body are not counted separately:
the Loop node's time already includes them.
"""

from __future__ import annotations

import ast
from collections import defaultdict

import onnx

REORDER = "layout reorders (onnxruntime)"
UNMAPPED = "other (unmapped)"


def module_names(node: onnx.NodeProto) -> list[str]:
    """The torch modules a node of an exported graph was traced in, outermost first, as
    qualified names relative to the exported model (``backbone_2d.blocks.2``): the exporter's
    ``pkg.torch.onnx.name_scopes`` metadata without its ``model.`` root and without the op's own
    name. Empty for nodes traced outside every submodule (index math, scatters) and for graphs
    an optimiser rewrote (the metadata does not survive)."""
    for p in node.metadata_props:
        if p.key == "pkg.torch.onnx.name_scopes":
            try:
                scopes = list(ast.literal_eval(p.value))
            except (ValueError, SyntaxError):
                return []
            return [s.split(".", 1)[1] for s in scopes if s.startswith("model.")]
    return []


def fused_from(node_name: str) -> str:
    """The exported node an onnxruntime-optimised node was made from: onnxruntime keeps the
    name and appends its rewrite (``node_MatMul_12/MatMulAddFusion`` came from ``node_MatMul_12``)."""
    return node_name.split("/", 1)[0]


def _module_stage(names: list[str], stages: list[tuple[str, tuple[str, ...]]]) -> str | None:
    """The stage whose module prefix the node's outermost module name starts with, if any."""
    for name in names:
        for stage, prefixes in stages:
            if any(name == p or name.startswith(p + ".") for p in prefixes):
                return stage
    return None


def node_stages(model: onnx.ModelProto, stages: list[tuple[str, tuple[str, ...]]],
                post_outputs: tuple[str, ...] = ()) -> dict[str, str]:
    """Top-level node name -> stage name, by the three rules of the module docstring."""
    order = [s for s, _ in stages]
    rank = {s: i for i, s in enumerate(order)}
    nodes = list(model.graph.node)               # topologically sorted (ONNX requires it)
    producer = {out: n.name for n in nodes for out in n.output}
    stage: dict[str, str | None] = {n.name: _module_stage(module_names(n), stages) for n in nodes}

    def parents(n):
        return [producer[i] for i in n.input if i in producer]

    post = set()                                 # nodes downstream of a post graph output
    post_tensors = set(post_outputs)
    for n in nodes:
        if stage[n.name] is None and (post_tensors & set(n.input) or any(p in post for p in parents(n))):
            post.add(n.name)
    for n in nodes:                              # rule 2, then rule 3 (ancestors), in topological order
        if stage[n.name] is not None:
            continue
        if n.name in post:
            stage[n.name] = order[-1]
            continue
        ancestors = [stage[p] for p in parents(n) if stage[p] is not None]
        if ancestors:
            stage[n.name] = max(ancestors, key=rank.__getitem__)
    consumers = defaultdict(list)
    for n in nodes:
        for p in parents(n):
            consumers[p].append(n.name)
    for n in reversed(nodes):                    # rule 3 (consumers), in reverse topological order
        if stage[n.name] is None:
            below = [stage[c] for c in consumers[n.name] if stage[c] is not None]
            stage[n.name] = min(below, key=rank.__getitem__) if below else order[0]
    return stage


def _resolve(event_node: str, stage: dict[str, str], by_output: dict[str, str]) -> str:
    """Stage of one profiled (possibly renamed) node."""
    if event_node in stage:
        return stage[event_node]
    if event_node.startswith(("ReorderInput", "ReorderOutput")):
        return REORDER
    base = fused_from(event_node)
    if base in stage:
        return stage[base]
    for suffix in ("_nchwc",):
        if base.endswith(suffix):
            base = base[: -len(suffix)]
    for candidate in (base, "node_" + base):
        if candidate in stage:
            return stage[candidate]
    if base in by_output:
        return stage[by_output[base]]
    return UNMAPPED


def _subgraph_node_names(model: onnx.ModelProto) -> set[str]:
    names = set()

    def walk(graph):
        for n in graph.node:
            for attr in n.attribute:
                for g in ([attr.g] if attr.type == onnx.AttributeProto.GRAPH else list(attr.graphs)):
                    names.update(m.name for m in g.node)
                    walk(g)
    walk(model.graph)
    return names


def stage_times_from_profile(events: list[dict], model: onnx.ModelProto,
                             stages: list[tuple[str, tuple[str, ...]]], post_outputs: tuple[str, ...],
                             runs: int) -> dict[str, float]:
    """Mean milliseconds per stage and run, from the onnxruntime profile events of ``runs`` runs
    of ``model`` (:func:`radaredge.bench.profile_runs`).

    Rows are the spec's stages in order, then the reorder and unmapped rows when non-zero.
    """
    stage = node_stages(model, stages, post_outputs)
    by_output = {out: n.name for n in model.graph.node for out in n.output}
    inner = _subgraph_node_names(model) - set(stage)
    total: dict[str, float] = {s: 0.0 for s, _ in stages}
    for e in events:
        name = e.get("name", "")
        if e.get("cat") != "Node" or not name.endswith("_kernel_time"):
            continue
        node = name[: -len("_kernel_time")]
        if node in inner:
            continue
        key = _resolve(node, stage, by_output)
        total[key] = total.get(key, 0.0) + e.get("dur", 0) / 1e3
    return {k: v / runs for k, v in total.items() if v > 0 or k in dict(stages)}
