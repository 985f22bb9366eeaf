"""Place recognition on towns that discriminate: Recall@1/5/10 at 5 m and 25 m with intervals.

The towns are street networks (``radaredge make-benchmark --layout network``): a database circuit
of 2 km or more through junctions, query days on its streets in both lanes and partly against
its direction (radaredge.data.road_network, radaredge.data.pr_benchmark). Towns have two roles,
never mixed:

- design towns, seeds 1 .. T (``--design-towns``, ``--design-km`` each): training, and the
  validation that picks the best epoch (``radaredge train``'s by-drive validation, each town's
  last query day); card and recipe choices are made on these only;
- test towns, seeds 1000 .. (``--test-towns``, ``--test-km``): this table only.

Rows, each on the same windows of the test towns (the database against every query window):
chance (a random ranking, computed), the no-learning polar occupancy descriptor of the same
points (radaredge.eval.baselines), the seeded network, the trained network's fp32 graph and its
int8 graph (onnxruntime, 2 threads). Each Recall@N comes with its 95 % percentile-bootstrap
interval over queries (radaredge.eval.recall_stats), at 5 m and at 25 m (TransLoc4D's
evaluation radius). The trained checkpoint is ``radaredge train --model CARD --data <design
towns>`` run here, or ``--run DIR`` of an earlier run (its train-log.json is the training record).

The graphs describe the test towns through ``radaredge run`` (Ray Data, one worker of 2 threads)
into ``<work>/descriptors/<row>/<town>/<database|queries>``, so a run stopped while scoring a
large card starts again where it stopped (finished shards are kept); graphs already exported
from the same checkpoint are reused.

Writes benchmarks/results/place-recognition-<card>-<date>.json, which benchmarks/render.py renders.

    python benchmarks/place_recognition.py --card tdfanet-edge
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import training_run
from result_file import save_result

import radaredge
from radaredge.artifacts import INT8, copy_path
from radaredge.data.pr_benchmark import make_pr_towns, make_route_benchmark
from radaredge.data.run_shards import read_run
from radaredge.eval.places import WindowSet, baseline_backend, describe_windows, load_windows, recall_at_n
from radaredge.eval.recall_stats import bootstrap_interval, chance_of_benchmark
from radaredge.eval.travel import AGAINST, WITH, against_database, window_headings
from radaredge.fleet.pipeline import run_graph

RADII = (5.0, 25.0)
NS = (1, 5, 10)
TEST_SEED = 1000


def towns(root: Path, count: int, seed: int, km: float) -> list[Path]:
    """The towns under ``root`` (``count`` of them, seeds ``seed`` .., database circuits of at
    least ``km`` km), made there first when ``root`` does not exist."""
    if not root.exists():
        make_pr_towns(root, count, seed, lambda path, s: make_route_benchmark(path, 3, km * 1000.0, s))
    return sorted(p for p in root.iterdir() if p.name.startswith("town-"))


def graph_descriptors(graph: Path, out: Path):
    """A describer for :func:`score`: ``descriptor_normalized`` of ``graph`` for every window of
    a town part, by ``radaredge run`` (onnxruntime, one Ray worker of THREADS threads) into
    ``out/<town>/<part>``, resumed where an earlier call stopped; checked against the window
    set's positions (the same windows in the same order)."""

    def describe(windows: WindowSet, town: str, part: str) -> tuple[np.ndarray, int, float]:
        report = run_graph(graph, windows.path, out / town / part, workers=1, threads=training_run.THREADS)
        _, poses, outputs = read_run(out / town / part)
        found = np.stack([poses["northing"], poses["easting"]], axis=1)
        if found.shape != windows.positions.shape or not np.allclose(found, windows.positions):
            raise SystemExit(f"{out / town / part}: its windows are not those of {windows.path}")
        return outputs["descriptor_normalized"], report.computed_windows, report.seconds

    return describe


def baseline_descriptors(features):
    """A describer for :func:`score`: the no-learning polar occupancy descriptor of every window."""

    def describe(windows: WindowSet, town: str, part: str) -> tuple[np.ndarray, int, float]:
        t0 = time.perf_counter()
        desc = describe_windows(windows, features, baseline_backend(features))
        return desc, len(windows), time.perf_counter() - t0

    return describe


