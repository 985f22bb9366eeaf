"""Place-recognition evaluation: Recall@N as TDFANet reports it, and the ``radaredge eval`` pipeline.

Protocol (TDFANet sec. IV-C, which follows TransLoc4D's): every query descriptor retrieves its
nearest database descriptors by exact Euclidean (L2) distance. A retrieved database entry is a
true positive when its ground-truth position lies within ``radius`` of the query's, the boundary
included. The radius is ours to choose: TransLoc4D's evaluation sets count a database scan
within 25 m as correct (phatli/TransLoc4D, scripts/generate_testsets.py, ``valDist=25``);
TDFANet's paper states 5 m only for its training positives (sec. IV-B). radaredge defaults to
the stricter 5 m; ``--radius 25`` gives TransLoc4D's. Recall@N is the percentage of queries with
at least one true positive among their top N. Queries without any database entry within the
radius cannot be answered correctly and are skipped: they count neither as hits nor in the
denominator, and the number skipped is reported. Positions are planar (northing, easting) in
metres.

Ties in descriptor distance rank the lower database index first: the numpy search sorts its
float64 distances stably, FAISS's flat index keeps the lower id among equal float32 distances.
From 20 queries on FAISS computes distances as |q|^2 + |d|^2 - 2 q.d, so near-ties (not
duplicates) may order differently from numpy.

``radaredge eval`` runs a K-frame place-recognition model over drives on disk (layout in
:mod:`radaredge.data.sequences`): one K-frame window per frame t >= K-1, placed at its last
frame, described once by the exported ``.onnx`` in onnxruntime and once by the torch reference
formulation, then scored with :func:`recall_at_n` for each and compared by
:func:`top1_agreement` (the same database window) and :func:`top1_place_agreement` (database
windows within the radius of each other).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from .. import atomic, runtime
from ..cards import ModelCard
from ..data.run_shards import read_run
from ..data.sequences import RadarSequence, drive_directories, load_sequence, name_the_scan, window_positions, windows
from ..errors import ConfigError, InputError
from ..exporting.graphs import DEBUG_PREFIX, require_same_weights
from ..models.factory import create_model
from ..registry import model_spec
from .baselines import polar_occupancy
from .recall_stats import bootstrap_interval

RECALL_NS = (1, 5, 10)
CURVE_NS = tuple(range(1, 26))
ONNX, REFERENCE, BASELINE = "onnxruntime", "torch_reference", "polar_occupancy"
BACKEND_LABELS = {ONNX: "onnxruntime", REFERENCE: "torch reference", BASELINE: "no learning"}

# ----------------------------------------------------------------------------- Recall@N


def _descriptor_set(desc, pos, what: str) -> tuple[np.ndarray, np.ndarray]:
    """``desc`` as float32 [M, D] and ``pos`` as float64 [M, 2], both finite; else InputError."""
    desc = np.asarray(desc, dtype=np.float32)
    pos = np.asarray(pos, dtype=np.float64)
    if desc.ndim != 2 or pos.shape != (len(desc), 2):
        raise InputError(
            f"{what}: expected descriptors [M, D] and positions [M, 2] (northing, easting m), "
            f"got {desc.shape} and {pos.shape}"
        )
    if not (np.isfinite(desc).all() and np.isfinite(pos).all()):
        raise InputError(f"{what}: descriptors and positions must be finite")
    return desc, pos


def _check_ns(ns: Sequence[int]) -> tuple[int, ...]:
    ns = tuple(ns)
    if not ns or any(isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1 for n in ns):
        raise ConfigError(f"ns must be positive integers (candidates per query), got {ns!r}")
    return tuple(int(n) for n in ns)


def nearest_neighbours(
    query_desc: np.ndarray, db_desc: np.ndarray, k: int, index=None, use_faiss: bool = True
) -> np.ndarray:
    """int64 [Q, k]: the database rows of the ``k`` nearest descriptors (exact L2) of each query,
    nearest first, lower database row first among equal distances.

    ``use_faiss`` searches a FAISS ``IndexFlatL2`` (``index``, or one built from ``db_desc``);
    otherwise numpy computes every distance in float64 and sorts stably.
    """
    if use_faiss:
        # optional: faiss comes with the eval and export extras
        import faiss

        if index is None:
            index = faiss.IndexFlatL2(db_desc.shape[1])
            index.add(np.ascontiguousarray(db_desc, dtype=np.float32))
        elif index.ntotal != len(db_desc) or index.d != db_desc.shape[1]:
            raise ConfigError(
                f"index holds {index.ntotal} vectors of dimension {index.d}; the database has "
                f"{len(db_desc)} of dimension {db_desc.shape[1]}"
            )
        return index.search(np.ascontiguousarray(query_desc, dtype=np.float32), k)[1].astype(np.int64)
    if index is not None:
        raise ConfigError("index is a FAISS index; pass use_faiss=True to search it")
    db = db_desc.astype(np.float64)
    return np.array(
        [np.argsort(np.square(db - q).sum(1), kind="stable")[:k] for q in query_desc.astype(np.float64)], dtype=np.int64
    ).reshape(len(query_desc), k)


def _check_radius(radius: float) -> float:
    if (
        isinstance(radius, bool)
        or not isinstance(radius, (int, float, np.integer, np.floating))
        or not np.isfinite(radius)
        or radius <= 0
    ):
        raise ConfigError(f"radius must be a positive distance in metres, got {radius!r}")
    return float(radius)


def answerable(query_pos: np.ndarray, db_pos: np.ndarray, radius: float) -> np.ndarray:
    """bool [Q]: the query has a database position within ``radius`` m (inclusive); positions
    [Q, 2] and [B, 2] (northing, easting) m. InputError when no query has one."""
    nearest = np.array([np.linalg.norm(db_pos - q, axis=1).min() for q in query_pos])
    mask = nearest <= radius
    if not mask.any():
        raise InputError(
            f"none of the {len(query_pos)} queries has a database entry within {radius:g} m, so "
            f"nothing can be evaluated; are both position sets (northing, easting) in one frame, in m?"
        )
    return mask


def recall_at_n(
    query_desc,
    query_pos,
    db_desc,
    db_pos,
    ns: Sequence[int] = RECALL_NS,
    radius: float = 5.0,
    index=None,
    use_faiss: bool = True,
) -> dict:
    """Recall@N of queries against a database (protocol in the module docstring).

    ``query_desc`` [Q, D] and ``db_desc`` [B, D] are descriptors, ``query_pos`` [Q, 2] and
    ``db_pos`` [B, 2] ground-truth positions (northing, easting) in metres, ``radius`` the
    true-positive distance in metres (inclusive). The top max(``ns``) database entries are
    retrieved per query (at most B; Recall@N for N > B equals Recall@B) by
    :func:`nearest_neighbours` with ``index`` / ``use_faiss``.

    Returns a dict: ``recall`` {N: percent of the evaluated queries}, ``evaluated`` and
    ``skipped`` (queries without a database entry within ``radius``), ``radius``, ``hits`` bool
    [evaluated, k] (a true positive within the top n + 1), and per query
    ``evaluated_mask`` bool [Q], ``ranked`` int64 [Q, k] (database rows, nearest first),
    ``top1`` int64 [Q], ``top1_distance`` float64 [Q] (m, ground truth between the query and its
    top-1) and ``top1_correct`` bool [Q] (``top1_distance`` <= ``radius``).
    Raises InputError when no query has a database entry within ``radius``.
    """
    query_desc, query_pos = _descriptor_set(query_desc, query_pos, "queries")
    db_desc, db_pos = _descriptor_set(db_desc, db_pos, "database")
    ns = _check_ns(ns)
    radius = _check_radius(radius)
    if len(query_desc) == 0 or len(db_desc) == 0 or query_desc.shape[1] != db_desc.shape[1]:
        raise InputError(
            f"need at least one query and one database descriptor of the same dimension, got "
            f"queries {query_desc.shape} and database {db_desc.shape}"
        )
    ranked = nearest_neighbours(query_desc, db_desc, min(max(ns), len(db_desc)), index, use_faiss)
    return recall_of_ranking(ranked, query_pos, db_pos, ns, radius)


def recall_of_ranking(
    ranked: np.ndarray, query_pos, db_pos, ns: Sequence[int] = RECALL_NS, radius: float = 5.0
) -> dict:
    """:func:`recall_at_n`'s result from a ranking already made: ``ranked`` int64 [Q, k], the
    database rows of each query's nearest descriptors, nearest first (e.g. a place map's index
    search); positions as in :func:`recall_at_n`."""
    query_pos = np.asarray(query_pos, dtype=np.float64)
    db_pos = np.asarray(db_pos, dtype=np.float64)
    ns, radius = _check_ns(ns), _check_radius(radius)
    evaluated = answerable(query_pos, db_pos, radius)
    distance = np.linalg.norm(db_pos[ranked] - query_pos[:, None, :], axis=2)  # [Q, k] m
    found = np.logical_or.accumulate(distance <= radius, axis=1)[evaluated]  # hit within the top n
    recall = {n: 100.0 * float(found[:, min(n, ranked.shape[1]) - 1].mean()) for n in ns}
    return {
        "recall": recall,
        "evaluated": int(evaluated.sum()),
        "skipped": int((~evaluated).sum()),
        "radius": radius,
        "hits": found,
        "evaluated_mask": evaluated,
        "ranked": ranked,
        "top1": ranked[:, 0],
        "top1_distance": distance[:, 0],
        "top1_correct": distance[:, 0] <= radius,
    }


def top1_agreement(a_top1, b_top1) -> float:
    """Fraction in [0, 1] of queries whose top-1 database entry is the same in ``a_top1`` and
    ``b_top1`` (database rows, [Q] each)."""
    a, b = np.asarray(a_top1), np.asarray(b_top1)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise InputError(
            f"top-1 agreement needs two non-empty [Q] index arrays of one shape, got {a.shape} and {b.shape}"
        )
    return float((a == b).mean())


def top1_place_agreement(a_top1, b_top1, db_pos: np.ndarray, radius: float) -> float:
    """Fraction in [0, 1] of queries whose two top-1 database entries (rows into ``db_pos``
    [B, 2], (northing, easting) m) lie within ``radius`` m of each other, the boundary included:
    the two backends retrieve the same place, if not the same window. Where database windows lie
    closer together than the radius, this is the agreement a place recogniser can promise."""
    top1_agreement(a_top1, b_top1)
    a, b = np.asarray(a_top1), np.asarray(b_top1)
    db_pos = np.asarray(db_pos, dtype=np.float64)
    if db_pos.ndim != 2 or db_pos.shape[1] != 2 or min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= len(db_pos):
        raise InputError(
            f"top-1 rows must index the {len(db_pos)} database positions [B, 2] (northing, easting), "
            f"got rows {min(a.min(), b.min())}..{max(a.max(), b.max())} into shape {db_pos.shape}"
        )
    return float((np.linalg.norm(db_pos[a] - db_pos[b], axis=1) <= _check_radius(radius)).mean())


# ----------------------------------------------------------------------------- drives and windows


@dataclass
class WindowSet:
    """The K-frame windows of every drive under one directory (the database or the queries).

    ``items`` holds per window (row into ``sequences``, frame indices oldest first);
    ``positions`` [W, 2] (northing, easting) m is the position of each window's last frame.
    """

    path: Path
    k: int
    sequences: list[RadarSequence]
    items: list[tuple[int, np.ndarray]]
    positions: np.ndarray

    def __len__(self) -> int:
        return len(self.items)

    def inputs(self, i: int, features: Sequence[str]) -> tuple[list[np.ndarray], np.ndarray]:
        """Window ``i``: its K scans (float32 [N_k, F], columns ``features``, oldest first) and
        their timestamps (s, relative to the oldest frame, so float32 keeps their differences)."""
        drive, frames = self.items[i]
        seq = self.sequences[drive]
        t = seq.timestamps[frames]
        return [seq.scan(f, features) for f in frames], t - t[0]

    def locate_error(self, i: int, message: str) -> str:
        """``message`` about window ``i`` naming its scan's file (:func:`name_the_scan`)."""
        row, frames = self.items[i]
        return name_the_scan(self.sequences[row], frames, message)

    def drive_windows(self) -> dict[str, int]:
        """Windows per drive, by drive name."""
        return {s.name: len(s) - self.k + 1 for s in self.sequences}

    def drive_rows(self) -> list[np.ndarray]:
        """The window rows of each drive, in drive order (for the trajectory plot)."""
        return [
            np.array([i for i, (drive, _) in enumerate(self.items) if drive == d], dtype=np.int64)
            for d in range(len(self.sequences))
        ]

    def window_info(self, i: int) -> dict:
        """Drive name, last frame, timestamp (s) and position (northing, easting m) of window ``i``."""
        drive, frames = self.items[i]
        seq = self.sequences[drive]
        last = int(frames[-1])
        return {
            "drive": seq.name,
            "frame": last,
            "timestamp": float(seq.timestamps[last]),
            "northing": float(seq.positions[last, 0]),
            "easting": float(seq.positions[last, 1]),
        }


