"""What the verbs need to know about a model: its graphs, their formulations and cases.

A model is one or more graphs that share one set of weights (:class:`ModelSpec`). Each graph
(:class:`GraphSpec`) names its inputs and outputs, its synthetic cases and its two formulations
(export and reference). The spec holds what the model *is*; what a verb does with a model (which
comparator judges an output, how int8 copies are made, what ``bench`` times, how it is evaluated
and trained) lives in that verb's package, keyed by the model's name, so the verbs know the
models and the models know no verb.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from ..cards import ModelCard
from ..errors import ConfigError


def _whole(model: torch.nn.Module) -> torch.nn.Module:
    return model


def _no_checks(card: ModelCard) -> list:
    return []


def _no_files(card: ModelCard) -> dict:
    return {}


@dataclass(frozen=True)
class GraphSpec:
    """One exported graph.

    - ``name``: the graph's file stem inside a multi-graph export (``text_encoder``); unused for a
      one-graph model, whose graph is the output file itself;
    - ``input_names(card)`` / ``dynamic_axes(card)``: the input signature; ``frame_inputs(card)``
      the inputs that take one point cloud [N, F] each (oldest first) and ``timestamps_input`` the
      one taking per-frame times (s), for :mod:`radaredge.runtime`;
    - ``output_names(card)``: graph outputs in order (:mod:`radaredge.parity.judges` says how
      parity judges each);
    - ``make_cases(card, n, seed)`` -> [(case name, {input name: numpy array})];
    - ``run_reference(module, feeds, trace=None)`` -> {output: tensor}, the reference formulation;
    - ``run_export(module, feeds, trace=None)`` -> the export formulation's outputs, filling ``trace``;
    - ``trace_order(card)``: intermediate tensor names in pipeline order (divergence reports);
    - ``module(model)``: the sub-module of the model this graph runs (the whole model by default).

    Optional: ``postprocess_reference(module, feeds, graph outputs, reference outputs, reference
    trace)`` -> each stage that follows a discrete decision (NMS, proposals, keypoint sampling)
    run by the reference on the graph's own inputs to that stage, which parity judges the graph
    against: a decision within float noise of a tie cannot then flip the verdict;
    ``stage_times(module, feeds, reference)`` ->
    {stage: s} for one torch run; ``onnx_stages`` (stage, module prefixes) and
    ``onnx_post_outputs``, the same stages inside onnxruntime (:mod:`radaredge.bench.profiling`).
    """

    name: str
    input_names: Callable[[ModelCard], list[str]]
    dynamic_axes: Callable[[ModelCard], dict]
    output_names: Callable[[ModelCard], list[str]]
    make_cases: Callable[[ModelCard, int, int], list[tuple[str, dict[str, np.ndarray]]]]
    run_reference: Callable
    run_export: Callable
    trace_order: Callable[[ModelCard], tuple[str, ...]] = lambda card: ()
    frame_inputs: Callable[[ModelCard], list[str]] = lambda card: []
    timestamps_input: str | None = None
    module: Callable[[torch.nn.Module], torch.nn.Module] = _whole
    postprocess_reference: Callable | None = None
    stage_times: Callable | None = None
    onnx_stages: tuple = ()
    onnx_post_outputs: tuple = ()


@dataclass(frozen=True)
class ModelSpec:
    """A model family: ``build(card)`` -> the whole nn.Module (seeded, eval mode) and its graphs;
    ``files(card)`` -> {file name: source path} copied beside the graphs (a tokenizer);
    ``runtime_checks(card)`` -> [:class:`radaredge.runtime.metadata.OutputCheck`] written into
    every graph's metadata and applied by the runtime after each run (capacity flags)."""

    build: Callable[[ModelCard], torch.nn.Module]
    graphs: tuple[GraphSpec, ...]
    files: Callable[[ModelCard], dict] = _no_files
    runtime_checks: Callable[[ModelCard], list] = _no_checks

    @property
    def multi_graph(self) -> bool:
        """True when the model exports as several graphs (a directory) rather than one file."""
        return len(self.graphs) > 1

    def graph(self, name: str | None = None) -> GraphSpec:
        """The graph called ``name``; the only graph when ``name`` is None."""
        if name is None and len(self.graphs) == 1:
            return self.graphs[0]
        for g in self.graphs:
            if g.name == name:
                return g
        raise ConfigError(f"no graph {name!r} in this model; its graphs: {[g.name for g in self.graphs]}")
