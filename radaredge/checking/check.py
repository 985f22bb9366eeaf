"""Parity between exported graphs (onnxruntime or OpenVINO) and the reference formulation (torch).

Per graph, three phases on the same cases (synthetic, or the scans of a recording:
:mod:`radaredge.checking.recording`): **run** the graph and the reference, **condition** (each
stage that follows a discrete decision -- NMS, proposals, keypoint sampling -- run by the
reference on the graph's own inputs to that stage, where the graph has such stages),
**compare** every output with the comparator its graph spec names (``judges``,
:mod:`radaredge.models.comparators`): a decision that flips on float noise is judged where it
is taken, and the end-to-end difference it causes is reported with the near-tie that explains
it. A FAILED verdict names the numbers that decided it and, when a debug export is available,
the first intermediate tensor where the two formulations diverge.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..cards import ModelCard
from ..errors import CapacityError
from ..exporting.graphs import DEBUG_PREFIX
from ..models.comparators import CaseResult, Comparator, OutputSummary
from ..models.spec import GraphSpec
from ..runtime.runners import graph_runner
from .capacity import CapacityTally


@dataclass
class GraphParity:
    """One graph's parity: per-case results and the per-output summary; true when it passed."""

    graph: str
    onnx: str
    comparators: tuple[Comparator, ...]
    cases: list[dict] = field(default_factory=list)  # {"case": name, "outputs": {name: CaseResult}}
    summary: dict[str, OutputSummary] = field(default_factory=dict)
    divergence: dict | None = None
    quantized: bool = False  # judged on the int8 budgets
    skipped: list[dict] = field(default_factory=list)  # recorded cases the reference refuses: {case, reason}
    capacity: CapacityTally | None = None  # recordings: what the graph's capacities did

    @property
    def passed(self) -> bool:
        return bool(self.cases) and all(self.summary.values())

    def __bool__(self) -> bool:
        return self.passed

    def to_dict(self) -> dict:
        return {
            "onnx": self.onnx,
            "passed": self.passed,
            "quantized": self.quantized,
            "summary": {k: s.to_dict() for k, s in self.summary.items()},
            "cases": [
                {"case": c["case"], "outputs": {k: asdict(r) for k, r in c["outputs"].items()}} for c in self.cases
            ],
            "divergence": self.divergence,
            "skipped": list(self.skipped),
            "capacity": self.capacity.to_dict() if self.capacity is not None else None,
        }

    def lines(self, unit: str = "frame") -> list[str]:
        """The per-output table, comparator notes, the divergence report and, for a recording,
        the cases the reference refused and the capacity summary (``unit``: frame or window)."""
        out = [f"{'output':<24}{'kind':<12}{'max abs':>11}{'max rel':>11}{'p99 abs':>11}{'min cos/IoU':>12}  verdict"]
        for comp in self.comparators:
            s = self.summary[comp.name]
            cos = (
                f"{s.min_cosine:.7f}"
                if s.min_cosine is not None
                else f"{s.min_iou:.7f}"
                if s.min_iou is not None
                else "-"
            )
            out.append(
                f"{s.name:<24}{s.kind:<12}{s.max_abs:>11.3g}{s.max_rel:>11.3g}{s.p99_abs:>11.3g}"
                f"{cos:>12}  {'PASSED' if s else 'FAILED'}  tol {s.tolerance}"
            )
            out += [f"{'':<24}{note}" for note in comp.notes(s)]
        d = self.divergence
        if d:
            if d["tensor"]:
                out.append(
                    f"first diverging intermediate (case {d['case']}): {d['tensor']} (max abs {d['max_abs']:.3g})"
                )
            else:
                out.append(
                    f"no intermediate diverges beyond tolerance in case {d['case']}: "
                    "the difference arises in the final outputs"
                )
        if self.skipped:
            out.append(
                f"not compared: {len(self.skipped)} {unit}(s) the reference refuses (the graph masks what does "
                f"not fit its capacity; the runtime refuses these inputs):"
            )
            out += [f"  {s['case']}: {s['reason']}" for s in self.skipped[:6]]
        if not self.cases:
            out.append(f"no {unit} could be compared: FAILED")
        if self.capacity is not None:
            out += self.capacity.lines(unit)
        return out


