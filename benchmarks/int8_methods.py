"""int8 calibration methods side by side on trained weights: how much of the task each keeps.

For a card and a checkpoint (the zoo's, or any ``radaredge train`` best.pth), this exports the
fp32 graph once, then one int8 copy per calibration method (``radaredge export --quantize int8
--calibration-method M``: min/max, percentile, entropy; the card's keep_fp32 and reduce_range,
synthetic calibration windows), and scores every copy against the fp32 graph on labelled data:

- a MAFF-Net card on the ``--split`` of the labelled set ``--data``: per class 3D AP with its 95 %
  bootstrap interval over frames, and int8's paired difference from fp32 with its interval (the
  same frames, so the interval is far narrower than either AP's);
- a TDFANet card over the ``--queries`` drives against the ``--database`` drives (a street-network
  test town of ``radaredge make-benchmark --layout network``): Recall@1/5/10 with intervals
  over queries, and int8's paired Recall@N difference from fp32 over the same queries.

A method meets the budget of docs/quantization.md (1 point per class of AP, or of Recall@1 in %)
when no class's difference interval lies wholly below -1.0 point, and it is *within* the budget
when every class's difference is above -1.0. Writes
``benchmarks/results/int8-methods-<card>-<split or town>-<date>.json``; benchmarks/render.py
renders it in benchmarks/README.md and in docs/quantization.md.

``--qat-weights`` adds a row for a ``radaredge train --qat`` fine-tune of the same weights: its
int8 graph (the learned ranges, ``export --quantize int8 --checkpoint``) against the *original*
weights' fp32 graph, paired over the same frames or queries, so the row says what a user
deploying the fine-tuned int8 graph gives up against the fp32 model they started from.
``--control-weights`` (with ``--qat-weights``) names an fp32 fine-tune of the same weights on the
same schedule without ``--qat``: its fp32 graph against the original's, and the QAT int8 graph
against it, both paired, separate what the extra epochs gain from what the fake quantisation
keeps.

``--search`` adds the row of ``radaredge quantize --keep-fp32 none --search``: the sensitivity
search for the layers to keep in fp32, started from every layer int8 (not from the card's own
list) and run on held-out data that is not the data scored (a detector's ``--search-split``,
default val; a place recogniser's ``--search-database`` and ``--search-queries`` drives, such as
another town); the int8 graph it chooses is then scored like the other rows, paired with the fp32
graph, and the row records the chosen list and every copy the search scored.

``--into FILE`` adds this run's methods to an earlier result of the same card, weights and data
(a method measured later, such as the slow entropy calibration): the fp32 graph must score what
the file recorded for it, so every row is paired with the same fp32 graph on the same frames or
queries; the merged file is written anew, dated now, with the run listed under ``added``.

    python benchmarks/int8_methods.py --card zoo/maffnet-vod-edge/card.yaml \\
        --weights zoo/maffnet-vod-edge/weights.pth --data set [--qat-weights runs/qat/best.pth \\
        [--control-weights runs/fp32/best.pth]]
    python benchmarks/int8_methods.py --card zoo/tdfanet-edge/card.yaml \\
        --weights zoo/tdfanet-edge/weights.pth --database town/database --queries town/queries \\
        [--search --search-database town-2/database --search-queries town-2/queries]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import training_run
from result_file import save_result, sha256_of, utc_stamp

import radaredge
from radaredge.artifacts import INT8, copy_path
from radaredge.cards import load_card
from radaredge.eval.detection import INT8_AP_BUDGET, ORT, ORT_INT8, ap_intervals, evaluate_detection
from radaredge.eval.places import BASELINE, ONNX
from radaredge.eval.places import evaluate as evaluate_places
from radaredge.eval.recall_stats import bootstrap_interval
from radaredge.exporting.quantize import CALIBRATION_METHODS, quantize_int8
from radaredge.quantizing.search import DEFAULT_BUDGET as RECALL_BUDGET
from radaredge.registry import model_spec
from zoo import AREA, detection_scores, place_scores

CLASSES = ("Car", "Pedestrian", "Cyclist", "mAP")
RECALL_NS = (1, 5, 10)


def verdict(differences: dict) -> str:
    """ "within" when every class's int8 - fp32 3D AP is above -budget, "meets" when none's
    interval lies wholly below it (the loss is not resolved beyond the budget), else "fails"."""
    if all(d["3d"] > -INT8_AP_BUDGET for d in differences.values()):
        return "within"
    if all(d["3d_interval"][1] >= -INT8_AP_BUDGET for d in differences.values()):
        return "meets"
    return "fails"


def _differences(minuend: dict, subtrahend: dict, delta_intervals: dict) -> dict:
    """class -> {3d: minuend - subtrahend 3D AP, 3d_interval: the paired interval of that
    difference from ``delta_intervals`` ([area][class][metric])}."""
    return {
        c: {"3d": minuend[c]["3d"] - subtrahend[c]["3d"], "3d_interval": delta_intervals[AREA][c]["3d"]}
        for c in CLASSES
    }


def _row(report, fp32_scores: dict, int8_scores: dict, delta_intervals: dict, command: str) -> dict:
    differences = _differences(int8_scores, fp32_scores, delta_intervals)
    return {
        "frames": len(report.frames),
        "fp32": fp32_scores,
        "int8": int8_scores,
        "int8_minus_fp32": differences,
        "verdict": verdict({c: d for c, d in differences.items() if c != "mAP"}),
        "export_command": command,
    }


def method_command(card, method: str) -> str:
    """The export command that writes ``method``'s int8 copy of the trained weights."""
    return f"radaredge export --model {card.name} --checkpoint WEIGHTS --quantize int8 --calibration-method {method}"


