"""Training curves of TDFANet: the mean loss and the validation Recall@1 at 5 m of every epoch.

Reads the newest ``place-recognition-<card>-<date>.json`` of each card (benchmarks/place_recognition.py,
solid lines: the run behind the benchmark table) and the newest ``tdfanet-variants-<card>-<date>.json``
and ``tdfanet-variants-<card>-<recipe>-<date>.json`` (benchmarks/tdfanet_variants.py, thin lines:
each variant's run) in benchmarks/results/, and
draws both panels to docs/models/tdfanet-training.png. Epoch 0 is the initialisation: it has a
validation recall and no loss.

    python benchmarks/plot_training.py
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
FIGURE = HERE.parent / "docs" / "models" / "tdfanet-training.png"


def newest(results: Path, prefix: str) -> dict[str, dict]:
    """The newest file (by its date in the name) of every card among ``<prefix><card>-<date>.json``."""
    found: dict[str, tuple[str, dict]] = {}
    for path in sorted(results.glob(f"{prefix}*.json")):
        card, day = path.stem[len(prefix) : -11], path.stem[-10:]
        if card not in found or day >= found[card][0]:
            found[card] = (day, json.loads(path.read_text()))
    return {card: data for card, (_, data) in sorted(found.items())}


def curves(results: Path) -> list[tuple[str, list[dict], bool]]:
    """(label, epochs, is the benchmark's own run) of every run to draw; each epoch a dict with
    ``epoch``, ``loss`` and ``val_R@1``."""
    out = []
    for card, d in newest(results, "place-recognition-").items():
        if d.get("train"):
            out.append((f"{card} (benchmark run)", d["train"]["epochs"], True))
    for card, d in newest(results, "tdfanet-variants-").items():
        for name, v in d["variants"].items():
            out.append((f"{card} {name}", v["history"], False))
    return out


def draw(results: Path, figure: Path) -> Path:
    """Writes the two-panel chart of ``results``'s runs to ``figure``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    runs = curves(results)
    if not runs:
        raise SystemExit(f"no place-recognition or tdfanet-variants results with training epochs in {results}")
    fig, (loss_ax, recall_ax) = plt.subplots(1, 2, figsize=(11, 4.2))
    for label, epochs, main in runs:
        style = {"linewidth": 2.2, "marker": "o"} if main else {"linewidth": 1.0, "marker": ".", "alpha": 0.8}
        trained = [e for e in epochs if e["loss"] is not None and math.isfinite(e["loss"])]
        loss_ax.plot([e["epoch"] for e in trained], [e["loss"] for e in trained], label=label, **style)
        recall_ax.plot([e["epoch"] for e in epochs], [e["val_R@1"] for e in epochs], label=label, **style)
    loss_ax.set(xlabel="epoch", ylabel="mean lazy quadruplet loss", title="training loss")
    recall_ax.set(
        xlabel="epoch (0: initialisation)", ylabel="Recall@1 at 5 m (%)", title="validation recall (design town)"
    )
    for ax in (loss_ax, recall_ax):
        ax.grid(alpha=0.3)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    recall_ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    figure.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(figure, dpi=110)
    plt.close(fig)
    print(f"wrote {figure}")
    return figure


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/plot_training.py", description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--out", type=Path, default=FIGURE)
    args = ap.parse_args(argv)
    draw(args.results, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
