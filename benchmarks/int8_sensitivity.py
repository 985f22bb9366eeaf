"""Which layers of a trained MAFF-Net does int8 hurt? Per-group sensitivity by detection AP.

For a trained checkpoint and a labelled set: the fp32 graph's 3D AP per class on the
``--choose-split`` (default ``val``: the layers are chosen on it, never on the test split), then,
for every group of quantisable layers (the VFE, SPA, CFA, CAF, each backbone block and deblock,
the head, and on a two-stage card the VSA, point head and ROI head; ``--groups`` names fewer), an
int8 copy in which *only that group* is quantised (every other group listed under
``quantization.keep_fp32``), scored the same way: the AP it loses is that group's sensitivity.
Then the choice, made on the choose split: when the card's int8 copy (its own ``keep_fp32``)
loses more than the budget there, the most sensitive groups join ``keep_fp32`` one at a time,
in order of the AP they cost alone, until the copy is within the budget on the choose split (or
no group that costs anything is left). On ``--split`` (default ``test``), the card's int8 copy
and, when a group was added, the chosen copy, each with its speed against fp32 on the same
frames. The rows of the card's newest earlier results file for the same checkpoint, data and
choose split are carried over for the groups this run does not probe (marked ``earlier_run``),
so runs with different ``--groups`` add up to one table, and ``--groups none`` probes nothing
and chooses from the earlier rows. Writes
``benchmarks/results/int8-sensitivity-<card>-<date>.json``.

    python benchmarks/int8_sensitivity.py --model maffnet-vod-edge --checkpoint runs/edge/best.pth \\
        --data bench-detection --split test
"""

from __future__ import annotations

import argparse
import copy
import json
import re
import statistics
import sys
import time
from pathlib import Path

import onnx
import torch
from result_file import RESULTS, portable, save_result, sha256_of

import radaredge
from radaredge import runtime
from radaredge.artifacts import INT8, copy_path
from radaredge.benchmarking.timing import cpu_name, pin_threads
from radaredge.cards import load_card, parse_card
from radaredge.data.kitti_detection import DetectionSet
from radaredge.errors import ConfigError
from radaredge.eval.detection import INT8_AP_BUDGET, ORT, ORT_INT8, card_points, evaluate_detection, layout_for_card
from radaredge.exporting.quantize import fp32_node_names
from radaredge.models import create_model
from radaredge.models.maffnet.rcnn import STAGE_TWO_MODULES
from radaredge.runtime.session import make_session, run_session

ROOT = Path(__file__).resolve().parent.parent


def layer_groups(model) -> list[str]:
    """Module-name prefixes of the groups with layers int8 quantises (Conv, Linear: the graph's
    Conv / MatMul / Gemm; the deblocks' transposed convolutions stay fp32), in pipeline order."""
    groups = ["vfe", "map_to_bev_module", "image_backbone", "fuser"]
    groups += [f"backbone_2d.blocks.{i}" for i in range(len(model.backbone_2d.blocks))]
    groups.append("dense_head")
    groups += [m for m in STAGE_TWO_MODULES if hasattr(model, m)]  # a two-stage card's stage two
    quantised = [
        n for n, m in model.named_modules() if isinstance(m, (torch.nn.Conv1d, torch.nn.Conv2d, torch.nn.Linear))
    ]
    return [g for g in groups if any(n.startswith(g + ".") for n in quantised)]


def _quantises(graph: onnx.ModelProto, group: str) -> bool:
    """Whether the exported graph has a Conv / MatMul / Gemm node inside module ``group``."""
    try:
        return bool(fp32_node_names(graph, [group]))
    except ConfigError:
        return False


def with_keep(card, keep: list[str]):
    """``card`` with ``quantization.keep_fp32`` = ``keep``."""
    data = copy.deepcopy(card.data)
    data["quantization"] = dict(data.get("quantization") or {}, keep_fp32=keep)
    return parse_card(data, card.path)


def ap_3d(report, backend: str) -> dict[str, float]:
    return {c: float(r["3d"]) for c, r in report.ap[backend]["entire_area"].items()}


