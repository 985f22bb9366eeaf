"""TDFANet's training recipe (paper sections III-D and IV-B) behind ``radaredge train``.

What the paper fixes, and this recipe follows:
- loss: the lazy quadruplet loss (eq. 10) with alpha 0.2, beta 0.1 (:mod:`.losses`);
- positives within 5 m of the query, true negatives beyond 10 m (:mod:`.places`);
- optimiser: Adam, learning rate 8e-4, exponential decay with base 0.9 (applied once per epoch);
- batch size 1 (one tuple per optimiser step; ``batch_size`` tuples per step otherwise).

What the paper leaves open, and how this recipe reads it (each an option, recorded in the log):
- The tuple follows PointNetVLAD (the loss's source, the paper's reference [18]): 2 positives,
  negatives and the other negative neg*. From ``hard_from_epoch`` on, ``hard_negatives`` of the
  negatives are the nearest to the query in descriptor space among up to ``hard_pool`` random
  true negatives, using the descriptors of the previous epoch's validation pass; the rest are
  random. PointNetVLAD takes 18 negatives, 10 of them hard from a pool of 4000; the defaults
  take 10, 6 of them hard (a tuple's cost on a CPU grows with its windows, and on the synthetic
  towns the shorter tuple reached the same recall). neg* is a random true negative of the query
  and of every negative (PointNetVLAD's code); the paper's text calls it a hard negative, which
  ``other_negative: hardest`` takes (the nearest such window in descriptor space).
- BatchNorm: the statistics are estimated once on ``norm_windows`` training windows (their
  average batch statistics, each window a batch) and then held fixed while the weights train
  (``batch_norm: frozen``), so training normalises exactly as the exported graph does;
  ``batch_norm: reestimate`` estimates them again from the same windows after every epoch, with
  the weights trained so far, and trains the next epoch with those. With
  per-window batch statistics (``batch_norm: window``) held-out Recall@1 was 14 points lower in
  eval mode than with the same weights normalised per window: one window's three frames are too
  few for statistics a whole drive shares.
- Distances are taken between L2-normalised descriptors, the ones retrieval compares
  (``descriptor_normalized``).
- An epoch is one tuple for every training window that has a positive in another drive, in a
  seeded random order. Positives come from other drives only: a drive's own neighbouring
  windows share scans with the query, and retrieval always meets another drive.
- With ``batch_norm: window`` each window is its own BatchNorm batch (its K frames; the pillar
  net's statistics over its padded pillars as OpenPCDet computes them). Pushing a whole tuple
  through as one batch is slower on a CPU (the tuple's 256-channel maps fall out of cache).
- Validation is by drive (:func:`.places.default_validation`): the held-out drives' windows are
  queries against every training window, scored by Recall@1/5/10 with the 5 m radius; the
  epoch with the best Recall@1 (then @5, @10) is kept as ``best.pth``. Epoch 0 is the
  initialisation, before any step.
- The RANSAC, the dynamic-point mask and the grid displacement hold no parameters: they run once
  per window before training (:meth:`radaredge.models.tdfanet.model.TDFANet.prepare`).
- ``last.pth`` is written after epoch 0 (the initial descriptors), after every epoch, and within
  an epoch every ``save_minutes`` of training (0: after every step), so an interrupted run of a
  large card loses at most that much; ``--resume`` continues at the next step as the run that
  never stopped would.
- ``qat`` (``radaredge train --qat``, ours) fine-tunes ``--checkpoint``'s weights with the int8
  graph's fake quantisation (:mod:`.qat`); the first activation ranges are observed on the
  ``norm_windows`` training windows before epoch 0, and best.pth keeps the learned ranges.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..cards import ModelCard
from ..config import Range, card_ranges, positive
from ..data.bag_drives import BagSource
from ..errors import ConfigError, InputError
from ..eval.places import RECALL_NS, recall_at_n
from ..progress import no_progress
from .losses import SECOND_TERMS, lazy_quadruplet_loss
from .places import OTHER_NEGATIVES, PlaceWindows, TupleMiner, load_place_windows
from .qat import resume_signature, start_qat
from .run import (
    RunDir,
    Stopwatch,
    TrainingState,
    TrainReport,
    pick_device,
    recipe_from_options,
    set_torch_rng_state,
    torch_rng_state,
)

BATCH_NORMS = ("frozen", "reestimate", "window")
FIXED_NORMS = ("frozen", "reestimate")  # training normalises with fixed statistics, as the graph does


@card_ranges(
    epochs=(1, 10_000),
    batch_size=(1, 1024),
    lr=positive(1.0),
    lr_decay=Range(0.0, 1.0, True),
    positives=(1, 64),
    negatives=(1, 256),
    hard_negatives=(0, 256),
    hard_pool=(1, 10**7),
    hard_from_epoch=(1, 10_000),
    alpha=(0.0, 10.0),
    beta=(0.0, 10.0),
    positive_radius=positive(1e4),
    negative_radius=positive(1e4),
    seed=(0, 2**32 - 1),
    weight_decay=(0.0, 1.0),
    norm_windows=(1, 10**6),
    tuples_per_epoch=(0, 10**7),
    save_minutes=(0.0, 10_000.0),
)
@dataclass(frozen=True)
class PlaceRecipe:
    """The options of TDFANet training (module docstring); defaults are the paper's where it
    gives a value and PointNetVLAD's tuple otherwise."""

    epochs: int = 5
    batch_size: int = 1  # tuples per optimiser step (paper: 1)
    lr: float = 8e-4  # Adam (paper)
    lr_decay: float = 0.9  # exponential decay per epoch (paper: base 0.9)
    weight_decay: float = 0.0
    positives: int = 2  # PointNetVLAD's (18 negatives, 10 hard); ours: 10, 6 hard
    negatives: int = 10
    hard_negatives: int = 6
    hard_pool: int = 4000
    hard_from_epoch: int = 1  # 1: mine from the first epoch on, with the initial descriptors
    alpha: float = 0.2  # eq. 10 margins (paper)
    beta: float = 0.1
    second_term: str = "paper"  # eq. 10 as printed, or "pointnetvlad" (see losses.py)
    batch_norm: str = "frozen"  # "frozen": statistics estimated once, then fixed; "reestimate": also after
    # every epoch from the trained weights; "window": batch statistics
    norm_windows: int = 200  # training windows the frozen statistics are estimated on
    tuples_per_epoch: int = 0  # ours: 0 = every training window once an epoch; N: N of them, drawn anew
    other_negative: str = "random"  # neg*: "random" true negative, or the "hardest" (nearest descriptor) one
    positive_radius: float = 5.0  # m (paper)
    negative_radius: float = 10.0  # m (paper)
    seed: int = 0
    save_minutes: float = 10.0  # ours: minutes of training between saves of last.pth within an epoch
    qat: bool = False  # quantisation-aware fine-tuning of --checkpoint (radaredge.training.qat)

    def __post_init__(self):
        if self.second_term not in SECOND_TERMS:
            raise ValueError(f"second_term must be one of {list(SECOND_TERMS)}, got {self.second_term!r}")
        if self.negative_radius < self.positive_radius:
            raise ValueError(
                f"negative_radius ({self.negative_radius} m) must not be below positive_radius "
                f"({self.positive_radius} m)"
            )
        if self.other_negative not in OTHER_NEGATIVES:
            raise ValueError(f"other_negative must be one of {list(OTHER_NEGATIVES)}, got {self.other_negative!r}")
        if self.batch_norm not in BATCH_NORMS:
            raise ValueError(f"batch_norm must be one of {list(BATCH_NORMS)}, got {self.batch_norm!r}")
        if self.hard_negatives > self.negatives:
            raise ValueError(f"hard_negatives ({self.hard_negatives}) cannot exceed negatives ({self.negatives})")

    @classmethod
    def from_options(cls, options: dict) -> "PlaceRecipe":
        """The recipe with ``options`` over the defaults (:func:`radaredge.training.run.recipe_from_options`)."""
        return recipe_from_options(cls, options, "TDFANet")