def score(describe, town_dirs: list[Path], k: int) -> dict:
    """Recall@N with intervals at each radius, pooled over the test towns' queries, of the
    descriptors ``describe`` gives (:func:`graph_descriptors`, :func:`baseline_descriptors`);
    under ``by_direction`` Recall@1 of the queries that drive with and against the database at
    their place (radaredge.eval.travel). ``windows_per_second`` counts the windows described in
    this call (none when every one was described before)."""
    hits = {r: [] for r in RADII}
    direction = {r: [] for r in RADII}
    evaluated = {r: 0 for r in RADII}
    seconds, described = 0.0, 0
    for town in town_dirs:
        db, queries = load_windows(town / "database", k), load_windows(town / "queries", k)
        db_desc, n_db, s_db = describe(db, town.name, "database")
        query_desc, n_q, s_q = describe(queries, town.name, "queries")
        seconds, described = seconds + s_db + s_q, described + n_db + n_q
        for r in RADII:
            res = recall_at_n(query_desc, queries.positions, db_desc, db.positions, NS, r)
            hits[r].append(res["hits"])
            evaluated[r] += res["evaluated"]
            way = against_database(queries.positions, window_headings(queries), db.positions, window_headings(db), r)
            direction[r].append(way[res["evaluated_mask"]])
    out = {
        "windows_described": described,
        "windows_per_second": round(described / seconds, 1) if described and seconds > 0 else None,
    }
    for r in RADII:
        found, way = np.concatenate(hits[r]), np.concatenate(direction[r])
        out[f"{r:g}"] = {
            "evaluated": evaluated[r],
            "recall": {str(n): 100.0 * float(found[:, n - 1].mean()) for n in NS},
            "interval_95": {str(n): list(bootstrap_interval(found[:, n - 1])) for n in NS},
            "by_direction": {
                name: {
                    "evaluated": int((way == code).sum()),
                    "recall_at_1": 100.0 * float(found[way == code, 0].mean()),
                    "interval_95": list(bootstrap_interval(found[way == code, 0])),
                }
                for name, code in (("with", WITH), ("against", AGAINST))
                if (way == code).any()
            },
        }
    return out


def _chance(towns: list[Path]) -> dict:
    """Chance Recall@1 per test town and radius (every scan a window)."""
    return {t.name: chance_of_benchmark(t, RADII) for t in towns}


def main(argv=None) -> int:
    ap = training_run.parser("python benchmarks/place_recognition.py", __doc__, "tdfanet-edge")
    ap.add_argument("--design-towns", type=int, default=3)
    ap.add_argument("--design-km", type=float, default=1.2)
    ap.add_argument("--test-towns", type=int, default=1)
    ap.add_argument("--test-km", type=float, default=2.2)
    ap.add_argument("--run", type=Path, help="an existing run directory of `radaredge train` (skips training)")
    args = ap.parse_args(argv)
    card, work, options, stamp = training_run.start(args)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    design = towns(work / "design-towns", args.design_towns, 1, args.design_km)
    test = towns(work / "test-towns", args.test_towns, TEST_SEED, args.test_km)
    t_data = time.perf_counter() - t0
    run, t_train, train = args.run, None, None
    if run is None:
        run = work / "run"
        t0 = time.perf_counter()
        report = radaredge.train(
            card, work / "design-towns", run, options=options, overwrite=True, log=lambda line: print(line, flush=True)
        )
        t_train, train = time.perf_counter() - t0, report.to_dict()
    else:
        train = json.loads((run / "train-log.json").read_text())
        t_train = train["seconds"]
    best = run / "best.pth"
    graphs = work / "graphs"
    fp32, seeded = graphs / f"{card.name}.onnx", graphs / f"{card.name}-seeded.onnx"
    int8, described = copy_path(fp32, INT8), work / "descriptors"
    if not (int8.is_file() and fp32.is_file() and fp32.stat().st_mtime > best.stat().st_mtime):
        for row in ("trained_fp32", "trained_int8"):  # another checkpoint's
            shutil.rmtree(described / row, ignore_errors=True)
        int8 = radaredge.export(card, fp32, checkpoint=best, quantize="int8").int8["tdfanet"]
    if not seeded.is_file():
        shutil.rmtree(described / "seeded", ignore_errors=True)
        radaredge.export(card, seeded)
    k = int(card.get("frames", 1))
    rows = {}
    for name, path in (("trained_fp32", fp32), ("trained_int8", int8), ("seeded", seeded)):
        rows[name] = score(graph_descriptors(path, described / name), test, k)
        print(f"{name}: R@1 at 5 m {rows[name]['5']['recall']['1']:.1f} %", flush=True)
    rows["no_learning"] = score(baseline_descriptors(card.features), test, k)
    out = {
        "date": stamp,
        "card": card.name,
        "machine": training_run.machine(),
        "command": f"python benchmarks/place_recognition.py --card {card.name} --design-towns {args.design_towns} "
        f"--design-km {args.design_km} --test-towns {args.test_towns} --test-km {args.test_km}"
        + training_run.settings_text(options)
        + (f" --run {args.run}" if args.run else ""),
        "towns": {
            "design": {
                "seeds": [int(t.name.split("-")[1]) for t in design],
                "route_km": args.design_km,
                "used_for": "training and the validation that picks the best epoch",
            },
            "test": {
                "seeds": [int(t.name.split("-")[1]) for t in test],
                "route_km": args.test_km,
                "used_for": "this table only",
            },
        },
        "frames_per_window": k,
        "chance": _chance(test),
        "data_seconds": round(t_data, 1),
        "train_seconds": None if t_train is None else round(t_train, 1),
        "checkpoint": str(best),
        "train": train,
        "rows": rows,
    }
    save_result(f"place-recognition-{card.name}", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