def load_windows(path: str | os.PathLike, k: int) -> WindowSet:
    """Every K-frame window of the drive(s) under ``path`` (see :func:`drive_directories`).
    InputError when a drive has fewer than ``k`` scans."""
    sequences = [load_sequence(d) for d in drive_directories(path)]
    short = [f"{s.name} ({len(s)})" for s in sequences if len(s) < k]
    if short:
        raise InputError(f"{path}: drive(s) {', '.join(short)} hold fewer scans than the K = {k} frames of one window")
    items = [(d, idx) for d, seq in enumerate(sequences) for idx in windows(seq, k)]
    positions = np.concatenate([window_positions(seq, k) for seq in sequences])
    return WindowSet(Path(path), k, sequences, items, positions)


@dataclass
class MapWindows:
    """The windows of a place map (``radaredge map build``) as eval's database: their descriptors
    (the map's graph, onnxruntime) and poses, in map order; ``drives`` [W] names each window's drive."""

    path: Path
    k: int
    positions: np.ndarray
    descriptors: np.ndarray
    drives: np.ndarray
    frames: np.ndarray
    timestamps: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)

    def drive_windows(self) -> dict[str, int]:
        names, counts = np.unique(self.drives, return_counts=True)
        return {str(n): int(c) for n, c in zip(names, counts)}

    def drive_rows(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.drives == n) for n in dict.fromkeys(self.drives.tolist())]

    def window_info(self, i: int) -> dict:
        return {
            "drive": str(self.drives[i]),
            "frame": int(self.frames[i]),
            "timestamp": float(self.timestamps[i]),
            "northing": float(self.positions[i, 0]),
            "easting": float(self.positions[i, 1]),
        }