def prepare_windows(model, data: PlaceWindows, device: torch.device, progress=no_progress) -> list:
    """:meth:`TDFANet.prepare` of every window of ``data``, on ``device``."""
    bar = progress("prepare windows (RANSAC, masks, alignment)", len(data))
    out = []
    with torch.no_grad():
        for i in range(len(data)):
            scans, t = data.inputs(i, model.features)
            for k, scan in enumerate(scans):
                bad = ~np.isfinite(scan)
                if bad.any():
                    point, column = (int(x[0]) for x in np.nonzero(bad))
                    raise InputError(
                        data.locate_error(
                            i,
                            f"frame {k}: non-finite value {scan[point, column]} at point "
                            f"{point}, column {model.features[column]!r}",
                        )
                    )
            out.append(
                model.prepare(
                    [torch.from_numpy(s).to(device) for s in scans],
                    torch.as_tensor(t, dtype=torch.float32, device=device),
                )
            )
            bar.update()
    bar.close()
    return out


def ego_motion_summary(data: PlaceWindows, prepared: Sequence) -> list[str]:
    """One line on the RANSAC ego velocity of the windows' current scans (how many are valid, the
    median forward speed), and a warning per drive whose radar seems to move backwards: a
    forward-looking radar on a car moving forwards has v_x > 0, and a reversed Doppler sign
    (positive approaching) flips it."""
    v = np.stack([w.ego_velocity[-1].cpu().numpy() for w in prepared])
    ok = np.array([bool(w.ego_valid[-1]) for w in prepared])
    lines = [
        f"ego velocity (RANSAC): valid in {100 * ok.mean():.0f} % of the windows' current scans, median speed "
        f"{np.median(np.linalg.norm(v[ok], axis=1)) if ok.any() else 0.0:.1f} m/s"
    ]
    for row, name in enumerate(data.names):
        mine = ok & (data.drive == row)
        if mine.sum() >= 3 and np.median(v[mine, 0]) < -0.5:
            lines.append(
                f"warning: {data.path / name}: the radar moves backwards in its RANSAC fits (median v_x "
                f"{np.median(v[mine, 0]):.1f} m/s); if the car drove forwards, its Doppler sign is reversed "
                f"(positive approaching; radaredge's v_r is positive moving away)"
            )
    return lines


