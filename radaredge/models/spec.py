"""What the exporter, parity checker and benchmark need to know about one model family."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from ..cards import ModelCard


@dataclass(frozen=True)
class OutputSpec:
    """One graph output and how parity compares it.

    ``kind``: ``dense`` (max abs / max rel / p99 against ``atol``), ``descriptor`` (cosine
    >= ``min_cosine`` plus dense statistics), ``exact`` (bit-equal labels, flags, masks),
    ``info`` (statistics reported, no verdict), ``boxes`` (detections [M, 7] matched one to one
    with the reference by rotated BEV IoU >= ``min_iou``, same label, score within
    ``max_score_diff``; its scores and labels outputs, named in ``group``, are of kind
    ``grouped`` and judged with it).

    For an int8 graph (:meth:`quantized`) descriptors are held to ``quantized_min_cosine``,
    detections to a matched-box recall of ``quantized_min_recall`` against the full reference at
    IoU >= ``quantized_min_iou`` (same label; scores reported, not judged), outputs marked
    ``quantized_info`` are reported only, and the rest keep their tolerances (they come from the
    fp32 preprocessing that quantisation does not touch).
    """

    name: str
    kind: str
    atol: float = 1e-4
    rtol: float = 1e-3
    min_cosine: float = 0.9999
    unit: str = ""
    quantized_min_cosine: float = 0.99
    quantized_info: bool = False
    group: tuple = ()            # ``boxes``: the names of its scores and labels outputs
    min_iou: float = 0.99        # ``boxes``: matched rotated BEV IoU
    max_score_diff: float = 1e-4  # ``boxes``: |score - matched reference score|
    min_recall: float | None = None  # ``boxes``: if set, judge the share of reference boxes matched over
    #                                  the case set (end to end) instead of requiring every box matched
    quantized_min_recall: float = 0.95   # ``boxes`` int8 budget: matched-box recall over the case set
    quantized_min_iou: float = 0.5       # ``boxes`` int8 budget: IoU (same label) that counts as a match
    angle_column: int = -1       # ``dense``: last-axis column holding an angle compared modulo angle_period
    angle_period: float = 0.0

    def quantized(self) -> "OutputSpec":
        """The budget this output is held to when the graph is int8-quantised."""
        if self.kind == "descriptor":
            return replace(self, min_cosine=self.quantized_min_cosine)
        if self.kind == "boxes":
            return replace(self, min_iou=self.quantized_min_iou, min_recall=self.quantized_min_recall,
                           max_score_diff=float("inf"))
        if self.quantized_info:
            return replace(self, kind="info")
        return self


@dataclass(frozen=True)
class ModelSpec:
    """Adapter between a model family and the generic commands.

    - ``build(card)`` -> nn.Module in eval mode, seeded;
    - ``input_names(card)`` / ``dynamic_axes(card)``: the graph's input signature;
    - ``outputs``: output specs in graph order;
    - ``make_cases(card, n, seed)`` -> list of (case name, {input name: numpy array});
    - ``run_reference(model, feeds)`` -> {output name: tensor}, the reference formulation;
    - ``run_export(model, feeds, trace)`` -> outputs of the export formulation, filling ``trace``;
    - ``trace_order(card)``: intermediate tensor names in pipeline order (divergence reports).
    """

    build: Callable[[ModelCard], torch.nn.Module]
    input_names: Callable[[ModelCard], list[str]]
    dynamic_axes: Callable[[ModelCard], dict]
    outputs: tuple[OutputSpec, ...]
    make_cases: Callable[[ModelCard, int, int], list[tuple[str, dict[str, np.ndarray]]]]
    run_reference: Callable
    run_export: Callable
    trace_order: Callable[[ModelCard], tuple[str, ...]]
    # Optional: (model, onnxruntime outputs) -> reference post-processing (NMS) of the graph's
    # own dense outputs. ``boxes`` outputs are then judged against it, so a score or IoU that
    # sits within float noise of a threshold cannot flip the verdict; the end-to-end match
    # against the full reference is still reported.
    postprocess_reference: Callable | None = None
    # Optional: (model, feeds, reference) -> {stage name: seconds} for one run in torch.
    stage_times: Callable | None = None
    # Optional: the same stages inside onnxruntime, as (stage name, module prefixes) in pipeline
    # order, plus the graph outputs after which everything is the last stage (see ort_stages).
    onnx_stages: tuple = ()
    onnx_post_outputs: tuple = ()

    @property
    def output_names(self) -> list[str]:
        return [o.name for o in self.outputs]


@dataclass(frozen=True)
class BundleSpec:
    """A model family exported as several graphs ("parts") that share one set of weights.

    - ``build(card)`` -> the whole nn.Module (seeded, eval mode);
    - ``parts``: part name -> the :class:`ModelSpec` of that graph, in export order;
    - ``part_module(model, name)`` -> the sub-module the part's spec runs and exports.

    ``radaredge export`` writes ``<dir>/<part>.onnx`` + sidecar per part and ``<dir>/bundle.json``;
    ``radaredge parity-check`` checks every part against its reference.
    """

    build: Callable[[ModelCard], torch.nn.Module]
    parts: dict
    part_module: Callable[[torch.nn.Module, str], torch.nn.Module]
    files: Callable[[ModelCard], dict] = lambda card: {}     # extra files copied into the bundle: name -> path
