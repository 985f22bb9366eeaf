"""int8 judged by the task, and the sensitivity search for the layers to keep in fp32.

A model's int8 copy is judged by the number its users judge the model by, on labelled data
(never the split the figures are reported on): 3D AP per class on a detection set's split, or
place-recognition Recall@1 over query drives against database drives. The budget is in those
points (default 1.0): the copy is within it when no metric drops by more than the budget.

The search (``radaredge quantize --search``) finds a small ``quantization.keep_fp32`` that meets
the budget, starting from the card's own list or, with ``--keep-fp32 none``, from every layer
quantised:

1. Groups: the modules that hold the quantised layers (Conv / MatMul / Gemm nodes, by the
   exporter's module scopes), top-level modules first, and a module that holds more than a third
   of those layers split into its children (MAFF-Net's BEV backbone into its blocks), again
   while that holds.
2. Forward selection: each round scores, for every group not yet kept, the int8 copy with that
   group added to the kept list (the first round, on top of the starting list alone, is each
   group's sensitivity), and keeps the group whose copy has the smallest worst-metric loss; the
   rounds go on until the copy is within the budget or every group is kept.

A group's effect depends on the others (a layer whose error another layer's drowns recovers
nothing alone, yet may be the one that brings the copy within budget once that other layer is
fp32), so each round scores the groups again instead of ranking them once by sensitivity
(docs/quantization.md shows both on trained weights).

Every copy scored is recorded in the report; the int8 graph written last is the chosen one, and its
``radaredge.quantization`` metadata names the kept modules.
"""

from __future__ import annotations

import copy
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import onnx

from ..artifacts import INT8, copy_kind, copy_path
from ..cards import ModelCard, parse_card
from ..errors import ConfigError
from ..eval.detection import ORT, ORT_INT8, evaluate_detection
from ..eval.places import ONNX
from ..eval.places import evaluate as evaluate_places
from ..eval.tasks import EvalInputs
from ..exporting.quantize import QUANTIZED_OPS, calibration_method_of, keep_fp32_patterns, quantize_int8
from ..node_scopes import module_names
from ..registry import model_spec

DEFAULT_BUDGET = 1.0  # task-metric points (AP, Recall@1 in %) int8 may lose per metric
SPLIT_SHARE = 1 / 3  # a group holding more than this share of the quantised layers is split


# A judge scores one graph: path -> {metric name: value in points}.
Judge = Callable[[Path], dict]


def _scopes(model: onnx.ModelProto) -> list[str]:
    """The innermost module name of every quantisable node (Conv / MatMul / Gemm) that has one."""
    out = []
    for node in model.graph.node:
        names = module_names(node) if node.op_type in QUANTIZED_OPS else []
        if names:
            out.append(names[-1])
    return out


def layer_groups(model: onnx.ModelProto, split_share: float = SPLIT_SHARE) -> list[str]:
    """Module-name prefixes partitioning the quantisable layers of an exported fp32 graph (module
    docstring, step 1), in graph order. A prefix holding more than ``split_share`` of the layers
    is replaced by the groups of its children, when that splits it."""
    scopes = _scopes(model)
    if not scopes:
        return []

    def split(prefix: str, depth: int) -> list[str]:
        members = [s for s in scopes if s == prefix or s.startswith(prefix + ".")] if prefix else scopes
        if prefix and (len(members) <= split_share * len(scopes) or prefix in members):
            return [prefix]  # small enough, or a layer sits in the module itself
        children = dict.fromkeys(".".join(s.split(".")[: depth + 1]) for s in members)
        parts = [g for c in children for g in split(c, depth + 1)]
        return parts if len(parts) > 1 or not prefix else [prefix]  # a chain of single children stays whole

    return split("", 0)


def with_keep(card: ModelCard, keep: list[str]) -> ModelCard:
    """``card`` with ``quantization.keep_fp32`` = ``keep``."""
    data = copy.deepcopy(card.data)
    data["quantization"] = dict(data.get("quantization") or {}, keep_fp32=list(keep))
    return parse_card(data, card.path)


