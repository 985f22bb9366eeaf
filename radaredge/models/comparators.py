"""Parity comparators: one class per kind of graph output, each owning how it is compared.

A comparator judges one output (or, for detections, the boxes/scores/labels triple) of the
exported graph against the reference formulation:

- :meth:`Comparator.compare` one case -> :class:`CaseResult`;
- :meth:`Comparator.summarise` the case set -> :class:`OutputSummary` (worst case, and verdicts
  that only exist over a set: retrieval top-1 agreement, matched-box recall);
- :meth:`Comparator.quantized` the budget an int8 graph is held to;
- :meth:`Comparator.notes` extra report lines.

Results are typed and their truth value is the verdict. Kinds: :class:`Dense` (max abs / max rel
/ p99 against atol + rtol), :class:`Descriptor` (cosine, and retrieval top-1 agreement over the
case set), :class:`Exact` (bit-equal labels, flags, masks), :class:`Info` (statistics reported,
no verdict), :class:`Boxes` (detections matched one to one by rotated BEV IoU).
"""

from __future__ import annotations

import abc
import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Mapping, Sequence

import numpy as np

from ..ops.box_iou import bev_iou_matrix_reference
from ..ops.nms import NmsConfig, describe_tie, near_ties

Outputs = Mapping[str, np.ndarray]

# Reference-score floors at which the int8 matched-box recall is also reported (not judged): a
# detector's low-score boxes sit next to the score threshold and to near-tie neighbours in the
# NMS, so int8 noise re-decides them first; these bands show whether confident boxes survive.
RECALL_SCORE_BANDS = (0.3, 0.5)

# An int8 graph must still retrieve the same case as the reference for this share of the cases.
# The parity cases are distinct scenes, so this is a weak retrieval test; accept a quantised
# place-recognition model with `radaredge eval` on a benchmark of nearby places as well.
QUANTIZED_MIN_TOP1 = 0.98


@dataclass
class CaseResult:
    """Statistics of one output on one case; true when it passed."""

    name: str
    kind: str
    passed: bool
    max_abs: float = 0.0
    max_rel: float = 0.0
    p99_abs: float = 0.0
    cosine: float | None = None
    min_iou: float | None = None
    mismatches: int = 0
    matched: int = 0  # boxes: reference boxes matched
    reference: int = 0  # boxes: reference boxes
    by_score: dict = field(default_factory=dict)  # int8 boxes: {band: [matched, reference boxes scored >= band]}
    end_to_end: dict | None = None  # boxes judged against the reference NMS of the graph's own anchors
    reason: str = ""

    def __bool__(self) -> bool:
        return self.passed


@dataclass
class OutputSummary:
    """The worst case of one output over the case set, and the set's verdict; true when it passed."""

    name: str
    kind: str
    passed: bool
    tolerance: dict | str
    max_abs: float = 0.0
    max_rel: float = 0.0
    p99_abs: float = 0.0
    min_cosine: float | None = None
    min_iou: float | None = None
    mismatches: int = 0
    failed_cases: list = field(default_factory=list)
    retrieval_top1: float | None = None  # descriptors: share of cases whose nearest reference is their own
    recall: float | None = None  # boxes judged by recall: matched share of reference boxes
    recall_by_score: dict | None = None
    end_to_end: dict | None = None

    def __bool__(self) -> bool:
        return self.passed

    def to_dict(self) -> dict:
        return asdict(self)


def _worst(name: str, kind: str, tolerance, results: Sequence[CaseResult], case_names: Sequence[str]) -> OutputSummary:
    cos = [r.cosine for r in results if r.cosine is not None]
    ious = [r.min_iou for r in results if r.min_iou is not None]
    return OutputSummary(
        name,
        kind,
        all(results),
        tolerance,
        max_abs=max((r.max_abs for r in results), default=0.0),
        max_rel=max((r.max_rel for r in results), default=0.0),
        p99_abs=max((r.p99_abs for r in results), default=0.0),
        min_cosine=min(cos) if cos else None,
        min_iou=min(ious) if ious else None,
        mismatches=sum(r.mismatches for r in results),
        failed_cases=[c for c, r in zip(case_names, results) if not r],
    )


