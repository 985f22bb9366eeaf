"""What every training recipe shares: the run directory, checkpoints, ``--resume``, the JSON log,
the device and the report.

A run directory holds

- ``best.pth``: the weights of the epoch with the best validation metric, under ``model_state``
  (``radaredge export --checkpoint`` reads it), with the card, the epoch and its metrics;
- ``last.pth``: everything needed to continue (weights, optimiser, scheduler, random states,
  history), rewritten after every epoch (TDFANet's also within one, :mod:`.tdfanet`); ``resume``
  starts from it;
- ``train-log.json``: the options, the data summary and one row per epoch.

Every file is written to a temporary name and renamed, so an interrupted run never leaves a
truncated checkpoint behind.
"""

from __future__ import annotations

import dataclasses
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import atomic_path, write_json
from ..cards import ModelCard
from ..config import check_numbers, check_writable_dir, field_range, refuse_overwriting_inputs
from ..errors import ConfigError
from ..models.checkpoints import check_checkpoint_file, read_checkpoint
from ..models.factory import check_weight_values

BEST, LAST, LOG = "best.pth", "last.pth", "train-log.json"
DEVICES = ("cpu", "cuda")


def recipe_from_options(cls: type, options: dict, model: str, aliases: dict | None = None):
    """The recipe dataclass ``cls`` with ``options`` (by field name or one of ``aliases``; None
    values skipped) over its defaults; ConfigError naming an unknown option or a bad value
    (numbers checked against the class's declared ranges, flags must be true or false)."""
    aliases = aliases or {}
    fields = {f.name: f for f in dataclasses.fields(cls)}
    given = {aliases.get(k, k): v for k, v in options.items() if v is not None}
    unknown = sorted(set(given) - set(fields))
    if unknown:
        also = f" (and {', '.join(f'{a} = {b}' for a, b in aliases.items())})" if aliases else ""
        raise ConfigError(f"unknown {model} training option(s) {unknown}; known: {sorted(fields)}{also}")
    for name, value in given.items():
        default, option = fields[name].default, f"--{name.replace('_', '-')}"
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{option}: expected true or false, got {value!r}")
        elif isinstance(default, (int, float)) or (default is None and isinstance(value, (int, float))):
            integral = isinstance(default, int) or fields[name].type in ("int | None", int)
            check_numbers(value, field_range(cls, name), integral, option)
        elif not isinstance(value, str):
            raise ConfigError(f"{option}: expected text, got {value!r}")
    try:
        return cls(**given)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def pick_device(name: str) -> torch.device:
    """``cpu`` or ``cuda`` as a torch device; ConfigError when CUDA is asked for and absent."""
    if name not in DEVICES:
        raise ConfigError(f"--device must be one of {list(DEVICES)}, got {name!r}")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            "--device cuda: this torch build sees no CUDA device (torch.cuda.is_available() is False); "
            "use --device cpu or install a CUDA build of torch"
        )
    return torch.device(name)


def _atomic_save(obj, path: Path) -> Path:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return path


def random_states(rng: np.random.Generator) -> dict:
    """The numpy generator's, Python's and torch's random states (plain containers and tensors);
    torch's CUDA generators' too once CUDA is in use (dropout on a GPU draws from them)."""
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() and torch.cuda.is_initialized() else None
    return {
        "numpy": rng.bit_generator.state,
        "torch": torch.get_rng_state(),
        "cuda": cuda,
        "python": list(random.getstate()[1]),
        "python_version": random.getstate()[0],
        "python_gauss": random.getstate()[2],
    }


def restore_random_states(rng: np.random.Generator, states: dict) -> None:
    rng.bit_generator.state = states["numpy"]
    torch.set_rng_state(states["torch"])
    if states.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])
    random.setstate((states["python_version"], tuple(states["python"]), states["python_gauss"]))


def torch_rng_state(device: torch.device) -> tuple:
    """torch's CPU generator state, and that of ``device``'s generator when it is a CUDA device:
    what random ops (dropout) on ``device`` draw from."""
    return torch.get_rng_state(), torch.cuda.get_rng_state(device) if device.type == "cuda" else None


def set_torch_rng_state(state: tuple, device: torch.device) -> None:
    """Undo the draws since :func:`torch_rng_state` returned ``state``."""
    torch.set_rng_state(state[0])
    if state[1] is not None:
        torch.cuda.set_rng_state(state[1], device)


