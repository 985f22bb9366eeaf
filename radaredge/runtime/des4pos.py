"""Torch-free Des4Pos query path: numpy + onnxruntime + faiss + tokenizers only.

    from radaredge.runtime.des4pos import Des4PosBundle, MapIndex
    bundle = Des4PosBundle("export/des4pos")            # three graphs + tokenizer.json + the manifest
    index = MapIndex.build(bundle, "city.npz")          # encodes every cell once (cached beside the map)
    for hit in bundle.locate("The pose is north of a red box.", index, top_k=3):
        print(hit["cell"], hit["score"], hit["position"])

Coarse stage: the text descriptor's inner product with the L2-normalised cell descriptors (a FAISS
``IndexFlatIP``; the cosine similarity, which ranks as L2 distance does on unit vectors) picks
the top-k cells. Fine stage: one ``fine_stage`` call on those k cells gives a position in each
(world m, float64), reported with the retrieval score.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import artifacts
from ..cards.des4pos import CellConfig, TextConfig
from ..errors import ConfigError, InputError
from .bundle import read_manifest
from .cellmap import CellMap, load_map, validate_map
from .model import RadarModel
from .model import load as load_graph
from .session import checked_threads
from .text_tokens import encode_hints, load_tokenizer, split_hints

PARTS = ("submap_encoder", "text_encoder", "fine_stage")
INDEX_CACHE_TAG = ".des4pos-"  # <map file name><tag><key>.npz: a MapIndex cache beside the map


class Des4PosBundle:
    """An exported Des4Pos bundle directory. ``text_encoder`` may name another text graph (e.g. the
    int8 copy of the text encoder) with the same interface."""

    def __init__(self, directory: str | Path, threads: int = 2, text_encoder: str | Path | None = None):
        self.directory = d = Path(directory)
        if text_encoder is not None and not Path(text_encoder).is_file():
            raise ConfigError(
                f"{text_encoder} does not exist; the int8 text encoder is written by "
                f"`radaredge export --model des4pos --quantize int8`"
            )
        manifest = artifacts.manifest_path(d)
        if not manifest.is_file():
            raise InputError(
                f"{d} is not a Des4Pos bundle (no {manifest.name}); export one with `radaredge export --model des4pos`"
            )
        self.manifest = read_manifest(manifest)
        self.graphs: dict[str, RadarModel] = {}
        for part in PARTS:
            info = self.manifest["parts"].get(part)
            if info is None:
                raise InputError(f"{manifest} lists no {part} graph")
            path = Path(text_encoder) if (part == "text_encoder" and text_encoder) else artifacts.part_path(d, part)
            g = load_graph(path, threads=threads)
            if g.info.bundle_weights_sha256 != self.manifest["weights_sha256"]:
                raise InputError(
                    f"{path} belongs to another export than {manifest} (bundle weights differ); re-export the bundle"
                )
            self.graphs[part] = g
        self.card = self.graphs["submap_encoder"].card
        self.weights_sha256: str = self.manifest["weights_sha256"]
        self.tokenizer = load_tokenizer(d / "tokenizer.json")
        cell, text = self.card.section("cell", CellConfig), self.card.section("text", TextConfig)
        self.slots, self.points = cell.max_objects, cell.points_per_object
        self.max_tokens, self.max_hints = text.max_tokens, text.max_hints

    # -- the three graphs -------------------------------------------------------------------
    def encode_cells(self, cells: CellMap, batch: int = 8, progress=None) -> tuple[np.ndarray, np.ndarray]:
        """(descriptors [C, D], object features [C, T, D]) of every cell, ``batch`` cells per call."""
        validate_map(cells, "map", (self.slots, self.points))
        sess = self.graphs["submap_encoder"].session
        out_d, out_o = [], []
        starts = range(0, len(cells), batch)
        for s in progress(starts) if progress else starts:
            sl = slice(s, s + batch)
            d, o = sess.run(
                ["descriptor", "object_features"],
                {
                    "points": np.ascontiguousarray(cells.points[sl], np.float32),
                    "num_points": np.ascontiguousarray(cells.num_points[sl], np.float32),
                    "object_mask": np.ascontiguousarray(cells.object_mask[sl], bool),
                },
            )
            out_d.append(d)
            out_o.append(o)
        return np.concatenate(out_d), np.concatenate(out_o)

    def tokenize(self, text: str) -> tuple[list[str], np.ndarray, np.ndarray]:
        hints = split_hints(text)
        ids, mask = encode_hints(self.tokenizer, hints, self.max_tokens, self.max_hints)
        return hints, ids, mask

    def encode_text(self, text: str) -> tuple[np.ndarray, np.ndarray]:
        """(descriptor [D], hint features [H, D]) of a description."""
        _, ids, mask = self.tokenize(text)
        d, h = self.graphs["text_encoder"].session.run(
            ["descriptor", "hint_features"], {"input_ids": ids, "attention_mask": mask}
        )
        return d, h

    def fine(self, index: "MapIndex", cells: np.ndarray, hint_features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(offset [k, 2] cell units from the centre, position [k, 2] world m) in ``cells``. A fine
        stage with its own object encoder (card ``fine.objects: encoder``) also takes the cells'
        object centres, colours and point counts, which the index keeps."""
        graph = self.graphs["fine_stage"]
        feeds = {
            "object_features": index.object_features[cells],
            "object_mask": index.object_mask[cells],
            "hint_features": hint_features,
            "cell_origin": index.origins[cells].astype(np.float64),
            "cell_size": index.sizes[cells].astype(np.float64),
        }
        wanted = [n for n in SUMMARY_INPUTS if n in graph.input_names]
        if wanted:
            if index.object_centres is None:
                raise InputError(
                    f"{graph.path.name} reads the objects' centres, colours and point counts; this "
                    f"index was built without them (use MapIndex.build, or pass the map's cells)"
                )
            summary = {
                "object_centres": index.object_centres,
                "object_colours": index.object_colours,
                "num_points": index.num_points,
            }
            feeds.update({n: np.ascontiguousarray(summary[n][cells], np.float32) for n in wanted})
        return graph.session.run(["offset", "position"], feeds)

    def locate(self, text: str, index: "MapIndex", top_k: int = 3) -> list[dict]:
        """The top-k cells for ``text`` with a position estimate in each, best first."""
        if top_k < 1:
            raise ConfigError(f"top_k must be >= 1, got {top_k}")
        desc, hints = self.encode_text(text)
        scores, cells = index.search(desc[None], min(top_k, len(index)))
        cells, scores = cells[0], scores[0]
        offset, position = self.fine(index, cells, hints)
        return [
            {
                "rank": r + 1,
                "cell": str(index.ids[c]),
                "score": float(s),
                "position": position[r].tolist(),
                "offset": offset[r].tolist(),
            }
            for r, (c, s) in enumerate(zip(cells, scores))
        ]


