"""Which object and hint features let Des4Pos's fine stage learn to place a pose in its cell?

The paper's fine stage (``FineStage``: CRA, eq. 10-12, a max and the offset MLP, seeded) is
trained on the training cities' described poses in their best cells, with the fine recipe's
defaults (Adam 3e-4, batch 32, mean L2 error of the offset in cell units), each time on another
pair of input streams behind a learned linear layer, and scored on the validation city (the last
by name) in metres, beside the cell centre:

object streams, per slot of the cell
- ``clean``: the generator's facts: one-hot class and colour (the colour name of the object's
  mean RGB, as make-city names it) and the centre (x, y) in the cell;
- ``objects``: the coarse stage's object encoder output (PointNet++ and the MLPs, before MFAM);
- ``mfam``: after MFAM (eq. 4-5), before the LSTM;
- ``lstm``: the bidirectional LSTM's states (``fine.object_state: lstm``);

hint streams, per hint of the description
- ``clean``: one-hot direction, colour and class, parsed from the sentence;
- ``learned``: the text encoder's fine per-hint feature of the checkpoint.

The checkpoint's coarse stage is frozen; only the linear layers and the fine stage train. A
stream pair that reaches well under the centre's error holds what the fine stage needs.

    python benchmarks/des4pos_fine_inputs.py --checkpoint <run>/best.pth --cities <make-city directory>

Writes benchmarks/results/des4pos-fine-inputs-<date>.json.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import training_run
from result_file import save_result

from radaredge.cards import load_card
from radaredge.data.text_city import CLASSES, COLOURS, colour_name
from radaredge.data.text_maps import load_text_maps
from radaredge.models import create_model
from radaredge.models.des4pos.model import FineStage
from radaredge.training.des4pos import backbone_features, cell_inputs, geometry_features, hint_table

HINT = re.compile(r"The pose is (?P<direction>\S+) of an? (?P<colour>\S+) (?P<label>.+)\.$")
DIRECTIONS = ("north", "south", "east", "west", "on-top")
OBJECT_STREAMS = ("clean", "objects", "mfam", "lstm")
HINT_STREAMS = ("clean", "learned")
PAIRS = (
    ("clean", "clean"),
    ("lstm", "learned"),
    ("lstm", "clean"),
    ("clean", "learned"),
    ("objects", "learned"),
    ("mfam", "learned"),
)


def _one_hot(index: int, n: int) -> np.ndarray:
    v = np.zeros(n, np.float32)
    v[index] = 1.0
    return v


def clean_objects(maps) -> np.ndarray:
    """[C, T, 7 + 8 + 2]: one-hot class, one-hot colour name, centre (x, y) in the cell (cell
    units, from its centre) of every slot; zero at padding slots."""
    cells = maps.cells
    classes, colours = sorted(CLASSES), sorted(COLOURS)
    out = np.zeros((*cells.object_mask.shape, len(classes) + len(colours) + 2), np.float32)
    for c, t in zip(*np.nonzero(cells.object_mask)):
        pts = cells.points[c, t, : int(cells.num_points[c, t])]
        out[c, t] = np.concatenate(
            [
                _one_hot(classes.index(str(cells.labels[c, t])), len(classes)),
                _one_hot(colours.index(colour_name(pts[:, 3:].mean(0))), len(colours)),
                pts[:, :2].mean(0) - 0.5,
            ]
        )
    return out


def coarse_objects(model, maps, stream: str) -> np.ndarray:
    """[C, T, D] of the frozen coarse encoder at ``stream`` (``objects``, ``mfam`` or ``lstm``), in
    the cells' slot order."""
    geometry = geometry_features(model, maps, "cpu")
    ids, out = np.arange(len(maps.cells.ids)), []
    with torch.no_grad():
        for i in range(0, len(ids), 16):
            pts, cnt, mask = cell_inputs(maps, ids[i : i + 16], "cpu")
            trace: dict = {}
            model.submap(pts, cnt, mask, trace=trace, geometry=geometry[torch.from_numpy(ids[i : i + 16])])
            t = mask.shape[1]
            ar = torch.arange(t).unsqueeze(0)
            # the encoder's sort, undone
            inverse = torch.argsort(torch.argsort(torch.where(mask, ar, ar + t), dim=1), dim=1)
            x = trace[stream]
            out.append(torch.gather(x, 1, inverse.unsqueeze(-1).expand_as(x)))
    return torch.cat(out).numpy()


def hint_streams(card, model, maps) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """({"clean": [Q, H, 20], "learned": [Q, H, D]}, hint mask [Q, H]) of every described pose."""
    table = hint_table(card, maps)
    with torch.no_grad():
        tokens, tmask = backbone_features(model, table, "cpu")
        _, fine = model.text.heads(model.text.prior_tokens(tokens, tmask), tmask)
    classes, colours = sorted(CLASSES), sorted(COLOURS)
    width = max(len(h) for h in maps.pose_hints)
    clean = np.zeros((len(maps.pose_hints), width, len(DIRECTIONS) + len(colours) + len(classes)), np.float32)
    learned = np.zeros((len(maps.pose_hints), width, fine.shape[1]), np.float32)
    mask = np.zeros((len(maps.pose_hints), width), bool)
    for q, hints in enumerate(maps.pose_hints):
        for j, sentence in enumerate(hints):
            m = HINT.match(sentence)
            if m is None:
                raise SystemExit(f"hint {sentence!r}: not make-city's 'The pose is <direction> of a <colour> <label>.'")
            clean[q, j] = np.concatenate(
                [
                    _one_hot(DIRECTIONS.index(m["direction"]), len(DIRECTIONS)),
                    _one_hot(colours.index(m["colour"]), len(colours)),
                    _one_hot(classes.index(m["label"]), len(classes)),
                ]
            )
            learned[q, j] = fine[table.index[sentence]].numpy()
            mask[q, j] = True
    return {"clean": clean, "learned": learned}, mask