def describe_all(model, prepared: Sequence, progress=no_progress, desc: str = "describe") -> np.ndarray:
    """L2-normalised descriptors [W, D] of every prepared window, eval mode, no gradients (each
    module's mode is restored afterwards)."""
    modes = [(m, m.training) for m in model.modules()]
    model.eval()
    bar = progress(desc, len(prepared))
    out = []
    with torch.no_grad():
        for w in prepared:
            out.append(F.normalize(model.describe([w]), dim=1)[0].cpu().numpy())
            bar.update()
    bar.close()
    for m, mode in modes:
        m.training = mode
    return np.stack(out)


def validation_recall(descriptors: np.ndarray, data: PlaceWindows, radius: float) -> dict[str, float]:
    """The epoch's validation metrics: ``val_R@N`` (%), Recall@1/5/10 of the validation windows
    against the training windows, and ``val_queries``, how many validation windows had a
    training window within ``radius`` m (the queries those percentages are of)."""
    val, train = data.validation, ~data.validation
    res = recall_at_n(
        descriptors[val],
        data.positions[val],
        descriptors[train],
        data.positions[train],
        RECALL_NS,
        radius,
        use_faiss=False,
    )
    return {**{f"val_R@{n}": float(r) for n, r in res["recall"].items()}, "val_queries": int(res["evaluated"])}


def _norms(model) -> list:
    return [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]


def estimate_norm_statistics(model, prepared: Sequence, windows: np.ndarray) -> None:
    """Set every BatchNorm's running statistics to the average of its batch statistics over
    ``windows`` (each window one batch, described in train mode without dropout or gradients),
    as "precise BN" estimates population statistics."""
    norms = _norms(model)
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average
    model.train()
    dropouts = [m for m in model.modules() if isinstance(m, torch.nn.Dropout)]
    for m in dropouts:
        m.eval()
    with torch.no_grad():
        for i in windows:
            model.describe([prepared[int(i)]])
    for m, momentum in zip(norms, momenta):
        m.momentum = momentum
    model.eval()


