"""Des4Pos's training recipe (paper sections III-B to IV-A; upstream: Text2Loc's scripts, which
upstream Des4Pos keeps unchanged) behind ``radaredge train``.

Stages, in order (``stages``; each keeps the weights of its best validation epoch):

1. ``objects``: Text2Pos's PointNet++ pretraining: the object network and its class head as an
   object classifier (cross-entropy on the object labels of the training cells), so the
   geometry feature knows what an object is. Text2Pos publishes such weights: ``object_weights``
   loads them (:mod:`radaredge.models.des4pos.weights`) and ``stages`` can then leave this out.
2. ``prior``: eq. 8, the STE's cross-modal prior. The prior head's max-pooled output is aligned
   by 1 - cosine to a teacher's embedding of each hint sentence. The paper's teacher is CLIP's
   text encoder; no package of the registries ships CLIP's weights for offline use, so the
   teacher is the frozen backbone's own sentence embedding (mean over tokens, L2-normalised:
   all-MiniLM-L6-v2's trained output), and ``text.prior_dim`` is its width. Adam 1e-4, batch 8
   (upstream's STE stage 1). The prior head is then frozen, as the paper says.
3. ``coarse``: eq. 9, symmetric InfoNCE (temperature 0.1) between the description descriptors
   and their best cells' descriptors over a batch of 64 descriptions; Adam 5e-4, StepLR 7 / 0.4
   (Text2Loc's command line). Two descriptions of one cell in a batch are not each other's
   negatives (``duplicate_cells: mask``; Text2Loc counts them as negatives, ``negatives``). The
   hints of a description are shuffled (Text2Loc). The PointNet++ stays frozen unless
   ``train_pointnet`` (Text2Loc fine-tunes it: on a CPU that is most of the time).
4. ``hints``: the fine text branch's warm-up. The fine stage below on the LSTM states, whatever
   the card's ``fine.object_state``, for ``hints_epochs``, keeping the last epoch's text branch;
   the CRA it trains beside it is thrown away (the ``fine`` stage starts its CRA again from the
   weights it had before ``hints``: seeded, or ``--checkpoint``'s).
   A CRA on a per-object stream trained together with a seeded text branch learns the training
   cities and not the objects; on the LSTM states, which each summarise the whole cell, it
   cannot, and the text branch it leaves is one the ``fine`` stage's CRA learns the objects
   from (measured: docs/models/des4pos.md, "Training"). No paper or upstream step.
5. ``fine``: eq. 13, the CRA regressor on the frozen coarse encoder's object features ("directly
   reused", III-C) and the fine text branch: the offset of the pose from its best cell's
   centre in cell units, loss the mean L2 norm of the error (eq. 13; ``fine_loss: mse`` is
   Text2Loc's 5 x mean squared error); Adam 3e-4, batch 32, constant rate (Text2Loc; it also
   warms up at 1e-5 for 2 epochs: ``fine_warmup_epochs``). With the card's ``fine.objects:
   encoder`` the fine stage's own object encoder trains with it, on each object's centre, mean
   colour and point count beside the frozen coarse states (Text2Loc's fine stage).

``coarse_weights`` starts from a Des4Pos checkpoint's weights outside the fine stage, which stays
seeded: ``--set stages=fine --set coarse_weights=run/best.pth`` retrains only the fine stage of a
trained model, with the same card or one whose fine stage differs. With ``fine_text_from:
coarse_weights`` the fine text branch comes from the checkpoint too and only the CRA starts
seeded (a CRA on MFAM's object stream learns from trained hint features, and from seeded ones
trained beside it learns the training cities instead: docs/models/des4pos.md).

Validation is by scene (:mod:`.text_maps`): object accuracy, prior cosine, cell retrieval recall
@1/3/5 (the best cell among the top k of the validation scenes' cells; the epoch with the best
@1, then @5, is kept) and the fine stage's mean position error in the best cell (m), beside
the error of the cell centre alone (``centre_error_m``), which the fine stage has to beat.

Frozen parts run once, not every step: the text backbone on every distinct hint, the prior head
after its stage, the PointNet++ after its stage, and the whole coarse encoder in the fine stage.
In train mode the object encoder's BatchNorm sees only real objects, never padding slots.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..cards import ModelCard
from ..config import Range, card_ranges, positive
from ..data.text_maps import TextMaps, load_text_maps
from ..errors import ConfigError, InputError
from ..models.des4pos.model import masked_max, object_summaries
from ..models.des4pos.spec import tokenizer_path
from ..models.des4pos.weights import load_object_weights
from ..progress import no_progress
from ..runtime.text_tokens import encode_hints, load_tokenizer
from .run import RunDir, Stopwatch, TrainingState, TrainReport, load_weights_outside, pick_device, recipe_from_options

STAGES = ("objects", "prior", "coarse", "hints", "fine")
ALIASES = {"epochs": "coarse_epochs", "lr": "coarse_lr", "batch_size": "coarse_batch"}


@card_ranges(
    object_epochs=(0, 10_000),
    object_lr=positive(1.0),
    object_batch=(1, 4096),
    prior_epochs=(0, 10_000),
    prior_lr=positive(1.0),
    prior_batch=(1, 4096),
    coarse_epochs=(0, 10_000),
    coarse_lr=positive(1.0),
    coarse_batch=(2, 4096),
    lr_step=(1, 10_000),
    lr_gamma=Range(0.0, 1.0, True),
    temperature=positive(10.0),
    hints_epochs=(0, 10_000),
    fine_epochs=(0, 10_000),
    fine_lr=positive(1.0),
    fine_batch=(1, 4096),
    fine_warmup_epochs=(0, 10_000),
    fine_warmup_lr=positive(1.0),
    seed=(0, 2**32 - 1),
)
@dataclass(frozen=True)
class TextRecipe:
    """Options of Des4Pos training (module docstring). ``epochs``, ``lr`` and ``batch_size`` given
    to ``radaredge train`` set the coarse stage's."""

    stages: str = "objects,prior,coarse,hints,fine"
    object_epochs: int = 6
    object_lr: float = 3.2e-3  # Text2Pos "lr1": 10**-2.5
    object_batch: int = 32
    prior_epochs: int = 10  # upstream STE stage 1
    prior_lr: float = 1e-4
    prior_batch: int = 8
    coarse_epochs: int = 20  # Text2Loc
    coarse_lr: float = 5e-4
    coarse_batch: int = 64
    lr_step: int = 7
    lr_gamma: float = 0.4
    temperature: float = 0.1  # eq. 9
    duplicate_cells: str = "mask"  # or "negatives" (Text2Loc)
    shuffle_hints: bool = True
    train_pointnet: bool = False
    hints_epochs: int = 4  # the fine text branch's warm-up beside a CRA on the LSTM states
    fine_epochs: int = 35  # Text2Loc
    fine_lr: float = 3e-4
    fine_batch: int = 32
    fine_loss: str = "l2"  # eq. 13; "mse": Text2Loc's 5 x MSE
    fine_warmup_epochs: int = 0  # Text2Loc: 2 epochs at fine_warmup_lr, then fine_lr
    fine_warmup_lr: float = 1e-5
    coarse_weights: str = ""  # a Des4Pos checkpoint: every weight outside the fine stage loaded from it
    # before the first stage (the fine stage stays seeded)
    fine_text_from: str = "seed"  # "coarse_weights": the fine text branch (text.fine_words, text.fine_mlp) loads
    # from coarse_weights too and only the CRA starts seeded
    object_weights: str = ""  # Text2Pos's pointnet_acc0.86_lr1_p256.pth (or a Text2Loc / Des4Pos checkpoint's
    # object encoder), loaded before the first stage
    seed: int = 0

    def __post_init__(self):
        stages = self.stage_list
        unknown = [s for s in stages if s not in STAGES]
        if unknown or not stages:
            raise ValueError(f"stages: unknown {unknown or [self.stages]}; choose from {', '.join(STAGES)}")
        if self.duplicate_cells not in ("mask", "negatives"):
            raise ValueError(f"duplicate_cells must be 'mask' or 'negatives', got {self.duplicate_cells!r}")
        if self.fine_loss not in ("l2", "mse"):
            raise ValueError(f"fine_loss must be 'l2' or 'mse', got {self.fine_loss!r}")
        if self.fine_text_from not in ("seed", "coarse_weights"):
            raise ValueError(f"fine_text_from must be 'seed' or 'coarse_weights', got {self.fine_text_from!r}")
        if self.fine_text_from == "coarse_weights" and not self.coarse_weights:
            raise ValueError("fine_text_from: coarse_weights needs --set coarse_weights=<checkpoint>")

    @property
    def stage_list(self) -> list[str]:
        return [s.strip() for s in self.stages.split(",") if s.strip()]

    @classmethod
    def from_options(cls, options: dict) -> "TextRecipe":
        """The recipe with ``options`` over the defaults (:func:`radaredge.training.run.recipe_from_options`)."""
        return recipe_from_options(cls, options, "Des4Pos", ALIASES)