@dataclass(frozen=True)
class Comparator(abc.ABC):
    """Base: compares output ``name``; subclasses set ``kind`` and the rules. ``conditioned``:
    the output comes after a discrete decision (NMS, proposals, keypoint sampling) and is judged
    against the reference run on the graph's own inputs to that stage (``post``), when the
    parity run supplies it."""

    name: str
    unit: str = ""
    conditioned: bool = False

    kind = "?"

    @property
    def uses_post(self) -> bool:
        """True when :meth:`compare` judges against the reference post-processing of the graph's
        own outputs (``post``) where the graph has one."""
        return self.conditioned

    def against(self, ref: Outputs, post: Outputs | None) -> Outputs:
        """What this output is judged against: ``post`` for a conditioned output that it holds."""
        return post if self.conditioned and post is not None and self.name in post else ref

    @property
    def outputs(self) -> tuple[str, ...]:
        """The graph outputs this comparator judges."""
        return (self.name,)

    @abc.abstractmethod
    def compare(self, got: Outputs, ref: Outputs, post: Outputs | None = None) -> CaseResult:
        """One case: the graph's outputs ``got`` against the reference's ``ref`` (``post``: the
        reference post-processing of ``got``, where the graph has one)."""

    @abc.abstractmethod
    def tolerance(self) -> dict | str:
        """What the verdict is held to, as reported."""

    def summarise(
        self,
        results: Sequence[CaseResult],
        case_names: Sequence[str],
        got: Sequence[Outputs] = (),
        ref: Sequence[Outputs] = (),
    ) -> OutputSummary:
        """Worst case per statistic over the set; ``got``/``ref`` are every case's outputs."""
        return _worst(self.name, self.kind, self.tolerance(), results, case_names)

    def quantized(self) -> "Comparator":
        """The budget this output is held to when the graph is int8-quantised."""
        return self

    def notes(self, summary: OutputSummary) -> list[str]:
        """Extra report lines under the output's row."""
        return []


def _operands(comp: "Comparator", got: Outputs, ref: Outputs):
    """(graph array, reference array, None), or (None, None, a failed result) when the shapes differ."""
    g, r = np.asarray(got[comp.name]), np.asarray(ref[comp.name])
    if g.shape != r.shape:
        return None, None, CaseResult(comp.name, comp.kind, False, reason=f"shape {g.shape} != reference {r.shape}")
    return g, r, None


def _dense_stats(
    c: CaseResult,
    got: np.ndarray,
    ref: np.ndarray,
    atol: float,
    rtol: float,
    angle_column: int = -1,
    angle_period: float = 0.0,
) -> np.ndarray | None:
    """Fill max abs / max rel / p99 and the atol + rtol mismatch count; the flat float64 pair, or
    None (and ``c`` failed) when a value is not finite."""
    g, r = got.astype(np.float64).ravel(), ref.astype(np.float64).ravel()
    if not (np.isfinite(g).all() and np.isfinite(r).all()):
        c.passed, c.reason = False, "non-finite values"
        return None
    diff = np.abs(g - r)
    if angle_period > 0 and got.ndim:
        # e.g. a heading whose direction bin is a near-tie: equal modulo the bin period
        d = diff.reshape(got.shape)[..., angle_column]
        diff.reshape(got.shape)[..., angle_column] = np.abs((d + angle_period / 2) % angle_period - angle_period / 2)
    if diff.size:
        c.max_abs = float(diff.max())
        c.max_rel = float((diff / np.maximum(np.abs(r), 1e-12)).max())
        c.p99_abs = float(np.percentile(diff, 99))
    c.mismatches = int((diff > atol + rtol * np.abs(r)).sum())
    return np.stack([g, r])


@dataclass(frozen=True)
class Dense(Comparator):
    """A float tensor: every element within ``atol + rtol * |reference|``. ``angle_column`` of the
    last axis is compared modulo ``angle_period`` when that is > 0. ``quantized_info``: an int8
    graph only reports it (network outputs whose int8 error is judged downstream)."""

    atol: float = 1e-4
    rtol: float = 1e-3
    quantized_info: bool = False
    angle_column: int = -1
    angle_period: float = 0.0

    kind = "dense"

    def compare(self, got, ref, post=None):
        g, r, bad = _operands(self, got, self.against(ref, post))
        if bad:
            return bad
        c = CaseResult(self.name, self.kind, True)
        pair = _dense_stats(c, g, r, self.atol, self.rtol, self.angle_column, self.angle_period)
        if pair is not None:
            self._judge(c, *pair)
        return c

    def _judge(self, c: CaseResult, got: np.ndarray, ref: np.ndarray) -> None:
        """The verdict of one case from its statistics and the flat float64 values."""
        c.passed = c.mismatches == 0
        if not c.passed:
            c.reason = (
                f"{c.mismatches} element(s) beyond atol {self.atol:g} + rtol {self.rtol:g} (max abs {c.max_abs:.3g})"
            )

    def tolerance(self):
        return {"atol": self.atol, "rtol": self.rtol}

    def quantized(self):
        return Info(**{f.name: getattr(self, f.name) for f in fields(self)}) if self.quantized_info else self