def load_weights_outside(model: torch.nn.Module, path, seeded: tuple[str, ...], part: str, option: str) -> str:
    """Load every tensor of ``model`` outside the modules ``seeded`` (state-dict name prefixes,
    e.g. ``("roi_head",)``, together called ``part``) from the checkpoint ``path``; those modules
    keep their current weights, whatever the checkpoint holds for them. Any other missing, unexpected or mis-shaped
    key, or a value no trained layer holds, is a ConfigError naming ``option``. Returns a
    one-line summary."""

    def kept(key: str) -> bool:
        return key.startswith(tuple(m + "." for m in seeded))

    state, _ = read_checkpoint(path)
    own = model.state_dict()
    outside = {k: v for k, v in state.items() if not kept(k)}
    missing = sorted(k for k in own if not kept(k) and k not in outside)
    unexpected = sorted(k for k in outside if k not in own)
    shapes = sorted(k for k in outside if k in own and tuple(outside[k].shape) != tuple(own[k].shape))
    problems = [
        f"{what} ({len(keys)}): {', '.join(keys[:8])}"
        for what, keys in (("missing keys", missing), ("unexpected keys", unexpected), ("wrong shapes", shapes))
        if keys
    ]
    if problems:
        raise ConfigError(f"{option} {path} does not fit this card's model outside {part}: {'; '.join(problems)}")
    check_weight_values(model, outside, path)
    model.load_state_dict({**own, **outside})
    n_seeded = sum(1 for k in own if kept(k))
    return f"{option}: {len(outside)} tensors from {path}; {part}'s {n_seeded} stay as they are"


def prepare_run_output(output: Path, resume: bool, overwrite: bool, inputs: dict) -> None:
    """Make ``output`` (a run directory) ready for a run, before any training, losing nothing it
    was not told to: ConfigError when it holds a previous run (best.pth, last.pth or
    train-log.json) and neither ``resume`` (go on with it) nor ``overwrite`` was asked for, or
    when one of the files a run writes is one of its ``inputs`` (option -> path: the data, the
    initial checkpoint, a recipe's weights). With ``overwrite`` the previous run's files are
    removed, so no old best.pth outlives the start of the new run."""
    if resume and overwrite:
        raise ConfigError("--resume continues the run in --output and --overwrite replaces it: choose one")
    files = [output / name for name in (BEST, LAST, LOG)]
    refuse_overwriting_inputs({"--output": [output, *files]}, inputs)
    held = [f for f in files if f.exists()]
    if held and not resume and not overwrite:
        raise ConfigError(
            f"--output {output}: holds a previous run ({', '.join(f.name for f in held)}); continue it "
            f"with --resume, replace it with --overwrite, or choose another --output"
        )
    if overwrite:
        for f in held:
            f.unlink()


@dataclass
class RunDir:
    """A training run's directory (module docstring) for ``card``'s model."""

    path: Path
    card: ModelCard

    def __post_init__(self):
        self.path = Path(self.path)
        check_writable_dir(self.path, "--output")  # made at the first save: a failed start leaves nothing

    @property
    def best(self) -> Path:
        return self.path / BEST

    @property
    def last(self) -> Path:
        return self.path / LAST

    @property
    def log(self) -> Path:
        return self.path / LOG

    def save_best(self, model: torch.nn.Module, epoch: int, metrics: dict, **extra) -> Path:
        """best.pth: the weights, the card, the epoch and its metrics, and a recipe's ``extra``
        entries (``qat``: a --qat run's learned ranges)."""
        return _atomic_save(
            {"model_state": model.state_dict(), "card": self.card.data, "epoch": epoch, "metrics": metrics, **extra},
            self.best,
        )

    def save_last(self, state: dict) -> Path:
        return _atomic_save(state, self.last)

    def write_log(self, log: dict) -> Path:
        return write_json(self.log, log)

    def require_last(self) -> None:
        """ConfigError unless ``last.pth`` exists and is bounded and headed as torch.save writes
        (``--resume`` needs it; checked before the data is read)."""
        if not self.last.is_file():
            raise ConfigError(
                f"--resume: {self.last} does not exist; start without --resume (or pass the --output "
                f"of the run to continue)"
            )
        try:
            check_checkpoint_file(self.last)
        except ConfigError as exc:
            raise ConfigError(f"--resume: {exc}") from None

    def load_last(self, signature: dict) -> dict:
        """The state of ``last.pth`` to resume from; ConfigError when there is none or it was
        written by another card or for other data (``signature`` differs)."""
        self.require_last()
        try:
            state = torch.load(str(self.last), map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unreadable file is the same user error
            raise ConfigError(
                f"--resume: {self.last} is not a readable radaredge training state ({type(exc).__name__})"
            ) from None
        if not isinstance(state, dict) or "signature" not in state:
            raise ConfigError(f"--resume: {self.last} is not a radaredge training state")
        if state["signature"] != signature:
            diff = sorted(
                k for k in set(signature) | set(state["signature"]) if signature.get(k) != state["signature"].get(k)
            )
            raise ConfigError(
                f"--resume: {self.last} was written for another run (differs in {', '.join(diff)}); "
                f"use the same card, data and recipe options, or a new --output"
            )
        return state


@dataclass
class TrainReport:
    """What a training run did: per epoch its metrics, the best epoch, and the files it wrote."""

    model: str
    output: Path
    metric: str  # the validation metric that picks the best epoch
    epochs: list[dict] = field(default_factory=list)
    best_epoch: int | None = None
    stage_best: dict = field(default_factory=dict)  # staged recipes: stage -> its best epoch (kept weights)
    data: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def best(self) -> dict | None:
        return next((e for e in self.epochs if e["epoch"] == self.best_epoch), None)

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "output": str(self.output),
            "best_checkpoint": str(Path(self.output) / BEST),
            "last_state": str(Path(self.output) / LAST),
            "metric": self.metric,
            "best_epoch": self.best_epoch,
            **({"stage_best": self.stage_best} if self.stage_best else {}),
            "seconds": round(self.seconds, 1),
            "data": self.data,
            "options": self.options,
            "epochs": self.epochs,
        }

    def lines(self) -> list[str]:
        out = [
            f"train {self.model}: {len(self.epochs)} epoch(s) in {self.seconds / 60:.1f} min; data: "
            + ", ".join(f"{k} {v}" for k, v in self.data.items() if not isinstance(v, (list, dict)))
        ]
        bests = []
        for stage in dict.fromkeys(e.get("stage") for e in self.epochs):  # rows of a staged recipe by stage
            rows = [e for e in self.epochs if e.get("stage") == stage]
            keys = [k for k in dict.fromkeys(k for e in rows for k in e) if k not in ("stage", "epoch", "seconds")]
            best, metric = (self.stage_best.get(stage), None) if stage else (self.best_epoch, self.metric)
            if stage:
                out.append(f"stage {stage}:")
            width = [max(12, len(k) + 2) for k in keys]
            out.append(f"{'epoch':>5}" + "".join(f"{k:>{w}}" for k, w in zip(keys, width)))
            for e in rows:
                mark = "  *" if e["epoch"] == best else ""
                out.append(
                    f"{e['epoch']:>5}" + "".join(f"{_fmt(e.get(k, '-')):>{w}}" for k, w in zip(keys, width)) + mark
                )
                if mark:
                    metric = metric or keys[1]
                    bests.append(f"{stage + ' ' if stage else ''}epoch {best} ({metric} {_fmt(e[metric])})")
        if bests:
            out.append(
                f"best {', '.join(bests)}: {Path(self.output) / BEST}; export it with `radaredge export "
                f"--model {self.model} --checkpoint {Path(self.output) / BEST}`"
            )
        return out