def score_method(card, fp32: Path, method: str, data: Path, split: str, work: Path) -> tuple[dict, object]:
    """One method's int8 copy of ``fp32`` scored beside it: fp32 and int8 AP, and int8 - fp32
    per class with the paired interval; and the evaluation report."""
    home = work / method
    home.mkdir()
    graph = home / fp32.name
    os.link(fp32, graph)
    quantize_int8(card, graph, copy_path(graph, INT8), method=method)
    report = evaluate_detection(card, graph, data, split, reference=False, openvino=False)
    scores = detection_scores(report, [ORT, ORT_INT8])
    command = method_command(card, method)
    return _row(report, scores[ORT], scores[ORT_INT8], report.delta_intervals[ORT_INT8], command), report


def search_command(card, held_out: str) -> str:
    """The command that chooses the search row's keep_fp32 on ``held_out`` (its data options)."""
    return f"radaredge quantize --model {card.name} --onnx GRAPH {held_out} --keep-fp32 none --search"


def searched_int8(card, fp32: Path, work: Path, **held_out) -> tuple[Path, dict]:
    """``fp32`` linked alone into ``work``/search with the int8 copy beside it that ``radaredge
    quantize --keep-fp32 none --search`` chooses on ``held_out`` (api.quantize's data options);
    (that graph's path, the search's report without the temporary int8 path)."""
    home = work / "search"
    home.mkdir()
    graph = home / fp32.name
    os.link(fp32, graph)
    report = radaredge.quantize(card, graph, keep_fp32="none", search=True, log=print, **held_out)
    searched = report.to_dict()
    searched.pop("int8")
    return graph, searched


def _evaluate_export(card, weights: Path, baseline, data: Path, split: str, home: Path, quantize=None):
    """Exports ``weights`` (int8 too with ``quantize``) into ``home`` and evaluates it on the frames
    ``baseline`` (an evaluation of the original weights' graph) saw."""
    home.mkdir()
    graph = home / f"{card.name}.onnx"
    radaredge.export(card, graph, checkpoint=weights, quantize=quantize)
    report = evaluate_detection(card, graph, data, split, reference=False, openvino=False)
    if [f.frame_id for f in report.frames] != [f.frame_id for f in baseline.frames]:
        raise SystemExit(f"the evaluation of {weights} saw other frames than the baseline's")
    return report


