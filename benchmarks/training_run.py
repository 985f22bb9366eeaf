"""What the training benchmarks (tdfanet_training.py, des4pos_training.py, ...) share: their
common options, the work directory and the machine description (results: result_file.save_result)."""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
from pathlib import Path

import torch

from radaredge.benchmarking.timing import cpu_name, int8_dot_product
from radaredge.cards import ModelCard, load_card
from radaredge.config import parse_settings

ROOT = Path(__file__).resolve().parent.parent
THREADS = 2


def parser(prog: str, doc: str, card: str) -> argparse.ArgumentParser:
    """The options every training benchmark takes: --card, --set KEY=VALUE, --work."""
    ap = argparse.ArgumentParser(prog=prog, description=doc.splitlines()[0])
    ap.add_argument("--card", default=card)
    ap.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="recipe option, as `radaredge train --set`",
    )
    ap.add_argument("--work", type=Path, help="default export/<card>-training")
    return ap


def start(args) -> tuple[ModelCard, Path, dict, str]:
    """(card, work directory, recipe options, date stamp) of a run on THREADS torch threads."""
    torch.set_num_threads(THREADS)
    card = load_card(args.card)
    return (
        card,
        args.work or ROOT / "export" / f"{card.name}-training",
        parse_settings(args.settings),
        dt.datetime.now().strftime("%Y-%m-%d %H:%M"),
    )


def machine() -> dict:
    return {
        "cpu": cpu_name(),
        "int8_dot_product": int8_dot_product(),
        "threads": THREADS,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cores": os.cpu_count(),
    }


def settings_text(options: dict) -> str:
    """The ``--set`` options of the recorded command."""
    return "".join(f" --set {k}={v}" for k, v in options.items())
