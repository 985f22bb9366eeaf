"""MAFF-Net's clustering-feature stage (upstream IMAGE_BACKBONE): GridDensityBEV vs the DBSCAN path.

Times, on 2 pinned cores and interleaved per run (radaredge.benchmarking.timing.benchmark), the map that feeds
the 3 -> 16 -> 32 -> 64 CNN and the whole stage (map + CNN), for:
- CQCA_cfa as upstream runs it: sklearn DBSCAN on (x, y, v_r_comp), a per-point cluster-size
  loop, a last-write-wins map (radaredge.ops.dbscan.cqca_cfa_map_sklearn), then the CNN in torch;
- the same with the cluster sizes counted by np.unique (DBSCAN's best case);
- GridDensityBEV in torch (radaredge's export formulation);
- GridDensityBEV in onnxruntime (the map, and the stage, exported alone).
Scans are synthetic VoD scans (one radar scan, and five scans merged as VoD's 5-frame clouds),
restricted to the card's grid so the upstream indexing is valid.

    .venv/bin/python benchmarks/cfa_speedup.py --runs 20     # prints a Markdown table, writes JSON

It imports radaredge as installed (``pip install -e .``, ``make setup``) and needs scikit-learn
(the ``dev`` extra) for the upstream rows.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from result_file import RESULTS, save_result, utc_stamp

from radaredge.benchmarking.timing import benchmark, cpu_name, pin_threads, require_ok
from radaredge.cards import load_card
from radaredge.data.synthetic import generate_scan
from radaredge.exporting.onnx_call import export_onnx
from radaredge.models import create_model
from radaredge.models.maffnet.spec import synthetic_columns
from radaredge.ops.dbscan import DbscanConfig, cqca_cfa_map_sklearn
from radaredge.ops.grid_density import GridDensityConfig
from radaredge.runtime.session import make_session


class _MapOnly(torch.nn.Module):
    def __init__(self, grid_density):
        super().__init__()
        self.gd = grid_density

    def forward(self, xyv):
        return self.gd(xyv, torch.ones(xyv.shape[0], dtype=torch.bool))[0]


class _Stage(torch.nn.Module):
    def __init__(self, cfa):
        super().__init__()
        self.cfa = cfa

    def forward(self, xyv):
        bev = self.cfa.grid_density(xyv, torch.ones(xyv.shape[0], dtype=torch.bool))[0]
        return self.cfa.conv(bev.unsqueeze(0))


def scans(g: GridDensityConfig, merged: int, count: int, seed: int) -> list[np.ndarray]:
    """``count`` synthetic (x, y, v_r_comp) clouds inside grid ``g``, each ``merged`` scans concatenated."""
    out = []
    for i in range(count):
        parts = []
        for j in range(merged):
            cols = synthetic_columns(
                generate_scan(seed=seed + 100 * i + j, num_cars=6, num_pedestrians=4, num_cyclists=3)
            )
            parts.append(np.stack([cols["x"], cols["y"], cols["v_r_comp"]], 1))
        xyv = np.concatenate(parts).astype(np.float32)
        inside = (
            (xyv[:, 0] >= g.x_min + 2 * g.resolution)
            & (xyv[:, 0] < g.x_min + g.map_w * g.resolution)
            & (xyv[:, 1] >= g.y_min + 2 * g.resolution)
            & (xyv[:, 1] < g.y_min + g.map_h * g.resolution)
        )
        out.append(np.ascontiguousarray(xyv[inside]))
    return out


def run(runs: int, warmup: int, threads: int, card_name: str = "maffnet-vod", count: int = 4, merges=(1, 5)) -> dict:
    """Time every backend on ``count`` synthetic clouds per entry of ``merges`` (scans merged into
    one cloud), ``runs`` interleaved runs after ``warmup``, on ``threads`` pinned threads. Returns
    the JSON document: the host, and one row per (cloud size, part, backend) with p50 / p90 in ms
    and the speed-up over the upstream per-point loop (its p50 over the row's)."""
    cores = pin_threads(threads)
    card = load_card(card_name)
    model = create_model(card)
    cfa = model.image_backbone
    g = cfa.grid_density.config
    upstream = DbscanConfig(
        eps=g.eps,
        min_samples=g.min_density,
        max_cluster_size=g.max_density,
        map_rows=g.map_h,
        map_cols=g.map_w,
        resolution=g.resolution,
        y_offset=-g.y_min,
    )
    example = torch.zeros(50, 3)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        export_onnx(_MapOnly(cfa.grid_density), (example,), tmp / "map.onnx", ["xyv"], ["map"], {"xyv": {0: "n"}})
        export_onnx(_Stage(cfa), (example,), tmp / "stage.onnx", ["xyv"], ["features"], {"xyv": {0: "n"}})
        map_session = make_session(tmp / "map.onnx", threads=threads)
        stage_session = make_session(tmp / "stage.onnx", threads=threads)

    def cnn(bev):
        return cfa.conv(bev.unsqueeze(0))

    def gd(xyv):
        return cfa.grid_density(torch.from_numpy(xyv), torch.ones(len(xyv), dtype=torch.bool))[0]

    map_backends = {
        "CQCA_cfa: DBSCAN + per-point loop (upstream)": lambda f: cqca_cfa_map_sklearn(f["xyv"], upstream),
        "CQCA_cfa: DBSCAN + np.unique counts": lambda f: cqca_cfa_map_sklearn(f["xyv"], upstream, vectorised=True),
        "GridDensityBEV, torch": lambda f: gd(f["xyv"]),
        "GridDensityBEV, onnxruntime": lambda f: map_session.run(None, {"xyv": f["xyv"]}),
    }
    stage_backends = {
        "CQCA_cfa: DBSCAN + per-point loop (upstream)": lambda f: cnn(cqca_cfa_map_sklearn(f["xyv"], upstream)[0]),
        "CQCA_cfa: DBSCAN + np.unique counts": lambda f: cnn(
            cqca_cfa_map_sklearn(f["xyv"], upstream, vectorised=True)[0]
        ),
        "GridDensityBEV, torch": lambda f: cnn(gd(f["xyv"])),
        "GridDensityBEV, onnxruntime": lambda f: stage_session.run(None, {"xyv": f["xyv"]}),
    }
    rows = []
    with torch.no_grad():
        for merged in merges:
            clouds = [{"xyv": c} for c in scans(g, merged, count, seed=7)]
            points = int(np.median([len(c["xyv"]) for c in clouds]))
            for part, backends in (("map", map_backends), ("map + CNN", stage_backends)):
                for r in require_ok(benchmark(backends, clouds, runs, warmup)):
                    rows.append(
                        {
                            "scans": merged,
                            "points": points,
                            "part": part,
                            "backend": r.backend,
                            "p50_ms": r.p50_ms,
                            "p90_ms": r.p90_ms,
                        }
                    )
    base = {(r["scans"], r["part"]): r["p50_ms"] for r in rows if r["backend"].endswith("(upstream)")}
    for r in rows:
        r["speedup_vs_upstream"] = base[(r["scans"], r["part"])] / r["p50_ms"]
    return {
        "card": card_name,
        "threads": threads,
        "cores": cores,
        "cpu": cpu_name(),
        "runs": runs,
        "date": utc_stamp(),
        "rows": rows,
    }


def table(result: dict) -> str:
    """The rows of :func:`run`'s result as a Markdown table (p50 in ms)."""
    lines = ["| cloud | part | backend | p50 ms | x vs upstream |", "|---|---|---|---:|---:|"]
    for r in result["rows"]:
        cloud = f"{r['scans']} scan{'s' if r['scans'] > 1 else ''}, {r['points']} pts"
        lines.append(f"| {cloud} | {r['part']} | {r['backend']} | {r['p50_ms']:.2f} | {r['speedup_vs_upstream']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--card", default="maffnet-vod")
    ap.add_argument("--clouds", type=int, default=4, help="synthetic clouds per cloud size")
    ap.add_argument(
        "--scans",
        type=lambda s: tuple(int(x) for x in s.split(",")),
        default=(1, 5),
        help="scans merged into one cloud, one cloud size per comma-separated count",
    )
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder of the JSON result")
    args = ap.parse_args(argv)
    result = run(args.runs, args.warmup, args.threads, args.card, args.clouds, args.scans)
    print(
        f"{args.card}: clustering-feature stage on {args.threads} thread(s), cores {result['cores']}, "
        f"{result['cpu']}, {args.runs} runs, {result['date']}"
    )
    print(table(result))
    save_result("cfa-speedup", result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