def score(card, checkpoint, out: Path, data, split: str) -> tuple[dict, dict]:
    """(fp32 3D AP per class, int8 3D AP per class) of ``card`` exported to ``out`` with its int8 copy."""
    net = create_model(card, checkpoint)
    radaredge.export(card, out, model=net, quantize="int8")
    report = evaluate_detection(card, out, data, split, checkpoint, reference=False, openvino=False)
    return ap_3d(report, ORT), ap_3d(report, ORT_INT8)


def speed(fp32: Path, int8: Path, data_points: list, threads: int, passes: int = 3) -> dict[str, float]:
    """Median ms per frame of the two graphs, alternating, on the same frames."""
    sessions = {"fp32": make_session(fp32, threads=threads), "int8": make_session(int8, threads=threads)}
    loaded = runtime.load(fp32, threads=threads)
    cases = [loaded.feeds([p]) for p in data_points]
    times: dict[str, list[float]] = {k: [] for k in sessions}
    for name, s in sessions.items():
        run_session(s, cases[0])
    for _ in range(passes):
        for c in cases:
            for name, s in sessions.items():
                t = time.perf_counter()
                run_session(s, c)
                times[name].append(time.perf_counter() - t)
    return {k: 1000 * statistics.median(v) for k, v in times.items()}


def latest_result(out: Path, card_name: str) -> Path | None:
    """The newest ``int8-sensitivity-<card_name>-<date>.json`` in ``out`` (None when there is none)."""
    dated = re.compile(re.escape(f"int8-sensitivity-{card_name}-") + r"\d{4}-\d{2}-\d{2}\.json")
    files = sorted(p for p in out.glob("int8-sensitivity-*.json") if dated.fullmatch(p.name))
    return files[-1] if files else None


def earlier_probes(path: Path | None, result: dict, probed: list[str]) -> list[dict]:
    """The group rows of an earlier run's results file ``path`` that probed the same checkpoint,
    data and choose split (and found the same fp32 AP on it), for the groups this run did not
    probe: ``--groups`` runs, one after another, add up to one sensitivity table."""
    if path is None:
        return []
    earlier = json.loads(path.read_text())
    fp32 = [{c: round(v, 2) for c, v in r.get("choose_fp32_ap", {}).items()} for r in (earlier, result)]
    same = [portable(earlier.get(k)) == portable(result[k]) for k in ("checkpoint", "data", "choose_split")]
    if earlier.get("checkpoint_sha256") and earlier["checkpoint_sha256"] != result["checkpoint_sha256"]:
        same.append(False)
    if not all(same) or fp32[0] != fp32[1]:
        return []
    return [
        {**r, "earlier_run": r.get("earlier_run", earlier.get("date"))}
        for r in earlier.get("groups", [])[1:]
        if r["group"] not in probed
    ]