def detection_judge(card: ModelCard, inputs: EvalInputs) -> Judge:
    """3D AP per class (entire area) of a graph on ``inputs``' labelled split."""
    inputs.require("3D-detection AP", ("data",), card.name, ("split", "dataset"))

    def judge(graph: Path) -> dict:
        report = evaluate_detection(
            card, graph, inputs.data, inputs.split, reference=False, dataset=inputs.dataset, openvino=False
        )
        backend = ORT_INT8 if copy_kind(graph) == INT8 else ORT
        return {c: float(v["3d"]) for c, v in report.ap[backend]["entire_area"].items()}

    return judge


def places_judge(card: ModelCard, inputs: EvalInputs) -> Judge:
    """Recall@1 (%) of a graph over ``inputs``' query drives against its database drives."""
    inputs.require("place recognition", ("database", "queries"), card.name, ("radius",))

    def judge(graph: Path) -> dict:
        report = evaluate_places(
            card, graph, inputs.database, inputs.queries, radius=inputs.radius, reference=False, baseline=False
        )
        return {"Recall@1": float(report.recall(ONNX, (1,))[1])}

    return judge


# evaluation name (ModelSpec.evaluation) -> fn(card, EvalInputs) -> Judge
JUDGES: dict[str, Callable[[ModelCard, EvalInputs], Judge]] = {
    "detection": detection_judge,
    "place recognition": places_judge,
}


def task_judge(card: ModelCard, inputs: EvalInputs) -> Judge:
    """The judge of the card's task (:data:`JUDGES`); ConfigError for a task it cannot score."""
    evaluation = model_spec(card).evaluation
    if evaluation not in JUDGES:
        raise ConfigError(
            f"{card.name} is evaluated by {evaluation}; radaredge quantize judges int8 by "
            f"{' or '.join(sorted(JUDGES))} (its int8 copy is checked by `radaredge parity-check --quantized`)"
        )
    return JUDGES[evaluation](card, inputs)


@dataclass
class Step:
    """One int8 copy scored: the modules kept in fp32 and each metric's int8 value and loss."""

    keep_fp32: list[str]
    int8: dict
    loss: dict

    @property
    def worst(self) -> float:
        return max(self.loss.values())

    def to_dict(self) -> dict:
        return {"keep_fp32": self.keep_fp32, "int8": self.int8, "loss": self.loss, "worst_loss": self.worst}


@dataclass
class QuantizeReport:
    """What ``radaredge quantize`` measured: the fp32 graph's metrics, the int8 copies scored
    (the starting keep_fp32's first: the card's own, or none; with ``--search`` every round of
    the forward selection, group -> the copy with that group added) and the int8 graph it wrote
    (the last step's ``keep_fp32``). True when that copy is within budget."""

    card: str
    method: str
    budget: float
    data: str
    fp32: dict
    start_step: Step
    rounds: list[dict[str, Step]] = field(default_factory=list)
    steps: list[Step] = field(default_factory=list)
    int8_path: str = ""

    @property
    def sensitivity(self) -> dict[str, Step]:
        """Group -> the copy with only that group kept in fp32 on top of the start (round one)."""
        return self.rounds[0] if self.rounds else {}

    @property
    def chosen(self) -> Step:
        return self.steps[-1] if self.steps else self.start_step

    def __bool__(self) -> bool:
        return self.chosen.worst <= self.budget

    def to_dict(self) -> dict:
        return {
            "card": self.card,
            "method": self.method,
            "budget_points": self.budget,
            "data": self.data,
            "fp32": self.fp32,
            "start_keep_fp32": self.start_step.to_dict(),
            "rounds": [{g: s.to_dict() for g, s in r.items()} for r in self.rounds],
            "steps": [s.to_dict() for s in self.steps],
            "keep_fp32": self.chosen.keep_fp32,
            "within_budget": bool(self),
            "int8": self.int8_path,
        }

    def lines(self) -> list[str]:
        def losses(step: Step) -> str:
            return ", ".join(f"{m} {step.int8[m]:.2f} ({-step.loss[m]:+.2f})" for m in self.fp32)

        out = [
            f"{self.card}: int8 ({self.method} calibration) judged on {self.data}; budget {self.budget:g} point(s)",
            "  fp32: " + ", ".join(f"{m} {v:.2f}" for m, v in self.fp32.items()),
            f"  int8, keep_fp32 {self.start_step.keep_fp32} (the start): {losses(self.start_step)}",
        ]
        for i, (candidates, step) in enumerate(zip(self.rounds, self.steps), 1):
            out.append(f"  round {i}, worst loss with each group added to {step.keep_fp32[:-1]}:")
            out += [f"    {g:<28} {s.worst:+.2f}" for g, s in candidates.items()]
            out.append(f"  int8, keep_fp32 {step.keep_fp32}: {losses(step)}")
        verdict = "within the budget" if self else "NOT within the budget"
        out.append(f"  chosen keep_fp32: {self.chosen.keep_fp32} ({verdict}); int8 graph: {self.int8_path}")
        return out