def load_map_windows(map_dir: str | os.PathLike, exported) -> MapWindows:
    """The database of the place map at ``map_dir`` for the exported graph ``exported`` (a
    :class:`radaredge.runtime.RadarModel`): ConfigError unless the map was built with the same
    weights; InputError when it is not a readable map."""
    map_dir = Path(map_dir)
    try:
        info = json.loads((map_dir / "map.json").read_text())
    except (OSError, ValueError):
        raise InputError(
            f"{map_dir}: no readable map.json; --map for place recognition takes a directory made by "
            f"`radaredge map build`"
        ) from None
    if info.get("weights_sha256") != exported.weights_sha256:
        raise ConfigError(
            f"{map_dir} was built with graph weights {str(info.get('weights_sha256'))[:12]}, "
            f"{exported.path} has {exported.weights_sha256[:12]}; evaluate with the map's graph or "
            f"build the map again"
        )
    _, poses, outputs = read_run(map_dir / "run")
    desc = np.asarray(outputs["descriptor_normalized"], dtype=np.float32).reshape(len(poses["frame"]), -1)
    return MapWindows(
        map_dir,
        exported.frames,
        np.stack([poses["northing"], poses["easting"]], 1),
        desc,
        np.asarray(poses["drive"]).astype(str),
        poses["frame"],
        poses["timestamp"],
    )


