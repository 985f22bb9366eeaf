"""Fit TDFANet's descriptors to recognise places in a synthetic town: a test article for int8.

Why. With the seeded weights, tdfanet-edge maps every window of the synthetic town benchmark to
nearly one descriptor: a query's nearest database descriptor is barely closer than the second,
so int8 noise decides which of two database windows 1 m apart comes first, and top-1 agreement
measures that tie-breaking. No trained TDFANet checkpoint is published. docs/quantization.md
describes what int8 does to the seeded and to the fitted descriptors.

What it does. It writes a training town with ``radaredge make-benchmark``'s generator (its own
world seed, 1 by default, not the benchmark's 0; six drives of 80 scans), runs the
parameter-free front once per K-frame window (RANSAC ego velocity, static mask, grid
displacement), and fits every layer behind it (pillar VFE, residual pyramid, deformable
aggregation, descriptor MLP, GeM p) as a place recogniser: batches of 8 windows drawn at random
plus, for each, a window of another drive within 3 m; a batch-hard triplet loss on the
L2-normalised descriptors (the farthest positive against the nearest window 15 m or more away,
margin 0.5); Adam at a constant learning rate. Positives are the other windows within 5 m, the
evaluation's true-positive radius: by default those of any drive (``--positives any-drive``),
which also pulls a drive's consecutive windows together, or only other drives' windows, as a
query meets the database (``--positives other-drive``). The choice decides what int8 does to
the fit (docs/quantization.md). The model stays in eval mode (batch norms keep their statistics
and act as learnt affine maps; dropout off). It prints Recall@1/5/10 (%) of the fitted export
formulation on a held-out town (the benchmark's world, seed 0) and writes a checkpoint, a test
article for int8 (descriptors that separate places), not a trained TDFANet: synthetic scans,
one street.

    python -m radaredge.fitting.tdfanet_places --out export/tdfanet-edge-fitted.pth
    radaredge export --model tdfanet-edge --checkpoint export/tdfanet-edge-fitted.pth \\
        --output export/tdfanet-edge-fitted.onnx --quantize int8
    radaredge make-benchmark --out bench-town
    radaredge eval --model tdfanet-edge --checkpoint export/tdfanet-edge-fitted.pth \\
        --onnx export/tdfanet-edge-fitted.int8.onnx --database bench-town/database --queries bench-town/queries
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..cards import load_card
from ..data.pr_benchmark import DATABASE_DIR, QUERIES_DIR, make_pr_benchmark
from ..evaluation import RECALL_NS, load_windows, recall_at_n
from ..exporter import build_model, save_checkpoint
from ..ops.alignment import grid_displacement
from ..ops.scan_batch import concat_scans

POSITIVE_RADIUS = 5.0   # m: windows this close are the same place (radaredge eval's radius)
NEGATIVE_RADIUS = 15.0  # m: windows this far apart are other places; 5-15 m is neither
PAIR_RADIUS = 3.0       # m: each anchor's batch partner, a window of another drive, lies this close
QUERY_DRIVES = 1000     # drive ids: database drives 0.., query drives 1000..
MARGIN = 0.5            # triplet margin on unit-length descriptors (distances 0..2)


@dataclass
class Window:
    """One K-frame window after the parameter-free front: ``points`` [N, F] of its K scans
    concatenated (oldest first), ``frame`` [N] int64 scan index per point, ``static`` [N] bool
    (RANSAC inliers), ``cells`` [K, 2] grid displacement to the last scan (cells), ``position``
    (northing, easting) m of the last scan, ``drive`` an id unique to its drive."""

    points: torch.Tensor
    frame: torch.Tensor
    static: torch.Tensor
    cells: torch.Tensor
    position: np.ndarray
    drive: int


def prepare_windows(model, town: Path, features) -> list[Window]:
    """Every K-frame window of the database and query drives under ``town`` (make-benchmark
    layout), run through the RANSAC and the grid displacement once (they hold no parameters)."""
    out = []
    for role_id, role in enumerate((DATABASE_DIR, QUERIES_DIR)):
        ws = load_windows(town / role, model.frames)
        for i in range(len(ws)):
            scans, timestamps = ws.inputs(i, features)
            pts, frame = concat_scans([torch.from_numpy(s) for s in scans])
            with torch.no_grad():
                everywhere = torch.ones(len(pts), dtype=torch.bool)
                v_ego, static, _ = model.ransac.estimate_frames(pts[:, :3], pts[:, 3], everywhere, frame, len(scans))
            cells = grid_displacement(v_ego, model.vfe.config.voxel_size,
                                      timestamps=torch.as_tensor(timestamps, dtype=torch.float32))
            out.append(Window(pts, frame, static, cells, ws.positions[i], QUERY_DRIVES * role_id + ws.items[i][0]))
    return out


def describe(model, w: Window) -> torch.Tensor:
    """Unit-length descriptor [D] of a prepared window: the export formulation from the pillar
    scatter on, with gradients."""
    bev = model.vfe.scatter_frames(w.points, w.static, w.frame, model.frames)[0]
    return F.normalize(model.aggregate(bev, w.cells, False, None), dim=0)


def sample_batch(windows: list[Window], rng: np.random.Generator, places: int = 8) -> list[int]:
    """``places`` random windows, each followed by a random window of another drive within
    PAIR_RADIUS m of it (when there is one), so every anchor has a positive in the batch."""
    pos = np.array([w.position for w in windows])
    drive = np.array([w.drive for w in windows])
    batch = []
    for a in rng.choice(len(windows), places, replace=False):
        near = np.flatnonzero((np.linalg.norm(pos - pos[a], axis=1) <= PAIR_RADIUS) & (drive != drive[a]))
        batch += [int(a), int(rng.choice(near))] if len(near) else [int(a)]
    return batch


def triplet_loss(desc: torch.Tensor, positions: torch.Tensor, drives: torch.Tensor,
                 same_drive: bool = True) -> torch.Tensor:
    """Batch-hard triplet loss of unit descriptors [B, D] with positions [B, 2] m and drive ids
    [B]: per anchor with both, relu(farthest positive - nearest negative + MARGIN), where positives
    are the other batch entries within POSITIVE_RADIUS m (with ``same_drive`` False only those of
    another drive) and negatives windows NEGATIVE_RADIUS m or more away; the mean over those
    anchors (0 when there is none)."""
    d = torch.cdist(desc, desc)
    g = torch.cdist(positions, positions)
    others = ~torch.eye(len(desc), dtype=torch.bool) if same_drive else drives[:, None] != drives[None, :]
    positive = (g <= POSITIVE_RADIUS) & others
    negative = g >= NEGATIVE_RADIUS
    hardest_pos = torch.where(positive, d, torch.full_like(d, -1.0)).max(1).values
    hardest_neg = torch.where(negative, d, torch.full_like(d, 9.0)).min(1).values
    both = positive.any(1) & negative.any(1)
    if not both.any():
        return desc.sum() * 0.0
    return F.relu(hardest_pos - hardest_neg + MARGIN)[both].mean()


def fit(model, windows: list[Window], steps: int, lr: float, seed: int = 0, same_drive: bool = True,
        log=print) -> None:
    """Adam at a constant ``lr`` over ``steps`` batches of :func:`sample_batch`, minimising
    :func:`triplet_loss` (``same_drive`` as there); every parameter trains (RANSAC and alignment
    have none). The model stays in eval mode."""
    model.eval()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    running = []
    for step in range(steps):
        idx = sample_batch(windows, rng)
        desc = torch.stack([describe(model, windows[i]) for i in idx])
        loss = triplet_loss(desc, torch.tensor(np.array([windows[i].position for i in idx])),
                            torch.tensor([windows[i].drive for i in idx]), same_drive)
        opt.zero_grad()
        loss.backward()
        opt.step()
        running.append(loss.item())
        if (step + 1) % 50 == 0 or step == steps - 1:
            log(f"  step {step + 1:4d}  loss {np.mean(running):.4f}  ({time.perf_counter() - t0:.0f} s)")
            running = []


def town_recall(model, windows: list[Window]) -> dict[int, float]:
    """Recall@1/5/10 (%) of the export formulation's query windows against the database windows
    of one prepared make-benchmark town (true positive within POSITIVE_RADIUS m)."""
    with torch.no_grad():
        desc = np.stack([describe(model, w).numpy() for w in windows])
    pos = np.array([w.position for w in windows])
    query = np.array([w.drive >= QUERY_DRIVES for w in windows])
    return recall_at_n(desc[query], pos[query], desc[~query], pos[~query], RECALL_NS, POSITIVE_RADIUS,
                       use_faiss=False)["recall"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m radaredge.fitting.tdfanet_places",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--card", default="tdfanet-edge")
    ap.add_argument("--steps", type=int, default=400,
                    help="Adam steps, one batch of 8 places (each with a partner window of another drive) each")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--positives", choices=("any-drive", "other-drive"), default="any-drive",
                    help="which windows within 5 m of an anchor are its positives")
    ap.add_argument("--train-seed", type=int, default=1, help="world seed of the training town")
    ap.add_argument("--test-seed", type=int, default=0, help="world seed of the held-out town (the benchmark's)")
    ap.add_argument("--out", type=Path,
                    help="default export/<card>-fitted.pth (-fitted-other-drive.pth), under the working directory")
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    card = load_card(args.card)
    model = build_model(card)
    suffix = "" if args.positives == "any-drive" else "-other-drive"
    out = args.out or Path("export") / f"{card.name}-fitted{suffix}.pth"
    with tempfile.TemporaryDirectory() as tmp:
        train_town, test_town = Path(tmp) / "train", Path(tmp) / "test"
        make_pr_benchmark(train_town, drives=6, frames_per_drive=80, seed=args.train_seed)
        make_pr_benchmark(test_town, seed=args.test_seed)
        windows = prepare_windows(model, train_town, card.features)
        print(f"training town (seed {args.train_seed}): {len(windows)} windows")
        test_windows = prepare_windows(model, test_town, card.features)
        before = town_recall(model, test_windows)
        fit(model, windows, args.steps, args.lr, same_drive=args.positives == "any-drive")
        after = town_recall(model, test_windows)
    fmt = lambda r: "/".join(f"{v:.1f}" for v in r.values())  # noqa: E731
    print(f"held-out town (seed {args.test_seed}) R@{'/'.join(map(str, RECALL_NS))}: seeded {fmt(before)} %, "
          f"fitted {fmt(after)} %")
    print(f"wrote {save_checkpoint(model, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
