"""What the verbs (export, parity, bench) need to know about a model: its graphs and its hooks.

A model is one or more graphs that share one set of weights (:class:`ModelSpec`). Each graph
(:class:`GraphSpec`) names its inputs, its outputs with their parity comparators, its synthetic
cases and its two formulations (export and reference). Model-specific extras are hooks on the
ModelSpec (how int8 copies are made, what ``bench`` times, files shipped beside the graphs, the
runtime checks written into the metadata); the verbs have one code path for every model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from ..cards import ModelCard
from ..comparators import Comparator


@dataclass(frozen=True)
class EvalInputs:
    """What ``eval`` was given; each model's ``evaluate`` hook takes what its task needs and
    refuses the rest. Place recognition: ``database``/``queries`` drives, ``radius`` (m),
    ``checkpoint`` and ``reference``; localisation: a cell ``map``."""

    database: str | None = None
    queries: str | None = None
    map: str | None = None
    checkpoint: str | None = None
    radius: float = 5.0
    reference: bool = True
    progress: Callable | None = None

    def require(self, task: str, needed: tuple[str, ...], card_name: str, uses: tuple[str, ...] = ()) -> None:
        """ConfigError unless exactly the inputs ``needed`` (of database, queries, map) are given
        and no option outside ``uses`` (of checkpoint, radius, reference) was set."""
        from ..errors import ConfigError
        missing = [n for n in needed if getattr(self, n) is None]
        extra = [n for n in ("database", "queries", "map") if n not in needed and getattr(self, n) is not None]
        options = (("checkpoint", "checkpoint", self.checkpoint is not None), ("radius", "radius", self.radius != 5.0),
                   ("reference", "no-reference", not self.reference))       # (name, option, set)
        extra += [option for name, option, given in options if given and name not in uses]
        if missing or extra:
            raise ConfigError(f"{card_name} is evaluated by {task} on {', '.join('--' + n for n in needed)}"
                              + (f"; missing {', '.join('--' + n for n in missing)}" if missing else "")
                              + (f"; {', '.join('--' + n for n in extra)} not used" if extra else ""))


@dataclass(frozen=True)
class TrainInputs:
    """What ``train`` was given besides the card, the model and the data: the run directory
    ``output``, ``device`` (cpu or cuda), ``resume`` from ``output``'s last state, the held-out
    ``validation`` drives or scenes (None: the model's default split), the scan ``data_format``,
    where ROS bags keep their scans and fixes (``bag``: the fields of
    :class:`radaredge.data.bag_drives.BagSource`), the recipe ``options`` (name -> value, None =
    the recipe's default), and the progress-bar factory ``progress(desc, total)`` and ``log(line)``."""

    output: str
    device: str = "cpu"
    resume: bool = False
    validation: tuple[str, ...] | None = None
    data_format: str | None = None
    bag: dict | None = None
    options: dict | None = None
    progress: Callable | None = None
    log: Callable[[str], None] | None = None


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
    - ``output_names(card)``: graph outputs in order; ``comparators(card)``: how parity judges
      them, each output judged by exactly one comparator;
    - ``make_cases(card, n, seed)`` -> [(case name, {input name: numpy array})];
    - ``run_reference(module, feeds, trace=None)`` -> {output: tensor}, the reference formulation;
    - ``run_export(module, feeds, trace=None)`` -> the export formulation's outputs, filling ``trace``;
    - ``trace_order(card)``: intermediate tensor names in pipeline order (divergence reports);
    - ``module(model)``: the sub-module of the model this graph runs (the whole model by default).

    Optional: ``postprocess_reference(module, feeds, graph outputs, reference outputs, reference
    trace)`` -> each stage that follows a discrete decision (NMS, proposals, keypoint sampling)
    run by the reference on the graph's own inputs to that stage, which the comparators with
    ``uses_post`` judge the graph against: a decision within float noise of a tie cannot then
    flip the verdict (see :class:`radaredge.comparators.Boxes`); ``stage_times(module, feeds, reference)`` ->
    {stage: s} for one torch run; ``onnx_stages`` (stage, module prefixes) and
    ``onnx_post_outputs``, the same stages inside onnxruntime (:mod:`radaredge.profiling`).
    """

    name: str
    input_names: Callable[[ModelCard], list[str]]
    dynamic_axes: Callable[[ModelCard], dict]
    output_names: Callable[[ModelCard], list[str]]
    comparators: Callable[[ModelCard], tuple[Comparator, ...]]
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
    """A model family: ``build(card)`` -> the whole nn.Module (seeded, eval mode) and its graphs.

    Hooks (each takes the card first):

    - ``files(card)`` -> {file name: source path} copied beside the graphs (a tokenizer);
    - ``runtime_checks(card)`` -> [:class:`radaredge.runtime.metadata.OutputCheck`] written into
      every graph's metadata and applied by the runtime after each run (capacity flags);
    - ``int8(card, paths, options)`` -> {graph name: int8 path}: how ``export --quantize int8``
      makes the int8 copies (default: static QDQ of every graph, :mod:`radaredge.quantize`);
      ``int8_calibrated`` says whether it takes calibration data;
    - ``bench_tasks(card, model, paths, options)`` -> [:class:`radaredge.timing.BenchTask`]: what
      ``bench`` times (default: each graph's pipeline in every backend);
    - ``evaluate(card, onnx, inputs)`` -> a report (``to_dict``, ``lines``, ``write_json``): the
      task metric ``eval`` computes from an :class:`EvalInputs` (none for a model without one);
    - ``train(card, model, data, inputs)`` -> a :class:`radaredge.training.run.TrainReport`: the
      model's training recipe on the data at ``data`` with a :class:`TrainInputs` (none for a
      model radaredge does not train).
    """

    build: Callable[[ModelCard], torch.nn.Module]
    graphs: tuple[GraphSpec, ...]
    files: Callable[[ModelCard], dict] = _no_files
    runtime_checks: Callable[[ModelCard], list] = _no_checks
    int8: Callable | None = None
    int8_calibrated: bool = True
    bench_tasks: Callable | None = None
    evaluate: Callable | None = None
    train: Callable | None = None

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
        from ..errors import ConfigError
        raise ConfigError(f"no graph {name!r} in this model; its graphs: {[g.name for g in self.graphs]}")