def set_train_mode(model, recipe: "PlaceRecipe") -> None:
    """Train mode (dropout on); with ``batch_norm: frozen`` the BatchNorm layers stay in eval mode
    and normalise with their fixed statistics, exactly as the exported graph does."""
    model.train()
    if recipe.batch_norm in FIXED_NORMS:
        for m in _norms(model):
            m.eval()


def _describe_window(model, window) -> torch.Tensor:
    """L2-normalised descriptor [1, D] of one prepared window (its own BatchNorm batch)."""
    return F.normalize(model.describe([window]), dim=1)


class _FrozenNormStatistics:
    """Within the block, BatchNorm layers normalise with batch statistics (train mode) but leave
    their running statistics as they are (momentum 0)."""

    def __init__(self, model):
        self.norms = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]

    def __enter__(self):
        self.saved = [(m.momentum, m.num_batches_tracked.clone()) for m in self.norms]
        for m in self.norms:
            m.momentum = 0.0

    def __exit__(self, *exc):
        for m, (momentum, tracked) in zip(self.norms, self.saved):
            m.momentum = momentum
            m.num_batches_tracked.copy_(tracked)


def tuple_loss(model, prepared: Sequence, tup, recipe: PlaceRecipe) -> tuple[torch.Tensor, int]:
    """Eq. 10 of one tuple, with gradients, and the number of windows described with gradients.

    Every window is described in train mode (its own BatchNorm batch), L2-normalised, and the
    tuple scored by :func:`lazy_quadruplet_loss`. The loss reaches the weights through at most a
    few windows: the query, the best positive, the hardest negative and neg* (and, in the
    ``pointnetvlad`` form, the negative nearest neg*). So all windows are first described
    without gradients, the loss's gradient with respect to those descriptors tells which
    windows it reaches, and only these are described again with gradients, with the same
    dropout masks (the random state is replayed) and without counting their BatchNorm batches
    twice. The loss and its gradient are exactly those of describing every window with
    gradients; a tuple already satisfying both margins costs no backward pass."""
    idx = [tup.query, *tup.positives, *tup.negatives, tup.other_negative]
    p, n = len(tup.positives), len(tup.negatives)

    def score(d: torch.Tensor) -> torch.Tensor:
        return lazy_quadruplet_loss(
            d[:1], d[1 : 1 + p][None], d[1 + p : 1 + p + n][None], d[-1:], recipe.alpha, recipe.beta, recipe.second_term
        )

    dev = next(model.parameters()).device
    states = []
    with torch.no_grad():
        rows = []
        for i in idx:
            states.append(torch_rng_state(dev))
            rows.append(_describe_window(model, prepared[i]))
    after = torch_rng_state(dev)
    probe = torch.cat(rows).requires_grad_(True)
    loss = score(probe)
    loss.backward()
    active = [j for j in range(len(idx)) if bool(probe.grad[j].abs().sum() > 0)]
    if not active:
        return loss.detach(), 0
    with _FrozenNormStatistics(model):  # these batches were counted by the pass above
        for j in active:
            set_torch_rng_state(states[j], dev)
            rows[j] = _describe_window(model, prepared[idx[j]])
    set_torch_rng_state(after, dev)
    return score(torch.cat(rows)), len(active)


def _signature(card: ModelCard, data: PlaceWindows, recipe: PlaceRecipe) -> dict:
    """What a resumed run must share with the one that wrote ``last.pth``."""
    options = dataclasses.asdict(recipe)
    keep = resume_signature({k: v for k, v in options.items() if k not in ("epochs", "save_minutes")})
    return {
        "card": card.data,
        "data": str(Path(data.path).resolve()),
        "windows": len(data),
        "validation": sorted({data.names[r] for r in data.drive[data.validation]}),
        "recipe": keep,
    }


def _rank(metrics: dict) -> tuple:
    return tuple(metrics[f"val_R@{n}"] for n in RECALL_NS)


