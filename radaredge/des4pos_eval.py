"""Des4Pos localisation recall over the described poses of a cell map, torch-free.

Protocol (Text2Loc / Des4Pos, :func:`radaredge.evaluation.localization_recall`): every pose of
the map that carries a description is located with the exported bundle as ``radaredge locate``
does (coarse retrieval of the top cells, then the fine stage's position in each); a pose counts
at (k, t) when one of the positions in its first k retrieved cells lies within t m of the pose,
cells of another scene than the pose's best cell never counting. The paper reports k = 1, 5, 10
and t = 5, 10, 15 m.

Maps: the ``.npz`` written by ``radaredge make-city`` (synthetic poses with template
descriptions) or a KITTI360Pose ``cells/<scene>.pkl`` whose ``poses/<scene>.pkl`` lies beside
``cells/`` (:func:`radaredge.data.cellmap.load_map`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .data.cellmap import load_map
from .errors import ConfigError, InputError
from .evaluation import LOCALIZATION_KS, LOCALIZATION_THRESHOLDS, localization_levels, localization_recall
from .runtime.des4pos import Des4PosBundle, MapIndex


@dataclass
class LocalizationReport:
    """Localisation recall of one bundle on one map. ``recall[k][t]`` is the fraction (0..1) of the
    ``queries`` poses with a position within ``t`` m among their first ``k`` retrieved cells."""

    model: str                                  # card name of the bundle
    bundle: str
    map: str
    cells: int                                  # cells in the map
    queries: int                                # described poses located
    ks: tuple[int, ...]
    thresholds: tuple[float, ...]               # m
    recall: dict[int, dict[float, float]]
    from_cache: bool                            # cell descriptors read from the cache beside the map

    def to_dict(self) -> dict:
        """JSON-ready: ``recall`` keyed by ``str(k)``, then by the threshold in m as ``f"{t:g}"``."""
        return {"model": self.model, "bundle": self.bundle, "map": self.map, "cells": self.cells,
                "queries": self.queries, "ks": list(self.ks), "thresholds_m": list(self.thresholds),
                "recall": {str(k): {f"{t:g}": r for t, r in by_t.items()} for k, by_t in self.recall.items()},
                "from_cache": self.from_cache}

    def lines(self) -> list[str]:
        """The text report: map, poses and the recall table."""
        return [f"eval {self.model}: {self.queries} described poses of {self.map} ({self.cells} cells"
                f"{', read from the cache' if self.from_cache else ''}), localisation recall:", *self.table().split("\n")]

    def write_json(self, path: str | os.PathLike) -> Path:
        """Write :meth:`to_dict` to ``path``; return it."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2))
        return path

    def table(self) -> str:
        """Recall in % as a text table, one row per k, one column per threshold."""
        head = ["k"] + [f"{t:g} m" for t in self.thresholds]
        rows = [[f"top-{k}"] + [f"{100 * self.recall[k][t]:.1f} %" for t in self.thresholds] for k in self.ks]
        width = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
        return "\n".join("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, width)))
                         for r in [head] + rows)


def evaluate_localization(bundle_dir: str | os.PathLike, map_path: str | os.PathLike,
                          top_k: Sequence[int] = LOCALIZATION_KS,
                          thresholds: Sequence[float] = LOCALIZATION_THRESHOLDS,
                          progress: Callable[[str], Callable] | None = None, *, threads: int = 2,
                          text_encoder: str | os.PathLike | None = None, cache: bool = True,
                          model: str | None = None) -> LocalizationReport:
    """Locate every described pose of the map at ``map_path`` with the Des4Pos bundle in
    ``bundle_dir`` and score the positions with :func:`radaredge.evaluation.localization_recall`
    at the ``top_k`` values k and ``thresholds`` (m); max(top_k) cells are retrieved per pose.

    ``progress(desc)`` returns a wrapper for the cell and pose loops (a progress bar);
    ``text_encoder`` names another text graph of the bundle (e.g. ``text_encoder.int8.onnx``);
    ``cache`` reads and writes the encoded cells beside the map as :meth:`MapIndex.build` does;
    ``model``, when given, must be the card name the bundle was exported from.
    InputError when the map has no described pose, a pose's best cell is not in the map, or a
    description does not fit the model (the pose is named).
    """
    ks, thresholds = localization_levels(top_k, thresholds)
    wrap = progress or (lambda desc: iter)
    bundle = Des4PosBundle(bundle_dir, threads=threads, text_encoder=text_encoder)
    if model is not None and bundle.card.name != model:
        raise ConfigError(f"{bundle_dir} is an export of card {bundle.card.name!r}, not {model!r}; pass the "
                          f"--model/--config it was exported with")
    cells = load_map(map_path, bundle.slots, bundle.points)
    texts = np.asarray(cells.pose_text, str)
    described = np.flatnonzero(np.char.str_len(texts) > 0)
    if len(described) == 0:
        raise InputError(f"{map_path} holds no described pose; make a map with poses with `radaredge make-city`, "
                         f"or put KITTI360Pose's poses/<scene>.pkl beside cells/")
    scene_of = dict(zip(cells.ids.tolist(), cells.scenes.tolist()))
    missing = [str(cells.pose_cell[q]) for q in described if str(cells.pose_cell[q]) not in scene_of]
    if missing:
        raise InputError(f"{map_path}: pose best cell {missing[0]} is not a cell of the map ({len(missing)} pose(s))")
    index = MapIndex.build(bundle, map_path, cache=cache, progress=wrap("cells"), cells=cells)
    k_max = min(max(ks), len(index))
    pred = np.zeros((len(described), k_max, 2))
    same = np.zeros((len(described), k_max), bool)
    for row, q in enumerate(wrap("poses")(described)):
        try:
            hits = bundle.locate(str(texts[q]), index, top_k=k_max)
        except InputError as exc:
            raise InputError(f"{map_path}: pose {q}: {exc}") from None
        pred[row] = [h["position"] for h in hits]
        same[row] = [scene_of[h["cell"]] == scene_of[str(cells.pose_cell[q])] for h in hits]
    recall = localization_recall(pred, cells.pose_w[described], ks, thresholds, same_scene=same)
    return LocalizationReport(bundle.card.name, str(bundle_dir), str(map_path), len(cells), len(described), ks,
                              thresholds, recall, index.from_cache)