Backend = Callable[[list, np.ndarray], np.ndarray]


def describe_windows(window_set: WindowSet, features: Sequence[str], backend: Backend, progress=None) -> np.ndarray:
    """Descriptors float32 [W, D] of every window by ``backend``, a function of (frames,
    timestamps) returning a descriptor; ``progress`` optionally wraps the window loop."""
    descs = []
    for i in (progress or iter)(range(len(window_set))):
        try:
            descs.append(np.asarray(backend(*window_set.inputs(i, features)), dtype=np.float32))
        except InputError as exc:
            raise InputError(window_set.locate_error(i, str(exc))) from None
    return np.stack(descs)


# ----------------------------------------------------------------------------- the eval pipeline


def onnx_backend(exported) -> Backend:
    """``descriptor_normalized`` of a :class:`radaredge.runtime.RadarModel` (onnxruntime)."""
    return lambda frames, timestamps: exported.run(frames, timestamps)["descriptor_normalized"]


def reference_backend(net) -> Backend:
    """``descriptor_normalized`` of the torch reference formulation, ``net.run(..., reference=True)``."""

    def describe(frames, timestamps):
        with torch.no_grad():
            out = net.run(
                [torch.from_numpy(f) for f in frames], torch.as_tensor(timestamps, dtype=torch.float32), reference=True
            )
        return out["descriptor_normalized"].numpy()

    return describe