SUMMARY_INPUTS = ("object_centres", "object_colours", "num_points")  # of a fine stage with its own object encoder


def object_summaries(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centres [..., 3], mean colours [..., 3]) float32 of objects ``points`` [..., P, 6]: the means of
    their stored points (x, y, z in cell units, r, g, b), as the torch model computes them."""
    pts = np.asarray(points, np.float32)
    return pts[..., :3].mean(-2, dtype=np.float32), pts[..., 3:].mean(-2, dtype=np.float32)


@dataclass
class MapIndex:
    """The encoded cells of one map and a FAISS inner-product index over their descriptors; with
    ``object_centres``, ``object_colours`` and ``num_points`` [C, T, ...] (:func:`object_summaries`
    of the map's points, and its point counts) a fine stage with its own object encoder can run."""

    ids: np.ndarray
    origins: np.ndarray
    sizes: np.ndarray
    object_mask: np.ndarray
    descriptors: np.ndarray
    object_features: np.ndarray
    cache: Path | None = None
    from_cache: bool = False
    object_centres: np.ndarray | None = None
    object_colours: np.ndarray | None = None
    num_points: np.ndarray | None = None

    def __post_init__(self):
        # optional: faiss (eval extra) is needed by locate and eval only
        import faiss

        self.index = faiss.IndexFlatIP(self.descriptors.shape[1])
        self.index.add(np.ascontiguousarray(self.descriptors, np.float32))

    def __len__(self) -> int:
        return len(self.ids)

    def search(self, query: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(scores [Q, k] cosine similarity, cell rows [Q, k]), best first."""
        return self.index.search(np.ascontiguousarray(query, np.float32), k)

    @classmethod
    def build(
        cls,
        bundle: Des4PosBundle,
        map_path: str | Path,
        cache: bool = True,
        progress=None,
        cells: CellMap | None = None,
    ) -> "MapIndex":
        """Encode the map's cells with the bundle, or read them from the cache written beside the map
        (``<map>.des4pos-<key>.npz``; the key hashes the map file, the bundle's weights and its
        cell-encoder graph).

        The cache is written atomically (a temporary file renamed into place) with a hash of its
        arrays; one that is unreadable, of the wrong shape or whose arrays do not match the hash
        is rebuilt with a warning, and a map directory that cannot be written only loses the
        cache (a warning), never the result."""
        map_path = Path(map_path)
        cells = cells if cells is not None else load_map(map_path, bundle.slots, bundle.points)
        h = hashlib.sha256(bundle.weights_sha256.encode())
        for source in (bundle.graphs["submap_encoder"].path, map_path):  # weights alone miss a new graph
            with open(source, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
        path = map_path.with_name(f"{map_path.name}{INDEX_CACHE_TAG}{h.hexdigest()[:16]}.npz")
        centres, colours = object_summaries(cells.points)
        common = dict(
            ids=cells.ids,
            origins=cells.origins,
            sizes=cells.sizes,
            object_mask=cells.object_mask,
            object_centres=centres,
            object_colours=colours,
            num_points=np.asarray(cells.num_points, np.float32),
        )
        if cache and path.is_file():
            arrays = _read_cache(path, len(cells), cells.object_mask.shape[1])
            if arrays is not None:
                return cls(**common, descriptors=arrays[0], object_features=arrays[1], cache=path, from_cache=True)
        desc, objs = bundle.encode_cells(cells, progress=progress)
        written = cache and _write_cache(path, desc, objs)
        return cls(**common, descriptors=desc, object_features=objs, cache=path if written else None)


def is_index_cache(path: str | Path) -> bool:
    """True for a cell-descriptor cache that :meth:`MapIndex.build` wrote beside a map."""
    return INDEX_CACHE_TAG in Path(path).name


def _digest(descriptors: np.ndarray, object_features: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in (descriptors, object_features):
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _read_cache(path: Path, cells: int, slots: int):
    """(descriptors [C, D], object features [C, T, D]) from a cache file, or None (with a
    warning) when it cannot be trusted."""
    try:
        with np.load(path, allow_pickle=False) as z:
            desc, objs, digest = z["descriptors"], z["object_features"], str(z["digest"])
        ok = (
            desc.ndim == 2
            and desc.shape[0] == cells
            and objs.shape == (cells, slots, desc.shape[1])
            and digest == _digest(desc, objs)
        )
    except Exception as exc:  # a truncated or foreign file: numpy, zipfile and key errors alike
        ok, why = False, f"{type(exc).__name__}: {exc}"
    else:
        why = "its arrays do not match the map or their hash"
    if ok:
        return desc, objs
    warnings.warn(f"{path}: ignoring the cell cache ({why}); encoding the map again", RuntimeWarning, stacklevel=3)
    return None


def _write_cache(path: Path, descriptors: np.ndarray, object_features: np.ndarray) -> bool:
    """Write the cache atomically beside the map; False (with a warning) when that is not possible."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(
                f,
                descriptors=descriptors,
                object_features=object_features,
                digest=np.array(_digest(descriptors, object_features)),
            )
        os.replace(tmp, path)
        return True
    except OSError as exc:
        if "tmp" in locals():
            Path(tmp).unlink(missing_ok=True)
        warnings.warn(
            f"cannot write the cell cache beside the map ({exc}); the map will be encoded again next time",
            RuntimeWarning,
            stacklevel=3,
        )
        return False


@dataclass
class LocateResult:
    """One description located in one map: its hints, the map's cells (encoded, or read from the
    cache), the ranked cells with a position each, and the time the map and the query took (ms)."""

    text: str
    map: str
    hints: list[str]
    index: MapIndex
    hits: list[dict]
    map_ms: float
    query_ms: float

    def to_dict(self) -> dict:
        return {
            "text": self.text,
            "hints": self.hints,
            "cells": len(self.index),
            "from_cache": self.index.from_cache,
            "map_ms": self.map_ms,
            "query_ms": self.query_ms,
            "results": self.hits,
        }

    def lines(self) -> list[str]:
        index = self.index
        how = (
            f"read from {index.cache.name}"
            if index.from_cache
            else "encoded" + (f", cached in {index.cache.name}" if index.cache else "")
        )
        out = [
            f"map {self.map}: {len(index)} cells ({how}) in {self.map_ms:.0f} ms",
            f"query: {len(self.hints)} hint(s), text encode + search + fine stage in {self.query_ms:.1f} ms",
            f"{'rank':>4}  {'cell':<32}{'score':>8}  {'x (m)':>11}{'y (m)':>11}",
        ]
        out += [
            f"{h['rank']:>4}  {h['cell']:<32}{h['score']:>8.4f}  {h['position'][0]:>11.2f}{h['position'][1]:>11.2f}"
            for h in self.hits
        ]
        return out


def locate_description(
    directory: str | Path,
    map_path: str | Path,
    text: str,
    top_k: int = 3,
    threads: int = 2,
    int8_text: bool = False,
    cache: bool = True,
    progress=None,
    model: str | None = None,
) -> LocateResult:
    """Locate ``text`` in the map at ``map_path`` with the Des4Pos export in ``directory`` (its int8
    text encoder with ``int8_text``): the map's cells encoded once (cached beside the map with
    ``cache``), the top-k cells retrieved, the fine stage's position in each. ``model``, when
    given, must be the export's card name (or ``des4pos``)."""
    if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
        raise ConfigError(f"--top-k: expected an integer >= 1 (candidate cells), got {top_k!r}")
    checked_threads(threads)
    if not Path(map_path).is_file():
        raise InputError(
            f"--map: {map_path} does not exist; make one with `radaredge make-city` or pass a "
            f"KITTI360Pose cells/<scene>.pkl"
        )
    if not split_hints(text):
        raise InputError(
            '--text: the description is empty; give one or more sentences, e.g. "The pose is north of a red box."'
        )
    int8_text_encoder = artifacts.copy_path(artifacts.part_path(directory, "text_encoder"), artifacts.INT8)
    bundle = Des4PosBundle(directory, threads=threads, text_encoder=int8_text_encoder if int8_text else None)
    if bundle.card.model != "des4pos" or (model not in (None, "des4pos", bundle.card.name)):
        raise ConfigError(f"{directory} holds {bundle.card.name}, not {model}")
    t0 = time.perf_counter()
    index = MapIndex.build(bundle, map_path, cache=cache, progress=progress)
    t1 = time.perf_counter()
    hits = bundle.locate(text, index, top_k)
    t2 = time.perf_counter()
    return LocateResult(text, str(map_path), bundle.tokenize(text)[0], index, hits, (t1 - t0) * 1e3, (t2 - t1) * 1e3)
