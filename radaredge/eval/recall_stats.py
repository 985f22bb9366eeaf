"""What a Recall@N figure is worth: the recall of chance, and a bootstrap interval over queries.

Chance: a retriever that ranks the database at random. Query q with m_q of the B database
entries within the radius is answered at rank N with probability 1 - C(B - m_q, N) / C(B, N);
chance Recall@N is that probability averaged over the queries with m_q >= 1 (the others are
skipped by :func:`radaredge.eval.places.recall_of_ranking`, so chance skips them too). Where
the database is one short street, every entry is near every query and chance alone scores high.

Interval: the percentile bootstrap over queries (resampling the evaluated queries with
replacement), which treats queries as independent; consecutive windows of one drive are not,
so the interval is on the narrow side.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..data.sequences import drive_directories, load_sequence
from ..errors import InputError

BOOTSTRAP_SAMPLES = 2000
CHANCE_RADII = (5.0, 25.0)


def neighbours_within(query_pos: np.ndarray, db_pos: np.ndarray, radius: float, block: int = 512) -> np.ndarray:
    """int64 [Q]: database positions within ``radius`` m (inclusive) of each query; positions
    [Q, 2] and [B, 2] (northing, easting) m."""
    query_pos, db_pos = np.asarray(query_pos, dtype=np.float64), np.asarray(db_pos, dtype=np.float64)
    counts = [
        (np.linalg.norm(db_pos[None] - query_pos[i : i + block, None], axis=2) <= radius).sum(1)
        for i in range(0, len(query_pos), block)
    ]
    return np.concatenate(counts or [np.zeros(0, dtype=np.int64)]).astype(np.int64)


def chance_recall(query_pos: np.ndarray, db_pos: np.ndarray, radius: float, ns: Sequence[int] = (1,)) -> dict:
    """Recall@N (percent) of a random ranking for each N of ``ns``, over the queries with a
    database position within ``radius`` m (module docstring); also the mean number of database
    positions within the radius of those queries (``database_within``)."""
    within = neighbours_within(query_pos, db_pos, radius)
    answerable = within[within > 0].astype(np.float64)
    if answerable.size == 0:
        raise InputError(f"no query has a database position within {radius:g} m; chance recall is undefined")
    total = len(db_pos)
    result = {}
    for n in ns:
        n = min(int(n), total)
        miss = np.ones_like(answerable)  # C(B - m, n) / C(B, n) as a running product
        for i in range(n):
            miss *= np.clip((total - answerable - i) / (total - i), 0.0, None)
        result[n] = 100.0 * float((1.0 - miss).mean())
    return {
        "recall": result,
        "database_within": float(answerable.mean()),
        "evaluated": int(answerable.size),
        "skipped": int((within == 0).sum()),
    }


def bootstrap_interval(
    hits: np.ndarray, samples: int = BOOTSTRAP_SAMPLES, level: float = 0.95, seed: int = 0
) -> tuple[float, float]:
    """The ``level`` percentile-bootstrap interval (percent) of the mean of ``hits`` ([Q], one per
    evaluated query: bool hits, or for a paired interval the difference of two methods' hits on
    the same queries), from ``samples`` resamples drawn with ``seed``."""
    hits = np.asarray(hits, dtype=np.float64)
    if hits.ndim != 1 or hits.size == 0:
        raise InputError(f"a bootstrap interval needs a non-empty [Q] array of hits, got shape {hits.shape}")
    rng = np.random.default_rng(seed)
    means = np.empty(samples)
    for i in range(0, samples, 256):
        rows = rng.integers(0, hits.size, (min(256, samples - i), hits.size))
        means[i : i + len(rows)] = hits[rows].mean(1)
    low, high = percentile_interval(100.0 * means, level)
    return low, high


def percentile_interval(values: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """The central ``level`` interval of bootstrap ``values`` (their percentiles)."""
    low, high = np.quantile(np.asarray(values, np.float64), [(1 - level) / 2, (1 + level) / 2])
    return float(low), float(high)


def benchmark_positions(root: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(database positions [B, 2], query positions [Q, 2]) (northing, easting) m of every scan
    under ``root``/database and ``root``/queries (the layout of ``radaredge make-benchmark``)."""
    sides = []
    for side in ("database", "queries"):
        drives = drive_directories(Path(root) / side)
        sides.append(np.concatenate([load_sequence(d).positions for d in drives]))
    return sides[0], sides[1]


def chance_of_benchmark(root: str | os.PathLike, radii: Sequence[float] = CHANCE_RADII) -> dict:
    """Chance Recall@1 of a place benchmark on disk, every scan a window, for each radius (m):
    {radius: {"recall_at_1": percent, "database_within": mean database scans within it}}."""
    db, queries = benchmark_positions(root)
    out = {}
    for radius in radii:
        c = chance_recall(queries, db, radius)
        out[f"{radius:g}"] = {
            "recall_at_1": c["recall"][1],
            "database_within": c["database_within"],
            "database_scans": len(db),
            "query_scans": len(queries),
            "skipped": c["skipped"],
        }
    return out