@dataclass
class TrainingState:
    """What every recipe's ``last.pth`` holds and ``--resume`` restores: the model's weights, the
    optimiser and learning-rate scheduler (when the recipe has one for the whole run), the random
    generators (``rng``, Python's, torch's), the epoch rows and best epoch of ``report``, the
    seconds trained and the epoch reached; a recipe adds its own keys (``extra``) and reads them
    back from the state :meth:`resume` returns. ``signature`` is what a resumed run must share
    with the one that wrote the file (card, data, recipe)."""

    run: RunDir
    signature: dict
    model: torch.nn.Module
    rng: np.random.Generator
    report: TrainReport
    optimizer: torch.optim.Optimizer | None = None
    scheduler: Any = None

    def save(self, epoch: int | None, clock: Stopwatch, **extra) -> Path:
        """Writes ``last.pth`` after ``epoch`` (None: the recipe counts epochs in ``extra``)."""
        state = {
            "signature": self.signature,
            "epoch": epoch,
            "model_state": self.model.state_dict(),
            "random": random_states(self.rng),
            "history": self.report.epochs,
            "best_epoch": self.report.best_epoch,
            "seconds": clock(),
            **extra,
        }
        if self.optimizer is not None:
            state["optimizer"] = self.optimizer.state_dict()
        if self.scheduler is not None:
            state["scheduler"] = self.scheduler.state_dict()
        return self.run.save_last(state)

    def resume(self, epochs: int | None = None, schedule: bool = False) -> tuple[dict, Stopwatch]:
        """Restores everything :meth:`save` wrote from ``last.pth`` and returns (the state, for the
        recipe's own keys; a stopwatch that carries the seconds already trained). ConfigError when
        the file is missing or from another run, when it already holds all ``epochs`` (with no
        epoch left half done), or, with ``schedule`` (a learning rate that spans the whole run),
        when it was written for another number of epochs."""
        state = self.run.load_last(self.signature)
        last = self.run.last
        if schedule and epochs is not None and state.get("epochs", epochs) != epochs:
            raise ConfigError(
                f"--resume: {last} was written for a {state['epochs']}-epoch schedule (the learning "
                f"rate spans all epochs); resume with --epochs {state['epochs']}"
            )
        if epochs is not None and state["epoch"] is not None and state["epoch"] >= epochs and not state.get("partial"):
            raise ConfigError(
                f"--resume: {last} already holds epoch {state['epoch']} of {epochs}; raise --epochs to train on"
            )
        self.model.load_state_dict(state["model_state"])
        if self.optimizer is not None:
            self.optimizer.load_state_dict(state["optimizer"])
        if self.scheduler is not None:
            self.scheduler.load_state_dict(state["scheduler"])
        restore_random_states(self.rng, state["random"])
        self.report.epochs, self.report.best_epoch = state["history"], state["best_epoch"]
        return state, Stopwatch(state["seconds"])


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


class Stopwatch:
    """Seconds since creation, plus time carried over from a resumed run."""

    def __init__(self, carried: float = 0.0):
        self.start, self.carried = time.perf_counter(), carried

    def __call__(self) -> float:
        return self.carried + time.perf_counter() - self.start