@dataclass(frozen=True)
class Info(Dense):
    """A :class:`Dense` output whose statistics are reported, with no verdict."""

    kind = "info"

    def _judge(self, c, got, ref):
        """Reported, not judged (shape and finiteness still are)."""

    def tolerance(self):
        return "reported only"

    def quantized(self):
        return self


@dataclass(frozen=True)
class Descriptor(Dense):
    """An embedding: cosine >= ``min_cosine`` per case, and over the case set each case's nearest
    reference descriptor (L2) must be its own for ``min_top1`` of the cases; the element-wise
    statistics of :class:`Dense` are reported beside. int8: ``quantized_min_cosine`` and
    :data:`QUANTIZED_MIN_TOP1`."""

    min_cosine: float = 0.9999
    min_top1: float = 1.0
    quantized_min_cosine: float = 0.99

    kind = "descriptor"

    def _judge(self, c, got, ref):
        denom = np.linalg.norm(got) * np.linalg.norm(ref)
        c.cosine = float(got @ ref / denom) if denom > 0 else float(np.array_equal(got, ref))
        c.passed = c.cosine >= self.min_cosine
        if not c.passed:
            c.reason = f"cosine {c.cosine:.6f} < {self.min_cosine}"

    def tolerance(self):
        return {"min_cosine": self.min_cosine, "min_top1": self.min_top1}

    def summarise(self, results, case_names, got=(), ref=()):
        s = super().summarise(results, case_names)
        if got:
            s.retrieval_top1 = retrieval_top1_agreement(
                np.stack([np.ravel(o[self.name]) for o in got]), np.stack([np.ravel(o[self.name]) for o in ref])
            )
            if s.retrieval_top1 < self.min_top1:
                s.passed = False
        return s

    def quantized(self):
        return replace(self, min_cosine=self.quantized_min_cosine, min_top1=QUANTIZED_MIN_TOP1)

    def notes(self, summary):
        if summary.retrieval_top1 is None:
            return []
        return [
            f"retrieval top-1 agreement over the case set: {summary.retrieval_top1 * 100:.1f}% "
            f"(needs >= {self.min_top1 * 100:.0f}%)"
        ]


@dataclass(frozen=True)
class Exact(Comparator):
    """Labels, flags, counts, masks: bit-equal."""

    kind = "exact"

    def compare(self, got, ref, post=None):
        g, r, bad = _operands(self, got, self.against(ref, post))
        if bad:
            return bad
        mism = int((g != r).sum())
        return CaseResult(
            self.name, self.kind, mism == 0, mismatches=mism, reason="" if mism == 0 else f"{mism} element(s) differ"
        )

    def tolerance(self):
        return "exact"


def retrieval_top1_agreement(got: np.ndarray, ref: np.ndarray) -> float:
    """Fraction of queries (graph descriptors [Q, D]) whose nearest reference descriptor (L2) is
    their own case; a reference exactly as near as their own (a case set that holds the same
    input twice) ties, and a tie counts as agreement."""
    if len(got) < 2:
        return 1.0
    d = ((got[:, None, :] - ref[None, :, :]) ** 2).sum(-1)
    return float((np.diagonal(d) <= d.min(1)).mean())


def match_boxes(got_boxes, got_labels, ref_boxes, ref_labels, min_iou: float):
    """Greedy one-to-one matching of detections [M, 7] by rotated BEV IoU (best pairs first, same
    label, IoU >= min_iou). Returns (pairs [(i_got, j_ref, iou)], unmatched got, unmatched ref)."""
    iou = (
        bev_iou_matrix_reference(got_boxes, ref_boxes)
        if len(got_boxes) and len(ref_boxes)
        else np.zeros((len(got_boxes), len(ref_boxes)))
    )
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
    return (
        pairs,
        [i for i in range(len(got_boxes)) if i not in used_g],
        [j for j in range(len(ref_boxes)) if j not in used_r],
    )


