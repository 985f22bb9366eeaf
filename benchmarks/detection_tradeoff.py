"""The MAFF-Net trade-off curve over training seeds: accuracy against speed for every card that
benchmarks/detection_seeds.py has measured, and each card's distance from the reference card.

Reads the newest ``detection-seeds-<card>-<date>.json`` of every card in ``--results``. They
must share the data set, the test split, the CPU and the timing protocol (a row from another
machine or set would not compare like with like; the script refuses it and names the file).
For every card, one row: its configuration, the number of seeds, the fp32 and int8 test mAP
(mean, sample standard deviation and 95 % t-interval of the mean over seeds), int8's paired
difference, the median ms per frame of both graphs, and the command. For every card but the
reference: its fp32 test mAP minus the reference's (95 % Welch interval over the two cards'
seeds), the share of the reference's mAP it keeps, and its fp32 speed-up. Writes
``benchmarks/results/detection-tradeoff-<date>.json``; benchmarks/render.py renders it in
benchmarks/README.md and in docs/models/maffnet.md.

    python benchmarks/detection_tradeoff.py                     # reference: maffnet-vod
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from result_file import RESULTS, save_result, utc_stamp
from seed_stats import difference_of_means

SEEDS_FILE = re.compile(r"^detection-seeds-(?P<card>.+)-(?P<stamp>\d{4}-\d{2}-\d{2}(?:-\d{4})?)\.json$")
# What every row must share to sit in one table.
SHARED = ("data", "split", "area")


def newest_seed_files(results: Path) -> dict[str, Path]:
    """card -> its newest detection-seeds result file in ``results`` (by the date in the name)."""
    newest: dict[str, tuple[str, Path]] = {}
    for path in sorted(Path(results).glob("detection-seeds-*.json")):
        m = SEEDS_FILE.match(path.name)
        if m and (m["card"] not in newest or m["stamp"] > newest[m["card"]][0]):
            newest[m["card"]] = (m["stamp"], path)
    return {card: path for card, (_, path) in sorted(newest.items())}


def check_comparable(docs: dict[str, dict], files: dict[str, Path]) -> None:
    """SystemExit naming the first file whose data, split, area, CPU (model string and int8
    dot-product instructions) or timing protocol differs
    from the first card's: such rows do not compare like with like."""
    first = next(iter(docs))
    for card, doc in docs.items():
        for key, a, b in [(k, doc[k], docs[first][k]) for k in SHARED] + [
            ("machine.cpu", doc["machine"]["cpu"], docs[first]["machine"]["cpu"]),
            # one model string ("AMD EPYC") covers CPUs with and without int8 dot products; a
            # study that does not record them is not known to share the others' CPU
            (
                "machine.int8_dot_product",
                doc["machine"].get("int8_dot_product"),
                docs[first]["machine"].get("int8_dot_product"),
            ),
            ("timing", doc["timing"], docs[first]["timing"]),
        ]:
            if a != b:
                raise SystemExit(
                    f"{files[card].name}: {key} is {a!r}, but {files[first].name} has {b!r}; "
                    "a trade-off table compares runs on the same data, split, CPU and timing"
                )


def card_row(doc: dict, file: Path) -> dict:
    """One card's row: configuration, seeds, fp32 / int8 mAP and speed summaries, the commands."""
    summary = doc["summary"]
    return {
        "card": doc["card"],
        "configuration": doc.get("configuration"),
        "seeds": [s["seed"] for s in doc["seeds"]],
        "checkpoint_sha256": {str(s["seed"]): s["checkpoint_sha256"] for s in doc["seeds"]},
        "fp32_mAP": summary["fp32"]["mAP"],
        "int8_mAP": summary["int8"]["mAP"],
        "int8_minus_fp32_mAP": summary["int8 - fp32"]["mAP"],
        "fp32_ms": summary["p50_ms"]["fp32"],
        "int8_ms": summary["p50_ms"]["int8"],
        "command": doc["command"],
        "score_command": doc["score_command"],
        "source": file.name,
    }


def versus(card: dict, ref: dict, card_doc: dict, ref_doc: dict) -> dict:
    """``card`` against the reference card: fp32 test mAP difference (Welch interval over seeds),
    the share of the reference's mean mAP kept, and the fp32 speed-up (ratio of mean medians)."""
    maps = [[s["scores"]["onnxruntime"]["mAP"]["3d"] for s in d["seeds"]] for d in (card_doc, ref_doc)]
    return {
        "card": card["card"],
        "reference": ref["card"],
        "fp32_mAP_difference": difference_of_means(*maps),
        "mAP_share": card["fp32_mAP"]["mean"] / ref["fp32_mAP"]["mean"] if ref["fp32_mAP"]["mean"] else None,
        "fp32_speedup": ref["fp32_ms"]["mean"] / card["fp32_ms"]["mean"],
    }


def tradeoff(results: Path, reference: str) -> dict:
    """The trade-off document from the newest seed study of every card in ``results``."""
    files = newest_seed_files(results)
    if not files:
        raise SystemExit(f"no detection-seeds-*.json in {results}: run benchmarks/detection_seeds.py first")
    docs = {card: json.loads(path.read_text()) for card, path in files.items()}
    check_comparable(docs, files)
    rows = sorted((card_row(docs[c], files[c]) for c in docs), key=lambda r: -r["fp32_ms"]["mean"])
    by_card = {r["card"]: r for r in rows}
    first = next(iter(docs.values()))
    return {
        "date": utc_stamp(),
        "data": first["data"],
        "split": first["split"],
        "area": first["area"],
        "machine": first["machine"],
        "timing": first["timing"],
        "reference": reference,
        "rows": rows,
        "versus_reference": [
            versus(by_card[c], by_card[reference], docs[c], docs[reference])
            for c in by_card
            if reference in by_card and c != reference
        ],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/detection_tradeoff.py", description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=RESULTS, help="where the seed studies are and the table goes")
    ap.add_argument("--reference", default="maffnet-vod", help="the card the others are compared to")
    args = ap.parse_args(argv)
    save_result("detection-tradeoff", tradeoff(args.results, args.reference), args.results, keep_same_day=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