def baseline_backend(features: Sequence[str]) -> Backend:
    """The no-learning :func:`radaredge.eval.baselines.polar_occupancy` descriptor of a window
    whose scans have the columns ``features``."""
    x, y = features.index("x"), features.index("y")
    return lambda frames, timestamps: polar_occupancy(frames, x, y)


def check_export(card: ModelCard, exported) -> None:
    """ConfigError unless the exported graph (a :class:`radaredge.runtime.RadarModel`, loaded
    with its contents and card checked) was made from ``card``: the same name, frame count and
    feature columns; InputError naming the file when the card embedded in the graph implies other
    point-frame inputs or outputs than the graph has (the model family's signature of that card,
    which the torch-free runtime cannot derive: a card edited after export, or a graph it does
    not belong to)."""
    if exported.card.name != card.name:
        raise ConfigError(
            f"{exported.path} is an export of card {exported.card.name!r}, not {card.name!r}; "
            f"pass the --model/--config it was exported with"
        )
    graph = model_spec(exported.card).graph(exported.info.part)
    frames, outputs = graph.frame_inputs(exported.card), graph.output_names(exported.card)
    have = exported.output_names  # a debug copy adds debug.<intermediate> outputs, renaming an output it traces
    if (
        exported.info.frame_inputs != frames
        or any(o not in have and DEBUG_PREFIX + o not in have for o in outputs)
        or any(not o.startswith(DEBUG_PREFIX) and o not in outputs for o in have)
    ):
        raise InputError(
            f"{exported.path}: its embedded card disagrees with the graph: the card's {graph.name} graph "
            f"takes point frames {frames} and gives {outputs}, this graph takes "
            f"{exported.info.frame_inputs} and gives {exported.output_names}; re-export it"
        )
    want = len(model_spec(card).graph(exported.info.part).frame_inputs(card))
    if exported.frames != want or exported.features != card.features:
        raise ConfigError(
            f"{exported.path} takes {exported.frames} frame(s) of {exported.features}, but card "
            f"{card.name!r} declares {want} of {card.features}; re-export it"
        )


