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
    ``info`` (statistics reported, no verdict).

    For an int8 graph (:meth:`quantized`) descriptors are held to ``quantized_min_cosine``,
    outputs marked ``quantized_info`` are reported only, and the rest keep their tolerances
    (they come from the fp32 preprocessing that quantisation does not touch).
    """

    name: str
    kind: str
    atol: float = 1e-4
    rtol: float = 1e-3
    min_cosine: float = 0.9999
    unit: str = ""
    quantized_min_cosine: float = 0.99
    quantized_info: bool = False

    def quantized(self) -> "OutputSpec":
        """The budget this output is held to when the graph is int8-quantised."""
        if self.kind == "descriptor":
            return replace(self, min_cosine=self.quantized_min_cosine)
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

    @property
    def output_names(self) -> list[str]:
        return [o.name for o in self.outputs]
