"""Loading upstream weights into Des4Pos's object encoder.

Text2Pos publishes its pretrained PointNet++ object network (``pointnet_acc0.86_lr1_p256.pth``, a
bare state_dict of 64 tensors: ``sa1..sa3.point_conv.local_nn.*``, ``ga.mlp.*``, ``lin1``,
``lin2``, ``class_classifier``, ``color_classifier``); Text2Loc and upstream Des4Pos load it
into their ObjectEncoder before training. A Text2Loc / Des4Pos coarse checkpoint holds the whole
object encoder under ``object_encoder.`` (its PointNet++ under ``object_encoder.pointnet.``).
:func:`load_object_weights` reads either into ``model.submap.objects``, key for key, and names
every key that does not fit the card.

What differs from upstream's computation with the same weights: upstream's PyG farthest point
sampling starts at a random point and PyG 1.7.2's PointConv adds one neighbour from another
object of the batch to every centre (PyG issue 2558); radaredge starts at point 0 and keeps each
object to itself, so features differ slightly from any one upstream run (which are themselves
random at inference).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from ...errors import ConfigError
from ..checkpoints import read_state_dict

T2L_PREFIX = "object_encoder."
# Text2Loc ObjectEncoder entries used only by its ablations (class / colour embeddings of the labels).
T2L_UNUSED = ("class_embedding.weight", "color_embedding.weight")


@dataclass
class ObjectWeightsReport:
    """What :func:`load_object_weights` loaded: tensors by part, and the upstream keys it left out."""

    path: str
    source: str
    loaded: int
    parts: list[str] = field(default_factory=list)
    unused: list[str] = field(default_factory=list)

    def summary(self) -> str:
        text = (
            f"loaded {self.loaded} tensors of the object encoder ({', '.join(self.parts)}) "
            f"from {self.path} ({self.source})"
        )
        return text + (f"; left out {', '.join(self.unused)} (unused by the model)" if self.unused else "")


def load_object_weights(model: torch.nn.Module, path: str | Path) -> ObjectWeightsReport:
    """Load Text2Pos PointNet++ weights, or a Text2Loc / Des4Pos checkpoint's object encoder,
    into ``model.submap.objects`` (module docstring). ConfigError naming the file and the keys
    for a file that holds neither, or whose tensors do not fit the card's object encoder."""
    state = read_state_dict(path)
    objects = model.submap.objects
    own = objects.state_dict()
    if any(k.startswith(T2L_PREFIX) for k in state):
        source = "Text2Loc/Des4Pos checkpoint"
        picked = {k[len(T2L_PREFIX) :]: v for k, v in state.items() if k.startswith(T2L_PREFIX)}
        unused = [T2L_PREFIX + k for k in T2L_UNUSED if k in picked]
        picked = {k: v for k, v in picked.items() if k not in T2L_UNUSED}
    elif any(k.startswith("sa1.") for k in state):
        source = "Text2Pos PointNet++"
        picked, unused = {"pointnet." + k: v for k, v in state.items()}, []
    else:
        raise ConfigError(
            f"{path}: neither Text2Pos PointNet++ weights (keys sa1.*, ga.*, lin1.*) nor a Text2Loc / "
            f"Des4Pos checkpoint (keys object_encoder.*); first keys: {sorted(state)[:5]}"
        )
    unexpected = sorted(set(picked) - set(own))
    shapes = sorted(
        f"{k} (file {tuple(picked[k].shape)}, card {tuple(own[k].shape)})"
        for k in set(picked) & set(own)
        if picked[k].shape != own[k].shape
    )
    missing = sorted(k for k in own if k.startswith("pointnet.") and k not in picked)
    problems = [
        f"{what} ({len(keys)}): {', '.join(keys[:8])}{' ...' if len(keys) > 8 else ''}"
        for what, keys in (
            ("keys the object encoder does not have", unexpected),
            ("wrong shapes", shapes),
            ("PointNet++ keys missing", missing),
        )
        if keys
    ]
    if problems:
        raise ConfigError(
            f"{path} ({source}) does not fit the card's object encoder (submap.sa_*, global_mlp, "
            f"head_mlp, object_classes, object_colors, embed_dim): {'; '.join(problems)}"
        )
    objects.load_state_dict({**own, **picked})
    parts = sorted({k.split(".")[0] for k in picked})
    return ObjectWeightsReport(str(path), source, len(picked), parts, unused)
