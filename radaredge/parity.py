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
from .runners import graph_runner


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
    min_iou: float | None = None
    mismatches: int = 0
    matched: int = 0              # ``boxes``: reference boxes matched
    reference: int = 0            # ``boxes``: reference boxes
    by_score: dict = field(default_factory=dict)   # int8 ``boxes``: {band: [matched, reference boxes scored >= band]}
    reason: str = ""


def match_boxes(got_boxes, got_scores, got_labels, ref_boxes, ref_scores, ref_labels, min_iou: float):
    """Greedy one-to-one matching of detections by rotated BEV IoU (best pairs first, same label,
    IoU >= min_iou). Returns (pairs [(i_got, j_ref, iou)], unmatched got indices, unmatched ref indices)."""
    from .ops.box_iou import bev_iou_matrix_reference

    iou = bev_iou_matrix_reference(got_boxes, ref_boxes) if len(got_boxes) and len(ref_boxes) else \
        np.zeros((len(got_boxes), len(ref_boxes)))
    iou = np.where(np.asarray(got_labels)[:, None] == np.asarray(ref_labels)[None, :], iou, -1.0)
    pairs, used_g, used_r = [], set(), set()
    for flat in np.argsort(-iou, axis=None, kind="stable"):
        i, j = divmod(int(flat), iou.shape[1])
        if iou[i, j] < min_iou:
            break
        if i in used_g or j in used_r:
            continue
        pairs.append((i, j, float(iou[i, j])))
        used_g.add(i)
        used_r.add(j)
    return (pairs, [i for i in range(len(got_boxes)) if i not in used_g],
            [j for j in range(len(ref_boxes)) if j not in used_r])


# Reference-score floors at which the int8 matched-box recall is also reported (not judged): a
# detector's low-score boxes sit next to the score threshold and to near-tie neighbours in the
# NMS, so int8 noise re-decides them first; these bands show whether confident boxes survive.
RECALL_SCORE_BANDS = (0.3, 0.5)


def compare_boxes(spec: OutputSpec, got: tuple, ref: tuple) -> Comparison:
    """Detections (boxes, scores, labels) against the reference's: counts, matched IoU, score diff."""
    gb, gs, gl = (np.asarray(a) for a in got)
    rb, rs, rl = (np.asarray(a) for a in ref)
    if not (np.isfinite(gb).all() and np.isfinite(gs).all()):
        return Comparison(spec.name, spec.kind, False, reason="non-finite boxes or scores")
    pairs, lone_g, lone_r = match_boxes(gb, gs, gl, rb, rs, rl, spec.min_iou)
    c = Comparison(spec.name, spec.kind, True, mismatches=len(lone_g) + len(lone_r), matched=len(pairs),
                   reference=len(rb))
    if pairs:
        c.max_abs = max(abs(float(gs[i]) - float(rs[j])) for i, j, _ in pairs)
        c.min_iou = min(iou for _, _, iou in pairs)
        c.max_rel = max(float(np.abs(gb[i] - rb[j]).max()) for i, j, _ in pairs)
    if spec.min_recall is not None:           # judged over the case set (summarise)
        found = np.zeros(len(rb), bool)
        found[[j for _, j, _ in pairs]] = True
        c.by_score = {f"{b:g}": [int(found[rs >= b].sum()), int((rs >= b).sum())] for b in RECALL_SCORE_BANDS}
        return c
    reasons = []
    if lone_g or lone_r:
        reasons.append(f"{len(gb)} boxes vs {len(rb)} in the reference; {len(lone_g) + len(lone_r)} unmatched "
                       f"at IoU >= {spec.min_iou}")
    if c.max_abs > spec.max_score_diff:
        reasons.append(f"score diff {c.max_abs:.3g} > {spec.max_score_diff:g}")
    c.passed = not reasons
    c.reason = "; ".join(reasons)
    return c