def score_qat(card, weights: Path, baseline, data: Path, split: str, work: Path, control: Path | None = None) -> dict:
    """The int8 graph of a --qat checkpoint (its learned ranges) against the original weights' fp32
    graph (``baseline``'s, an evaluation of the same frames), paired over the frames; its own fp32
    AP beside it. With ``control`` (an fp32 fine-tune on the same schedule without --qat), also
    the control's fp32 - the original fp32 and the QAT int8 - the control's fp32, paired."""
    report = _evaluate_export(card, weights, baseline, data, split, work / "qat", quantize="int8")
    curves = {ORT: baseline.curves[ORT], ORT_INT8: report.curves[ORT_INT8]}
    _, deltas = ap_intervals(curves, baseline.classes, baseline.areas, ORT)
    scores = detection_scores(report, [ORT, ORT_INT8])
    original = detection_scores(baseline, [ORT])[ORT]
    row = _row(
        report,
        original,
        scores[ORT_INT8],
        deltas[ORT_INT8],
        f"radaredge export --model {card.name} --checkpoint QAT_WEIGHTS --quantize int8",
    )
    row = {**row, "qat_fp32": scores[ORT], "checkpoint": str(weights), "checkpoint_sha256": sha256_of(weights)}
    if control is None:
        return row
    print(f"control: exporting {control} (fp32) and scoring ...", flush=True)
    held = _evaluate_export(card, control, baseline, data, split, work / "control")
    control_scores = detection_scores(held, [ORT])[ORT]
    curves = {"original": baseline.curves[ORT], "control": held.curves[ORT], "qat": report.curves[ORT_INT8]}
    _, versus_original = ap_intervals(curves, baseline.classes, baseline.areas, "original")
    _, versus_control = ap_intervals(curves, baseline.classes, baseline.areas, "control")
    int8_minus_control = _differences(scores[ORT_INT8], control_scores, versus_control["qat"])
    row["control"] = {
        "checkpoint": str(control),
        "checkpoint_sha256": sha256_of(control),
        "fp32": control_scores,
        "fp32_minus_original_fp32": _differences(control_scores, original, versus_original["control"]),
        "qat_int8_minus_control_fp32": int8_minus_control,
        "verdict": verdict({c: d for c, d in int8_minus_control.items() if c != "mAP"}),
    }
    return row


def recall_verdict(difference: dict) -> str:
    """The budget's verdict on an int8 - fp32 Recall@1 difference ({value, interval}, points)."""
    if difference["value"] > -RECALL_BUDGET:
        return "within"
    return "meets" if difference["interval"][1] >= -RECALL_BUDGET else "fails"


def _recall_differences(report, baseline) -> dict:
    """N -> {value, interval}: ``report``'s Recall@N minus ``baseline``'s (onnxruntime each, the
    same query windows) in points, with the paired 95 % bootstrap interval over the queries."""
    mine, theirs = report.results[ONNX], baseline.results[ONNX]
    if not np.array_equal(mine["evaluated_mask"], theirs["evaluated_mask"]):
        raise SystemExit(f"{report.onnx} was scored on other queries than {baseline.onnx}")
    out = {}
    for n in RECALL_NS:
        paired = mine["hits"][:, n - 1].astype(np.float64) - theirs["hits"][:, n - 1].astype(np.float64)
        out[str(n)] = {"value": 100.0 * float(paired.mean()), "interval": list(bootstrap_interval(paired))}
    return out


def _places_row(report, baseline, command: str) -> dict:
    """A method's row: fp32 (``baseline``) and int8 (``report``) Recall@N, int8 - fp32 paired, verdict."""
    differences = _recall_differences(report, baseline)
    return {
        "queries": report.evaluated,
        "fp32": place_scores(baseline, [ONNX])[ONNX],
        "int8": place_scores(report, [ONNX])[ONNX],
        "int8_minus_fp32": differences,
        "verdict": recall_verdict(differences["1"]),
        "export_command": command,
    }