@dataclass
class EvalReport:
    """Result of :func:`evaluate`: per backend the :func:`recall_at_n` result over ``CURVE_NS``."""

    model: str
    onnx: str
    checkpoint: str | None
    radius: float
    database: WindowSet
    queries: WindowSet
    results: dict[str, dict]
    agreement: float | None
    place_agreement: float | None

    def recall(self, backend: str, ns: Sequence[int] = RECALL_NS) -> dict[int, float]:
        """Recall@N in percent of ``backend`` for each N of ``ns`` (within ``CURVE_NS``)."""
        return {n: self.results[backend]["recall"][n] for n in ns}

    def interval(self, backend: str, ns: Sequence[int] = RECALL_NS) -> dict[int, tuple[float, float]]:
        """95 % bootstrap interval over queries (percent) of ``backend``'s Recall@N for each N of
        ``ns`` (:func:`radaredge.eval.recall_stats.bootstrap_interval`)."""
        hits = self.results[backend]["hits"]
        return {n: bootstrap_interval(hits[:, min(n, hits.shape[1]) - 1]) for n in ns}

    @property
    def evaluated(self) -> int:
        return next(iter(self.results.values()))["evaluated"]

    @property
    def skipped(self) -> int:
        return next(iter(self.results.values()))["skipped"]

    def _query(self, i: int) -> dict:
        entry = {**self.queries.window_info(i), "evaluated": bool(self.results[ONNX]["evaluated_mask"][i])}
        for name, res in self.results.items():
            top = int(res["top1"][i])
            match = self.database.window_info(top)
            entry[name] = {
                "top1": top,
                "top1_drive": match["drive"],
                "top1_frame": match["frame"],
                "top1_distance_m": float(res["top1_distance"][i]),
                "correct": bool(res["top1_correct"][i]),
            }
        return entry

    def to_dict(self) -> dict:
        """The JSON report: setup, counts, Recall@1/5/10 and the Recall@N curve (N = 1..25) per
        backend, top-1 agreement by window and by place, and per query its window, position and top-1 match."""

        def side(ws) -> dict:
            return {"path": str(ws.path), "windows": len(ws), "drives": ws.drive_windows()}

        return {
            "model": self.model,
            "onnx": self.onnx,
            "checkpoint": self.checkpoint,
            "radius_m": self.radius,
            "frames_per_window": self.database.k,
            "database": side(self.database),
            "queries": side(self.queries),
            "evaluated": self.evaluated,
            "skipped": self.skipped,
            "recall": {name: {str(n): r for n, r in self.recall(name).items()} for name in self.results},
            "recall_interval_95": {
                name: {str(n): list(ci) for n, ci in self.interval(name).items()} for name in self.results
            },
            "recall_curve": {name: [self.results[name]["recall"][n] for n in CURVE_NS] for name in self.results},
            "top1_agreement": self.agreement,
            "top1_place_agreement": self.place_agreement,
            "per_query": [self._query(i) for i in range(len(self.queries))],
        }

    def lines(self) -> list[str]:
        """The text report: setup, counts, Recall@1/5/10 per backend and top-1 agreement."""
        lines = []
        q, db = self.queries, self.database
        source = f"the map {db.path}" if isinstance(db, MapWindows) else "database"
        lines.append(
            f"eval {self.model}: {len(q)} query windows from {len(q.drive_windows())} drive(s) vs {len(db)} "
            f"{source} windows from {len(db.drive_windows())} drive(s), K = {db.k}, true positive within "
            f"{self.radius:g} m"
        )
        lines.append(
            f"{self.evaluated} queries evaluated, {self.skipped} skipped (no database window within {self.radius:g} m)"
        )
        lines.append(f"{'backend':<18}" + "".join(f"{f'R@{n} [95 % interval]':>24}" for n in RECALL_NS))
        for name in self.results:
            cells = (
                f"{r:.2f} [{lo:.1f}, {hi:.1f}]"
                for r, (lo, hi) in zip(self.recall(name).values(), self.interval(name).values())
            )
            lines.append(f"{BACKEND_LABELS[name]:<18}" + "".join(f"{c:>24}" for c in cells))
        if self.agreement is not None:
            lines.append(
                f"top-1 agreement {BACKEND_LABELS[ONNX]} vs {BACKEND_LABELS[REFERENCE]}: "
                f"{self.agreement * 100:.1f} % of {len(q)} queries the same window, "
                f"{self.place_agreement * 100:.1f} % within {self.radius:g} m of each other"
            )
        return lines

    def write_json(self, path: str | os.PathLike) -> Path:
        return atomic.write_json(path, self.to_dict())

    def plot(self, path: str | os.PathLike) -> Path:
        """PNG: left, the query windows at their (easting, northing) coloured by whether the ONNX
        top-1 is correct, over the database trajectory in grey; right, Recall@N for N = 1..25."""
        # optional: matplotlib (eval extra) draws the plot only when one is asked for
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=(12, 5), layout="constrained")
        FigureCanvasAgg(fig)
        left, right = fig.subplots(1, 2)
        for d, rows in enumerate(self.database.drive_rows()):
            track = self.database.positions[rows]
            left.plot(
                track[:, 1],
                track[:, 0],
                color="0.75",
                lw=5,
                solid_capstyle="round",
                zorder=1,
                label="database" if d == 0 else None,
            )
        res, pos = self.results[ONNX], self.queries.positions
        for mask, colour, label in (
            (res["evaluated_mask"] & res["top1_correct"], "tab:green", "top-1 correct"),
            (res["evaluated_mask"] & ~res["top1_correct"], "tab:red", "top-1 wrong"),
            (~res["evaluated_mask"], "0.4", "skipped (no positive)"),
        ):
            if mask.any():
                left.scatter(pos[mask, 1], pos[mask, 0], s=14, color=colour, label=label, zorder=2)
        left.set(
            xlabel="easting (m)",
            ylabel="northing (m)",
            aspect="equal",
            title=f"queries ({BACKEND_LABELS[ONNX]}), true positive within {self.radius:g} m",
        )
        left.legend(loc="best", fontsize="small")
        for name, style in ((ONNX, "-"), (REFERENCE, "--")):
            if name in self.results:
                right.plot(
                    CURVE_NS,
                    [self.results[name]["recall"][n] for n in CURVE_NS],
                    style,
                    marker=".",
                    label=BACKEND_LABELS[name],
                )
        right.set(
            xlabel="N (retrieved database windows)",
            ylabel="Recall@N (%)",
            ylim=(0, 101),
            xlim=(1, CURVE_NS[-1]),
            title=f"{self.model}: {self.evaluated} queries",
        )
        right.grid(alpha=0.3)
        right.legend(loc="lower right")
        with atomic.atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=100, format="png")
        return Path(path)


