"""Fleet scale on this machine: `radaredge run`'s throughput with 1 and 2 Ray workers against a plain
loop over the same windows, and a place map's large index at 10^6 descriptors.

    python benchmarks/fleet_scale.py [--vectors 1000000] [--frames 250]

Writes benchmarks/results/fleet-scale-<date>.json (then `python benchmarks/render.py`).

1. Throughput: the seeded `tdfanet-edge` graph over 4 synthetic drives (`make_pr_benchmark`),
   windows per second of the plain loop (:func:`run_sequential`, one session, 1 thread), of Ray
   Data with 1 worker and with 2 workers (1 thread each), each into a fresh directory, in one run.
2. Index: ``--vectors`` 256-d descriptors shaped like a fleet's: unit vectors around 20,000
   places (several windows per place, as revisits give), queries are held-out windows of those
   places. The large-map index (IVF-PQ with exact re-ranking of its shortlist,
   :func:`radaredge.fleet.maps.index_parameters`) against exact search: recall@1 (the same
   nearest vector), build time, serialised size, single-query latency p50 on 2 threads.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from result_file import save_result  # noqa: E402

from radaredge.data.pr_benchmark import make_pr_benchmark  # noqa: E402
from radaredge.fleet import maps  # noqa: E402
from radaredge.fleet.pipeline import run_graph, run_sequential  # noqa: E402
from radaredge.runtime.backends import cpu_model  # noqa: E402


def throughput(frames: int, work: Path) -> dict:
    import radaredge

    make_pr_benchmark(work / "town", drives=4, frames_per_drive=frames, seed=11)
    graph = work / "tdfanet-edge.onnx"
    radaredge.export("tdfanet-edge", graph)
    data = work / "town"
    rows = {}
    seq = run_sequential(graph, data, work / "plain", shard_windows=64)
    rows["plain loop"] = seq.to_dict()
    for workers in (1, 2):
        r = run_graph(graph, data, work / f"ray-{workers}", workers=workers, threads=1, shard_windows=64)
        rows[f"ray {workers} worker{'s' if workers > 1 else ''}"] = r.to_dict()
    plain, one, two = (rows[k]["windows_per_second"] for k in ("plain loop", "ray 1 worker", "ray 2 workers"))
    return {
        "graph": "tdfanet-edge (seeded weights)",
        "drives": 4,
        "windows": seq.windows,
        "rows": rows,
        "ratio_2_to_1_workers": two / one,
        "ray_overhead": plain / one - 1.0,
    }


def fleet_like(n: int, dim: int, places: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """``n`` database unit vectors around ``places`` place centres, and 1,000 queries: other
    windows of randomly chosen places (the same noise)."""
    centres = rng.normal(size=(places, dim)).astype(np.float32)
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)

    def around(ids):
        x = centres[ids] + rng.normal(0, 0.35 / np.sqrt(dim), (len(ids), dim)).astype(np.float32)
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    db = np.concatenate(
        [around(rng.integers(0, places, 100_000)) for _ in range(n // 100_000)]
        + ([around(rng.integers(0, places, n % 100_000))] if n % 100_000 else [])
    )
    return db, around(rng.integers(0, places, 1000))


def index_scale(n: int, dim: int = 256) -> dict:
    import faiss

    faiss.omp_set_num_threads(2)
    rng = np.random.default_rng(0)
    db, queries = fleet_like(n, dim, 20_000, rng)
    exact = faiss.IndexFlatL2(dim)
    exact.add(db)
    t = time.perf_counter()
    truth = exact.search(queries, 1)[1][:, 0]
    exact_s = (time.perf_counter() - t) / len(queries)
    params = maps.index_parameters("auto", n, dim)
    t = time.perf_counter()
    index = maps.build_index(db, params)
    build_s = time.perf_counter() - t
    got = maps._search(index, queries, 1)[1][:, 0]
    lat = []
    for q in queries[:200]:
        t = time.perf_counter()
        index.search(q[None], 10)
        lat.append(time.perf_counter() - t)
    size = faiss.serialize_index(index).nbytes
    return {
        "vectors": n,
        "dim": dim,
        "places": 20_000,
        "queries": len(queries),
        "index": params,
        "recall_at_1_vs_exact": float((got == truth).mean()),
        "build_s": build_s,
        "query_p50_ms": 1000 * float(np.median(lat)),
        "exact_query_ms": 1000 * exact_s,
        "index_bytes": int(size),
        "vectors_bytes": int(db.nbytes),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vectors", type=int, default=1_000_000)
    ap.add_argument("--frames", type=int, default=250)
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="fleet-scale-"))
    try:
        result = {
            "cpu": f"{cpu_model()}, {os.cpu_count()} cores",
            "throughput": throughput(args.frames, work),
            "index": index_scale(args.vectors),
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)
    save_result("fleet-scale", result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