@dataclass(frozen=True)
class Boxes(Comparator):
    """Detections: boxes [M, 7] (x, y, z, dx, dy, dz, heading; m, rad) with their ``scores`` and
    ``labels`` outputs, matched one to one with the reference's by rotated BEV IoU >= ``min_iou``
    and the same label; every box matched and scores within ``max_score_diff``.

    With ``min_recall`` set (the int8 budget: ``quantized_min_recall`` at IoU
    ``quantized_min_iou``), the verdict is instead the share of reference boxes matched over the
    whole case set, reported also per reference-score band (:data:`RECALL_SCORE_BANDS`).

    When the parity run supplies ``post`` (the reference post-processing applied to the graph's
    own dense outputs), boxes are judged against it, so a score or IoU within float noise of a
    threshold cannot flip the verdict; the end-to-end match against the full reference is
    reported beside it.
    """

    scores: str = "scores"
    labels: str = "labels"
    min_iou: float = 0.99
    max_score_diff: float = 1e-4
    min_recall: float | None = None
    quantized_min_recall: float = 0.95
    quantized_min_iou: float = 0.5

    kind = "boxes"

    @property
    def outputs(self):
        return (self.name, self.scores, self.labels)

    @property
    def uses_post(self):
        return self.min_recall is None

    def _match(self, got: Outputs, ref: Outputs) -> CaseResult:
        gb, gs, gl = (np.asarray(got[n]) for n in self.outputs)
        rb, rs, rl = (np.asarray(ref[n]) for n in self.outputs)
        if not (np.isfinite(gb).all() and np.isfinite(gs).all()):
            return CaseResult(self.name, self.kind, False, reason="non-finite boxes or scores")
        pairs, lone_g, lone_r = match_boxes(gb, gl, rb, rl, self.min_iou)
        c = CaseResult(
            self.name, self.kind, True, mismatches=len(lone_g) + len(lone_r), matched=len(pairs), reference=len(rb)
        )
        if pairs:
            c.max_abs = max(abs(float(gs[i]) - float(rs[j])) for i, j, _ in pairs)
            c.min_iou = min(iou for _, _, iou in pairs)
            c.max_rel = max(float(np.abs(gb[i] - rb[j]).max()) for i, j, _ in pairs)
        if self.min_recall is not None:  # judged over the case set (summarise)
            found = np.zeros(len(rb), bool)
            found[[j for _, j, _ in pairs]] = True
            c.by_score = {f"{b:g}": [int(found[rs >= b].sum()), int((rs >= b).sum())] for b in RECALL_SCORE_BANDS}
            return c
        reasons = []
        if lone_g or lone_r:
            reasons.append(
                f"{len(gb)} boxes vs {len(rb)} in the reference; {len(lone_g) + len(lone_r)} unmatched "
                f"at IoU >= {self.min_iou}"
            )
        if c.max_abs > self.max_score_diff:
            reasons.append(f"score diff {c.max_abs:.3g} > {self.max_score_diff:g}")
        c.passed = not reasons
        c.reason = "; ".join(reasons)
        return c

    def compare(self, got, ref, post=None):
        if post is None or self.min_recall is not None:
            return self._match(got, ref)
        c = self._match(got, post)
        e2e = self._match(got, ref)
        c.end_to_end = {
            "unmatched": e2e.mismatches,
            "boxes": int(len(got[self.name])),
            "reference_boxes": int(len(ref[self.name])),
            "max_score_diff": e2e.max_abs,
        }
        return c

    def tolerance(self):
        if self.min_recall is not None:
            return {"min_recall": self.min_recall, "min_iou": self.min_iou}
        return {"min_iou": self.min_iou, "max_score_diff": self.max_score_diff}

    def summarise(self, results, case_names, got=(), ref=()):
        s = super().summarise(results, case_names)
        if self.min_recall is not None:
            ref_n = sum(r.reference for r in results)
            s.recall = sum(r.matched for r in results) / ref_n if ref_n else 1.0
            s.recall_by_score = {
                f"{b:g}": [sum(r.by_score.get(f"{b:g}", [0, 0])[i] for r in results) for i in (0, 1)]
                for b in RECALL_SCORE_BANDS
            }
            s.passed = s.recall >= self.min_recall
            s.failed_cases = [] if s.passed else ["the case set"]
        e2e = [r.end_to_end for r in results if r.end_to_end is not None]
        if e2e:
            s.end_to_end = {k: sum(e[k] for e in e2e) for k in ("unmatched", "boxes", "reference_boxes")}
        return s

    def quantized(self):
        return replace(
            self, min_iou=self.quantized_min_iou, min_recall=self.quantized_min_recall, max_score_diff=float("inf")
        )

    def notes(self, s):
        if s.recall is not None:
            lines = [
                f"boxes: end to end vs the full reference; matched-box recall {s.recall * 100:.1f} % "
                f"(needs >= {self.min_recall * 100:.0f} % at IoU >= {self.min_iou}); "
                f"max abs = score diff, max rel = box coordinate diff"
            ]
            bands = "; ".join(
                f">= {b}: {100 * m / n:.1f} % of {n}" if n else f">= {b}: no boxes"
                for b, (m, n) in (s.recall_by_score or {}).items()
            )
            if bands:
                lines.append(f"recall by reference score (reported, not judged): {bands}")
            return lines
        against = (
            "the graph's NMS vs the reference NMS on the graph's anchor outputs" if s.end_to_end else "vs the reference"
        )
        lines = [f"boxes: {against}; max abs = score diff, max rel = box coordinate diff, {s.mismatches} unmatched"]
        e = s.end_to_end
        if e:
            lines.append(
                f"end to end vs the full reference: {e['boxes']} vs {e['reference_boxes']} boxes, "
                f"{e['unmatched']} unmatched"
                + (
                    " (reported, not judged: the NMS is judged on the graph's own inputs above; an "
                    "earlier decision within float noise changes its input)"
                    if e["unmatched"]
                    else ""
                )
            )
        return lines