def score_places(card, args, work: Path) -> tuple[dict, dict]:
    """(rows per method, and qat / control rows; the setup fields of the result file) of a place
    recogniser over ``args.queries`` against ``args.database``."""

    def evaluate(graph: Path, no_learning: bool = False):
        return evaluate_places(
            card, graph, args.database, args.queries, radius=args.radius, reference=False, baseline=no_learning
        )

    fp32 = work / f"{card.name}.onnx"
    radaredge.export(card, fp32, checkpoint=args.weights)
    print("fp32: scoring (and the no-learning descriptor) ...", flush=True)
    baseline = evaluate(fp32, no_learning=True)
    rows = {}
    for method in args.methods:
        print(f"{method}: quantising and scoring ...", flush=True)
        int8 = copy_path(fp32, INT8)
        quantize_int8(card, fp32, int8, method=method)
        rows[method] = _places_row(evaluate(int8), baseline, method_command(card, method))
    if args.qat_weights:
        print(f"qat: exporting {args.qat_weights} with its learned ranges and scoring ...", flush=True)
        home = work / "qat"
        home.mkdir()
        exported = radaredge.export(card, home / fp32.name, checkpoint=args.qat_weights, quantize="int8")
        qat_int8 = evaluate(next(iter(exported.int8.values())))
        command = f"radaredge export --model {card.name} --checkpoint QAT_WEIGHTS --quantize int8"
        rows["qat"] = {
            **_places_row(qat_int8, baseline, command),
            "qat_fp32": place_scores(evaluate(home / fp32.name), [ONNX])[ONNX],
            "checkpoint": str(args.qat_weights),
            "checkpoint_sha256": sha256_of(args.qat_weights),
        }
        if args.control_weights:
            print(f"control: exporting {args.control_weights} (fp32) and scoring ...", flush=True)
            (work / "control").mkdir()
            held = work / "control" / fp32.name
            radaredge.export(card, held, checkpoint=args.control_weights)
            control = evaluate(held)
            versus_control = _recall_differences(qat_int8, control)
            rows["qat"]["control"] = {
                "checkpoint": str(args.control_weights),
                "checkpoint_sha256": sha256_of(args.control_weights),
                "fp32": place_scores(control, [ONNX])[ONNX],
                "fp32_minus_original_fp32": _recall_differences(control, baseline),
                "qat_int8_minus_control_fp32": versus_control,
                "verdict": recall_verdict(versus_control["1"]),
            }
    if args.search:
        print("search: choosing keep_fp32 on the held-out drives, from every layer int8 ...", flush=True)
        held_out = {"database": args.search_database, "queries": args.search_queries, "radius": args.radius}
        graph, searched = searched_int8(card, fp32, work, **held_out)
        options = f"--database {args.search_database} --queries {args.search_queries} --radius {args.radius:g}"
        row = _places_row(evaluate(copy_path(graph, INT8)), baseline, search_command(card, options))
        rows["search"] = {**row, "keep_fp32": searched["keep_fp32"], "search": searched}
    setup = {
        "task": "place recognition",
        "database": str(args.database),
        "queries": str(args.queries),
        "radius_m": args.radius,
        "no_learning": place_scores(baseline, [BASELINE])[BASELINE],
        "budget_recall_points": RECALL_BUDGET,
    }
    return rows, setup


def score_detection(card, args, work: Path) -> tuple[dict, dict]:
    """(rows per method, and the qat row; the setup fields of the result file) of a detector on
    ``args.split`` of ``args.data``."""
    fp32 = work / f"{card.name}.onnx"
    radaredge.export(card, fp32, checkpoint=args.weights)
    rows = {}
    for method in args.methods:
        print(f"{method}: quantising and scoring on the {args.split} split ...", flush=True)
        rows[method], baseline = score_method(card, fp32, method, args.data, args.split, work)
    if args.qat_weights:
        print(f"qat: exporting {args.qat_weights} with its learned ranges and scoring ...", flush=True)
        rows["qat"] = score_qat(card, args.qat_weights, baseline, args.data, args.split, work, args.control_weights)
    if args.search:
        print(f"search: choosing keep_fp32 on the {args.search_split} split, from every layer int8 ...", flush=True)
        graph, searched = searched_int8(card, fp32, work, data=args.data, split=args.search_split)
        report = evaluate_detection(card, graph, args.data, args.split, reference=False, openvino=False)
        scores = detection_scores(report, [ORT, ORT_INT8])
        command = search_command(card, f"--data {args.data} --split {args.search_split}")
        row = _row(report, scores[ORT], scores[ORT_INT8], report.delta_intervals[ORT_INT8], command)
        rows["search"] = {**row, "keep_fp32": searched["keep_fp32"], "search": searched}
    setup = {
        "task": "detection",
        "data": str(args.data),
        "split": args.split,
        "area": AREA,
        "budget_ap_points": INT8_AP_BUDGET,
    }
    return rows, setup