@dataclass
class ParityReport:
    """Parity of every graph of a model; true when every graph passed."""

    model: str
    onnx: str
    runtime: str = "onnxruntime"
    quantized: bool = False
    graphs: dict[str, GraphParity] = field(default_factory=dict)
    task: object | None = None  # with --quantized, the int8 graph's task metric (lines, to_dict, bool)
    data: object | None = None  # with --data, the recording (radaredge.checking.recording.Recording)

    @property
    def passed(self) -> bool:
        return all(self.graphs.values()) and (self.task is None or bool(self.task))

    def __bool__(self) -> bool:
        return self.passed

    def graph(self, name: str | None = None) -> GraphParity:
        """The graph ``name``'s parity; the only graph's when ``name`` is None."""
        return self.graphs[name] if name is not None else next(iter(self.graphs.values()))

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "onnx": self.onnx,
            "runtime": self.runtime,
            "quantized": self.quantized,
            "passed": self.passed,
            "graphs": {n: g.to_dict() for n, g in self.graphs.items()},
            "task": self.task.to_dict() if self.task is not None else None,
            "data": self.data.to_dict() if self.data is not None else None,
        }

    def lines(self) -> list[str]:
        out = []
        unit = self.data.unit if self.data is not None else "case"
        for name, g in self.graphs.items():
            budget = (
                " [int8 budget]"
                if g.quantized
                else " [fp32: the model's int8 policy keeps this graph fp32]"
                if self.quantized
                else ""
            )
            cases = f"{len(g.cases)} recorded {unit}s" if self.data is not None else f"{len(g.cases)} cases"
            out.append(
                f"parity {self.model}: {Path(g.onnx).name} ({self.runtime}) vs reference (torch), {cases}{budget}"
            )
            if self.data is not None:
                out += self.data.lines()
            out += g.lines(unit)
            if len(self.graphs) > 1:
                out.append(f"{name}: {'PASSED' if g else 'FAILED'}")
        if self.runtime == "openvino" and not self.passed:
            out.append(
                "note: OpenVINO's CPU plugin has no float64 kernels; what a graph computes in float64 "
                "carries float32 error there"
            )
        if len(self.graphs) > 1:
            out.append(f"{self.model}: {sum(map(bool, self.graphs.values()))}/{len(self.graphs)} graphs passed")
        if self.task is not None:
            out += self.task.lines()
        out.append("PASSED" if self.passed else "FAILED")
        return out


def _numpy(outputs: dict) -> dict[str, np.ndarray]:
    return {k: v.detach().numpy() for k, v in outputs.items()}