def compare(spec: OutputSpec, got: np.ndarray, ref: np.ndarray) -> Comparison:
    """Compare one output of onnxruntime (``got``) with the reference (``ref``). For ``boxes``,
    ``got`` and ``ref`` are (boxes, scores, labels) tuples; ``grouped`` outputs are judged there."""
    if spec.kind == "boxes":
        return compare_boxes(spec, got, ref)
    if spec.kind == "grouped":
        return Comparison(spec.name, spec.kind, True, reason="compared with the boxes")
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
    if spec.angle_period > 0 and got.ndim:
        # e.g. a heading whose direction bin is a near-tie: equal modulo the bin period
        d = diff.reshape(got.shape)[..., spec.angle_column]
        diff.reshape(got.shape)[..., spec.angle_column] = np.abs(
            (d + spec.angle_period / 2) % spec.angle_period - spec.angle_period / 2)
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
    runtime: str = "onnxruntime"

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
        ious = [r["min_iou"] for r in rows if r.get("min_iou") is not None]
        out[spec.name] = {
            "kind": spec.kind,
            "passed": all(r["passed"] for r in rows),
            "max_abs": max((r["max_abs"] for r in rows), default=0.0),
            "max_rel": max((r["max_rel"] for r in rows), default=0.0),
            "p99_abs": max((r["p99_abs"] for r in rows), default=0.0),
            "min_cosine": min(cos) if cos else None,
            "min_iou": min(ious) if ious else None,
            "mismatches": sum(r["mismatches"] for r in rows),
            "tolerance": ({"min_cosine": spec.min_cosine} if spec.kind == "descriptor" else
                          {"min_iou": spec.min_iou, "max_score_diff": spec.max_score_diff} if spec.kind == "boxes" else
                          "with " + next((o.name for o in outputs if spec.name in o.group), "?")
                          if spec.kind == "grouped" else
                          {"atol": spec.atol, "rtol": spec.rtol} if spec.kind == "dense" else
                          "reported only" if spec.kind == "info" else "exact"),
            "failed_cases": [c["case"] for c, r in zip(cases, rows) if not r["passed"]],
        }
        if spec.kind == "boxes" and spec.min_recall is not None:
            ref_n = sum(r["reference"] for r in rows)
            recall = sum(r["matched"] for r in rows) / ref_n if ref_n else 1.0
            bands = {f"{b:g}": [sum(r["by_score"].get(f"{b:g}", [0, 0])[i] for r in rows) for i in (0, 1)]
                     for b in RECALL_SCORE_BANDS}
            out[spec.name].update(recall=recall, passed=recall >= spec.min_recall, recall_by_score=bands,
                                  tolerance={"min_recall": spec.min_recall, "min_iou": spec.min_iou},
                                  failed_cases=[] if recall >= spec.min_recall else ["the case set"])
        e2e = [r["end_to_end"] for r in rows if "end_to_end" in r]
        if e2e:
            out[spec.name]["end_to_end"] = {"unmatched": sum(e["unmatched"] for e in e2e),
                                            "boxes": sum(e["boxes"] for e in e2e),
                                            "reference_boxes": sum(e["reference_boxes"] for e in e2e)}
    return out


# An int8 graph must still retrieve the same case as the reference for this share of the cases.
# The parity cases are distinct scenes, so this is a weak retrieval test; accept a quantised
# place-recognition model with `radaredge eval` on a benchmark of nearby places as well.
QUANTIZED_MIN_TOP1 = 0.98