# How far the fp32 scores of a run merged with --into may lie from the file's (AP or Recall points):
# the same graph on the same data scores the same, up to the CPU's float summation order.
FP32_TOLERANCE = 1e-6


def _max_abs_difference(a, b, where: str = "fp32") -> float:
    """The largest absolute difference between the numbers of two score trees of the same shape
    (dicts, lists, numbers); ValueError naming the first place where their shapes differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            raise ValueError(f"{where} has the keys {sorted(b)} in the file, {sorted(a)} here")
        return max((_max_abs_difference(a[k], b[k], f"{where}.{k}") for k in a), default=0.0)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and len(a) == len(b):  # JSON: tuples -> lists
        return max((_max_abs_difference(x, y, f"{where}[{i}]") for i, (x, y) in enumerate(zip(a, b))), default=0.0)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return abs(float(a) - float(b))
    raise ValueError(f"{where} is {b!r} in the file, {a!r} here")


def _refuse_into(earlier: dict, path: Path, doc: dict) -> None:
    """SystemExit when the result ``earlier`` (read from ``path``) is not of ``doc``'s card,
    weights and data, or already has one of ``doc``'s methods."""
    for key in ("card", "checkpoint_sha256", "task", "split", "area", "radius_m"):
        if earlier.get(key) != doc.get(key):
            raise SystemExit(
                f"{path}: {key} is {earlier.get(key)!r}, this run's {doc.get(key)!r}; "
                "--into adds methods to a result of the same card, weights and data"
            )
    if both := sorted(set(earlier["methods"]) & set(doc["methods"])):
        raise SystemExit(f"{path}: already has the rows {both}; --into adds methods it lacks")


def merge_into(path: Path, doc: dict) -> dict:
    """``doc`` (this run's result) merged into the earlier result at ``path``: its method rows
    join the file's, the run is listed under ``added`` (command, date, machine, methods) and the
    merged result is dated now. SystemExit when the card, the weights or the data differ, when a
    method is in both, or when this run's fp32 graph scores otherwise than the file's did (its
    rows would then not be paired with the same fp32 graph on the same frames or queries)."""
    earlier = json.loads(Path(path).read_text())
    _refuse_into(earlier, path, doc)
    recorded = next(iter(earlier["methods"].values()))["fp32"]
    for method, row in doc["methods"].items():
        try:
            shift = _max_abs_difference(row["fp32"], recorded)
        except ValueError as err:
            raise SystemExit(f"{path}: {err}") from None
        if shift > FP32_TOLERANCE:
            raise SystemExit(
                f"{path}: the fp32 graph scores up to {shift:.3g} points away from the file's here ({method}); "
                "not the same graph on the same data, so its rows would not pair with the file's"
            )
    added = {key: doc[key] for key in ("command", "date", "machine")}
    return {
        **earlier,
        "date": doc["date"],
        "methods": {**earlier["methods"], **doc["methods"]},
        "added": [*earlier.get("added", []), {**added, "methods": list(doc["methods"])}],
    }