@dataclass(frozen=True)
class Proposals(Comparator):
    """A second stage's proposals: rois [R, 7] (m, rad) with ``labels`` [R] and the ``valid`` slot
    mask [R], as a proposal layer selects them from per-anchor class logits and boxes by
    class-agnostic NMS (``iou_thresh``, ``pre_max``, ``post_max``).

    Judged where the decision is taken: the graph's rois equal (``max_box_diff``, same labels,
    same valid slots) the reference proposal layer run on the graph's own ``logits`` and
    ``anchor_boxes`` (``post``). End to end, the valid rois are matched one to one with the full
    reference's by rotated BEV IoU >= ``min_iou`` and label; rois left unmatched pass only when
    the reference's proposal NMS has a decision within float noise (:func:`radaredge.ops.nms.near_ties`,
    score noise ``score_tol`` = (atol, rtol) of the logits, IoU noise ``iou_tol``), which the
    report names. The second stage's ``rcnn_scores`` of matched rois are compared end to end too
    (reported). An int8 graph reports the end-to-end match without judging it.
    """

    labels: str = "roi_labels"
    valid: str = "roi_valid"
    logits: str = "anchor_logits"
    anchor_boxes: str = "anchor_boxes"
    rcnn_scores: str = "rcnn_scores"
    iou_thresh: float = 0.7
    pre_max: int = 1024
    post_max: int = 100
    min_iou: float = 0.99
    max_box_diff: float = 1e-6
    score_tol: tuple = (1e-4, 1e-3)
    iou_tol: float = 1e-3
    judge_end_to_end: bool = True

    kind = "proposals"

    @property
    def outputs(self):
        return (self.name, self.labels, self.valid)

    @property
    def uses_post(self):
        return True

    def _conditioned(self, got: Outputs, post: Outputs, c: CaseResult) -> list[str]:
        gv, pv = np.asarray(got[self.valid], bool), np.asarray(post[self.valid], bool)
        if gv.shape != pv.shape or not np.array_equal(gv, pv):
            return [
                f"{int(gv.sum())} valid rois vs {int(pv.sum())} from the reference proposal layer on the "
                f"graph's anchors"
            ]
        diff = np.abs(np.asarray(got[self.name], np.float64)[gv] - np.asarray(post[self.name], np.float64)[gv])
        c.max_abs = float(diff.max()) if diff.size else 0.0
        wrong = int((np.asarray(got[self.labels])[gv] != np.asarray(post[self.labels])[gv]).sum())
        c.mismatches = wrong + int((diff > self.max_box_diff).any(1).sum()) if diff.size else wrong
        return (
            [
                f"{c.mismatches} roi(s) differ from the reference proposal layer on the graph's anchors "
                f"(max box diff {c.max_abs:.3g})"
            ]
            if c.mismatches
            else []
        )

    def _end_to_end(self, got: Outputs, ref: Outputs) -> dict:
        gv, rv = np.asarray(got[self.valid], bool), np.asarray(ref[self.valid], bool)
        gi, ri = np.flatnonzero(gv), np.flatnonzero(rv)
        pairs, lone_g, lone_r = match_boxes(
            np.asarray(got[self.name])[gv],
            np.asarray(got[self.labels])[gv],
            np.asarray(ref[self.name])[rv],
            np.asarray(ref[self.labels])[rv],
            self.min_iou,
        )
        e = {"rois": len(gi), "reference_rois": len(ri), "unmatched": len(lone_g) + len(lone_r), "near_ties": []}
        if self.rcnn_scores in got and self.rcnn_scores in ref and pairs:
            gs, rs = np.asarray(got[self.rcnn_scores]), np.asarray(ref[self.rcnn_scores])
            e["rcnn_score_diff"] = max(abs(float(gs[gi[i]]) - float(rs[ri[j]])) for i, j, _ in pairs)
        if e["unmatched"]:
            config = NmsConfig(
                score_thresh=-math.inf, iou_thresh=self.iou_thresh, pre_max=self.pre_max, post_max=self.post_max
            )
            e["near_ties"] = near_ties(
                np.asarray(ref[self.anchor_boxes]),
                np.asarray(ref[self.logits]).max(-1),
                config,
                tuple(self.score_tol),
                self.iou_tol,
            )
        return e

    def compare(self, got, ref, post=None):
        c = CaseResult(self.name, self.kind, True)
        reasons = self._conditioned(got, post, c) if post is not None else []
        e = self._end_to_end(got, ref)
        c.end_to_end, c.matched, c.reference = e, e["reference_rois"] - e["unmatched"], e["reference_rois"]
        if self.judge_end_to_end and e["unmatched"] and not e["near_ties"]:
            reasons.append(
                f"{e['unmatched']} roi(s) unmatched end to end, and no decision of the reference's "
                f"proposal NMS is within float noise"
            )
        c.passed, c.reason = not reasons, "; ".join(reasons)
        return c

    def tolerance(self):
        return {
            "max_box_diff": self.max_box_diff,
            "end_to_end": "matched, or a near tie" if self.judge_end_to_end else "reported",
            "min_iou": self.min_iou,
        }

    def summarise(self, results, case_names, got=(), ref=()):
        s = super().summarise(results, case_names)
        ties = [{"case": name, **t} for name, r in zip(case_names, results) for t in r.end_to_end["near_ties"]]
        s.end_to_end = {
            "unmatched": sum(r.end_to_end["unmatched"] for r in results),
            "rois": sum(r.end_to_end["rois"] for r in results),
            "reference_rois": sum(r.end_to_end["reference_rois"] for r in results),
            "cases_with_unmatched": [n for n, r in zip(case_names, results) if r.end_to_end["unmatched"]],
            "near_ties": ties,
            "rcnn_score_diff": max((r.end_to_end.get("rcnn_score_diff", 0.0) for r in results), default=0.0),
        }
        return s

    def quantized(self):
        return replace(self, judge_end_to_end=False)

    def notes(self, s):
        lines = [
            f"rois: the graph's proposal layer vs the reference proposal layer on the graph's {self.logits} "
            f"and {self.anchor_boxes}; max abs = box diff, {s.mismatches} differing"
        ]
        e = s.end_to_end or {}
        if e:
            lines.append(
                f"end to end vs the full reference: {e['rois']} vs {e['reference_rois']} rois, "
                f"{e['unmatched']} unmatched; {self.rcnn_scores} of matched rois within "
                f"{e['rcnn_score_diff']:.3g}"
            )
            if e["cases_with_unmatched"]:
                lines.append(
                    f"near ties in the reference's proposal NMS (score noise atol {self.score_tol[0]:g} + "
                    f"rtol {self.score_tol[1]:g}, IoU noise {self.iou_tol:g}), in "
                    f"{', '.join(e['cases_with_unmatched'])}:"
                )
                lines += [f"  {t['case']}: {describe_tie(t)}" for t in e["near_ties"][:6]]
                if not e["near_ties"]:
                    lines.append("  none")
        return lines