class _ReadOut(nn.Module):
    """A linear layer per stream into the fine stage's width, then the seeded fine stage."""

    def __init__(self, fine_config, width: int, object_dim: int, hint_dim: int):
        super().__init__()
        self.objects, self.hints = nn.Linear(object_dim, width), nn.Linear(hint_dim, width)
        self.fine = FineStage(fine_config, width)

    def forward(self, objects, object_mask, hints, hint_mask):
        return self.fine.offsets(self.objects(objects), object_mask, self.hints(hints), hint_mask)


def train_read_out(fine_config, width, maps, objects, hints, hint_mask, epochs, lr, batch, seed=0) -> list[dict]:
    """Per epoch: training loss (cell units), validation mean error (m) and share within 5 m."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    cells = maps.cells
    target = torch.from_numpy(
        ((maps.pose_w - cells.origins[maps.pose_cell]) / cells.sizes[maps.pose_cell, None] - 0.5).astype(np.float32)
    )
    size = cells.sizes[maps.pose_cell]
    objects, object_mask = torch.from_numpy(objects), torch.from_numpy(cells.object_mask)
    hints, hint_mask = torch.from_numpy(hints), torch.from_numpy(hint_mask)
    model = _ReadOut(fine_config, width, objects.shape[-1], hints.shape[-1])
    opt = torch.optim.Adam(model.parameters(), lr)
    train_q, val_q = np.flatnonzero(~maps.validation), np.flatnonzero(maps.validation)

    def predict(q):
        c = torch.from_numpy(maps.pose_cell[q])
        return model(objects[c], object_mask[c], hints[q], hint_mask[q])

    rows = []
    for epoch in range(1, epochs + 1):
        model.train()
        losses = []
        for q in np.array_split(rng.permutation(train_q), max(1, len(train_q) // batch)):
            loss = (predict(q) - target[q]).norm(dim=1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
        model.eval()
        with torch.no_grad():
            err = (predict(val_q) - target[val_q]).norm(dim=1).numpy() * size[val_q]
        rows.append(
            {
                "epoch": epoch,
                "loss": float(np.mean(losses)),
                "error_m": float(err.mean()),
                "within_5m": 100 * float((err <= 5).mean()),
            }
        )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/des4pos_fine_inputs.py", description=__doc__.splitlines()[0])
    ap.add_argument("--card", default="des4pos")
    ap.add_argument(
        "--checkpoint", type=Path, required=True, help="a trained run's best.pth (its coarse stage is used)"
    )
    ap.add_argument("--cities", type=Path, required=True, help="make-city maps; the last by name validates")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--batch", type=int, default=32)
    args = ap.parse_args(argv)
    torch.set_num_threads(training_run.THREADS)
    card = load_card(args.card)
    model = create_model(card, args.checkpoint).eval()
    maps = load_text_maps(
        args.cities, model.cell_config.max_objects, model.cell_config.points_per_object, model.text_config.max_hints
    )
    hints, hint_mask = hint_streams(card, model, maps)
    objects = {s: clean_objects(maps) if s == "clean" else coarse_objects(model, maps, s) for s in OBJECT_STREAMS}
    cells = maps.cells
    val_q = np.flatnonzero(maps.validation)
    centre = np.linalg.norm(
        maps.pose_w[val_q] - cells.origins[maps.pose_cell[val_q]] - cells.sizes[maps.pose_cell[val_q], None] / 2, axis=1
    )
    fine_config, width = model.fine.cfg, model.submap.cfg.embed_dim
    print(
        f"{len(val_q)} validation poses; the cell centre misses by {centre.mean():.2f} m, "
        f"{100 * (centre <= 5).mean():.1f} % within 5 m",
        flush=True,
    )
    runs = []
    for obj, hint in PAIRS:
        t0 = time.perf_counter()
        rows = train_read_out(
            fine_config, width, maps, objects[obj], hints[hint], hint_mask, args.epochs, args.lr, args.batch
        )
        best = min(rows, key=lambda r: r["error_m"])
        runs.append(
            {"objects": obj, "hints": hint, "epochs": rows, "best": best, "seconds": round(time.perf_counter() - t0, 1)}
        )
        print(
            f"objects {obj:8s} hints {hint:8s}: best epoch {best['epoch']}, {best['error_m']:.2f} m, "
            f"{best['within_5m']:.1f} % within 5 m",
            flush=True,
        )
    out = {
        "card": card.name,
        "machine": training_run.machine(),
        "command": f"python benchmarks/des4pos_fine_inputs.py --checkpoint {args.checkpoint} --cities {args.cities}"
        f" --epochs {args.epochs} --lr {args.lr:g} --batch {args.batch}",
        "training_poses": int((~maps.validation).sum()),
        "validation_poses": len(val_q),
        "cells": len(cells.ids),
        "centre": {"error_m": float(centre.mean()), "within_5m": 100 * float((centre <= 5).mean())},
        "runs": runs,
    }
    save_result("des4pos-fine-inputs", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
