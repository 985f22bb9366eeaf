"""The model factory, in the timm manner: :func:`create_model` builds a card's model (seeded,
eval mode) and loads a checkpoint into it, accounting for every key and checking every value;
:func:`weights_hash` is the fingerprint exports and parity use to tie a graph to its weights."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..atomic import atomic_path
from ..cards import ModelCard
from ..errors import ConfigError
from ..ops.gem import GeM
from ..registry import model_spec
from .checkpoints import read_checkpoint
from .spec import ModelSpec


def weights_hash(model: torch.nn.Module) -> str:
    """SHA-256 over the state dict (names, shapes and bytes, in key order)."""
    h = hashlib.sha256()
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def save_checkpoint(model: torch.nn.Module, path: str | Path) -> Path:
    """Write the model's state_dict to ``path`` (parent directories created), in the form
    :func:`load_checkpoint` and ``--checkpoint`` read. Returns the path."""
    with atomic_path(path) as tmp:
        torch.save(model.state_dict(), tmp)
    return Path(path)


# Entries of an OpenPCDet ``model_state`` that are bookkeeping, not weights (Detector3DTemplate's step counter).
IGNORED_CHECKPOINT_KEYS = ("global_step",)


@dataclass
class LoadReport:
    """What :func:`load_checkpoint` did: tensors loaded, and the dropped keys by the rule that dropped them."""

    path: str
    loaded: int
    dropped: dict[str, list[str]] = field(default_factory=dict)  # rule -> keys
    ignored: list[str] = field(default_factory=list)

    def summary(self) -> str:
        parts = [f"loaded {self.loaded} tensors from {self.path}"]
        parts += [f"dropped {len(keys)} ({rule})" for rule, keys in self.dropped.items()]
        if self.ignored:
            parts.append(f"ignored {', '.join(self.ignored)}")
        return "; ".join(parts)


def load_checkpoint(model: torch.nn.Module, path: str | Path) -> LoadReport:
    """Load a state_dict ``.pth`` into ``model`` and account for every key.

    Keys the model declares as having no effect on its output (``model.checkpoint_drop_rules()``:
    (rule, key prefixes, only zero-size tensors) per rule, e.g. upstream MAFF-Net parameters that
    its test-time path never reads) are dropped by rule; :data:`IGNORED_CHECKPOINT_KEYS` are
    ignored. Any other missing, unexpected or shape-mismatched key is a one-line ConfigError
    naming the keys.
    """
    obj, trained_features = read_checkpoint(path)
    features = getattr(model, "features", None)
    if trained_features is not None and features is not None and list(features) != trained_features:
        raise ConfigError(
            f"checkpoint {path} was trained on point columns {trained_features}, in that order; this "
            f"card's features are {list(features)}. The first layer's weights follow the column "
            f"order: list the card's features as the checkpoint's"
        )
    rules = model.checkpoint_drop_rules() if hasattr(model, "checkpoint_drop_rules") else []
    own = model.state_dict()
    report = LoadReport(str(path), 0)
    state = {}
    for key, value in obj.items():
        rule = next(
            (
                r
                for r, prefixes, empty_only in rules
                if key not in own and key.startswith(tuple(prefixes)) and (value.numel() == 0 or not empty_only)
            ),
            None,
        )
        if rule is not None:
            report.dropped.setdefault(rule, []).append(key)
        elif key in IGNORED_CHECKPOINT_KEYS and key not in own:
            report.ignored.append(key)
        else:
            state[key] = value
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    shapes = sorted(
        f"{k} (checkpoint {tuple(state[k].shape)}, model {tuple(own[k].shape)})"
        for k in set(own) & set(state)
        if tuple(state[k].shape) != tuple(own[k].shape)
    )
    problems = []
    for what, keys in (("missing keys", missing), ("unexpected keys", unexpected), ("wrong shapes", shapes)):
        if keys:
            more = f" and {len(keys) - 12} more" if len(keys) > 12 else ""
            problems.append(f"{what} ({len(keys)}): {', '.join(keys[:12])}{more}")
    if problems:
        raise ConfigError(f"checkpoint {path} does not fit this card's model: {'; '.join(problems)}")
    check_weight_values(model, state, path)
    model.load_state_dict(state)
    report.loaded = len(state)
    return report


# What a trained network's tensors stay within: learned weights (a larger one drives float32
# activations to Inf within a few layers) and running statistics (variances of raw inputs in m,
# m/s, dBsm included).
MAX_ABS_PARAMETER = 1e6
MAX_ABS_STATISTIC = 1e12


def check_weight_values(model: torch.nn.Module, state: dict, path) -> None:
    """ConfigError naming the key unless every tensor of ``state`` has values its layer can hold:
    a real dtype (read_checkpoint refuses complex and non-finite values), magnitudes within
    :data:`MAX_ABS_PARAMETER` (parameters) or :data:`MAX_ABS_STATISTIC` (buffers), BatchNorm
    running variances >= 0 and GeM exponents p > 0."""
    params = {name for name, _ in model.named_parameters()}
    for key, value in state.items():
        if not value.is_floating_point() or not value.numel():
            continue
        bound = MAX_ABS_PARAMETER if key in params else MAX_ABS_STATISTIC
        peak = float(value.abs().max())
        if peak > bound:
            raise ConfigError(
                f"checkpoint {path}: {key} holds a value of magnitude {peak:.3g}; a trained network's "
                f"{'weights' if key in params else 'statistics'} stay within {bound:g} (this one "
                f"would overflow float32 activations)"
            )
    for name, module in model.named_modules():
        prefix = f"{name}." if name else ""
        if isinstance(module, torch.nn.modules.batchnorm._NormBase) and f"{prefix}running_var" in state:
            low = float(state[f"{prefix}running_var"].min()) if state[f"{prefix}running_var"].numel() else 0.0
            if low < 0:
                raise ConfigError(
                    f"checkpoint {path}: {prefix}running_var has a negative variance ({low:.3g}); "
                    f"BatchNorm variances are >= 0"
                )
        if isinstance(module, GeM) and f"{prefix}p" in state:
            p = float(state[f"{prefix}p"].min())
            if p <= 0:
                raise ConfigError(f"checkpoint {path}: {prefix}p = {p:.3g}; GeM pooling needs an exponent p > 0")


def create_model(
    card: ModelCard, checkpoint: str | Path | None = None, spec: ModelSpec | None = None
) -> torch.nn.Module:
    """The card's model (``spec`` when the caller resolved it), seeded, with ``checkpoint``
    loaded when given (its :class:`LoadReport` as ``model.checkpoint_report``)."""
    model = (spec or model_spec(card)).build(card)
    if checkpoint:
        model.checkpoint_report = load_checkpoint(model, checkpoint)
    return model.eval()