def _require_held_out(ap: argparse.ArgumentParser, args, places: bool) -> None:
    """argparse error unless --search has held-out data apart from the data scored."""
    if not places:
        if args.search_split == args.split:
            ap.error(f"--search-split {args.search_split} is the split scored; search on held-out data")
        return
    if args.search_database is None or args.search_queries is None:
        ap.error("--search on a place recogniser needs --search-database and --search-queries (another town)")
    scored = {args.database.resolve(), args.queries.resolve()}
    if {args.search_database.resolve(), args.search_queries.resolve()} & scored:
        ap.error("--search-database and --search-queries must be other drives than --database and --queries")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/int8_methods.py", description=__doc__.splitlines()[0])
    ap.add_argument("--card", required=True, help="a card name or file (the zoo's card.yaml for its weights)")
    ap.add_argument("--weights", type=Path, required=True, help="the trained checkpoint")
    ap.add_argument("--data", type=Path, help="detection: the labelled set (its --split is scored)")
    ap.add_argument("--split", default="test", help="detection: the split scored (default test)")
    ap.add_argument("--database", type=Path, help="place recognition: the database drive(s)")
    ap.add_argument("--queries", type=Path, help="place recognition: the query drive(s)")
    ap.add_argument("--radius", type=float, default=5.0, help="place recognition: true-positive radius, m")
    ap.add_argument(
        "--methods",
        nargs="*",
        default=list(CALIBRATION_METHODS),
        choices=list(CALIBRATION_METHODS),
        help="calibration methods to score (default all; none with --search or --qat-weights for those rows alone)",
    )
    ap.add_argument("--qat-weights", type=Path, help="a `radaredge train --qat` fine-tune of --weights (best.pth)")
    ap.add_argument(
        "--control-weights",
        type=Path,
        help="an fp32 fine-tune of --weights on the --qat-weights schedule without --qat (best.pth)",
    )
    ap.add_argument(
        "--search",
        action="store_true",
        help="add the row of `radaredge quantize --keep-fp32 none --search` run on held-out data",
    )
    ap.add_argument("--search-split", default="val", help="detection: the split --search chooses on (default val)")
    ap.add_argument("--search-database", type=Path, help="place recognition: --search's database drive(s)")
    ap.add_argument("--search-queries", type=Path, help="place recognition: --search's query drive(s)")
    ap.add_argument("--into", type=Path, help="an earlier result of the same card, weights and data to add rows to")
    ap.add_argument("--results", type=Path, default=training_run.ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    if args.control_weights and not args.qat_weights:
        ap.error("--control-weights is the control of a --qat-weights fine-tune; pass both")
    if not (args.methods or args.search or args.qat_weights):
        ap.error("nothing to score: give --methods, --search or --qat-weights")
    card = load_card(args.card)
    places = model_spec(card).evaluation == "place recognition"
    needed = ("database", "queries") if places else ("data",)
    if missing := [f"--{name}" for name in needed if getattr(args, name) is None]:
        ap.error(f"{card.name} is scored by {model_spec(card).evaluation}, which needs {' and '.join(missing)}")
    if args.qat_weights and not (places or args.methods):
        ap.error("a detector's --qat-weights row pairs with a calibration method's frames; give --methods too")
    if args.search:
        _require_held_out(ap, args, places)
    if args.into:  # before the long scoring: the file must be of these weights and lack these methods
        planned = args.methods + (["qat"] if args.qat_weights else []) + (["search"] if args.search else [])
        earlier = json.loads(args.into.read_text())
        mine = {"card": card.name, "checkpoint_sha256": sha256_of(args.weights), "methods": dict.fromkeys(planned)}
        _refuse_into(earlier, args.into, {**earlier, **mine})
    torch.set_num_threads(training_run.THREADS)
    with tempfile.TemporaryDirectory(prefix="radaredge-int8-methods-") as tmp:
        rows, setup = (score_places if places else score_detection)(card, args, Path(tmp))
    doc = {
        "date": utc_stamp(),
        "card": card.name,
        "checkpoint": str(args.weights),
        "checkpoint_sha256": sha256_of(args.weights),
        **setup,
        "command": "python benchmarks/int8_methods.py " + shlex.join(sys.argv[1:] if argv is None else argv),
        "machine": training_run.machine(),
        "methods": rows,
    }
    if args.into:
        doc = merge_into(args.into, doc)
    where = args.queries.parent.name if places else args.split
    save_result(f"int8-methods-{card.name}-{where}", doc, args.results, keep_same_day=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
