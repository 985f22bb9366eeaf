"""Des4Pos training and evaluation data: cell maps with described poses, joined, split by scene.

``root`` is one map, or a directory of maps: ``.npz`` cell maps (``radaredge make-city``) and
KITTI360Pose scenes (``cells/<scene>.pkl`` with ``poses/<scene>.pkl`` beside ``cells/``). Each
map is one scene. The maps are joined into one :class:`TextMaps`: every cell with its scene,
every described pose with its best cell (an index into the cells) and its hint sentences.

Validation is by scene: the scenes named in ``validation``, by default the last map by name
when there are two or more (KITTI360Pose's own split puts whole scenes in val and test too).
With a single map, every tenth described pose (seeded) is held out instead.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..runtime.cellmap import CellMap, load_map, validate_map
from ..runtime.des4pos import is_index_cache
from ..runtime.text_tokens import split_hints


def find_maps(root: str | os.PathLike) -> list[Path]:
    """The maps under ``root`` (module docstring), sorted; InputError when there is none."""
    root = Path(root)
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise InputError(
            f"{root} does not exist; expected a cell map (.npz from `radaredge make-city`, a KITTI360Pose "
            f"cells/<scene>.pkl) or a directory of them"
        )
    maps = (
        sorted(p for p in root.glob("*.npz") if not is_index_cache(p))
        + sorted((root / "cells").glob("*.pkl"))
        + sorted(root.glob("*/cells/*.pkl"))
    )
    if not maps:
        raise InputError(
            f"{root}: no cell maps; expected .npz maps from `radaredge make-city` or KITTI360Pose "
            f"cells/<scene>.pkl with poses/<scene>.pkl"
        )
    return maps


@dataclass
class TextMaps:
    """Cells and described poses of several scenes, joined."""

    cells: CellMap  # every cell of every map
    map_of_cell: np.ndarray  # [C] the map (scene) index of each cell
    names: list[str]  # map names, by index
    paths: list[Path]  # map files, by index
    pose_w: np.ndarray  # [Q, 2] float64 m
    pose_id: np.ndarray  # [Q] int: the pose's index in its own map
    pose_cell: np.ndarray  # [Q] int: the best cell, an index into ``cells``
    pose_hints: list[list[str]]  # [Q] hint sentences
    validation: np.ndarray  # [Q] bool: a validation pose

    @property
    def cell_validation(self) -> np.ndarray:
        """[C] bool: cells of the validation scenes (with a single map: none)."""
        held = {int(self.map_of_cell[c]) for c in self.pose_cell[self.validation]}
        if len(self.names) == 1:
            return np.zeros(len(self.map_of_cell), bool)
        return np.isin(self.map_of_cell, list(held))


def _join(maps: list[CellMap]) -> CellMap:
    cat = lambda name: np.concatenate([getattr(m, name) for m in maps])  # noqa: E731
    return CellMap(
        ids=cat("ids"),
        scenes=cat("scenes"),
        origins=cat("origins"),
        sizes=cat("sizes"),
        points=cat("points"),
        num_points=cat("num_points"),
        object_mask=cat("object_mask"),
        labels=np.concatenate([np.asarray(m.labels, "<U24") for m in maps]),
    )


def load_text_maps(
    root: str | os.PathLike,
    slots: int,
    points: int,
    max_hints: int,
    validation: Sequence[str] | None = None,
    seed: int = 0,
    split: bool = True,
) -> TextMaps:
    """The maps under ``root`` packed for a model of ``slots`` objects of ``points`` points
    (module docstring). InputError naming the map for one without described poses, a pose whose
    best cell is not in its map, a description with more than ``max_hints`` hints, or an unknown
    validation scene. ``split`` False: no pose is a validation pose (evaluation)."""
    paths = find_maps(root)
    names = [p.stem for p in paths]
    if len(set(names)) != len(names):
        raise InputError(f"{root}: two maps share a name ({names}); scenes are told apart by name")
    if validation is not None:
        unknown = sorted(set(validation) - set(names))
        if unknown:
            raise InputError(f"validation scene(s) {unknown} are not maps under {root}; maps: {names}")
        held = set(validation)
    else:
        held = {max(names)} if len(names) > 1 else set()  # the last map by name
    if not split:
        held = set()
    maps, map_of_cell, pose_w, pose_id, pose_cell, hints, val = [], [], [], [], [], [], []
    offset = 0
    for i, (path, name) in enumerate(zip(paths, names)):
        m = load_map(path, slots, points)
        validate_map(m, str(path), (slots, points))
        texts = np.asarray(m.pose_text, str)
        described = np.flatnonzero(np.char.str_len(texts) > 0)
        if not len(described):
            raise InputError(
                f"{path}: no described pose; make maps with poses (`radaredge make-city --poses N`) "
                f"or put KITTI360Pose's poses/<scene>.pkl beside cells/"
            )
        index = {cid: j for j, cid in enumerate(m.ids.tolist())}
        for q in described:
            cell = index.get(str(m.pose_cell[q]))
            if cell is None:
                raise InputError(f"{path}: pose {q}'s best cell {m.pose_cell[q]} is not a cell of the map")
            h = split_hints(str(texts[q]))
            if not h or len(h) > max_hints:
                raise InputError(f"{path}: pose {q} has {len(h)} hint sentence(s); the card takes 1 to {max_hints}")
            pose_w.append(m.pose_w[q])
            pose_id.append(q)
            pose_cell.append(offset + cell)
            hints.append(h)
            val.append(name in held)
        maps.append(m)
        map_of_cell += [i] * len(m)
        offset += len(m)
    validation_mask = np.array(val)
    if not held and split:  # a single map: every tenth pose, seeded
        rng = np.random.default_rng(seed)
        validation_mask = np.zeros(len(val), bool)
        validation_mask[rng.permutation(len(val))[: max(1, len(val) // 10)]] = True
    if validation_mask.all():
        raise InputError(f"{root}: every described pose is a validation pose; training needs another map")
    return TextMaps(
        _join(maps),
        np.array(map_of_cell),
        names,
        paths,
        np.array(pose_w, np.float64),
        np.array(pose_id),
        np.array(pose_cell),
        hints,
        validation_mask,
    )
