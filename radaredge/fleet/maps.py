"""Place-recognition maps: a fleet's windows described by one graph, in a FAISS index that persists.

``MAP/`` holds ``run/`` (the :func:`radaredge.fleet.pipeline.run_graph` shards the map was built
from), ``index.faiss``, ``poses.npz`` (drive, frame, timestamp, northing, easting of each indexed
window, in index order) and ``map.json`` (the card, the graph's weights hash, the index kind and
parameters, the drives). A query describes its windows with the same graph (a graph of other
weights is refused) and searches the index.

Index kinds, by size or by choice:

- ``flat``: exact L2 search (FAISS ``IndexFlatL2``), the search ``radaredge eval`` makes; the
  default up to :data:`EXACT_LIMIT` windows. Rankings equal eval's, so Recall@N does too.
- ``ivfpq``: an inverted file with product-quantised codes, trained on a sample, whose shortlist
  (``k_factor`` x k) is re-ranked by exact distances (``IndexRefineFlat``): the default above
  :data:`EXACT_LIMIT`.
- ``hnsw``: a graph index over the full vectors (``IndexHNSWFlat``).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .. import atomic, runtime
from ..data.run_shards import RunChanges, read_run
from ..errors import ConfigError, InputError
from ..eval.places import RECALL_NS, recall_of_ranking
from .pipeline import ShardWorker, available_cpus, bound_threads, plan_shards, run_graph

DESCRIPTOR = "descriptor_normalized"
EXACT_LIMIT = 100_000
INDEX_KINDS = ("auto", "flat", "ivfpq", "hnsw")
MAP_JSON = "map.json"


def index_parameters(kind: str, n: int, dim: int) -> dict:
    """The index of ``kind`` (``auto``: flat up to :data:`EXACT_LIMIT` vectors, else ivfpq) for
    ``n`` vectors of ``dim``: its parameters. IVF lists ~ 4 sqrt(n); PQ with dim / 8 sub-vectors of
    8 bits; 32 lists probed; a shortlist of 64 x k re-ranked exactly (a fleet revisits each place
    many times, so a query's nearest windows are near-ties that PQ distances cannot order: 8 x k
    kept the exact first result 53 % of the time on benchmarks/fleet_scale.py's descriptors, 64 x k
    all of them). HNSW with 32 links, efSearch 128."""
    if kind not in INDEX_KINDS:
        raise ConfigError(f"index must be one of {', '.join(INDEX_KINDS)}, got {kind!r}")
    if kind == "auto":
        kind = "flat" if n <= EXACT_LIMIT else "ivfpq"
    if kind == "flat":
        return {"kind": "flat", "metric": "L2"}
    if kind == "hnsw":
        return {"kind": "hnsw", "metric": "L2", "M": 32, "ef_construction": 80, "ef_search": 128}
    nlist = max(1, min(2 ** round(math.log2(4 * math.sqrt(n))), n // 39))
    m = next(m for m in (dim // 8, dim // 4, dim // 2, dim, 1) if m >= 1 and dim % m == 0)
    return {
        "kind": "ivfpq",
        "metric": "L2",
        "nlist": nlist,
        "m": m,
        "nbits": 8,
        "nprobe": min(32, nlist),
        "k_factor": 64,
        "train_size": min(n, max(256 * 39, 40 * nlist)),
    }


def build_index(vectors: np.ndarray, params: dict, seed: int = 0):
    """A FAISS index of ``vectors`` float32 [n, d] with ``params`` (:func:`index_parameters`)."""
    # optional: faiss comes with the eval and export extras
    import faiss

    x = np.ascontiguousarray(vectors, dtype=np.float32)
    d = x.shape[1]
    if params["kind"] == "flat":
        index = faiss.IndexFlatL2(d)
    elif params["kind"] == "hnsw":
        index = faiss.IndexHNSWFlat(d, params["M"])
        index.hnsw.efConstruction = params["ef_construction"]
        index.hnsw.efSearch = params["ef_search"]
    else:
        ivf = faiss.IndexIVFPQ(faiss.IndexFlatL2(d), d, params["nlist"], params["m"], params["nbits"])
        rng = np.random.default_rng(seed)
        sample = x[np.sort(rng.choice(len(x), params["train_size"], replace=False))]
        ivf.train(sample)
        ivf.nprobe = params["nprobe"]
        index = faiss.IndexRefineFlat(ivf)
        index.k_factor = params["k_factor"]
    index.add(x)
    return index


def _search(index, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    dist, rows = index.search(np.ascontiguousarray(queries, dtype=np.float32), k)
    return dist, rows.astype(np.int64)


@dataclass
class MapReport:
    """What :func:`build_map` built."""

    map: str
    windows: int
    drives: list[str]
    index: dict
    build_seconds: float
    run: dict

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def lines(self) -> list[str]:
        return [
            f"{self.map}: {self.windows} windows of {len(self.drives)} drive(s), {self.index['kind']} index "
            f"built in {self.build_seconds:.1f} s",
            f"descriptors: {self.run['computed_windows']} computed, "
            f"{self.run['windows'] - self.run['computed_windows']} from earlier shards",
            *RunChanges(**self.run.get("changes", {})).lines(),
        ]


def build_map(
    graph: str | Path,
    drives: str | Path,
    out: str | Path,
    *,
    index: str = "auto",
    workers: int | None = None,
    threads: int = 1,
    backend: str = "onnxruntime",
    ray_address: str | None = None,
    fmt: str | None = None,
    progress: Callable | None = None,
) -> MapReport:
    """Describe every window of the drives under ``drives`` with the place-recognition graph
    ``graph`` (:func:`run_graph`, into ``out/run``: resumable, checked against the data as it is
    now, ``threads`` and ``workers`` cut down to the CPUs there with a warning) and index the
    descriptors in ``out`` (index.faiss, poses.npz and map.json replaced together)."""
    out = Path(out)
    model = runtime.load(graph, threads=1)
    if DESCRIPTOR not in model.output_names:
        raise ConfigError(
            f"{graph} ({model.card.name}) has no {DESCRIPTOR} output; a map indexes the descriptors "
            f"of a place-recognition graph (tdfanet, tdfanet-edge)"
        )
    report = run_graph(
        graph,
        drives,
        out / "run",
        workers=workers,
        threads=threads,
        backend=backend,
        ray_address=ray_address,
        fmt=fmt,
        progress=progress,
    )
    manifest, poses, outputs = read_run(out / "run")
    desc = outputs[DESCRIPTOR].reshape(len(poses["frame"]), -1)
    params = index_parameters(index, *desc.shape)
    start = time.perf_counter()
    built = build_index(desc, params)
    seconds = time.perf_counter() - start
    # optional: faiss comes with the eval and export extras
    import faiss

    drive_names = list(dict.fromkeys(poses["drive"].tolist()))
    # the index, its poses and map.json are moved into place together: a map never pairs one
    # build's index with another's poses
    with atomic.Staging(out) as staging:
        faiss.write_index(built, str(staging.path(out / "index.faiss")))
        np.savez(
            staging.path(out / "poses.npz"), **{k: (v.astype(str) if k == "drive" else v) for k, v in poses.items()}
        )
        staging.path(out / MAP_JSON).write_text(
            atomic.dumps(
                {
                    "model": model.card.name,
                    "card": model.card.to_yaml(),
                    "graph": str(Path(graph).resolve()),
                    "weights_sha256": model.weights_sha256,
                    "descriptor": DESCRIPTOR,
                    "windows": int(len(desc)),
                    "dim": int(desc.shape[1]),
                    "index": params,
                    "drives": drive_names,
                    "data": manifest["data"],
                    "window_frames": manifest["window_frames"],
                }
            ),
            encoding="utf-8",
        )
        staging.commit()
    return MapReport(str(out), int(len(desc)), drive_names, params, seconds, report.to_dict())


def load_map(map_dir: str | Path) -> tuple[dict, object, dict[str, np.ndarray]]:
    """(map.json, the FAISS index, the poses) of a built map; InputError naming what is missing."""
    map_dir = Path(map_dir)
    try:
        info = json.loads((map_dir / MAP_JSON).read_text())
    except (OSError, ValueError):
        raise InputError(
            f"{map_dir}: no readable {MAP_JSON}; expected a directory made by `radaredge map build`"
        ) from None
    import faiss

    try:
        index = faiss.read_index(str(map_dir / "index.faiss"))
        with np.load(map_dir / "poses.npz") as z:
            poses = {k: z[k] for k in z.files}
    except (OSError, RuntimeError, ValueError) as exc:
        raise InputError(
            f"{map_dir}: its index or poses cannot be read ({str(exc).splitlines()[0][:160]}); build the map again"
        ) from None
    if index.ntotal != info.get("windows") or len(poses.get("frame", ())) != index.ntotal:
        raise InputError(
            f"{map_dir}: index.faiss holds {index.ntotal} vectors, map.json {info.get('windows')} "
            f"windows and poses.npz {len(poses.get('frame', ()))}; build the map again"
        )
    return info, index, poses


@dataclass
class QueryReport:
    """What :func:`query_map` found: per query window its top-k map windows, and Recall@N."""

    map: str
    drive: str
    queries: list[dict]
    recall: dict | None
    radius: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def lines(self) -> list[str]:
        out = [f"{self.drive}: {len(self.queries)} query windows against {self.map}"]
        if self.recall is not None:
            r = self.recall
            out.append(
                f"Recall@N within {self.radius:g} m ({r['evaluated']} queries, {r['skipped']} without a map "
                f"window that close): " + ", ".join(f"@{n} {v:.1f} %" for n, v in r["recall"].items())
            )
        for q in self.queries[:5]:
            top = q["top"][0]
            out.append(
                f"  frame {q['frame']}: top-1 {top['drive']} frame {top['frame']} "
                f"({top['northing']:.1f}, {top['easting']:.1f}) m, descriptor distance {top['distance']:.4f}"
            )
        if len(self.queries) > 5:
            out.append(f"  ... {len(self.queries) - 5} more in --json")
        return out


def query_map(
    map_dir: str | Path,
    drive: str | Path,
    *,
    onnx: str | Path | None = None,
    top_k: int = 10,
    radius: float = 5.0,
    ns: Sequence[int] = RECALL_NS,
    threads: int = 2,
    backend: str = "onnxruntime",
) -> QueryReport:
    """Localise every window of the drive ``drive`` against the map: its descriptors by the map's
    graph (``onnx``, default the one recorded; its weights must be the map's), the top ``top_k``
    map windows with their poses and, from the drive's positions, Recall@N within ``radius`` m."""
    threads = bound_threads(threads, available_cpus())
    info, index, poses = load_map(map_dir)
    graph = Path(onnx) if onnx is not None else Path(info["graph"])
    worker = ShardWorker(str(graph), threads, backend)
    if worker.model.weights_sha256 != info["weights_sha256"]:
        raise ConfigError(
            f"{graph} has weights {worker.model.weights_sha256[:12]}, but {map_dir} was built with "
            f"{info['weights_sha256'][:12]}; query with the map's graph or build the map again"
        )
    if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
        raise ConfigError(f"top_k must be a positive integer, got {top_k!r}")
    rows, outs = [], []
    for plan in plan_shards(drive, worker.model.frames, 1 << 30):
        r, o = worker.outputs(plan)
        rows += r
        outs += o
    desc = np.stack([o[DESCRIPTOR].reshape(-1) for o in outs])
    k = min(max(top_k, max(ns)), index.ntotal)
    dist, ranked = _search(index, desc, k)
    db_pos = np.stack([poses["northing"], poses["easting"]], 1)
    query_pos = np.array([[r["northing"], r["easting"]] for r in rows])
    recall = recall_of_ranking(ranked, query_pos, db_pos, ns, radius)
    queries = [
        {
            **r,
            "top": [
                {
                    "drive": str(poses["drive"][j]),
                    "frame": int(poses["frame"][j]),
                    "timestamp": float(poses["timestamp"][j]),
                    "northing": float(poses["northing"][j]),
                    "easting": float(poses["easting"][j]),
                    "distance": float(d),
                }
                for j, d in zip(ranked[i, :top_k], dist[i, :top_k])
            ],
        }
        for i, r in enumerate(rows)
    ]
    summary = {"recall": recall["recall"], "evaluated": recall["evaluated"], "skipped": recall["skipped"]}
    return QueryReport(str(map_dir), str(drive), queries, summary, float(radius))