def choose_keep(card, args, rows: list[dict], fp32: dict, card_int8: dict) -> list[dict]:
    """The greedy choice on the choose split (module docstring): one step per ``keep_fp32`` tried,
    from the card's own, each with its int8 AP and loss per class there; the last step's
    ``keep_fp32`` is the choice. ``rows`` are the probed groups' rows."""
    keep = list(card.get("quantization.keep_fp32", []) or [])
    loss = {c: fp32[c] - card_int8[c] for c in fp32}
    steps = [{"keep_fp32": list(keep), "int8_ap": card_int8, "loss": loss}]
    ranked = [r["group"] for r in sorted(rows, key=lambda r: -r["worst_loss"]) if r["worst_loss"] > 0]
    for group in (g for g in ranked if g not in keep):
        if max(loss.values()) <= INT8_AP_BUDGET:
            break
        keep.append(group)
        _, int8 = score(with_keep(card, keep), args.checkpoint, args.work / "choice.onnx", args.data, args.choose_split)
        loss = {c: fp32[c] - int8[c] for c in fp32}
        steps.append({"keep_fp32": list(keep), "int8_ap": int8, "loss": loss})
        print(
            f"{args.choose_split}: keeping {keep} in fp32: int8 loses "
            f"{', '.join(f'{c} {v:+.2f}' for c, v in loss.items())}",
            flush=True,
        )
    return steps


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--split", default="test", help="The split the results are reported on.")
    ap.add_argument("--choose-split", default="val", help="The split the sensitive groups are chosen on.")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--groups",
        help="Comma-separated groups to probe (default: every group; none: no group, the "
        "earlier run's rows only); on a large card each probe exports an int8 copy and "
        "scores the whole choose split.",
    )
    ap.add_argument("--work", type=Path, default=ROOT / "export" / "int8-sensitivity")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    cores = pin_threads(args.threads)
    card = load_card(args.model)
    groups = layer_groups(create_model(card))
    args.work.mkdir(parents=True, exist_ok=True)
    choose_fp32, choose_int8 = score(
        card, args.checkpoint, args.work / f"{card.name}.onnx", args.data, args.choose_split
    )
    graph = onnx.load(str(args.work / f"{card.name}.onnx"), load_external_data=False)
    groups = [g for g in groups if _quantises(graph, g)]
    probed = groups
    if args.groups:
        probed = [] if args.groups == "none" else [g.strip() for g in args.groups.split(",") if g.strip()]
        unknown = sorted(set(probed) - set(groups))
        if unknown:
            raise SystemExit(f"--groups: {unknown} are not quantised groups of {card.name}; its groups: {groups}")
    rows = []
    _, int8 = score(with_keep(card, groups), args.checkpoint, args.work / "no-group.onnx", args.data, args.choose_split)
    loss = {c: choose_fp32[c] - int8[c] for c in choose_fp32}
    rows.append({"group": "(none: every group fp32)", "int8_ap": int8, "loss": loss, "worst_loss": max(loss.values())})
    print(f"every group fp32: int8 loses {', '.join(f'{c} {v:+.2f}' for c, v in loss.items())}", flush=True)
    for g in probed:
        only = with_keep(card, [x for x in groups if x != g])
        _, int8 = score(only, args.checkpoint, args.work / f"only-{g}.onnx", args.data, args.choose_split)
        loss = {c: choose_fp32[c] - int8[c] for c in choose_fp32}
        rows.append({"group": g, "int8_ap": int8, "loss": loss, "worst_loss": max(loss.values())})
        print(f"only {g:<24} int8 loses {', '.join(f'{c} {v:+.2f}' for c, v in loss.items())}", flush=True)
    fp32_ap, card_int8 = score(card, args.checkpoint, args.work / f"{card.name}.onnx", args.data, args.split)
    print(f"{args.split}: fp32 {fp32_ap}\ncard's int8 {card_int8}", flush=True)
    result = {
        "model": card.name,
        "checkpoint": str(args.checkpoint),
        "checkpoint_sha256": sha256_of(args.checkpoint),
        "data": str(args.data),
        "split": args.split,
        "choose_split": args.choose_split,
        "choose_fp32_ap": choose_fp32,
        "budget_ap_points": INT8_AP_BUDGET,
        "fp32_ap": fp32_ap,
        "card_int8_ap": card_int8,
        "card_keep_fp32": card.get("quantization.keep_fp32", []) or [],
        "groups": rows,
        "unprobed_groups": [g for g in groups if g not in probed],
    }
    rows += earlier_probes(latest_result(args.out, card.name), result, probed)
    result["unprobed_groups"] = [g for g in groups if g not in {r["group"] for r in rows}]
    result["choice"] = choose_keep(card, args, rows[1:], choose_fp32, choose_int8)
    keep = result["choice"][-1]["keep_fp32"]
    the_set = DetectionSet(args.data, args.split, layout_for_card(card), int(card.get("input.scans_accumulated", 1)))
    step = max(1, len(the_set) // 12)
    points = [card_points(the_set.frame(i, card.features), card) for i in range(0, len(the_set), step)]
    fp32_graph = args.work / f"{card.name}.onnx"
    result["card_speed_ms"] = speed(fp32_graph, copy_path(fp32_graph, INT8), points, args.threads)
    if keep != result["card_keep_fp32"]:
        out = args.work / f"{card.name}-kept.onnx"
        _, int8 = score(with_keep(card, keep), args.checkpoint, out, args.data, args.split)
        result["kept"] = {
            "keep_fp32": keep,
            "int8_ap": int8,
            "loss": {c: fp32_ap[c] - int8[c] for c in fp32_ap},
            "speed_ms": speed(out, copy_path(out, INT8), points, args.threads),
        }
        print(f"{args.split}: keeping {keep} in fp32: int8 {int8}", flush=True)
    result.update(cpu=cpu_name(), threads=args.threads, cores=cores)
    save_result(f"int8-sensitivity-{card.name}", result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