def check_graph(
    card: ModelCard,
    graph: GraphSpec,
    module: torch.nn.Module,
    onnx_path,
    cases_n: int = 20,
    seed: int = 0,
    quantized: bool = False,
    runtime: str = "onnxruntime",
    debug_onnx=None,
    progress=None,
    recorded: list | None = None,
) -> GraphParity:
    """Parity of one graph: ``onnx_path`` run in ``runtime`` (onnxruntime, or OpenVINO's CPU plugin)
    against ``graph``'s reference formulation of ``module`` on ``cases_n`` cases drawn with ``seed``,
    or on ``recorded`` cases ([(name, feeds)] of a recording,
    :func:`radaredge.checking.recording.recorded_cases`): then the report also summarises the
    graph's capacity outputs over them (:class:`radaredge.checking.capacity.CapacityTally`), and a
    case the reference refuses for a capacity (more non-empty pillars than MAFF-Net's sparse
    attention holds) is listed as not compared instead of ending the check.

    ``quantized`` holds each output to its int8 budget (:meth:`Comparator.quantized`).
    ``debug_onnx`` (a path, or a callable returning one, called only on failure) names the debug
    export used to locate the first diverging intermediate.
    """
    judged = graph.judges(card)
    judged = tuple(c.quantized() for c in judged) if quantized else tuple(judged)
    run_graph = graph_runner(onnx_path, runtime)
    cases = graph.make_cases(card, cases_n, seed) if recorded is None else list(recorded)
    conditioned = graph.postprocess_reference is not None and any(c.uses_post for c in judged)
    report = GraphParity(graph.name, str(onnx_path), judged, quantized=quantized)
    if recorded is not None:
        report.capacity = CapacityTally(card, graph.frame_inputs(card))
    # phase 1: run the graph and the reference on every case; phase 2: the reference stages that
    # follow a discrete decision, run on the graph's own inputs to them (see GraphSpec)
    got_all, ref_all, post_all, names = [], [], [], []
    for name, feeds in progress(cases) if progress else cases:
        got = run_graph(feeds)
        if report.capacity is not None:
            report.capacity.add(name, feeds, got)
        trace: dict = {}
        try:
            with torch.no_grad():
                ref = _numpy(graph.run_reference(module, feeds, trace if conditioned else None))
                post = _numpy(graph.postprocess_reference(module, feeds, got, ref, trace)) if conditioned else None
        except CapacityError as exc:
            if recorded is None:
                raise
            report.skipped.append({"case": name, "reason": str(exc)})
            continue
        names.append(name)
        got_all.append(got)
        ref_all.append(ref)
        post_all.append(post)
    # phase 3: compare
    per_output: dict[str, list[CaseResult]] = {c.name: [] for c in judged}
    for name, got, ref, post in zip(names, got_all, ref_all, post_all):
        row = {c.name: c.compare(got, ref, post) for c in judged}
        for k, r in row.items():
            per_output[k].append(r)
        report.cases.append({"case": name, "outputs": row})
    report.summary = {c.name: c.summarise(per_output[c.name], names, got_all, ref_all) for c in judged}
    if names and not report.passed and debug_onnx is not None and graph.trace_order(card):
        path = debug_onnx() if callable(debug_onnx) else debug_onnx
        report.divergence = locate_divergence(card, graph, module, path, report, cases, runtime)
    return report


def first_divergence(trace_order, got_trace: dict, ref_trace: dict, atol: float = 1e-3, rtol: float = 1e-3):
    """Name and max abs error of the first intermediate (pipeline order) beyond tolerance, or None."""
    for name in trace_order:
        if name not in got_trace or name not in ref_trace:
            continue
        g = np.asarray(got_trace[name], np.float64)
        r = np.asarray(ref_trace[name], np.float64)
        if g.shape != r.shape:
            return name, float("inf")
        err = np.abs(g - r)
        if (err > atol + rtol * np.abs(r)).any():
            return name, float(err.max())
    return None


def locate_divergence(
    card, graph: GraphSpec, module, debug_onnx, report: GraphParity, cases, runtime: str = "onnxruntime"
) -> dict | None:
    """Re-run the first failing case through the debug export (in ``runtime``) and the traced reference."""
    compared = dict(cases)
    failing = next((c["case"] for c in report.cases if not all(c["outputs"].values())), None)
    # a summary that failed with no single case failing: the first compared case (never one the
    # reference refused for a capacity, which report.cases leaves out)
    feeds = compared[failing or report.cases[0]["case"]]
    got = {
        k[len(DEBUG_PREFIX) :]: v
        for k, v in graph_runner(debug_onnx, runtime)(feeds).items()
        if k.startswith(DEBUG_PREFIX)
    }
    ref_trace: dict = {}
    with torch.no_grad():
        graph.run_reference(module, feeds, ref_trace)
    ref_trace = {k: v.detach().numpy() for k, v in ref_trace.items()}
    hit = first_divergence(graph.trace_order(card), got, ref_trace)
    return {"case": failing, "tensor": hit[0], "max_abs": hit[1]} if hit else {"case": failing, "tensor": None}
