"""Des4Pos evaluation: the paper's Table I (localisation) and Table II (cell retrieval) over a
multi-scene database, for the exported bundle and the torch reference side by side.

Protocol (Text2Loc / Des4Pos): the database is every cell of every map given (a map, or a
directory of maps, :mod:`radaredge.data.text_maps`); every described pose of those maps is a
query. Its text descriptor retrieves the top cells by cosine similarity; the fine stage gives a
position in each.

- **Table I**, localisation recall (:func:`radaredge.eval.places.localization_recall`): a pose
  counts at (k, t) when one of the positions in its first k retrieved cells lies within t m of
  the pose, cells of another scene never counting; k = 1, 5, 10 and t = 5, 10, 15 m. Twice: with
  the fine stage's positions, and with each retrieved cell's centre (no fine stage), which is
  what the fine stage has to beat. Each figure comes with its 95 % percentile-bootstrap interval
  over the queries (:func:`radaredge.eval.recall_stats.bootstrap_interval`), and so does the fine
  stage's gain: the mean over queries of (hit with the fine stage) - (hit with the centre), a
  paired difference, whose interval is narrower than the two tables' intervals suggest because
  both rows are the same queries.
- **Table II**, cell-retrieval recall@k: the pose's best cell (the cell whose centre is nearest,
  KITTI360Pose's ``best_cell``) is among its top k; k = 1, 3, 5.

Backends: ``onnxruntime`` runs the bundle's three graphs (torch-free, the cell descriptors
cached beside each map); ``torch reference`` runs the card's reference formulation (real objects
and tokens only, one cell and one hint at a time) with the weights the bundle was exported from
(``checkpoint``; the hash is checked).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from .. import atomic
from ..data.text_maps import TextMaps, load_text_maps
from ..errors import ConfigError, InputError
from ..models.factory import create_model, weights_hash
from ..runtime.des4pos import Des4PosBundle, MapIndex, object_summaries
from .places import LOCALIZATION_KS, LOCALIZATION_THRESHOLDS, localization_levels, localization_recall
from .recall_stats import bootstrap_interval

RETRIEVAL_KS = (1, 3, 5)
ONNX, REFERENCE = "onnxruntime", "torch reference"
FINE, CENTRE = "localization", "localization_centre"  # Table I with the fine stage / with the cell centres
GAIN = "localization_gain"  # FINE - CENTRE, per query, averaged (a paired difference)
INTERVAL = "_interval"  # suffix: the 95 % bootstrap interval of a Table I


def retrieval_recall(retrieved: np.ndarray, truth: np.ndarray, ks: Sequence[int] = RETRIEVAL_KS) -> dict[int, float]:
    """Cell-retrieval recall: the fraction (0..1) of queries whose true cell ``truth`` [Q] is among
    the first k of ``retrieved`` [Q, K] (database rows, best first), per k; InputError for a k
    larger than K."""
    retrieved, truth = np.asarray(retrieved), np.asarray(truth)
    if retrieved.ndim != 2 or truth.shape != (len(retrieved),) or not len(truth):
        raise InputError(
            f"expected retrieved cells [Q, K] and true cells [Q] with Q >= 1, got {retrieved.shape} and {truth.shape}"
        )
    too_deep = [k for k in ks if not 1 <= k <= retrieved.shape[1]]
    if too_deep:
        raise InputError(f"recall@{too_deep[0]} needs the top {too_deep[0]} cells; {retrieved.shape[1]} were retrieved")
    hit = retrieved == truth[:, None]
    return {int(k): float(hit[:, :k].any(1).mean()) for k in ks}


def localization_hits(
    pred_w: np.ndarray, pose_w: np.ndarray, ks: Sequence[int], thresholds: Sequence[float], same_scene: np.ndarray
) -> dict[int, dict[float, np.ndarray]]:
    """Per query, whether it counts at (k, t) (bool [Q]), by the rule of
    :func:`radaredge.eval.places.localization_recall` (whose fractions are the means of these):
    ``pred_w`` [Q, K, 2], ``pose_w`` [Q, 2] m, ``same_scene`` [Q, K] (False never counts)."""
    dist = np.linalg.norm(np.asarray(pred_w, np.float64) - np.asarray(pose_w, np.float64)[:, None, :], axis=2)
    best = np.minimum.accumulate(np.where(np.asarray(same_scene, bool), dist, np.inf), axis=1)
    return {k: {t: best[:, k - 1] <= t for t in thresholds} for k in ks}


def _intervals(hits: dict) -> dict[int, dict[float, tuple[float, float]]]:
    """The 95 % percentile-bootstrap interval (fractions) of the mean of every (k, t) of ``hits``
    (per-query hits, or per-query differences of two hit arrays)."""
    return {
        k: {t: tuple(v / 100.0 for v in bootstrap_interval(h)) for t, h in by_t.items()} for k, by_t in hits.items()
    }


@dataclass
class LocalizationReport:
    """Table I and Table II of one bundle on a database of maps, per backend (module docstring).
    ``results[backend]["localization"][k][t]`` (with the fine stage),
    ``results[backend]["localization_centre"][k][t]`` (each retrieved cell's centre, no fine
    stage) and ``results[backend]["retrieval"][k]`` are fractions in 0..1;
    ``results[backend]["localization_gain"][k][t]`` is their paired difference (fine stage minus
    centre, -1..1). The two Table I and the gain have their 95 % bootstrap intervals over
    queries, (low, high) fractions, under the same keys with ``_interval`` appended."""

    model: str  # card name of the bundle
    bundle: str
    maps: list[str]
    cells: int  # database cells, all maps
    queries: int  # described poses located
    ks: tuple[int, ...]
    thresholds: tuple[float, ...]  # m
    retrieval_ks: tuple[int, ...]
    results: dict[str, dict] = field(default_factory=dict)
    checkpoint: str | None = None
    from_cache: bool = False  # every map's cell descriptors read from its cache

    @property
    def recall(self) -> dict[int, dict[float, float]]:
        """Table I of the exported bundle."""
        return self.results[ONNX]["localization"]

    @property
    def centre_recall(self) -> dict[int, dict[float, float]]:
        """Table I of the exported bundle's retrieval with each cell's centre as the position."""
        return self.results[ONNX][CENTRE]

    @property
    def retrieval(self) -> dict[int, float]:
        """Table II of the exported bundle."""
        return self.results[ONNX]["retrieval"]

    def to_dict(self) -> dict:
        """JSON-ready: localisation (``localization``: fine stage, ``localization_centre``: cell
        centres) keyed by ``str(k)`` then by ``f"{t:g}"`` (m), its intervals (``..._interval``) as
        [low, high], retrieval by ``str(k)``."""

        def table(by_k):
            return {
                str(k): {f"{t:g}": (list(r) if isinstance(r, tuple) else r) for t, r in by_t.items()}
                for k, by_t in by_k.items()
            }

        return {
            "model": self.model,
            "bundle": self.bundle,
            "maps": self.maps,
            "cells": self.cells,
            "queries": self.queries,
            "ks": list(self.ks),
            "thresholds_m": list(self.thresholds),
            "retrieval_ks": list(self.retrieval_ks),
            "checkpoint": self.checkpoint,
            "from_cache": self.from_cache,
            "results": {
                name: {
                    **{
                        key: table(res[key])
                        for key in (FINE, FINE + INTERVAL, CENTRE, CENTRE + INTERVAL, GAIN, GAIN + INTERVAL)
                        if key in res
                    },
                    "retrieval": {str(k): r for k, r in res["retrieval"].items()},
                }
                for name, res in self.results.items()
            },
        }

    def write_json(self, path: str | os.PathLike) -> Path:
        """Write :meth:`to_dict` to ``path``; return it."""
        return atomic.write_json(path, self.to_dict())

    def lines(self) -> list[str]:
        """The text report: database, then Table I and Table II with one column per backend."""
        where = self.maps[0] if len(self.maps) == 1 else f"{len(self.maps)} maps"
        return [
            f"eval {self.model}: {self.queries} described poses of {where} against {self.cells} cells"
            f"{' (cell descriptors read from the cache)' if self.from_cache else ''}",
            (
                "Table I, localisation recall (a position within t m among the top-k cells), fine stage "
                "[95 % bootstrap interval over queries]:"
            ),
            *self.table().split("\n"),
            "Table I without the fine stage (each retrieved cell's centre as the position):",
            *self.table(CENTRE).split("\n"),
            "The fine stage's gain (percentage points, the same queries with and without it):",
            *self.table(GAIN).split("\n"),
            "Table II, cell-retrieval recall (the best cell among the top k):",
            *self.retrieval_table().split("\n"),
        ]

    def table(self, which: str = FINE) -> str:
        """Table I in % (``which``: ``localization``, the fine stage's positions,
        ``localization_centre``, the cells' centres, or ``localization_gain``, the fine stage's
        gain in points) with its bootstrap intervals when computed: one row per k, a column per
        threshold and backend."""
        head = ["k"] + [
            f"{t:g} m" + (f" ({name})" if len(self.results) > 1 else "")
            for name in self.results
            for t in self.thresholds
        ]

        def cell(res, k, t):
            low_high = res.get(which + INTERVAL, {}).get(k, {}).get(t)
            text = f"{100 * res[which][k][t]:+.1f}" if which == GAIN else f"{100 * res[which][k][t]:.1f} %"
            return text if low_high is None else f"{text} [{100 * low_high[0]:.1f}, {100 * low_high[1]:.1f}]"

        rows = [
            [f"top-{k}"] + [cell(res, k, t) for res in self.results.values() for t in self.thresholds] for k in self.ks
        ]
        return _text_table(head, rows)

    def retrieval_table(self) -> str:
        """Table II in %: one row per k, a column per backend."""
        head = ["k"] + [f"recall ({name})" for name in self.results]
        rows = [
            [f"top-{k}"] + [f"{100 * res['retrieval'][k]:.1f} %" for res in self.results.values()]
            for k in self.retrieval_ks
        ]
        return _text_table(head, rows)


def _text_table(head: list[str], rows: list[list[str]]) -> str:
    width = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    return "\n".join(
        "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, width))) for r in [head] + rows
    )


def _scores(retrieved: np.ndarray, positions: np.ndarray, maps: TextMaps, ks, thresholds, retrieval_ks) -> dict:
    """Table I with the fine stage's ``positions`` [Q, K, 2] and with the centres of the retrieved
    cells (no fine stage), their paired difference (the fine stage's gain), each with its
    bootstrap interval, and Table II."""
    top = retrieved[:, : positions.shape[1]]
    same = maps.map_of_cell[top] == maps.map_of_cell[maps.pose_cell][:, None]
    centres = maps.cells.origins[top] + 0.5 * maps.cells.sizes[top][..., None]
    out, hits = {}, {}
    for key, pred in ((FINE, positions), (CENTRE, centres)):
        out[key] = localization_recall(pred, maps.pose_w, ks, thresholds, same_scene=same)
        hits[key] = localization_hits(pred, maps.pose_w, ks, thresholds, same)
        out[key + INTERVAL] = _intervals(hits[key])
    gain = {k: {t: hits[FINE][k][t].astype(np.float64) - hits[CENTRE][k][t] for t in thresholds} for k in ks}
    out[GAIN] = {k: {t: float(d.mean()) for t, d in by_t.items()} for k, by_t in gain.items()}
    out[GAIN + INTERVAL] = _intervals(gain)
    out["retrieval"] = retrieval_recall(retrieved, maps.pose_cell, retrieval_ks)
    return out


def _onnx_backend(bundle: Des4PosBundle, maps: TextMaps, depth: int, fine_k: int, cache: bool, wrap):
    """(retrieved rows [Q, depth], positions [Q, fine_k, 2], every map from its cache) of the bundle."""
    indices = []
    for path in maps.paths:
        indices.append(MapIndex.build(bundle, path, cache=cache, progress=wrap(f"cells of {path.name}")))
    cells = maps.cells
    centres, colours = object_summaries(cells.points)
    index = MapIndex(
        np.array([f"{maps.names[m]}/{c}" for m, c in zip(maps.map_of_cell, cells.ids)]),
        cells.origins,
        cells.sizes,
        cells.object_mask,
        np.concatenate([i.descriptors for i in indices]),
        np.concatenate([i.object_features for i in indices]),
        object_centres=centres,
        object_colours=colours,
        num_points=np.asarray(cells.num_points, np.float32),
    )
    retrieved = np.zeros((len(maps.pose_w), depth), np.int64)
    positions = np.zeros((len(maps.pose_w), fine_k, 2))
    for q in wrap("poses")(range(len(maps.pose_w))):
        try:
            desc, hints = bundle.encode_text(" ".join(maps.pose_hints[q]))
        except InputError as exc:
            raise InputError(
                f"{maps.paths[maps.map_of_cell[maps.pose_cell[q]]]}: pose {maps.pose_id[q]}: {exc}"
            ) from None
        retrieved[q] = index.search(desc[None], depth)[1][0]
        positions[q] = bundle.fine(index, retrieved[q, :fine_k], hints)[1]
    return retrieved, positions, all(i.from_cache for i in indices)


def _reference_backend(bundle: Des4PosBundle, maps: TextMaps, checkpoint, depth: int, fine_k: int, wrap):
    """The same with the card's torch reference formulation and the bundle's weights."""
    model = create_model(bundle.card, checkpoint)
    if weights_hash(model) != bundle.weights_sha256:
        source = f"checkpoint {checkpoint}" if checkpoint else "the seeded initialisation of this card"
        raise ConfigError(
            f"{bundle.directory} was exported with other weights than {source}; pass the "
            f"--checkpoint it was exported with (or --no-reference)"
        )
    cells = maps.cells
    descs, objects = [], []
    centres, colours = object_summaries(cells.points)
    summaries = [
        tuple(
            torch.from_numpy(np.ascontiguousarray(a[c][cells.object_mask[c]], np.float32))
            for a in (centres, colours, cells.num_points)
        )
        for c in range(len(cells.ids))
    ]
    with torch.no_grad():
        for c in wrap("cells (torch reference)")(range(len(cells.ids))):
            m = cells.object_mask[c]
            d, h = model.submap.reference(cells.points[c][m], cells.num_points[c][m])
            descs.append(d.numpy())
            objects.append(h)
        descs = np.stack(descs)
        retrieved = np.zeros((len(maps.pose_w), depth), np.int64)
        positions = np.zeros((len(maps.pose_w), fine_k, 2))
        for q in wrap("poses (torch reference)")(range(len(maps.pose_w))):
            _, ids, mask = bundle.tokenize(" ".join(maps.pose_hints[q]))
            d, h = model.text.reference([ids[i][mask[i] > 0] for i in range(len(ids))])
            scores = descs @ d.numpy()
            retrieved[q] = np.argsort(-scores, kind="stable")[:depth]
            top = retrieved[q, :fine_k]
            positions[q] = model.fine.reference(
                [objects[c] for c in top],
                h,
                cells.origins[top],
                cells.sizes[top],
                [summaries[c] for c in top] if model.fine.needs_summaries else None,
            )[1].numpy()
    return retrieved, positions


def evaluate_localization(
    bundle_dir: str | os.PathLike,
    maps_path: str | os.PathLike,
    top_k: Sequence[int] = LOCALIZATION_KS,
    thresholds: Sequence[float] = LOCALIZATION_THRESHOLDS,
    progress: Callable[[str], Callable] | None = None,
    *,
    threads: int = 2,
    text_encoder: str | os.PathLike | None = None,
    cache: bool = True,
    model: str | None = None,
    retrieval_ks: Sequence[int] = RETRIEVAL_KS,
    reference: bool = False,
    checkpoint: str | os.PathLike | None = None,
) -> LocalizationReport:
    """Table I at the ``top_k`` values and ``thresholds`` (m) and Table II at ``retrieval_ks`` of
    the Des4Pos bundle in ``bundle_dir`` over the maps at ``maps_path`` (module docstring), and of
    the torch reference with ``reference`` (weights: ``checkpoint``, or the card's seeded ones).

    ``progress(desc)`` returns a wrapper for the cell and pose loops (a progress bar);
    ``text_encoder`` names another text graph of the bundle (e.g. its int8 copy);
    ``cache`` reads and writes each map's encoded cells beside it (:meth:`MapIndex.build`);
    ``model``, when given, must be the card name the bundle was exported from.
    InputError when a map has no described pose, a pose's best cell is not in its map, or a
    description does not fit the model (the map and pose are named); ConfigError when the
    database holds fewer cells than the deepest k.
    """
    ks, thresholds = localization_levels(top_k, thresholds)
    r_ks = tuple(sorted({int(k) for k in retrieval_ks}))
    if not r_ks or r_ks[0] < 1:
        raise ConfigError(f"retrieval recall needs k >= 1, got {list(retrieval_ks)}")
    if checkpoint is not None and not reference:
        raise ConfigError("--checkpoint gives the torch reference its weights; it is not used with --no-reference")
    wrap = progress or (lambda desc: iter)
    bundle = Des4PosBundle(bundle_dir, threads=threads, text_encoder=text_encoder)
    if model is not None and bundle.card.name != model:
        raise ConfigError(
            f"{bundle_dir} is an export of card {bundle.card.name!r}, not {model!r}; pass the "
            f"--model/--config it was exported with"
        )
    maps = load_text_maps(maps_path, bundle.slots, bundle.points, bundle.max_hints, split=False)
    fine_k = max(ks)
    depth = max(fine_k, max(r_ks))
    if depth > len(maps.cells.ids):
        raise ConfigError(
            f"top-{depth} recall needs at least {depth} database cells; {maps_path} has "
            f"{len(maps.cells.ids)} (use a larger database, or smaller k)"
        )
    retrieved, positions, cached = _onnx_backend(bundle, maps, depth, fine_k, cache, wrap)
    results = {ONNX: _scores(retrieved, positions, maps, ks, thresholds, r_ks)}
    if reference:
        retrieved, positions = _reference_backend(bundle, maps, checkpoint, depth, fine_k, wrap)
        results[REFERENCE] = _scores(retrieved, positions, maps, ks, thresholds, r_ks)
    return LocalizationReport(
        bundle.card.name,
        str(bundle_dir),
        [str(p) for p in maps.paths],
        len(maps.cells.ids),
        len(maps.pose_w),
        ks,
        thresholds,
        r_ks,
        results,
        str(checkpoint) if checkpoint else None,
        cached,
    )
