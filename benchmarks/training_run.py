"""What the training benchmarks (tdfanet_training.py, des4pos_training.py) share: their common
options, the work directory, the machine description and the result file."""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
from pathlib import Path

import torch

from radaredge.cards import ModelCard, load_card
from radaredge.config import parse_settings
from radaredge.bench.timing import cpu_name
from result_file import write_result

ROOT = Path(__file__).resolve().parent.parent
THREADS = 2


def parser(prog: str, doc: str, card: str) -> argparse.ArgumentParser:
    """The options every training benchmark takes: --card, --set KEY=VALUE, --work."""
    ap = argparse.ArgumentParser(prog=prog, description=doc.splitlines()[0])
    ap.add_argument("--card", default=card)
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                    help="recipe option, as `radaredge train --set`")
    ap.add_argument("--work", type=Path, help="default export/<card>-training")
    return ap


def start(args) -> tuple[ModelCard, Path, dict, str]:
    """(card, work directory, recipe options, date stamp) of a run on THREADS torch threads."""
    torch.set_num_threads(THREADS)
    card = load_card(args.card)
    return (card, args.work or ROOT / "export" / f"{card.name}-training", parse_settings(args.settings),
            dt.datetime.now().strftime("%Y-%m-%d %H:%M"))


def machine() -> dict:
    return {"cpu": cpu_name(), "threads": THREADS, "python": platform.python_version(), "torch": torch.__version__,
            "cores": os.cpu_count()}


def settings_text(options: dict) -> str:
    """The ``--set`` options of the recorded command."""
    return "".join(f" --set {k}={v}" for k, v in options.items())


def write(path: Path, result: dict) -> Path:
    """Writes ``result`` as portable JSON to ``path`` (:func:`result_file.write_result`)."""
    return write_result(path, result)


def save(card: ModelCard, stamp: str, result: dict) -> Path:
    """Writes benchmarks/results/<card>-training-<date>.json, or <card>-training-<date>-<HHMM>.json
    when a run of the same day is there already (each run keeps its file; the renderer shows the
    newest)."""
    path = ROOT / "benchmarks" / "results" / f"{card.name}-training-{stamp[:10]}.json"
    if path.exists():
        path = path.with_name(f"{card.name}-training-{stamp[:10]}-{stamp[11:16].replace(':', '')}.json")
    return write(path, result)