def _alone(work: Path, name: str) -> Path:
    """A fresh folder of ``work`` holding only a file called ``name``: a judge scores exactly the
    graph it is given (an int8 copy without its fp32 graph, an fp32 graph without an earlier
    int8 copy beside it)."""
    return Path(tempfile.mkdtemp(dir=work)) / name


def _int8_copy(card: ModelCard, fp32: Path, keep: list[str], method: str | None, work: Path) -> Path:
    """An int8 copy of ``fp32`` with ``keep`` in fp32, alone in a folder of ``work``; its path."""
    out = _alone(work, copy_path(Path(fp32.name), INT8).name)
    quantize_int8(with_keep(card, keep), fp32, out, method=method)
    return out


def quantize_judged(
    card: ModelCard,
    fp32: Path,
    inputs: EvalInputs,
    method: str | None = None,
    budget: float = DEFAULT_BUDGET,
    search: bool = False,
    log: Callable[[str], None] = lambda line: None,
    keep: list[str] | None = None,
) -> QuantizeReport:
    """Write the int8 copy of the fp32 graph ``fp32`` beside it, judged by the task on
    ``inputs``: with ``keep`` in fp32 (default the card's ``keep_fp32``), or with ``search`` the
    list the module docstring's search chooses, starting from ``keep``."""
    judge = task_judge(card, inputs)
    own = keep_fp32_patterns(card if keep is None else with_keep(card, keep))
    with tempfile.TemporaryDirectory(prefix="radaredge-quantize-") as tmp:
        work = Path(tmp)
        log(f"scoring the fp32 graph on {_described(inputs)} ...")
        alone = _alone(work, fp32.name)
        shutil.copyfile(fp32, alone)
        fp32_scores = judge(alone)

        def step(keep: list[str]) -> tuple[Step, Path]:
            path = _int8_copy(card, fp32, keep, method, work)
            scores = judge(path)
            s = Step(list(keep), scores, {m: fp32_scores[m] - scores[m] for m in fp32_scores})
            log(f"keep_fp32 {keep}: worst loss {s.worst:+.2f}")
            return s, path

        start_step, start_path = step(own)
        report = QuantizeReport(
            card.name,
            calibration_method_of(card, method),
            budget,
            _described(inputs),
            fp32_scores,
            start_step,
        )
        chosen_path = start_path
        if search:
            groups = [g for g in layer_groups(onnx.load(str(fp32), load_external_data=False)) if g not in own]
            keep, current = list(own), start_step
            while groups and current.worst > budget:
                scored = {g: step(keep + [g]) for g in groups}
                report.rounds.append({g: s for g, (s, _) in scored.items()})
                best = min(groups, key=lambda g: scored[g][0].worst)  # ties: the earlier group in the graph
                current, chosen_path = scored[best]
                report.steps.append(current)
                keep.append(best)
                groups.remove(best)
        out = copy_path(fp32, INT8)
        shutil.copyfile(chosen_path, out)
    report.int8_path = str(out)
    return report


def _described(inputs: EvalInputs) -> str:
    if inputs.data is not None:
        return f"the {inputs.split} split of {inputs.data}"
    return f"queries {inputs.queries} against database {inputs.database}"
