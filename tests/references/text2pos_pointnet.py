"""Upstream reference: Text2Pos's PointNet++ object network on one object, in plain numpy.

Written from reading mako443/Text2Pos-CVPR2022 ``models/pointcloud/pointnet2.py`` and
``models/modules.py`` (the network Text2Loc and upstream Des4Pos load their object weights into),
and PyG's ``fps`` / ``radius`` / ``PointConv``; shares no code with radaredge. It reads a
state_dict in Text2Pos's own key layout (``sa1.point_conv.local_nn.0.0.weight`` ...).

- ``get_mlp``: every layer Linear -> BatchNorm1d (eval: running statistics, eps 1e-5) -> ReLU.
- Set abstraction ``sa1..sa3`` (ratio 0.5, radii 0.2 / 0.3 / 0.4): farthest point sampling keeps
  ceil(N / 2) points; for each kept centre, the points closer than the radius (at most 32, the
  lowest indices) are its neighbours; ``PointConv`` takes the max over them of
  ``local_nn([x_j, pos_j - pos_centre])``.
- Global layer ``ga``: ``mlp([x, pos])`` on the 32 remaining points, max over them.
- ``features2 = relu(lin2(relu(lin1(features0))))``: the 256-d geometry feature.

Two PyG behaviours are pinned down: FPS starts at point 0 (PyG draws the start at random), and
no neighbour comes from another object of the batch (PyG 1.7.2's PointConv adds a self loop by
index, which for a sampled subset points into other objects: pyg-team/pytorch_geometric#2558).
"""

from __future__ import annotations

import math

import numpy as np

RADII = (0.2, 0.3, 0.4)
MAX_NEIGHBOURS = 32


def _array(sd, key) -> np.ndarray:
    return sd[key].detach().cpu().numpy().astype(np.float64)


def get_mlp(x: np.ndarray, sd: dict, prefix: str, eps: float = 1e-5) -> np.ndarray:
    i = 0
    while f"{prefix}.{i}.0.weight" in sd:
        lin, bn = f"{prefix}.{i}.0", f"{prefix}.{i}.1"
        x = x @ _array(sd, f"{lin}.weight").T + _array(sd, f"{lin}.bias")
        x = (x - _array(sd, f"{bn}.running_mean")) / np.sqrt(_array(sd, f"{bn}.running_var") + eps)
        x = np.maximum(x * _array(sd, f"{bn}.weight") + _array(sd, f"{bn}.bias"), 0.0)
        i += 1
    return x


def fps(pos: np.ndarray, count: int) -> list[int]:
    chosen = [0]
    nearest = np.full(len(pos), np.inf)
    for _ in range(1, count):
        nearest = np.minimum(nearest, ((pos - pos[chosen[-1]]) ** 2).sum(1))
        chosen.append(int(np.argmax(nearest)))
    return chosen


def set_abstraction(x: np.ndarray, pos: np.ndarray, sd: dict, prefix: str, radius: float):
    centres = fps(pos, math.ceil(0.5 * len(pos)))
    out = []
    for c in centres:
        near = [j for j in range(len(pos)) if ((pos[j] - pos[c]) ** 2).sum() < radius * radius][:MAX_NEIGHBOURS]
        message = np.concatenate([x[near], pos[near] - pos[c]], 1)
        out.append(get_mlp(message, sd, f"{prefix}.point_conv.local_nn").max(0))
    return np.stack(out), pos[centres]


def features2(xyz: np.ndarray, rgb: np.ndarray, sd: dict) -> np.ndarray:
    """The 256-d feature of one object: ``xyz`` [P, 3] (the frame Text2Loc feeds: cell units),
    ``rgb`` [P, 3] in [0, 1] (the input features ``x``)."""
    x, pos = np.asarray(rgb, np.float64), np.asarray(xyz, np.float64)
    for level, radius in enumerate(RADII, 1):
        x, pos = set_abstraction(x, pos, sd, f"sa{level}", radius)
    f0 = get_mlp(np.concatenate([x, pos], 1), sd, "ga.mlp").max(0)
    f1 = np.maximum(f0 @ _array(sd, "lin1.weight").T + _array(sd, "lin1.bias"), 0.0)
    return np.maximum(f1 @ _array(sd, "lin2.weight").T + _array(sd, "lin2.bias"), 0.0)
