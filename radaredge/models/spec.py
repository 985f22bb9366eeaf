"""What every verb needs to know about a model, declared once by its family's package.

A model is one or more graphs that share one set of weights (:class:`ModelSpec`). Each graph
(:class:`GraphSpec`) names its inputs and outputs, its synthetic cases, its two formulations
(export and reference) and the comparator that judges each output in ``parity-check``. The
model spec adds what the other verbs read: how ``export --quantize int8`` makes its copies
(:class:`Int8Plan`), what ``bench`` times beyond the default (:class:`BenchTask`), and the names
of the evaluation and training recipe that ``eval`` and ``train`` implement. The verbs look the
spec up (:func:`radaredge.registry.model_spec`) and keep no table of models; the models import
no verb.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from ..cards import ModelCard
from ..errors import ConfigError
from .comparators import Comparator


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
    - ``output_names(card)``: graph outputs in order;
    - ``judges(card)``: the comparator that judges each judged output in ``parity-check``
      (:mod:`radaredge.models.comparators`), graph output order;
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
    ``onnx_post_outputs``, the same stages inside onnxruntime (:mod:`radaredge.benchmarking.profiling`).
    """

    name: str
    input_names: Callable[[ModelCard], list[str]]
    dynamic_axes: Callable[[ModelCard], dict]
    output_names: Callable[[ModelCard], list[str]]
    make_cases: Callable[[ModelCard, int, int], list[tuple[str, dict[str, np.ndarray]]]]
    run_reference: Callable
    run_export: Callable
    judges: Callable[[ModelCard], tuple[Comparator, ...]]
    trace_order: Callable[[ModelCard], tuple[str, ...]] = lambda card: ()
    frame_inputs: Callable[[ModelCard], list[str]] = lambda card: []
    timestamps_input: str | None = None
    module: Callable[[torch.nn.Module], torch.nn.Module] = _whole
    postprocess_reference: Callable | None = None
    stage_times: Callable | None = None
    onnx_stages: tuple = ()
    onnx_post_outputs: tuple = ()


@dataclass(frozen=True)
class Int8Plan:
    """How ``export --quantize int8`` makes a model's int8 copies: ``method`` ``static`` (QDQ with
    calibrated activations, :func:`radaredge.exporting.quantize.static_int8`) or ``dynamic``
    (int8 MatMul/Gemm weights, activations quantised at run time, no calibration); ``graphs``
    the graphs that get a copy (None: every graph); the others stay fp32."""

    method: str = "static"
    graphs: tuple[str, ...] | None = None

    @property
    def calibrated(self) -> bool:
        """The method takes calibration data."""
        return self.method == "static"

    def quantises(self, graph: str) -> bool:
        """``graph`` gets an int8 copy."""
        return self.graphs is None or graph in self.graphs


@dataclass(frozen=True)
class BenchTask:
    """What one ``bench`` table times: ``backends`` (name -> fn(case)) on ``cases``, ``runs``
    timed runs after ``warmup``; the speed-up column is relative to ``baseline``; with
    ``items_per_case`` (e.g. 8 cells a batch) a throughput column ``items/s`` in ``item_unit``."""

    name: str
    title: str
    backends: dict[str, Callable]
    cases: list
    runs: int
    warmup: int = 3
    baseline: str = "torch reference"
    items_per_case: int | None = None
    item_unit: str = ""
    facts: dict = field(default_factory=dict)  # what the title states, for JSON


@dataclass(frozen=True)
class ModelSpec:
    """A model: ``build(card)`` -> the whole nn.Module (seeded, eval mode) and its graphs;
    ``files(card)`` -> {file name: source path} copied beside the graphs (a tokenizer);
    ``runtime_checks(card)`` -> [:class:`radaredge.runtime.metadata.OutputCheck`] written into
    every graph's metadata and applied by the runtime after each run (capacity flags);
    ``int8``: how its int8 copies are made; ``bench_tasks(card, model, graph paths, options)``
    -> [:class:`BenchTask`] what ``bench`` times instead of every graph's pipeline (None: that
    default); ``evaluation``: the task ``eval`` scores it by (a name in
    :data:`radaredge.eval.tasks.EVALUATIONS`; None: none) and ``recipe`` the training recipe
    (a name in :data:`radaredge.training.recipes.RECIPES`; None: not trained here)."""

    build: Callable[[ModelCard], torch.nn.Module]
    graphs: tuple[GraphSpec, ...]
    files: Callable[[ModelCard], dict] = _no_files
    runtime_checks: Callable[[ModelCard], list] = _no_checks
    int8: Int8Plan = Int8Plan()
    bench_tasks: Callable | None = None
    evaluation: str | None = None
    recipe: str | None = None

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