# ----------------------------------------------------------------------------- text features


@dataclass
class HintTable:
    """Every distinct hint sentence, tokenised: ``ids`` / ``mask`` [U, L]; ``index`` sentence -> row."""

    sentences: list[str]
    ids: torch.Tensor
    mask: torch.Tensor
    index: dict[str, int]


def hint_table(card: ModelCard, maps: TextMaps) -> HintTable:
    text = card.get("text", {}) or {}
    max_tokens = int(text.get("max_tokens", 32))
    sentences = sorted({h for hints in maps.pose_hints for h in hints})
    tok = load_tokenizer(tokenizer_path(card))
    ids, mask = [], []
    for i in range(0, len(sentences), 256):
        chunk = sentences[i : i + 256]
        a, b = encode_hints(tok, chunk, max_tokens, len(chunk))
        ids.append(a)
        mask.append(b)
    return HintTable(
        sentences,
        torch.from_numpy(np.concatenate(ids)),
        torch.from_numpy(np.concatenate(mask)),
        {s: i for i, s in enumerate(sentences)},
    )


def _chunks(n: int, size: int):
    for i in range(0, n, size):
        yield slice(i, min(n, i + size))


def backbone_features(model, table: HintTable, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The frozen backbone's token features [U, L, C] of every hint, and the token mask [U, L]."""
    out = []
    with torch.no_grad():
        for sl in _chunks(len(table.sentences), 128):
            out.append(model.text.backbone(table.ids[sl].to(device), table.mask[sl].to(device)))
    return torch.cat(out), table.mask.to(device) > 0


def teacher_embedding(tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Eq. 8's target: the backbone's sentence embedding, the mean over real tokens, L2-normalised."""
    w = mask.unsqueeze(-1).to(tokens.dtype)
    return F.normalize((tokens * w).sum(1) / w.sum(1).clamp(min=1.0), dim=-1)


# ----------------------------------------------------------------------------- batches


def _padded_hints(maps: TextMaps, table: HintTable, poses: np.ndarray, rng: np.random.Generator | None):
    """Hint rows [B, H] (index into the table; -1 padding) and mask [B, H] of ``poses``; shuffled
    per description with ``rng``."""
    rows = []
    for q in poses:
        hints = list(maps.pose_hints[q])
        if rng is not None:
            hints = [hints[i] for i in rng.permutation(len(hints))]
        rows.append([table.index[h] for h in hints])
    width = max(len(r) for r in rows)
    idx = np.full((len(rows), width), -1, np.int64)
    for i, r in enumerate(rows):
        idx[i, : len(r)] = r
    idx = torch.from_numpy(idx)
    return idx, idx >= 0


def text_descriptors(
    model, prior: torch.Tensor, tmask: torch.Tensor, hint_rows: torch.Tensor, hint_mask: torch.Tensor
) -> torch.Tensor:
    """Description descriptors [B, D] from cached prior token features ([U, L, p], mask [U, L])."""
    flat = hint_rows.clamp(min=0).reshape(-1)
    coarse, _ = model.text.heads(prior[flat], tmask[flat])
    coarse = coarse.reshape(*hint_rows.shape, -1)
    return model.text.pool(coarse, hint_mask.to(coarse.device))


def hint_fine_features(model, prior, tmask, hint_rows) -> torch.Tensor:
    flat = hint_rows.clamp(min=0).reshape(-1)
    _, fine = model.text.heads(prior[flat], tmask[flat])
    return fine.reshape(*hint_rows.shape, -1)


def cell_inputs(maps: TextMaps, cells, device):
    c = maps.cells
    pick = lambda a, dtype: torch.from_numpy(np.ascontiguousarray(a[cells])).to(device=device, dtype=dtype)  # noqa: E731
    return (pick(c.points, torch.float32), pick(c.num_points, torch.float32), pick(c.object_mask, torch.bool))


def geometry_features(model, maps: TextMaps, device, progress=no_progress) -> torch.Tensor:
    """The PointNet++ feature [C, T, F] of every slot of every cell (eval mode, no gradients)."""
    enc = model.submap.objects
    c, t = maps.cells.object_mask.shape
    out = torch.zeros(c, t, enc.mlp_pointnet[0][0].in_features, device=device)
    bar = progress("PointNet++ features of every object", c)
    was = enc.training
    enc.eval()
    with torch.no_grad():
        for sl in _chunks(c, 8):
            pts, _, mask = cell_inputs(maps, np.arange(c)[sl], device)
            xyz, rgb = pts[..., :3], pts[..., 3:]
            real = mask
            flat_xyz, flat_rgb = xyz[real], rgb[real]
            centre = flat_xyz.mean(1, keepdim=True)
            feats = enc.pointnet(enc.local(flat_xyz, centre), flat_rgb)
            block = torch.zeros(real.shape[0], t, feats.shape[-1], device=device)
            block[real] = feats
            out[sl] = block
            bar.update(sl.stop - sl.start)
    bar.close()
    enc.train(was)
    return out


def cell_descriptors(model, maps: TextMaps, cells: np.ndarray, geometry, device, stream: str | None = None):
    """(descriptors [len(cells), D], object features [len(cells), T, D] of ``stream``, default the
    card's ``fine.object_state``) of the coarse encoder."""
    pts, cnt, mask = cell_inputs(maps, cells, device)
    geom = geometry[torch.from_numpy(cells).to(device)] if geometry is not None else None
    return model.submap(pts, cnt, mask, geometry=geom, stream=stream)


def retrieval_recall(text: torch.Tensor, cells: torch.Tensor, truth: np.ndarray, ks=(1, 3, 5)) -> dict[int, float]:
    """Recall@k (%): the query's best cell (``truth``, a row of ``cells``) among its top k by cosine."""
    scores = text @ cells.T
    order = torch.argsort(scores, dim=1, descending=True, stable=True).cpu().numpy()
    rank = np.argmax(order == truth[:, None], axis=1)
    return {k: 100.0 * float((rank < k).mean()) for k in ks}


# ----------------------------------------------------------------------------- the recipe


class _Stage:
    """One stage's optimiser, scheduler, epochs and validation; the best epoch's weights kept."""

    def __init__(
        self, name: str, params, lr: float, epochs: int, start: int, step: int | None = None, gamma: float = 1.0
    ):
        self.name, self.epochs = name, epochs
        self.params = [p for p in params if p.requires_grad]
        self.opt = torch.optim.Adam(self.params, lr=lr)
        self.sched = torch.optim.lr_scheduler.StepLR(self.opt, step_size=step or 10**9, gamma=gamma)
        with warnings.catch_warnings():  # --resume: the learning rate of the epoch it resumes at
            warnings.filterwarnings("ignore", "Detected call of `lr_scheduler.step", UserWarning)
            for _ in range(1, start):
                self.sched.step()

    def run_epoch(self, model, epoch: int, order: np.ndarray, batch: int, loss_of: Callable, progress) -> float:
        """One training epoch over ``order`` in chunks of ``batch``: ``loss_of(indices)`` is the
        chunk's loss (None skips the chunk); returns the mean loss."""
        model.train()
        bar = progress(f"{self.name} epoch {epoch}/{self.epochs}", len(order))
        losses = []
        for sl in _chunks(len(order), batch):
            loss = loss_of(order[sl])
            if loss is not None:
                self.opt.zero_grad()
                loss.backward()
                self.opt.step()
                losses.append(float(loss.detach()))
                bar.set_postfix(loss=f"{np.mean(losses[-20:]):.3f}")
            bar.update(sl.stop - sl.start)
        bar.close()
        self.sched.step()
        model.eval()
        if not losses:
            raise InputError(
                f"stage {self.name}: {len(order)} training item(s) make no batch of {batch}; "
                f"more training data is needed"
            )
        return float(np.mean(losses))


def _set_trainable(model, names: Sequence[str]) -> list:
    """Only the parameters under the dotted module ``names`` train; returns them."""
    params = []
    for name, p in model.named_parameters():
        p.requires_grad_(any(name == n or name.startswith(n + ".") for n in names))
        if p.requires_grad:
            params.append(p)
    return params


def train_text(
    card: ModelCard,
    model,
    data_root: str | Path,
    output: str | Path,
    recipe: TextRecipe,
    device: str = "cpu",
    resume: bool = False,
    validation: Sequence[str] | None = None,
    progress=no_progress,
    log: Callable[[str], None] = lambda line: None,
) -> TrainReport:
    """Train ``model`` (a Des4Pos of ``card``) on the maps under ``data_root`` with ``recipe``,
    stage by stage; write the run directory ``output`` and return the report."""
    dev = pick_device(device)
    start_cra = {k: v.detach().clone() for k, v in model.state_dict().items() if k.startswith("fine.")}
    run = RunDir(output, card)
    if resume:
        run.require_last()
    cell, text_cfg = model.cell_config, model.text_config
    maps = load_text_maps(
        data_root, cell.max_objects, cell.points_per_object, text_cfg.max_hints, validation, recipe.seed
    )
    train_q, val_q = np.flatnonzero(~maps.validation), np.flatnonzero(maps.validation)
    val_cells = np.flatnonzero(maps.cell_validation) if maps.cell_validation.any() else np.arange(len(maps.cells))
    summary = {
        "root": str(data_root),
        "maps": len(maps.names),
        "cells": len(maps.cells.ids),
        "training_poses": len(train_q),
        "validation_poses": len(val_q),
        "validation_maps": sorted({maps.names[int(maps.map_of_cell[c])] for c in maps.pose_cell[val_q]}),
    }
    log(
        f"data: {summary['maps']} map(s), {summary['cells']} cells, {len(train_q)} training and {len(val_q)} "
        f"validation described poses"
    )
    if recipe.coarse_weights and not resume:
        seeded, part = (
            (("fine",), "the CRA") if recipe.fine_text_from == "coarse_weights" else (FINE_MODULES, "the fine stage")
        )
        log(load_weights_outside(model, recipe.coarse_weights, seeded, part, "coarse_weights"))
    if recipe.object_weights and not resume:
        log(load_object_weights(model, recipe.object_weights).summary())
    model.to(dev)
    rng = np.random.default_rng(recipe.seed)
    torch.manual_seed(recipe.seed)
    table = hint_table(card, maps)
    tokens, tmask = backbone_features(model, table, dev)
    report = TrainReport(
        card.name, run.path, "cell_R@1", data=summary, options={**dataclasses.asdict(recipe), "device": device}
    )
    signature = {
        "card": card.data,
        "data": str(Path(data_root).resolve()),
        "poses": len(maps.pose_w),
        "recipe": {k: v for k, v in dataclasses.asdict(recipe).items() if not k.endswith("epochs")},
    }
    done: dict[str, int] = {}
    clock = Stopwatch()
    saved: dict = {"keepers": {}, "optimizers": {}}
    training = TrainingState(run, signature, model, rng, report)  # each stage's optimiser is in `saved`
    if resume:
        state, clock = training.resume()
        done, report.stage_best = dict(state["done"]), dict(state["stage_best"])
        saved = {"keepers": dict(state.get("keepers", {})), "optimizers": dict(state.get("optimizers", {}))}
        log(f"resuming after {', '.join(f'{s} epoch {e}' for s, e in done.items())} from {run.last}")
    current: dict = {}  # the running stage's _Stage and _Keeper

    def keep(stage: _Stage, names, better) -> _Keeper:
        """The stage's keeper of its best epoch; on --resume both continue where last.pth left them."""
        if stage.name in saved["optimizers"]:
            stage.opt.load_state_dict(saved["optimizers"][stage.name])
        current.update(stage=stage, keeper=_Keeper(model, names, better, saved["keepers"].get(stage.name)))
        return current["keeper"]

    def checkpoint(stage: str, epoch: int):
        report.seconds = clock()
        if current:
            saved["keepers"][stage] = current["keeper"].to_dict()
            saved["optimizers"][stage] = current["stage"].opt.state_dict()
        training.save(None, clock, done={**done, stage: epoch}, stage_best=report.stage_best, **saved)
        run.write_log(report.to_dict())

    def epoch_row(stage: str, epoch: int, loss: float, metrics: dict):
        if not math.isfinite(loss):
            raise ConfigError(f"training diverged in stage {stage}, epoch {epoch} (loss {loss}); lower its lr")
        row = {"stage": stage, "epoch": epoch, "loss": loss, **metrics, "seconds": round(clock(), 1)}
        report.epochs.append(row)
        log(f"{stage} epoch {epoch}: loss {loss:.4f}, " + ", ".join(f"{k} {v:.2f}" for k, v in metrics.items()))

    geometry = None
    prior = None
    for stage in recipe.stage_list:
        epochs = getattr(recipe, f"{'object' if stage == 'objects' else stage}_epochs")
        if done.get(stage, 0) >= epochs and stage in report.stage_best:
            continue  # finished before --resume: its best weights are in last.pth
        if stage in ("coarse", "hints", "fine") and prior is None:
            with torch.no_grad():
                model.eval()
                prior = torch.cat([model.text.prior_tokens(tokens[sl], tmask[sl]) for sl in _chunks(len(tokens), 256)])
        if stage in ("coarse", "hints", "fine") and geometry is None and not recipe.train_pointnet:
            geometry = geometry_features(model, maps, dev, progress)
        runner = {
            "objects": _objects_stage,
            "prior": _prior_stage,
            "coarse": _coarse_stage,
            "hints": _hints_stage,
            "fine": _fine_stage,
        }[stage]
        best = runner(
            model,
            maps,
            recipe,
            epochs,
            done.get(stage, 0) + 1,
            dev,
            rng,
            progress,
            epoch_row,
            checkpoint,
            keep,
            tokens=tokens,
            tmask=tmask,
            prior=prior,
            table=table,
            geometry=geometry,
            train_q=train_q,
            val_q=val_q,
            val_cells=val_cells,
            start_cra=start_cra,
        )
        done[stage] = epochs
        if best is not None:
            report.stage_best[stage] = best
            log(f"{stage}: kept epoch {best}")
        checkpoint(stage, epochs)  # the stage's best weights, so --resume skips it
        current.clear()
        if stage == "prior":
            prior = None  # the prior head changed: its features are recomputed
        if stage == "objects":
            geometry = None
    model.eval()
    for p in model.parameters():
        p.requires_grad_(True)
    final = {}
    for row in report.epochs:  # the kept epoch's metrics of every stage
        if report.stage_best.get(row["stage"]) == row["epoch"]:
            final.update({k: v for k, v in row.items() if k not in ("stage", "epoch", "loss", "seconds")})
    run.save_best(model, sum(done.values()), final)
    report.best_epoch = report.stage_best.get("coarse")
    report.seconds = clock()
    run.write_log(report.to_dict())
    return report


FINE_MODULES = ("fine", "text.fine_words", "text.fine_mlp")  # what the fine stage trains


class _Keeper:
    """A stage's best validation epoch (``better(new, best)`` on the metrics) and the weights of
    the stage's modules (``names``) at that epoch; ``saved`` continues one from ``last.pth``."""

    def __init__(self, model, names: Sequence[str], better: Callable[[dict, dict], bool], saved: dict | None = None):
        self.model, self.names, self.better = model, tuple(names), better
        saved = saved or {}
        self.epoch, self.metrics, self.state = saved.get("epoch"), saved.get("metrics"), saved.get("state")

    def offer(self, epoch: int, metrics: dict) -> None:
        if self.metrics is None or self.better(metrics, self.metrics):
            self.epoch, self.metrics = epoch, metrics
            self.state = {
                k: v.detach().clone()
                for k, v in self.model.state_dict().items()
                if k.startswith(tuple(n + "." for n in self.names))
            }

    def restore(self) -> int | None:
        """Load the best epoch's weights back; returns that epoch (None when no epoch ran)."""
        if self.state is not None:
            self.model.load_state_dict({**self.model.state_dict(), **self.state})
        return self.epoch

    def to_dict(self) -> dict:
        return {"epoch": self.epoch, "metrics": self.metrics, "state": self.state}


def _objects_stage(
    model, maps, recipe, epochs, start, dev, rng, progress, epoch_row, checkpoint, keep, *, val_cells, **_
):
    """Text2Pos's object classification on the objects of the training cells, its accuracy on the
    validation cells' objects (with one map, on every 10th object, left out of training)."""
    enc = model.submap.objects
    classes = {c: i for i, c in enumerate(model.submap.cfg.object_classes)}
    cells = maps.cells
    slots = np.argwhere(cells.object_mask)
    labels = np.array([classes.get(str(cells.labels[c, s]), -1) for c, s in slots])
    if (labels < 0).any():
        c, s = slots[np.flatnonzero(labels < 0)[0]]
        raise InputError(
            f"cell {cells.ids[c]}, object {s}: label {cells.labels[c, s]!r} is not one of the card's "
            f"submap.object_classes ({len(classes)} classes); the object stage trains a classifier "
            f"over them"
        )
    held = maps.cell_validation[slots[:, 0]]
    train_i, val_i = np.flatnonzero(~held), np.flatnonzero(held)
    if not len(val_i):  # one map: every 10th object is held out instead
        val_i = train_i[::10]
        train_i = np.setdiff1d(train_i, val_i)
    names = ["submap.objects.pointnet"]
    stage = _Stage("objects", _set_trainable(model, names), recipe.object_lr, epochs, start, 1, 0.9)
    keeper = keep(stage, names, lambda m, b: m["object_acc"] > b["object_acc"])

    def batch(idx):
        pts = torch.from_numpy(cells.points[slots[idx, 0], slots[idx, 1]]).to(dev)
        xyz, rgb = pts[..., :3], pts[..., 3:]
        feats = enc.pointnet(enc.local(xyz, xyz.mean(1, keepdim=True)), rgb)
        return enc.pointnet.class_classifier(feats), torch.from_numpy(labels[idx]).to(dev)

    for epoch in range(start, epochs + 1):
        loss = stage.run_epoch(
            model,
            epoch,
            rng.permutation(train_i),
            recipe.object_batch,
            lambda idx: F.cross_entropy(*batch(idx)),
            progress,
        )
        with torch.no_grad():
            correct = sum(
                int((batch(val_i[sl])[0].argmax(1).cpu() == torch.from_numpy(labels[val_i[sl]])).sum())
                for sl in _chunks(len(val_i), 64)
            )
        metrics = {"object_acc": 100.0 * correct / len(val_i)}
        epoch_row("objects", epoch, loss, metrics)
        keeper.offer(epoch, metrics)
        checkpoint("objects", epoch)
    return keeper.restore()


def _prior_stage(
    model,
    maps,
    recipe,
    epochs,
    start,
    dev,
    rng,
    progress,
    epoch_row,
    checkpoint,
    keep,
    *,
    tokens,
    tmask,
    table,
    val_q,
    **_,
):
    """Eq. 8: the prior head's pooled output against the teacher's sentence embedding."""
    teacher = teacher_embedding(tokens, tmask)
    if teacher.shape[1] != model.text_config.prior_dim:
        raise ConfigError(
            f"text.prior_dim is {model.text_config.prior_dim}, but the prior's teacher (the backbone's "
            f"sentence embedding) is {teacher.shape[1]} wide; set text.prior_dim: {teacher.shape[1]}"
        )
    val_rows = sorted({table.index[h] for q in val_q for h in maps.pose_hints[q]})
    train_rows = np.array(sorted(set(range(len(table.sentences))) - set(val_rows)) or val_rows)
    val_rows = np.array(val_rows or train_rows[::10])
    names = ["text.prior", "text.prior_mlp"]
    stage = _Stage("prior", _set_trainable(model, names), recipe.prior_lr, epochs, start)
    keeper = keep(stage, names, lambda m, b: m["prior_cosine"] > b["prior_cosine"])

    def cosine(rows):
        pooled = masked_max(model.text.prior_tokens(tokens[rows], tmask[rows]), tmask[rows], 1)
        return F.cosine_similarity(pooled, teacher[rows], dim=-1)

    for epoch in range(start, epochs + 1):
        loss = stage.run_epoch(
            model,
            epoch,
            rng.permutation(train_rows),
            recipe.prior_batch,
            lambda rows: (1.0 - cosine(torch.from_numpy(rows).to(dev))).mean(),
            progress,
        )
        with torch.no_grad():
            metrics = {"prior_cosine": float(cosine(torch.from_numpy(val_rows).to(dev)).mean())}
        epoch_row("prior", epoch, loss, metrics)
        keeper.offer(epoch, metrics)
        checkpoint("prior", epoch)
    return keeper.restore()


def _coarse_stage(
    model,
    maps,
    recipe,
    epochs,
    start,
    dev,
    rng,
    progress,
    epoch_row,
    checkpoint,
    keep,
    *,
    prior,
    tmask,
    table,
    geometry,
    train_q,
    val_q,
    val_cells,
    **_,
):
    """Eq. 9: symmetric InfoNCE between descriptions and their best cells."""
    names = ["submap", "text.align_words", "text.align_mlp", "text.align_hints"]
    params = _set_trainable(model, names)
    if not recipe.train_pointnet:
        for p in model.submap.objects.pointnet.parameters():
            p.requires_grad_(False)
    stage = _Stage(
        "coarse",
        [p for p in params if p.requires_grad],
        recipe.coarse_lr,
        epochs,
        start,
        recipe.lr_step,
        recipe.lr_gamma,
    )
    rank = lambda m: (m["cell_R@1"], m["cell_R@5"])  # noqa: E731
    keeper = keep(stage, names, lambda m, b: rank(m) > rank(b))

    def loss_of(poses):
        if len(poses) < 2:  # InfoNCE needs a negative
            return None
        rows, hmask = _padded_hints(maps, table, poses, rng if recipe.shuffle_hints else None)
        t = text_descriptors(model, prior, tmask, rows.to(dev), hmask)
        cells, inverse = np.unique(maps.pose_cell[poses], return_inverse=True)
        c, _ = cell_descriptors(model, maps, cells, geometry, dev)
        return info_nce(
            t,
            c[torch.from_numpy(inverse).to(dev)],
            torch.from_numpy(maps.pose_cell[poses]).to(dev),
            recipe.temperature,
            recipe.duplicate_cells == "mask",
        )

    for epoch in range(start, epochs + 1):
        loss = stage.run_epoch(model, epoch, rng.permutation(train_q), recipe.coarse_batch, loss_of, progress)
        metrics = coarse_metrics(model, maps, prior, tmask, geometry, val_q, val_cells, dev, table)
        epoch_row("coarse", epoch, loss, metrics)
        keeper.offer(epoch, metrics)
        checkpoint("coarse", epoch)
    return keeper.restore()


def info_nce(
    text: torch.Tensor, cells: torch.Tensor, cell_ids: torch.Tensor, temperature: float, mask_duplicates: bool
) -> torch.Tensor:
    """Eq. 9 over a batch: text [B, D] and the descriptors of their best cells [B, D] (both
    L2-normalised), the cells' ids [B]: the mean over the batch of the text-to-cell plus the
    cell-to-text cross-entropy of the diagonal (Text2Loc's ContrastiveLoss). With
    ``mask_duplicates`` an entry pairing a text with another description's copy of its own
    cell is left out of both softmaxes instead of counting as a negative."""
    s = text @ cells.T / temperature
    if mask_duplicates:
        same = (cell_ids[:, None] == cell_ids[None, :]) & ~torch.eye(len(cell_ids), dtype=torch.bool, device=s.device)
        s = s.masked_fill(same, float("-inf"))
    target = torch.arange(len(text), device=s.device)
    return F.cross_entropy(s, target) + F.cross_entropy(s.T, target)


def coarse_metrics(model, maps, prior, tmask, geometry, val_q, val_cells, dev, table) -> dict:
    """Cell retrieval recall@1/3/5 (%) of the validation descriptions against the validation cells."""
    model.eval()
    with torch.no_grad():
        descs = []
        for sl in _chunks(len(val_cells), 16):
            descs.append(cell_descriptors(model, maps, val_cells[sl], geometry, dev)[0])
        cells = torch.cat(descs)
        texts = []
        for sl in _chunks(len(val_q), 128):
            rows, hmask = _padded_hints(maps, table, val_q[sl], None)
            texts.append(text_descriptors(model, prior, tmask, rows.to(dev), hmask))
        text = torch.cat(texts)
    where = {c: i for i, c in enumerate(val_cells.tolist())}
    truth = np.array([where[int(c)] for c in maps.pose_cell[val_q]])
    return {f"cell_R@{k}": v for k, v in retrieval_recall(text, cells, truth).items()}


def _hints_stage(model, maps, recipe, epochs, start, dev, rng, progress, epoch_row, checkpoint, keep, **kw):
    """The fine text branch's warm-up: eq. 13 on the LSTM states; the last epoch is kept."""
    return _fit_fine(
        model,
        maps,
        recipe,
        epochs,
        start,
        dev,
        rng,
        progress,
        epoch_row,
        checkpoint,
        keep,
        "hints",
        "lstm",
        lambda m, b: True,
        **kw,
    )


def _fine_stage(
    model, maps, recipe, epochs, start, dev, rng, progress, epoch_row, checkpoint, keep, *, start_cra, **kw
):
    """Eq. 13 on the card's object stream; after a ``hints`` warm-up the CRA starts again from the
    weights it had when training began."""
    if "hints" in recipe.stage_list and start == 1:
        model.load_state_dict({**model.state_dict(), **start_cra})
    return _fit_fine(
        model,
        maps,
        recipe,
        epochs,
        start,
        dev,
        rng,
        progress,
        epoch_row,
        checkpoint,
        keep,
        "fine",
        None,
        lambda m, b: m["fine_error_m"] < b["fine_error_m"],
        **kw,
    )


def _fit_fine(
    model,
    maps,
    recipe,
    epochs,
    start,
    dev,
    rng,
    progress,
    epoch_row,
    checkpoint,
    keep,
    name,
    stream,
    better,
    *,
    prior,
    tmask,
    table,
    geometry,
    train_q,
    val_q,
    **_,
):
    """Eq. 13: the CRA regressor and the fine text branch on the frozen coarse encoder's object
    features (``stream``, or the card's ``fine.object_state``), stage ``name``; ``better`` picks
    the epoch kept."""
    with torch.no_grad():
        model.eval()
        feats = []
        for sl in _chunks(len(maps.cells.ids), 16):
            feats.append(cell_descriptors(model, maps, np.arange(len(maps.cells.ids))[sl], geometry, dev, stream)[1])
        objects = torch.cat(feats)
    object_mask = torch.from_numpy(maps.cells.object_mask).to(dev)
    origin = torch.from_numpy(maps.cells.origins).to(dev)
    size = torch.from_numpy(maps.cells.sizes).to(dev)
    target_all = (
        (torch.from_numpy(maps.pose_w).to(dev) - origin[maps.pose_cell]) / size[maps.pose_cell, None] - 0.5
    ).float()
    # what the cell centre alone (a zero offset, the coarse stage's answer) misses by: the bar to beat
    centre_m = float(
        (target_all[torch.from_numpy(val_q).to(dev)].double().norm(dim=1) * size[maps.pose_cell[val_q]]).mean()
    )
    summaries = None
    if model.fine.needs_summaries:  # fine.objects: encoder
        centres, colours = object_summaries(torch.from_numpy(maps.cells.points))
        summaries = (centres.to(dev), colours.to(dev), torch.from_numpy(maps.cells.num_points).to(dev))
    names = list(FINE_MODULES)
    stage = _Stage(name, _set_trainable(model, names), recipe.fine_lr, epochs, start)
    keeper = keep(stage, names, better)

    def predict(poses):
        rows, hmask = _padded_hints(maps, table, poses, None)
        hints = hint_fine_features(model, prior, tmask, rows.to(dev))
        cells = torch.from_numpy(maps.pose_cell[poses]).to(dev)
        return model.fine.offsets(
            objects[cells],
            object_mask[cells],
            hints,
            hmask.to(dev),
            None if summaries is None else tuple(x[cells] for x in summaries),
        )

    def loss_of(poses):
        err = predict(poses) - target_all[torch.from_numpy(poses).to(dev)]
        return err.norm(dim=1).mean() if recipe.fine_loss == "l2" else 5.0 * (err**2).mean()

    for epoch in range(start, epochs + 1):
        for group in stage.opt.param_groups:  # Text2Loc's warm-up: a low rate for the first epochs
            group["lr"] = recipe.fine_warmup_lr if epoch <= recipe.fine_warmup_epochs else recipe.fine_lr
        loss = stage.run_epoch(model, epoch, rng.permutation(train_q), recipe.fine_batch, loss_of, progress)
        with torch.no_grad():
            errs = []
            for sl in _chunks(len(val_q), 128):
                poses = val_q[sl]
                e = (predict(poses) - target_all[torch.from_numpy(poses).to(dev)]).double()
                errs.append((e.norm(dim=1) * size[maps.pose_cell[poses]]).cpu().numpy())
            err_m = np.concatenate(errs)
        metrics = {
            "fine_error_m": float(err_m.mean()),
            "fine_within_5m": 100.0 * float((err_m <= 5).mean()),
            "centre_error_m": centre_m,
        }
        epoch_row(name, epoch, loss, metrics)
        keeper.offer(epoch, metrics)
        checkpoint(name, epoch)
    return keeper.restore()
