"""Parity between the exported ONNX (onnxruntime) and the reference formulation (torch).

Comparators per output kind (DESIGN.md): dense tensors -> max abs, max rel, p99 abs and an
atol + rtol element-wise check; descriptors -> cosine (and, over the case set, retrieval top-1
agreement); exact -> bit equality. A FAILED verdict names the numbers that decided it and, when
a debug export is available, the first intermediate tensor where the two formulations diverge.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from .models.spec import OutputSpec


@dataclass
class Comparison:
    """Statistics of one output on one case."""

    name: str
    kind: str
    passed: bool
    max_abs: float = 0.0
    max_rel: float = 0.0
    p99_abs: float = 0.0
    cosine: float | None = None
    mismatches: int = 0
    reason: str = ""


def compare(spec: OutputSpec, got: np.ndarray, ref: np.ndarray) -> Comparison:
    """Compare one output of onnxruntime (``got``) with the reference (``ref``)."""
    got, ref = np.asarray(got), np.asarray(ref)
    if got.shape != ref.shape:
        return Comparison(spec.name, spec.kind, False, reason=f"shape {got.shape} != reference {ref.shape}")
    if spec.kind == "exact":
        mism = int((got != ref).sum())
        return Comparison(spec.name, spec.kind, mism == 0, mismatches=mism,
                          reason="" if mism == 0 else f"{mism} element(s) differ")
    g, r = got.astype(np.float64).ravel(), ref.astype(np.float64).ravel()
    if not (np.isfinite(g).all() and np.isfinite(r).all()):
        return Comparison(spec.name, spec.kind, False, reason="non-finite values")
    diff = np.abs(g - r)
    c = Comparison(spec.name, spec.kind, True)
    if diff.size:
        c.max_abs = float(diff.max())
        c.max_rel = float((diff / np.maximum(np.abs(r), 1e-12)).max())
        c.p99_abs = float(np.percentile(diff, 99))
    bad = diff > spec.atol + spec.rtol * np.abs(r)
    c.mismatches = int(bad.sum())
    if spec.kind == "info":
        return c
    if spec.kind == "descriptor":
        denom = np.linalg.norm(g) * np.linalg.norm(r)
        c.cosine = float(g @ r / denom) if denom > 0 else float(np.array_equal(g, r))
        c.passed = c.cosine >= spec.min_cosine
        if not c.passed:
            c.reason = f"cosine {c.cosine:.6f} < {spec.min_cosine}"
    else:
        c.passed = c.mismatches == 0
        if not c.passed:
            c.reason = f"{c.mismatches} element(s) beyond atol {spec.atol:g} + rtol {spec.rtol:g} (max abs {c.max_abs:.3g})"
    return c


def retrieval_top1_agreement(got: np.ndarray, ref: np.ndarray) -> float:
    """Fraction of queries (ONNX descriptors) whose nearest reference descriptor (L2) is their own case."""
    if len(got) < 2:
        return 1.0
    d = ((got[:, None, :] - ref[None, :, :]) ** 2).sum(-1)
    return float((d.argmin(1) == np.arange(len(got))).mean())


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


@dataclass
class ParityReport:
    model: str
    onnx: str
    cases: list[dict] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    retrieval_top1: float | None = None
    min_retrieval_top1: float = 1.0
    quantized: bool = False
    divergence: dict | None = None

    @property
    def passed(self) -> bool:
        return all(s["passed"] for s in self.summary.values()) and (
            self.retrieval_top1 is None or self.retrieval_top1 >= self.min_retrieval_top1)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["passed"] = self.passed
        return d


def summarise(outputs, cases: list[dict]) -> dict:
    """Worst case per output over all cases."""
    out = {}
    for spec in outputs:
        rows = [c["outputs"][spec.name] for c in cases]
        cos = [r["cosine"] for r in rows if r["cosine"] is not None]
        out[spec.name] = {
            "kind": spec.kind,
            "passed": all(r["passed"] for r in rows),
            "max_abs": max((r["max_abs"] for r in rows), default=0.0),
            "max_rel": max((r["max_rel"] for r in rows), default=0.0),
            "p99_abs": max((r["p99_abs"] for r in rows), default=0.0),
            "min_cosine": min(cos) if cos else None,
            "mismatches": sum(r["mismatches"] for r in rows),
            "tolerance": ({"min_cosine": spec.min_cosine} if spec.kind == "descriptor" else
                          {"atol": spec.atol, "rtol": spec.rtol} if spec.kind == "dense" else
                          "reported only" if spec.kind == "info" else "exact"),
            "failed_cases": [c["case"] for c, r in zip(cases, rows) if not r["passed"]],
        }
    return out


# An int8 graph must still retrieve the same case as the reference for this share of the cases.
# The parity cases are distinct scenes, so this is a weak retrieval test; accept a quantised
# place-recognition model with `radaredge eval` on a benchmark of nearby places as well.
QUANTIZED_MIN_TOP1 = 0.98


def run_parity(card, onnx_path, model, cases_n: int = 20, seed: int = 0, debug_onnx=None, progress=None,
               quantized: bool = False) -> ParityReport:
    """Run onnxruntime on ``onnx_path`` and the reference formulation on the same cases.

    ``quantized`` applies the int8 budget of each output (:meth:`OutputSpec.quantized`) and
    requires retrieval top-1 agreement >= QUANTIZED_MIN_TOP1 instead of 100 %. ``debug_onnx``
    (a path, or a callable returning one, called only on failure) names the debug export used
    to locate the first diverging intermediate.
    """
    from .ort import make_session, run_session
    from .registry import model_spec

    spec = model_spec(card)
    session = make_session(onnx_path, threads=2)
    report = ParityReport(card.name, str(onnx_path), quantized=quantized,
                          min_retrieval_top1=QUANTIZED_MIN_TOP1 if quantized else 1.0)
    outputs = [o.quantized() for o in spec.outputs] if quantized else list(spec.outputs)
    desc_specs = [o for o in outputs if o.kind == "descriptor"]
    got_desc, ref_desc = [], []
    cases = spec.make_cases(card, cases_n, seed)
    for name, feeds in (progress(cases) if progress else cases):
        got = run_session(session, feeds)
        with torch.no_grad():
            ref = {k: v.detach().numpy() for k, v in spec.run_reference(model, feeds).items()}
        comps = {o.name: asdict(compare(o, got[o.name], ref[o.name])) for o in outputs}
        report.cases.append({"case": name, "outputs": comps})
        if desc_specs:
            got_desc.append(got[desc_specs[0].name])
            ref_desc.append(ref[desc_specs[0].name])
    report.summary = summarise(outputs, report.cases)
    if desc_specs:
        report.retrieval_top1 = retrieval_top1_agreement(np.stack(got_desc), np.stack(ref_desc))
    if not report.passed and debug_onnx is not None:
        path = debug_onnx() if callable(debug_onnx) else debug_onnx
        report.divergence = locate_divergence(card, spec, model, path, report, cases)
    return report


def locate_divergence(card, spec, model, debug_onnx, report: ParityReport, cases) -> dict | None:
    """Re-run the first failing case through the debug export and the traced reference."""
    from .ort import make_session, run_session

    failing = next((c["case"] for c in report.cases if not all(o["passed"] for o in c["outputs"].values())), None)
    feeds = dict(cases)[failing] if failing else cases[0][1]
    from .export import DEBUG_PREFIX
    got = {k[len(DEBUG_PREFIX):]: v for k, v in run_session(make_session(debug_onnx, threads=2), feeds).items()
           if k.startswith(DEBUG_PREFIX)}
    ref_trace: dict = {}
    with torch.no_grad():
        spec.run_reference(model, feeds, ref_trace)
    ref_trace = {k: v.detach().numpy() for k, v in ref_trace.items()}
    hit = first_divergence(spec.trace_order(card), got, ref_trace)
    return {"case": failing, "tensor": hit[0], "max_abs": hit[1]} if hit else {"case": failing, "tensor": None}