def evaluate(
    card: ModelCard,
    onnx_path: str | os.PathLike,
    database: str | os.PathLike | None,
    queries: str | os.PathLike,
    checkpoint: str | os.PathLike | None = None,
    radius: float = 5.0,
    reference: bool = True,
    progress: Callable[[str], Callable] | None = None,
    map_dir: str | os.PathLike | None = None,
    baseline: bool = True,
) -> EvalReport:
    """Recall@N of the exported ``onnx_path`` (onnxruntime), with ``reference`` of the card's
    torch reference formulation (``checkpoint`` or the seeded initialisation), and of the
    no-learning :func:`radaredge.eval.baselines.polar_occupancy` descriptor of the same points,
    over the K-frame windows of the ``queries`` drive(s) against those of the ``database``
    drive(s), each searched in an exact-L2 FAISS index; plus the top-1 agreement of the graph
    and the reference, by window and by place
    (top-1 windows within ``radius`` m of each other). ``progress(desc)`` returns
    a wrapper for the window loops (a progress bar). ``baseline=False`` leaves the no-learning
    descriptor out (a caller that scores many graphs of one model on the same windows needs it
    once).

    ``map_dir`` instead of ``database``: the windows of a place map (``radaredge map build``) with
    the descriptors it holds, searched exactly; the map's graph must be ``onnx_path``'s weights,
    and neither the torch reference nor the baseline is run (the map holds the graph's
    descriptors only)."""

    radius = _check_radius(radius)
    exported = runtime.load(onnx_path)
    check_export(card, exported)
    k = exported.frames
    if (database is None) == (map_dir is None):
        raise ConfigError("place recognition takes the database as --database drives or as a --map, one of the two")
    if map_dir is not None:
        if reference:
            raise ConfigError(
                f"--map {map_dir} holds the graph's descriptors only, so the torch reference cannot be "
                f"compared on it; add --no-reference, or pass the drives as --database"
            )
        db_windows = load_map_windows(map_dir, exported)
    else:
        db_windows = load_windows(database, k)
    query_windows = load_windows(queries, k)
    answerable(query_windows.positions, db_windows.positions, radius)
    backends = {ONNX: onnx_backend(exported)}
    if reference:
        net = create_model(card, checkpoint)
        require_same_weights(exported, net, checkpoint)
        backends[REFERENCE] = reference_backend(net)
    if map_dir is None and baseline:
        backends[BASELINE] = baseline_backend(exported.features)
    wrap = progress or (lambda desc: iter)
    results = {}
    # One backend after the other: onnxruntime's worker threads spin after each run, which slows
    # torch down when the two alternate on a 2-core machine.
    for name, backend in backends.items():
        db_desc = (
            db_windows.descriptors
            if isinstance(db_windows, MapWindows)
            else describe_windows(db_windows, exported.features, backend, wrap(f"database {BACKEND_LABELS[name]}"))
        )
        query_desc = describe_windows(
            query_windows, exported.features, backend, wrap(f"queries {BACKEND_LABELS[name]}")
        )
        results[name] = recall_at_n(
            query_desc, query_windows.positions, db_desc, db_windows.positions, CURVE_NS, radius
        )
    agreement = place = None
    if reference:
        agreement = top1_agreement(results[ONNX]["top1"], results[REFERENCE]["top1"])
        place = top1_place_agreement(results[ONNX]["top1"], results[REFERENCE]["top1"], db_windows.positions, radius)
    return EvalReport(
        card.name,
        str(onnx_path),
        str(checkpoint) if checkpoint else None,
        radius,
        db_windows,
        query_windows,
        results,
        agreement,
        place,
    )