def run_parity(card, onnx_path, model, cases_n: int = 20, seed: int = 0, debug_onnx=None, progress=None,
               quantized: bool = False, spec=None, runtime: str = "onnxruntime") -> ParityReport:
    """Run ``onnx_path`` in ``runtime`` (onnxruntime, or OpenVINO's CPU plugin) and the
    reference formulation on the same cases.

    ``quantized`` applies the int8 budget of each output (:meth:`OutputSpec.quantized`) and
    requires retrieval top-1 agreement >= QUANTIZED_MIN_TOP1 instead of 100 %. ``debug_onnx``
    (a path, or a callable returning one, called only on failure) names the debug export used
    to locate the first diverging intermediate. ``spec`` (default: the card's) is the part's
    ModelSpec when ``onnx_path`` is one graph of a bundle.
    """
    from .registry import model_spec

    spec = spec or model_spec(card)
    run_graph = graph_runner(onnx_path, runtime)
    report = ParityReport(card.name, str(onnx_path), quantized=quantized,
                          min_retrieval_top1=QUANTIZED_MIN_TOP1 if quantized else 1.0, runtime=runtime)
    outputs = [o.quantized() for o in spec.outputs] if quantized else list(spec.outputs)
    desc_specs = [o for o in outputs if o.kind == "descriptor"]
    got_desc, ref_desc = [], []
    cases = spec.make_cases(card, cases_n, seed)
    for name, feeds in (progress(cases) if progress else cases):
        got = run_graph(feeds)
        with torch.no_grad():
            ref = {k: v.detach().numpy() for k, v in spec.run_reference(model, feeds).items()}
        comps = {}
        for o in outputs:
            if o.kind == "boxes" and spec.postprocess_reference is not None and o.min_recall is None:
                with torch.no_grad():
                    post = {k: v.detach().numpy() for k, v in spec.postprocess_reference(model, got).items()}
                comps[o.name] = asdict(compare(o, *_operands(o, got, post)))
                e2e = compare(o, *_operands(o, got, ref))
                comps[o.name]["end_to_end"] = {"unmatched": e2e.mismatches, "boxes": int(len(got[o.name])),
                                               "reference_boxes": int(len(ref[o.name])), "max_score_diff": e2e.max_abs}
            else:
                comps[o.name] = asdict(compare(o, *_operands(o, got, ref)))
        report.cases.append({"case": name, "outputs": comps})
        if desc_specs:
            got_desc.append(np.ravel(got[desc_specs[0].name]))     # [D], or [1, D] from a batched graph
            ref_desc.append(np.ravel(ref[desc_specs[0].name]))
    report.summary = summarise(outputs, report.cases)
    if desc_specs:
        report.retrieval_top1 = retrieval_top1_agreement(np.stack(got_desc), np.stack(ref_desc))
    if not report.passed and debug_onnx is not None:
        path = debug_onnx() if callable(debug_onnx) else debug_onnx
        report.divergence = locate_divergence(card, spec, model, path, report, cases, runtime)
    return report


def _operands(spec: OutputSpec, got: dict, ref: dict):
    """What :func:`compare` takes for ``spec``: the output itself, or (boxes, scores, labels)."""
    if spec.kind == "boxes":
        names = (spec.name, *spec.group)
        return tuple(got[n] for n in names), tuple(ref[n] for n in names)
    return got[spec.name], ref[spec.name]


def locate_divergence(card, spec, model, debug_onnx, report: ParityReport, cases,
                      runtime: str = "onnxruntime") -> dict | None:
    """Re-run the first failing case through the debug export (in ``runtime``) and the traced reference."""
    failing = next((c["case"] for c in report.cases if not all(o["passed"] for o in c["outputs"].values())), None)
    feeds = dict(cases)[failing] if failing else cases[0][1]
    from .export import DEBUG_PREFIX
    got = {k[len(DEBUG_PREFIX):]: v for k, v in graph_runner(debug_onnx, runtime)(feeds).items()
           if k.startswith(DEBUG_PREFIX)}
    ref_trace: dict = {}
    with torch.no_grad():
        spec.run_reference(model, feeds, ref_trace)
    ref_trace = {k: v.detach().numpy() for k, v in ref_trace.items()}
    hit = first_divergence(spec.trace_order(card), got, ref_trace)
    return {"case": failing, "tensor": hit[0], "max_abs": hit[1]} if hit else {"case": failing, "tensor": None}