def train_places(
    card: ModelCard,
    model,
    data_root: str | Path,
    output: str | Path,
    recipe: PlaceRecipe,
    device: str = "cpu",
    resume: bool = False,
    validation: Sequence[str] | None = None,
    data_format: str | None = None,
    progress=no_progress,
    log: Callable[[str], None] = lambda line: None,
    bag: BagSource | None = None,
    checkpoint: str | None = None,
) -> TrainReport:
    """Train ``model`` (a TDFANet of ``card``) on the drives under ``data_root`` with ``recipe``;
    write the run directory ``output`` (:mod:`.run`) and return the report. ``validation`` names
    the held-out drives (paths relative to ``data_root``; default one per directory of drives),
    ``data_format`` the scan format of every drive (default inferred), ``bag`` where ROS bag
    drives keep their scans and GNSS fixes; ``checkpoint`` the initial weights' file (a ``qat``
    run fine-tunes them, :mod:`.qat`)."""
    dev = pick_device(device)
    run = RunDir(output, card)
    if resume:
        run.require_last()  # before reading the data, not after
    data = load_place_windows(
        data_root, model.frames, validation, data_format, recipe.positive_radius, model.features, bag
    )
    miner = TupleMiner(
        data,
        recipe.positives,
        recipe.negatives,
        recipe.hard_negatives,
        recipe.positive_radius,
        recipe.negative_radius,
        recipe.hard_pool,
        recipe.other_negative,
    )
    summary = {
        "root": str(data_root),
        "drives": len(data.names),
        "windows": len(data),
        "training_windows": int((~data.validation).sum()),
        "validation_windows": int(data.validation.sum()),
        "queries_per_epoch": min(len(miner.queries), recipe.tuples_per_epoch or len(miner.queries)),
        "validation_drives": sorted({data.names[r] for r in data.drive[data.validation]}),
    }
    log(
        f"data: {summary['drives']} drives, {summary['windows']} windows of K = {model.frames} "
        f"({summary['training_windows']} training, {summary['validation_windows']} validation); "
        f"{summary['queries_per_epoch']} training queries per epoch"
    )
    model.to(dev)
    fake_quant = start_qat(model, card, "fp32", bool(checkpoint) or resume) if recipe.qat else None
    prepared = prepare_windows(model, data, dev, progress)
    for line in ego_motion_summary(data, prepared):
        log(line)
    rng = np.random.default_rng(recipe.seed)
    torch.manual_seed(recipe.seed)
    opt = torch.optim.Adam(model.parameters(), lr=recipe.lr, weight_decay=recipe.weight_decay)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=recipe.lr_decay)
    signature = _signature(card, data, recipe)
    report = TrainReport(
        card.name, run.path, "val_R@1", data=summary, options={**dataclasses.asdict(recipe), "device": device}
    )
    start, best_rank = 1, None
    train_rows = np.flatnonzero(~data.validation)
    norm_rows = np.sort(
        np.random.default_rng(recipe.seed).choice(train_rows, min(recipe.norm_windows, len(train_rows)), replace=False)
    )
    partial = None  # the epoch a mid-epoch last.pth stopped in: its queries, tuples done, losses
    saved_state = TrainingState(run, signature, model, rng, report, opt, sched)
    if resume:
        state, clock = saved_state.resume(recipe.epochs)
        start, partial = state["epoch"] + 1, state.get("partial")
        best_rank = _rank(report.best) if report.best is not None else None
        descriptors = state["descriptors"].numpy()
        if fake_quant is not None:
            fake_quant.load_state_dict(state["qat"])
        where = f"{partial['done']} of epoch {start}'s tuples" if partial else f"epoch {state['epoch']}"
        log(f"resuming after {where} from {run.last}")
    else:
        clock = Stopwatch()
        if fake_quant is not None:  # the first activation ranges, on training windows
            with fake_quant.observing():
                describe_all(model, [prepared[i] for i in norm_rows])
        if recipe.batch_norm in FIXED_NORMS:
            estimate_norm_statistics(model, prepared, norm_rows)
        descriptors = describe_all(model, prepared, progress, "epoch 0: describe windows")
        metrics = validation_recall(descriptors, data, recipe.positive_radius)
        report.epochs.append(
            {"epoch": 0, "loss": float("nan"), "lr": recipe.lr, **metrics, "seconds": round(clock(), 1)}
        )
        report.seconds = clock()
        log(_epoch_line(report.epochs[-1]))

    def save_last(epoch: int, partial: dict | None = None) -> None:
        """last.pth after ``epoch``, or within the next epoch (``partial``)."""
        saved_state.save(
            epoch,
            clock,
            descriptors=torch.from_numpy(descriptors),
            **({"partial": partial} if partial else {}),
            **({"qat": fake_quant.state_dict()} if fake_quant else {}),
        )

    if not resume:
        save_last(0)
        run.write_log(report.to_dict())
    for epoch in range(start, recipe.epochs + 1):
        miner.set_descriptors(descriptors if epoch >= recipe.hard_from_epoch else None)
        if partial:
            queries, done, losses = partial["queries"].numpy(), partial["done"], list(partial["losses"])
            partial = None
        else:
            queries, done, losses = rng.permutation(miner.queries)[: recipe.tuples_per_epoch or None], 0, []
        set_train_mode(model, recipe)
        bar = progress(f"epoch {epoch}/{recipe.epochs}", len(queries))
        bar.update(done)
        saved = clock()
        for first in range(done, len(queries), recipe.batch_size):
            batch = [miner.tuple_for(int(q), rng) for q in queries[first : first + recipe.batch_size]]
            scored = [tuple_loss(model, prepared, t, recipe) for t in batch]
            loss = torch.stack([s for s, _ in scored]).mean()
            opt.zero_grad()
            if any(active for _, active in scored):
                loss.backward()
            else:  # Adam still steps on a zero gradient (its moments decay)
                for param in model.parameters():
                    param.grad = torch.zeros_like(param)
            opt.step()
            losses.append(float(loss.detach()))
            bar.update(len(batch))
            bar.set_postfix(loss=f"{np.mean(losses[-50:]):.4f}", val_R1=f"{report.epochs[-1]['val_R@1']:.1f}")
            done = first + len(batch)
            if done < len(queries) and clock() - saved >= 60.0 * recipe.save_minutes:
                save_last(epoch - 1, {"queries": torch.from_numpy(queries), "done": done, "losses": losses})
                saved = clock()
        bar.close()
        lr = opt.param_groups[0]["lr"]
        sched.step()
        if recipe.batch_norm == "reestimate":
            estimate_norm_statistics(model, prepared, norm_rows)
        descriptors = describe_all(model, prepared, progress, f"epoch {epoch}: describe windows")
        metrics = validation_recall(descriptors, data, recipe.positive_radius)
        loss_mean = float(np.mean(losses)) if losses else float("nan")
        if not math.isfinite(loss_mean) or not np.isfinite(descriptors).all():
            raise ConfigError(f"training diverged in epoch {epoch} (loss {loss_mean}); lower --lr (now {recipe.lr:g})")
        report.epochs.append({"epoch": epoch, "loss": loss_mean, "lr": lr, **metrics, "seconds": round(clock(), 1)})
        if best_rank is None or _rank(metrics) > best_rank:
            best_rank, report.best_epoch = _rank(metrics), epoch
            run.save_best(model, epoch, metrics, **({"qat": fake_quant.checkpoint_entry()} if fake_quant else {}))
        report.seconds = clock()
        save_last(epoch)
        run.write_log(report.to_dict())
        log(_epoch_line(report.epochs[-1]) + ("  (best)" if report.best_epoch == epoch else ""))
    report.seconds = clock()
    run.write_log(report.to_dict())
    if fake_quant is not None:
        fake_quant.remove()
    model.eval()
    return report


def _epoch_line(e: dict) -> str:
    recall = " / ".join(f"{e[f'val_R@{n}']:.1f}" for n in RECALL_NS)
    loss = "-" if not math.isfinite(e["loss"]) else f"{e['loss']:.4f}"
    return (
        f"epoch {e['epoch']:>3}: loss {loss}, validation R@{'/'.join(map(str, RECALL_NS))} {recall} %, "
        f"{e['seconds'] / 60:.1f} min"
    )