# ----------------------------------------------------------------------------- text-to-point-cloud localisation

LOCALIZATION_KS = (1, 5, 10)
LOCALIZATION_THRESHOLDS = (5.0, 10.0, 15.0)


def localization_levels(ks: Sequence[int], thresholds: Sequence[float]) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """``ks`` as positive ints and ``thresholds`` as positive finite distances (m); else ConfigError."""
    ks = _check_ns(ks)
    if not thresholds or any(not np.isfinite(t) or t <= 0 for t in thresholds):
        raise ConfigError(f"thresholds must be positive distances in metres, got {thresholds!r}")
    return ks, tuple(float(t) for t in thresholds)


def localization_recall(
    pred_w,
    pose_w,
    ks: Sequence[int] = LOCALIZATION_KS,
    thresholds: Sequence[float] = LOCALIZATION_THRESHOLDS,
    same_scene=None,
) -> dict:
    """Top-k localisation recall as Text2Loc / Des4Pos report it (``calc_sample_accuracies``);
    :func:`radaredge.eval.localisation.evaluate_localization` computes it for an exported bundle.

    ``pred_w`` [Q, K, 2]: the position predicted in each of a query's K retrieved cells, best
    first (world x, y m); ``pose_w`` [Q, 2]: the ground-truth pose. A query counts at (k, t) when
    one of its first k predictions lies within t m of the pose (planar Euclidean, boundary
    included). Predictions in cells of another scene than the query's (``same_scene`` [Q, K]
    False) never count, however close. Returns {k: {t: fraction of queries in [0, 1]}}; a k larger
    than K is an InputError (it would silently be recall at K).
    """
    pred = np.asarray(pred_w, np.float64)
    pose = np.asarray(pose_w, np.float64)
    if pred.ndim != 3 or pred.shape[2] != 2 or pose.shape != (pred.shape[0], 2) or pred.shape[0] == 0:
        raise InputError(
            f"expected predictions [Q, K, 2] and poses [Q, 2] (m) with Q >= 1, got {pred.shape} and {pose.shape}"
        )
    if not (np.isfinite(pred).all() and np.isfinite(pose).all()):
        raise InputError("predicted and ground-truth positions must be finite")
    ks, thresholds = localization_levels(ks, thresholds)
    dist = np.linalg.norm(pred - pose[:, None, :], axis=2)  # [Q, K]
    if same_scene is not None:
        same = np.asarray(same_scene, bool)
        if same.shape != dist.shape:
            raise InputError(f"same_scene must be [Q, K] = {dist.shape}, got {same.shape}")
        dist = np.where(same, dist, np.inf)
    if max(ks) > pred.shape[1]:
        raise InputError(f"top-{max(ks)} recall needs {max(ks)} predictions per query; {pred.shape[1]} were given")
    best = np.minimum.accumulate(dist, axis=1)  # min over the first k
    return {k: {t: float((best[:, k - 1] <= t).mean()) for t in thresholds} for k in ks}
