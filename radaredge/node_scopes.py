"""Which torch module an exported ONNX node came from, and which exported node an
onnxruntime-optimised node came from (profiling and int8 quantisation both ask)."""

from __future__ import annotations

import ast

import onnx


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
