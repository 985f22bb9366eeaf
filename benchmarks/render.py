"""Build benchmarks/README.md from the committed JSON files in benchmarks/results/.

Every figure on that page comes from a results file, so nobody edits a measurement by hand and
none goes stale unnoticed (tests/test_docs.py checks that the committed page equals
``render(benchmarks/results)``). This module reads JSON and writes Markdown, nothing else: it
imports neither torch nor radaredge, so it runs anywhere.

Files it knows, by name (``<kind>-<YYYY-MM-DD>.json``):

- ``suite-<date>.json``: ``make bench`` (``benchmarks/run.py``), every card and backend;
- ``<card>-<date>.json``: ``radaredge bench --model <card>`` saved with ``--save``;
- ``compare-<label>-<date>.json``: ``benchmarks/compare_graphs.py``, two graphs alternately;
- ``maffnet-capacity-<date>.json``: ``benchmarks/maffnet_capacity.py``;
- ``cfa-speedup-<date>.json``: ``benchmarks/cfa_speedup.py``;
- ``place-recognition-<card>-<date>.json``: ``benchmarks/place_recognition.py``;
- ``tdfanet-variants-<card>-<date>.json``: ``benchmarks/tdfanet_variants.py``;
- ``detection-seeds-<card>-<date>.json``: ``benchmarks/detection_seeds.py``, a card over training seeds;
- ``detection-tradeoff-<date>.json``: ``benchmarks/detection_tradeoff.py``, those cards side by side, also
  written into docs/models/maffnet.md (:data:`GENERATED`);
- ``int8-methods-<card>-<split>-<date>.json``: ``benchmarks/int8_methods.py``, int8 calibration methods on
  trained weights, also written into docs/quantization.md;
- ``int8-speed[-<int8 dot-product set>]-<date>.json``: ``benchmarks/int8_speed.py``, int8 against fp32 speed
  on the zoo's weights with onnxruntime's profile of both, one study per kind of CPU, also written into
  docs/quantization.md;
- ``<card>-training-<date>.json``: ``benchmarks/tdfanet_training.py`` or
  ``benchmarks/des4pos_training.py``, a training run and its held-out recall.

The newest file of each kind is rendered in full; older ones are listed under "History".

    python benchmarks/render.py            # rewrites benchmarks/README.md and the GENERATED blocks
"""

from __future__ import annotations

import datetime as dt
import json
import re
import sys
from pathlib import Path
from typing import Callable

HERE = Path(__file__).resolve().parent
RESULTS_DIR = HERE / "results"
ZOO_DIR = HERE.parent / "zoo"
README = HERE / "README.md"
DOCS = HERE.parent / "docs"

# What the int8 export quantises when a suite file does not record it (radaredge's quantiser).
DEFAULT_QUANTIZED_OPS = ("Conv", "MatMul", "Gemm")
_NAME = re.compile(r"^(?P<kind>.+)-(?P<date>\d{4}-\d{2}-\d{2})(?:-\d{4})?\.json$")  # -HHMM: a second run that day


# --- reading -----------------------------------------------------------------------------------


class Result:
    """One results file: its kind, the key it is newest-of within that kind, and its content."""

    def __init__(self, path: Path):
        self.path = path
        m = _NAME.match(path.name)
        self.stem = m["kind"] if m else path.stem
        self.day = dt.date.fromisoformat(m["date"]) if m else None
        self.data = json.loads(path.read_text())
        self.kind = _kind(self.stem, self.data)

    @property
    def key(self) -> str:
        """Files with the same key are runs of the same study; the newest one is rendered."""
        return "suite" if self.kind == "suite" else self.stem

    @property
    def when(self) -> str:
        """The run's own time stamp when it has one, else the date in the file name."""
        d = self.data.get("date") if isinstance(self.data, dict) else None
        return str(d) if d else (self.day.isoformat() if self.day else "undated")

    def sort_key(self):
        return (self.day or dt.date.min, self.when, self.path.name)


def _kind(stem: str, data) -> str:
    if not isinstance(data, dict):
        return "other"
    if stem == "suite":
        return "suite"
    if stem.startswith("compare-"):
        return "compare"
    if stem == "maffnet-capacity":
        return "capacity"
    if stem == "cfa-speedup":
        return "cfa"
    if stem == "maffnet-train-step":
        return "train-step"
    if stem == "fleet-scale":
        return "fleet"
    if stem.startswith("maffnet-trained-"):
        return "trained"
    if stem.startswith("detection-seeds-"):
        return "seeds"
    if stem == "detection-tradeoff":
        return "tradeoff"
    if stem.startswith("int8-methods-"):
        return "int8-methods"
    if stem == "int8-speed" or stem.startswith("int8-speed-"):
        return "int8-speed"  # one study per kind of CPU: -<int8 dot-product set> when it has one
    if stem.startswith("place-recognition-"):
        return "places"
    if stem.startswith("tdfanet-variants-"):
        return "variants"
    if stem == "real-data":
        return "real"
    if stem.endswith("-training") and "train" in data:
        return "training"
    if any(k in data for k in ("tasks", "results", "rows", "query")):
        return "bench"
    return "other"


def load(results_dir: Path) -> list[Result]:
    return sorted((Result(p) for p in Path(results_dir).glob("*.json")), key=Result.sort_key)


def newest_by_key(results: list[Result], kind: str) -> list[Result]:
    """The newest file of every key of ``kind``, ordered by key."""
    newest: dict[str, Result] = {}
    for r in results:  # sorted oldest first, so the last one wins
        if r.kind == kind:
            newest[r.key] = r
    return [newest[k] for k in sorted(newest)]


# --- formatting helpers --------------------------------------------------------------------------


def _num(v, fmt: str = ".1f", missing: str = "-") -> str:
    return missing if v is None else format(v, fmt)


def _diffs(diffs: dict) -> str:
    """``output diff, ...`` as `radaredge bench` prints OpenVINO's largest output differences."""
    return ", ".join(f"{k} {v:.2g}" if v != float("inf") else f"{k} (other shape)" for k, v in diffs.items())


def _table(header: list[str], rows: list[list[str]], align: list[str] | None = None) -> list[str]:
    align = align or ["---"] + ["---:"] * (len(header) - 1)
    return ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|"] + ["| " + " | ".join(r) + " |" for r in rows]


def _link(r: Result, results_dir: Path) -> str:
    return f"[{r.path.name}]({Path(results_dir).name}/{r.path.name})"


def _machine(d: dict) -> str:
    """``AMD EPYC, 2 threads pinned to cores [0, 1], 20 timed runs`` from whatever the file records."""
    parts = []
    if d.get("cpu"):
        isa = d.get("int8_dot_product")
        parts.append(str(d["cpu"]) + ("" if isa is None else f" ({_int8_dot_product_text(isa)})"))
    if d.get("threads") is not None:
        cores = f" pinned to cores {d['cores']}" if d.get("cores") is not None else ""
        parts.append(f"{d['threads']} threads{cores}")
    if d.get("runs") is not None:
        parts.append(f"{d['runs']} timed runs per backend")
    return ", ".join(parts)


def _stamp(r: Result, d: dict) -> str:
    """``<when>: <machine>`` or just ``<when>`` when the file records no machine."""
    machine = _machine(d)
    return f"{r.when}: {machine}" if machine else r.when


# --- sections --------------------------------------------------------------------------------


def _suite_weights(m: dict) -> str:
    """The weights a suite card was timed with: the zoo's (path and sha256 prefix) or seeded
    (suites before the zoo recorded none: seeded)."""
    if "weights_sha256" not in m:
        return "seeded"
    return f"`{m['weights']}` (`{m['weights_sha256'][:12]}`)"


def suite_section(r: Result, results_dir: Path) -> list[str]:
    s = r.data
    models = s.get("models", [])
    out = ["## Speed suite", ""]
    warm = f" after {s.get('warmup', 3)} warm-ups" if s.get("runs") else ""
    intro = (
        f"`make bench` (`benchmarks/run.py`) on {_stamp(r, s)}{warm}, backends alternating every run; "
        f"every card exported and quantised afresh by the run."
    )
    if s.get("gemm_peak_gflops") is not None:
        intro += (
            f" Measured fp32 GEMM peak on these threads (best of 20 1024 x 1024 products): "
            f"{s['gemm_peak_gflops']:.1f} GFLOP/s."
        )
    out += [intro + f" JSON: {_link(r, results_dir)}; chart: [suite.png](suite.png).", ""]
    rows = []
    for m in models:
        for row in m.get("rows", []):
            frac = row.get("peak_fraction")
            rows.append(
                [
                    m["model"],
                    row["backend"],
                    _num(row.get("p50_ms")),
                    _num(row.get("p90_ms")),
                    _num(row.get("fps"), ".2f"),
                    _num(row.get("gmacs"), ".2f"),
                    _num(None if frac is None else 100 * frac),
                ]
            )
    out += _table(
        ["model", "backend", "p50 ms", "p90 ms", "FPS", "GMACs", "% of fp32 GEMM peak"],
        rows,
        ["---", "---"] + ["---:"] * 5,
    )
    rows = []
    for m in models:
        share = m.get("quantised_op_time_share")
        rows.append(
            [
                m["model"],
                _suite_weights(m),
                _num(m.get("ort_vs_reference"), ".2f") + "x",
                _num(m.get("int8_vs_fp32"), ".2f") + "x",
                _num(None if share is None else 100 * share, ".0f") + " %",
            ]
        )
    out += [""] + _table(
        ["model", "weights", "onnxruntime fp32 vs torch reference", "int8 vs fp32", "fp32 time in quantised ops"],
        rows,
        ["---", "---"] + ["---:"] * 3,
    )
    with_ov = [m for m in models if "openvino_vs_onnxruntime" in m]
    if with_ov:
        rows = [
            [m["model"], f"{m['openvino_vs_onnxruntime']:.2f}x", _diffs(m.get("openvino_max_abs_diff") or {})]
            for m in with_ov
        ]
        out += [""] + _table(
            ["model", "OpenVINO fp32 vs onnxruntime fp32", "largest output difference from onnxruntime"],
            rows,
            ["---", "---:", "---"],
        )
    ops = ", ".join(s.get("quantized_ops") or DEFAULT_QUANTIZED_OPS)
    out += [
        "",
        "GMACs count matrix products and convolutions, plus bilinear sampling (4 MACs per sample and "
        "channel) and scatter updates (1 per element), which common counters report as zero; pointwise "
        "ops are not counted. The int8 row's share of the fp32 peak can exceed 100 %: int8 arithmetic is "
        f"not bound by it. int8 quantises only {ops} (static QDQ, uint8 activations, per-channel int8 "
        "weights on 7 bits unless a card sets quantization.reduce_range: false). By Amdahl's law its "
        "speed-up cannot exceed 1 / (1 - share + share / s) for a kernel speed-up s, so a low share of fp32 "
        "time in those ops explains a small int8 gain. OpenVINO's largest difference on `boxes` can be an "
        "ordering effect: two near-tied boxes swap output slots (`radaredge parity-check --runtime "
        "openvino` matches boxes by IoU).",
        "",
    ]
    return out


def _status(row: dict) -> str:
    status = str(row.get("status", ""))
    return f"{status}: {row['error']}" if row.get("error") else status


def _bench_rows(rows: list[dict], items_per_case: int | None = None, item_unit: str = "") -> list[str]:
    """One row per backend; a failed backend keeps its row, with its status and no times."""
    has_status = any("status" in row for row in rows)
    per_item = bool(items_per_case)
    header = (
        ["backend"]
        + (["status"] if has_status else [])
        + ["p50 ms", "p90 ms", "p99 ms", "FPS"]
        + ([f"{item_unit or 'items'}/s"] if per_item else [])
    )
    body = []
    for row in rows:
        p50 = row.get("p50_ms")
        body.append(
            [str(row.get("backend", "?"))]
            + ([_status(row)] if has_status else [])
            + [_num(p50), _num(row.get("p90_ms")), _num(row.get("p99_ms")), _num(row.get("fps"), ".2f")]
            + ([_num(items_per_case * 1e3 / p50 if p50 else None)] if per_item else [])
        )
    return _table(header, body, ["---"] * (2 if has_status else 1) + ["---:"] * (5 if per_item else 4))


def _ratios(t: dict) -> list[str]:
    parts = [f"{v:.2f}x vs {k}" for k, v in (t.get("onnxruntime_speedup") or {}).items()]
    out = ["onnxruntime speed-up: " + ", ".join(parts) + "."] if parts else []
    if t.get("int8_vs_fp32") is not None:
        out.append(f"int8 vs fp32: {t['int8_vs_fp32']:.2f}x.")
    if t.get("openvino_vs_onnxruntime") is not None:
        out.append(f"OpenVINO vs onnxruntime: {t['openvino_vs_onnxruntime']:.2f}x.")
    return [" ".join(out), ""] if out else []


def _graph_extras(g: dict, label: str = "") -> list[str]:
    """Per graph: peak memory, OpenVINO's largest output difference, stage split, top ops."""
    out = []
    rss = g.get("onnxruntime_peak_rss_mib")
    if rss is not None:
        out += [
            f"{label}onnxruntime peak resident set: {rss:.0f} MiB (a fresh numpy + onnxruntime process "
            "running the bench inputs).",
            "",
        ]
    ov = g.get("openvino_vs_onnxruntime_max_abs")
    if ov:
        out += [f"{label}largest OpenVINO output difference from onnxruntime: {_diffs(ov)}.", ""]
    if g.get("stage_ms"):
        out += _stage_table(g["stage_ms"]) + [""]
    if g.get("top_ops"):
        out += _table(["onnxruntime op", "kernel ms per run"], [[str(op), _num(ms)] for op, ms in g["top_ops"]]) + [""]
    return out


def _stage_table(stage_ms: dict) -> list[str]:
    """Backends as rows, stages as columns (union of every backend's stages, in first-seen order)."""
    stages: list[str] = []
    for per in stage_ms.values():
        for k in per:
            if k not in stages:
                stages.append(k)
    rows = [[backend] + [_num(per.get(k)) for k in stages] for backend, per in stage_ms.items()]
    return _table(["per stage, ms"] + stages, rows)


def bench_section(results: list[Result], results_dir: Path) -> list[str]:
    if not results:
        return []
    out = [
        "## Per-model benches",
        "",
        "`radaredge bench --model <card> --save benchmarks/results/<card>-<date>.json`: the newest saved run "
        "of each card. Times of different runs are comparable only on the same machine on the same day; read "
        "the ratios within one run.",
        "",
    ]
    for r in results:
        d = r.data
        name = d.get("model", r.stem)
        out += [f"### {name}", "", f"{_stamp(r, d)}. JSON: {_link(r, results_dir)}.", ""]
        for task in (d.get("tasks") or {}).values():  # radaredge bench --save
            if task.get("title"):
                out += [f"{task['title']}:", ""]
            out += _bench_rows(task.get("rows", []), task.get("items_per_case"), task.get("item_unit", "")) + [""]
            out += _ratios(task)
        graphs = d.get("graphs") or {}
        for gname, g in graphs.items():
            out += _graph_extras(g or {}, f"{gname}: " if len(graphs) > 1 else "")
        rows = d.get("results") or d.get("rows")  # earlier `bench --json` files
        if rows:
            out += _bench_rows(rows) + [""]
        if d.get("query"):
            out += (
                [
                    f"Query (tokenise, text encode, search over {d.get('map_cells', '?')} cells, fine stage on the "
                    f"top {d.get('top_k', '?')}):",
                    "",
                ]
                + _bench_rows(d["query"])
                + [""]
            )
        if d.get("cell_batches"):
            batch = d.get("cell_batch")
            cps = d.get("cells_per_s") or {}
            body = [
                [str(row.get("backend")), _num(row.get("p50_ms")), _num(cps.get(row.get("backend")))]
                for row in d["cell_batches"]
            ]
            out += (
                [f"Cell encoding, batches of {batch} cells:", ""]
                + _table(["backend", "p50 ms per batch", "cells/s"], body)
                + [""]
            )
        out += _ratios(d)
        out += _graph_extras(
            {
                "onnxruntime_peak_rss_mib": d.get("onnxruntime_peak_rss_mib"),
                "openvino_vs_onnxruntime_max_abs": d.get("openvino_vs_onnxruntime_max_abs"),
                "stage_ms": d.get("stage_ms"),
                "top_ops": d.get("top_ops"),
            }
        )
    return out


def compare_section(results: list[Result], results_dir: Path) -> list[str]:
    if not results:
        return []
    out = [
        "## Graph comparisons",
        "",
        "`benchmarks/compare_graphs.py` times two graphs of one card alternately in one run, then splits each "
        "graph's onnxruntime kernel time by stage (median over several profiled passes, mean ms per case).",
        "",
    ]
    for r in results:
        d = r.data
        graphs = d.get("graphs", [])
        label = r.stem[len("compare-") :]
        cases = ", ".join(f"{c} ({p} points)" for c, p in zip(d.get("cases", []), d.get("points", [])))
        out += [
            f"### {label}",
            "",
            f"{d.get('model', '?')}, {_stamp(r, d)}, {d.get('profile_rounds', '?')} profiled passes. "
            f"Cases: {cases or '-'}. JSON: {_link(r, results_dir)}.",
            "",
        ]
        names = [f"`{g.get('onnx', '?')}`" for g in graphs]
        stages: list[str] = []
        for g in graphs:
            for k in g.get("stage_ms", {}):
                if k not in stages:
                    stages.append(k)
        rows = [
            ["p50 ms (whole graph)"] + [_num(g.get("p50_ms")) for g in graphs],
            ["p90 ms (whole graph)"] + [_num(g.get("p90_ms")) for g in graphs],
        ]
        rows += [[k] + [_num(g.get("stage_ms", {}).get(k)) for g in graphs] for k in stages]
        out += _table([""] + names, rows) + [""]
    return out


def capacity_section(r: Result | None, results_dir: Path) -> list[str]:
    if r is None:
        return []
    d = r.data
    spa, db = d.get("spa_capacity"), d.get("dbscan_capacity")
    clouds = d.get("clouds", [])
    n = len({c.get("seed") for c in clouds})
    out = [
        "## MAFF-Net capacity",
        "",
        f"`benchmarks/maffnet_capacity.py`, {r.when}: how full synthetic VoD 5-frame clouds make the "
        f"fixed-size stages of `{d.get('card', '?')}` ({n} cloud{'s' if n != 1 else ''}, each with "
        f"and without the crop; `spa.capacity` {spa}, "
        f"`cfa.dbscan.capacity` {db}). Scan points are the points inside the x-y range, the ones DBSCAN "
        f"clusters. JSON: {_link(r, results_dir)}.",
        "",
    ]

    def margin(cap, n):
        return "-" if not cap or not n else f"{cap / n:.1f}x"

    rows = []
    for label, key in (("camera field of view crop", "camera_fov"), ("no crop", "no_crop")):
        m = d.get(key)
        if m:
            rows.append(
                [
                    label,
                    f"{m['points']:,}",
                    f"{m['scan_points']:,}",
                    margin(db, m["scan_points"]),
                    f"{m['pillars']:,}",
                    margin(spa, m["pillars"]),
                ]
            )
    out += _table(
        [
            "largest cloud",
            "points",
            "scan points",
            "DBSCAN capacity margin",
            "non-empty pillars",
            "SPA capacity margin",
        ],
        rows,
        ["---"] + ["---:"] * 5,
    ) + [""]
    return out


def cfa_section(r: Result | None, results_dir: Path) -> list[str]:
    if r is None:
        return []
    d = r.data
    rows = d.get("rows", [])
    backends: list[str] = []
    for row in rows:
        if row["backend"] not in backends:
            backends.append(row["backend"])
    groups: dict[tuple, dict] = {}
    for row in rows:
        groups.setdefault((row["scans"], row["points"], row["part"]), {})[row["backend"]] = row
    body = []
    for (scans, points, part), by in groups.items():
        cells = []
        for b in backends:
            row = by.get(b)
            cells.append("-" if row is None else f"{row['p50_ms']:.1f} ms ({row['speedup_vs_upstream']:.2f}x)")
        body.append([f"{scans} scan{'s' if scans != 1 else ''}, {points:,} points", part] + cells)
    out = [
        "## Clustering stage: GridDensityBEV against DBSCAN",
        "",
        f"`benchmarks/cfa_speedup.py` on `{d.get('card', '?')}`, {_stamp(r, d)}. MAFF-Net's "
        "clustering-feature map alone and with the 3 -> 16 -> 32 -> 64 CNN; p50 and the speed-up over "
        f"upstream's CQCA_cfa. JSON: {_link(r, results_dir)}.",
        "",
    ]
    out += _table(["cloud", "part"] + backends, body, ["---", "---"] + ["---:"] * len(backends)) + [""]
    return out


def real_data_section(r: Result | None, results_dir: Path) -> list[str]:
    if r is None:
        return []
    d = r.data
    cards = d.get("cards", [])
    out = [
        "## Recorded radar: the published View-of-Delft and TJ4DRadSet frames",
        "",
        f"`benchmarks/real_data.py`, {_stamp(r, d)}; {d.get('weights', '?')}. Every card that takes scans on "
        "its dataset's published sample (View-of-Delft `example_set`: 3 frames; TJ4DRadSet `Sample`: 41 "
        "consecutive frames; docs/data.md), fed as `parity-check --data` feeds it. Time: p50 of the fp32 graph "
        "in onnxruntime, recorded frames and the speed suite's synthetic cases interleaved in one run; peak "
        "memory: a fresh numpy + onnxruntime process. Command: "
        f"`{d.get('command', '?')}`. JSON: {_link(r, results_dir)}.",
        "",
    ]
    rows = []
    for c in cards:
        p, t, m = c["points"], c["p50_ms"], c["peak_rss_mib"]
        rows.append(
            [
                f"`{c['card']}`",
                f"{c['timed']} of {c['available']} {c['unit']}s",
                f"{p['points_per_scan']:,.0f}",
                f"{100 * p['in_range_share']:.0f} %",
                f"{100 * p['over_pillar_cap_share']:.1f} %",
                f"{t['recording']:,.0f}",
                f"{t['synthetic']:,.0f}",
                f"{t['recording'] / t['synthetic']:.2f}x",
                f"{m['recording']:,.0f} / {m['synthetic']:,.0f}",
            ]
        )
    out += _table(
        [
            "card",
            "timed",
            "points a scan",
            "in range",
            "over a pillar's cap",
            "recorded ms",
            "synthetic ms",
            "ratio",
            "peak MiB (recorded / synthetic)",
        ],
        rows,
        ["---"] + ["---:"] * 8,
    ) + [""]
    grids = [c for c in cards if "grid_density" in c]
    if grids:
        out += [
            "GridDensityBEV's max-pool labelling on every frame of the recording: the frames whose components "
            "converge in the card's `cc_iterations`, the max-pool steps the frames need, the share of non-noise "
            "cells whose label is partial, and the labels against the true (exact) components:",
            "",
        ]
        rows = []
        for c in grids:
            g = c["grid_density"]
            rows.append(
                [
                    f"`{c['card']}`",
                    f"{g['cc_mode']}, {g['cc_iterations']}",
                    f"{g['converged']} of {g['frames']}",
                    f"{g['steps_median']:.0f} / {g['steps_max']}",
                    f"{100 * g['partial_cell_share']:.0f} %",
                    f"{g['labels']:,} / {g['components']:,}",
                ]
            )
        out += _table(
            [
                "card",
                "cc (mode, iterations)",
                "converged",
                "steps needed (median / max)",
                "cells with a partial label",
                "labels / components",
            ],
            rows,
            ["---"] + ["---:"] * 5,
        ) + [""]
    varied = [c for c in cards if c.get("variants")]
    if varied:
        out += [
            "Where frames do not converge, the same graph with the components made exact, on the timed frames "
            "(boxes: top 20 by score per frame, same class, BEV IoU >= 0.5 against the card's own graph):",
            "",
        ]
        rows = []
        for c in varied:
            base = c["p50_ms"]["recording"]
            for v in c["variants"]:
                ms = c["p50_ms"][v["name"]]
                compared = (
                    f"of {v['boxes_compared']:,}"
                    if "boxes_compared" in v
                    else f"(top 20 a frame; {v['boxes']:,} boxes in all)"
                )
                rows.append(
                    [
                        f"`{c['card']}`",
                        v["name"],
                        f"{v['converged']} of {c['timed']}",
                        f"{ms:,.0f} ({ms / base:.2f}x)",
                        f"{v['boxes_changed']} {compared}",
                    ]
                )
        out += _table(
            ["card", "setting", "converged", "recorded ms (vs the card's)", "boxes changed"],
            rows,
            ["---", "---"] + ["---:"] * 3,
        ) + [""]
    return out


def train_step_section(r: Result | None, results_dir: Path) -> list[str]:
    if r is None:
        return []
    d = r.data
    body = [
        [
            row["precision"],
            row["formulation"],
            f"{row['median_s']:.3f}",
            f"{row['p90_s']:.3f}",
            f"{row['speedup']:.2f}x",
        ]
        for row in d.get("rows", [])
    ]
    out = [
        "## MAFF-Net training step",
        "",
        f"`benchmarks/maffnet_train_step.py` on `{d.get('card', '?')}`, {_stamp(r, d)}. Seconds per training "
        f"scan (median and 90th percentile over {d.get('steps', '?')} optimiser steps of {d.get('batch_size', '?')} "
        f"scans, the variants taking turns; {d.get('weights', 'seeded weights')}), and the speed-up over the "
        f"export formulation on NCHW tensors in the same precision. JSON: {_link(r, results_dir)}.",
        "",
    ]
    out += _table(
        ["precision", "formulation", "s per scan", "p90", "speed-up"], body, ["---", "---", "---:", "---:", "---:"]
    ) + [""]
    return out


def training_section(results: list[Result], results_dir: Path) -> list[str]:
    out = []
    for r in results:
        d = r.data
        if "heldout" in d:
            out += des4pos_training_section(r, results_dir)
            continue
        if "test_trained" in d:
            out += maffnet_training_section(r, results_dir)
            continue
        train, held = d["train"], d["heldout_town"]
        m = d.get("machine", {})
        data = train.get("data", {})
        out += [
            "## TDFANet training",
            "",
            f"`benchmarks/tdfanet_training.py`, {r.when}: {m.get('cpu', '?')}, {m.get('threads', '?')} threads. "
            f"`{d['command']}`: {data.get('drives', '?')} drives, {data.get('training_windows', '?')} training and "
            f"{data.get('validation_windows', '?')} validation windows, "
            f"{data.get('queries_per_epoch', '?')} tuples "
            f"per epoch. Training took {d['train_seconds'] / 60:.1f} min. JSON: {_link(r, results_dir)}.",
            "",
        ]
        rows = [
            [
                str(e["epoch"]),
                "-" if e["loss"] != e["loss"] else f"{e['loss']:.4f}",
                *(_num(e[f"val_R@{n}"]) for n in (1, 5, 10)),
                _num(e["seconds"] / 60),
                "best" if e["epoch"] == train.get("best_epoch") else "",
            ]
            for e in train["epochs"]
        ]
        out += _table(
            ["epoch", "loss", "val R@1 %", "val R@5 %", "val R@10 %", "min", ""], rows, ["---:"] * 6 + ["---"]
        ) + [""]
        out += [
            f"On the one-street town of seed {held['seed']} (`radaredge make-benchmark`'s default; never trained "
            f"on, but the town the edge card's pillar size and int8 `keep_fp32` layers were chosen on, so a design "
            f"town, not a test; about 11 database windows lie within 5 m of a query, so chance alone scores about "
            f"19 % R@1), `radaredge eval`, onnxruntime, true positive within 5 m:",
            "",
        ]
        labels = (
            ("seeded_fp32", "seeded weights, fp32"),
            ("trained_fp32", "trained, fp32"),
            ("trained_int8", "trained, int8"),
        )
        rows = [
            [label, *(_num(held[k]["recall"][str(n)]) for n in (1, 5, 10)), str(held[k]["evaluated"])]
            for k, label in labels
            if k in held
        ]
        out += _table(["graph", "R@1 %", "R@5 %", "R@10 %", "queries"], rows, ["---"] + ["---:"] * 4) + [""]
        agree = held.get("int8_top1_agreement_with_fp32", {})
        p8 = d.get("parity_int8", {})
        out += [
            f"Parity on the trained weights: fp32 {'PASSED' if d['parity_fp32']['passed'] else 'FAILED'}, "
            f"int8 budget {'PASSED' if p8.get('passed') else 'FAILED'}. int8 retrieves the same top-1 window "
            f"as fp32 for {100 * agree.get('same_window', float('nan')):.1f} % of the queries and a window "
            f"within 5 m of it for {100 * agree.get('within_radius', float('nan')):.1f} %.",
            "",
        ]
    return out


def maffnet_training_section(r: Result, results_dir: Path) -> list[str]:
    """benchmarks/maffnet_training.py: the epochs, then 3D / BEV AP on the test split per backend."""
    d = r.data
    train, m = d["train"], d.get("machine", {})
    data = train.get("data", {})
    out = [
        f"## MAFF-Net training: {d['card']}",
        "",
        f"`benchmarks/maffnet_training.py`, {r.when}: {m.get('cpu', '?')}, {m.get('threads', '?')} threads. "
        f"`{d['command']}`: {data.get('train_frames', '?')} training frames, validation on "
        f"{data.get('validation_frames', '?')} frames of `{data.get('validation_split', '?')}`. Training took "
        f"{_num((d.get('train_seconds') or 0) / 60)} min. JSON: {_link(r, results_dir)}.",
        "",
    ]
    classes = [k[len("AP3d_") :] for k in train["epochs"][0] if k.startswith("AP3d_")]
    rows = [
        [
            str(e["epoch"]),
            "-" if e["loss"] is None or e["loss"] != e["loss"] else f"{e['loss']:.3f}",
            *(_num(e.get(f"AP3d_{c}")) for c in classes),
            _num(e.get("mAP3d")),
            _num(e["seconds"] / 60),
            "best" if e["epoch"] == train.get("best_epoch") else "",
        ]
        for e in train["epochs"]
    ]
    out += _table(
        ["epoch", "loss", *(f"val 3D AP {c}" for c in classes), "val mAP", "min", ""],
        rows,
        ["---:"] * (len(classes) + 4) + ["---"],
    ) + [""]
    t, s0 = d["test_trained"], d["test_seeded"]
    out += [
        f"The `test` split ({t['frames']} frames, drives never trained or validated on), `radaredge eval`: 3D AP "
        "(BEV AP) per class, entire area, 11 recall positions, VoD's IoU thresholds; frames per second of "
        "each backend's frame loop.",
        "",
    ]
    backends = [("seeded, onnxruntime fp32", s0, "onnxruntime")] + [(f"trained, {b}", t, b) for b in t["ap"]]
    rows = []
    for label, rep, b in backends:
        per = rep["ap"][b]["entire_area"]
        mean3d = sum(v["3d"] for v in per.values()) / len(per)
        rows.append(
            [
                label,
                *(f"{_num(per[c]['3d'], '.2f')} ({_num(per[c]['bev'], '.2f')})" for c in per),
                _num(mean3d, ".2f"),
                _num(rep["fps"].get(b)),
            ]
        )
    names = list(t["ap"][next(iter(t["ap"]))]["entire_area"])
    out += _table(["graph", *names, "mAP 3D", "FPS"], rows, ["---"] + ["---:"] * (len(names) + 2)) + [""]
    errors = t.get("box_errors", {}).get("onnxruntime")
    if errors:
        out += [
            "Box errors of the trained fp32 graph's detections on the same frames (`radaredge eval`: each "
            "detection, in descending score, takes the nearest unmatched labelled box of its class within "
            "2 m in bird's-eye view; radar frame, metres; dz is detection minus ground truth):",
            "",
        ]
        rows = [
            [
                c,
                f"{e['matched']} / {e['ground_truth']}",
                *(_num(e[k], ".2f") for k in ("xy", "dz", "abs_dz", "abs_dl", "abs_dw", "abs_dh")),
                _num(e["heading_deg"], ".1f"),
            ]
            for c, e in errors.items()
        ]
        out += _table(
            ["class", "matched", "centre xy", "dz (bias)", "abs dz", "abs dl", "abs dw", "abs dh", "heading deg"],
            rows,
            ["---"] + ["---:"] * 8,
        ) + [""]
    return out


def _stage_metrics(rows: list[dict]) -> list[str]:
    return [k for k in rows[0] if k not in ("stage", "epoch", "loss", "seconds")]


def _with_interval(res: dict, key: str, k: int, t: float) -> str:
    """One Table I figure (%; the fine stage's gain in signed points) of a Des4Pos held-out run,
    with its bootstrap interval when recorded."""
    value = _num(res[key].get(str(k), {}).get(f"{t:g}"), "+.1f" if key == "localization_gain" else ".1f")
    low_high = res.get(key + "_interval", {}).get(str(k), {}).get(f"{t:g}")
    return value if low_high is None else f"{value} [{_num(low_high[0])}, {_num(low_high[1])}]"


def des4pos_training_section(r: Result, results_dir: Path) -> list[str]:
    """A Des4Pos training run (benchmarks/des4pos_training.py): the stages' epochs, parity on the
    trained weights, and Tables I and II on held-out cities, seeded vs trained, both backends."""
    d = r.data
    train, held = d["train"], d["heldout"]
    m, data = d.get("machine", {}), train.get("data", {})
    variant = r.stem.removesuffix("-training")
    out = [
        "## Des4Pos training" + ("" if variant == "des4pos" else f" (`{variant}`)"),
        "",
        f"`benchmarks/des4pos_training.py`, {r.when}: {m.get('cpu', '?')}, {m.get('threads', '?')} threads. "
        f"`{d['command']}`: {data.get('maps', '?')} cities, {data.get('cells', '?')} cells, "
        f"{data.get('training_poses', '?')} training and {data.get('validation_poses', '?')} validation described "
        f"poses. Training took {d['train_seconds'] / 60:.1f} min. JSON: {_link(r, results_dir)}.",
        "",
    ]
    best = train.get("stage_best", {})
    for stage in dict.fromkeys(e["stage"] for e in train["epochs"]):
        rows = [e for e in train["epochs"] if e["stage"] == stage]
        keys = _stage_metrics(rows)
        body = [
            [
                str(e["epoch"]),
                f"{e['loss']:.4f}",
                *(_num(e[k], ".2f") for k in keys),
                _num(e["seconds"] / 60),
                "kept" if e["epoch"] == best.get(stage) else "",
            ]
            for e in rows
        ]
        out += [f"Stage `{stage}`:", ""]
        out += _table(["epoch", "loss", *keys, "min", ""], body, ["---:"] * (len(keys) + 3) + ["---"]) + [""]
    verdict = lambda p: "PASSED" if p.get("passed") else "FAILED"  # noqa: E731
    par = d.get("parity", {})
    runs = [(w, b) for w in ("seeded", "trained") for b in held.get(w, {})]
    centres = any("localization_centre" in held[w][b] for w, b in runs)
    unit = (
        "% with the fine stage's positions and with the retrieved cells' centres alone (no fine stage), "
        "in brackets the 95 % percentile-bootstrap interval over the queries"
        + (
            "; the gain is the fine stage's, in points, over the same queries (a paired difference)"
            if any("localization_gain" in held[w][b] for w, b in runs)
            else ""
        )
        + ":"
        if centres
        else "%:"
    )
    out += [
        f"Parity of the exported bundle (three graphs) against the torch reference: trained weights "
        f"{verdict(par.get('trained', {}))}, seeded weights {verdict(par.get('seeded', {}))}.",
        "",
        f"Held-out cities (`{d.get('eval_command', '?')}`): {held['cells']} cells of {len(held['maps'])} "
        f"cities in one database, {held['queries']} described poses as queries. Table I, localisation "
        f"accuracy (a position within t m among the top-k cells), {unit}",
        "",
    ]
    ks = sorted({int(k) for w, b in runs for k in held[w][b]["localization"]})
    ts = sorted({float(t) for w, b in runs for k in held[w][b]["localization"].values() for t in k}, key=float)
    if centres:
        out += _table(
            ["weights", "backend", "position"] + [f"top-{k} {t:g} m" for k in ks for t in ts],
            [
                [w, b, label, *(_with_interval(held[w][b], key, k, t) for k in ks for t in ts)]
                for w, b in runs
                for key, label in (
                    ("localization", "fine stage"),
                    ("localization_centre", "cell centre"),
                    ("localization_gain", "gain"),
                )
                if key in held[w][b]
            ],
            ["---", "---", "---"] + ["---:"] * (len(ks) * len(ts)),
        ) + [""]
    else:  # files from before the cell-centre rows
        head = ["weights", "backend"] + [f"top-{k} {t:g} m" for k in ks for t in ts]
        body = [[w, b, *(_num(held[w][b]["localization"][str(k)][f"{t:g}"]) for k in ks for t in ts)] for w, b in runs]
        out += _table(head, body, ["---", "---"] + ["---:"] * (len(head) - 2)) + [""]
    out += ["Table II, cell-retrieval recall (the pose's best cell among the top k), %:", ""]
    rk = sorted({int(k) for w, b in runs for k in held[w][b]["retrieval"]})
    body = [[w, b, *(_num(held[w][b]["retrieval"][str(k)]) for k in rk)] for w, b in runs]
    out += _table(["weights", "backend"] + [f"R@{k}" for k in rk], body, ["---", "---"] + ["---:"] * len(rk)) + [""]
    return out


def _summary(r: Result) -> str:
    d = r.data
    if r.kind == "suite":
        return f"{r.when}, {', '.join(m['model'] for m in d.get('models', []))}, {d.get('runs', '?')} runs"
    if r.kind == "compare":
        graphs = d.get("graphs", [])
        return f"{r.when}, {d.get('model', '?')}: " + " vs ".join(f"`{g.get('onnx', '?')}`" for g in graphs)
    if r.kind == "bench":
        return f"{r.when}, `radaredge bench --model {d.get('model', r.stem)}`"
    if r.kind == "training":
        return f"{r.when}, `{d.get('command', '?')}`"
    return r.when


def history_section(results: list[Result], rendered: set[Path], results_dir: Path) -> list[str]:
    older = [r for r in reversed(results) if r.path not in rendered and r.kind != "other"]
    if not older:
        return []
    return (
        [
            "## History",
            "",
            "Earlier result files, newest first. They were measured on the code of their day; `git log` on a "
            "file tells what changed since.",
            "",
        ]
        + [f"- {_link(r, results_dir)}: {_summary(r)}" for r in older]
        + [""]
    )


def fleet_section(r: Result | None, results_dir: Path) -> list[str]:
    if r is None:
        return []
    d = r.data
    t, ix = d.get("throughput", {}), d.get("index", {})
    out = [
        "## Fleet scale",
        "",
        f"`benchmarks/fleet_scale.py`, {r.when}, {_machine(d)}: `radaredge run` with {t.get('graph', '?')} over "
        f"{t.get('drives', '?')} synthetic drives ({t.get('windows', '?')} windows), each engine into a fresh "
        f"directory in one run; then a place map's large index. JSON: {_link(r, results_dir)}.",
        "",
    ]
    rows = [
        [
            name,
            str(row.get("workers")),
            f"{row.get('computed_windows'):,}",
            _num(row.get("seconds")),
            _num(row.get("windows_per_second")),
        ]
        for name, row in t.get("rows", {}).items()
    ]
    out += _table(["engine", "workers", "windows", "s", "windows/s"], rows, ["---", "---:", "---:", "---:", "---:"])
    out += [
        "",
        f"Throughput 2 workers / 1 worker: {_num(t.get('ratio_2_to_1_workers'), '.2f')}x. Ray's overhead "
        f"against the plain loop (1 worker): "
        f"{_num(100 * t['ray_overhead'] if 'ray_overhead' in t else None)} %.",
        "",
    ]
    if ix:
        p = ix.get("index", {})
        kind = (
            f"IVF-PQ {p.get('nlist')} lists, {p.get('m')} x {p.get('nbits')}-bit codes, {p.get('nprobe')} probed, "
            f"shortlist {p.get('k_factor')} x k re-ranked exactly"
            if p.get("kind") == "ivfpq"
            else p.get("kind")
        )
        out += _table(
            [
                "vectors",
                "index",
                "recall@1 vs exact",
                "build s",
                "query p50 ms (2 threads)",
                "exact search ms a query (1,000 batched)",
                "index MiB",
                "vectors MiB",
            ],
            [
                [
                    f"{ix.get('vectors'):,} x {ix.get('dim')}",
                    kind,
                    _num(ix.get("recall_at_1_vs_exact"), ".3f"),
                    _num(ix.get("build_s")),
                    _num(ix.get("query_p50_ms"), ".2f"),
                    _num(ix.get("exact_query_ms"), ".1f"),
                    _num(ix.get("index_bytes", 0) / 2**20, ".0f"),
                    _num(ix.get("vectors_bytes", 0) / 2**20, ".0f"),
                ]
            ],
            ["---:", "---", "---:", "---:", "---:", "---:", "---:", "---:"],
        )
        out += [
            "",
            f"Descriptors: unit vectors around {ix.get('places', '?'):,} places, {ix.get('queries', '?')} "
            "queries that are other windows of those places; recall@1 counts a query whose first result is the "
            "exact search's. The arithmetic for 10^8 windows is in [docs/fleet.md](../docs/fleet.md).",
            "",
        ]
    return out


def _test_map(training: Result | None, backend: str) -> float | None:
    """Mean 3D AP (entire area) of ``backend`` on the test split of a MAFF-Net training result."""
    if training is None or backend not in training.data["test_trained"]["ap"]:
        return None
    per = training.data["test_trained"]["ap"][backend]["entire_area"]
    return sum(v["3d"] for v in per.values()) / len(per)


def _recall_cell(row: dict, radius: str, n: int) -> str:
    r = row[radius]
    low, high = r["interval_95"][str(n)]
    return f"{r['recall'][str(n)]:.1f} [{low:.1f}, {high:.1f}]"


def places_section(results: list[Result], results_dir: Path) -> list[str]:
    """Place recognition on the street-network test towns (benchmarks/place_recognition.py)."""
    out = []
    for r in results:
        d = r.data
        towns, m = d["towns"], d.get("machine", {})
        chance = d["chance"]
        first = next(iter(chance.values()))
        out += [
            f"## Place recognition on street-network towns: {d['card']}",
            "",
            f"`benchmarks/place_recognition.py`, {r.when}: {m.get('cpu', '?')}, {m.get('threads', '?')} threads. "
            f"`{d['command']}`. Design towns (seeds {towns['design']['seeds']}, database circuits of at least "
            f"{towns['design']['route_km']} km) were used for {towns['design']['used_for']}; test towns (seeds "
            f"{towns['test']['seeds']}, circuits of at least {towns['test']['route_km']} km) for "
            f"{towns['test']['used_for']}. "
            f"{first['5']['database_scans']} database and {first['5']['query_scans']} query scans per test town; "
            f"K = {d['frames_per_window']} frames a window. Weights: `{d['checkpoint']}`"
            + (f" (trained here in {d['train_seconds'] / 60:.1f} min)" if d.get("train_seconds") else "")
            + f". JSON: {_link(r, results_dir)}.",
            "",
            "Recall@N in % of the evaluated queries with its 95 % bootstrap interval over queries; onnxruntime "
            "for the graphs. A true positive lies within 5 m (radaredge's default) or 25 m (TransLoc4D's "
            "evaluation sets) of the query.",
            "",
        ]
        rows = [
            [
                "chance (random ranking)",
                " / ".join(f"{c['5']['recall_at_1']:.2f}" for c in chance.values()),
                "-",
                "-",
                " / ".join(f"{c['25']['recall_at_1']:.2f}" for c in chance.values()),
            ]
        ]
        labels = (
            ("no_learning", "no learning (polar occupancy)"),
            ("seeded", "seeded network, fp32"),
            ("trained_fp32", "trained, fp32"),
            ("trained_int8", "trained, int8"),
        )
        rows += [
            [label, *(_recall_cell(d["rows"][k], "5", n) for n in (1, 5, 10)), _recall_cell(d["rows"][k], "25", 1)]
            for k, label in labels
            if k in d["rows"]
        ]
        out += _table(["descriptor", "R@1 at 5 m", "R@5 at 5 m", "R@10 at 5 m", "R@1 at 25 m"], rows) + [""]
        split = [
            (label, d["rows"][k]["5"]["by_direction"])
            for k, label in labels
            if "by_direction" in d["rows"].get(k, {}).get("5", {})
        ]
        if split:
            counts = split[0][1]
            out += [
                "Recall@1 at 5 m of the queries that drive with the database at their place and of those that "
                "drive against it (heading more than 90 degrees from the nearest database window's; "
                + ", ".join(f"{counts[w]['evaluated']} {w}" for w in ("with", "against") if w in counts)
                + " queries):",
                "",
            ]
            out += _table(
                ["descriptor", "with", "against"],
                [[label, *(_direction_cell(by.get(w)) for w in ("with", "against"))] for label, by in split],
            ) + [""]
    return out


def _direction_cell(r: dict | None) -> str:
    if r is None:
        return "-"
    low, high = r["interval_95"]
    return f"{r['recall_at_1']:.1f} [{low:.1f}, {high:.1f}]"


_VARIANT_TEXT = {
    "frozen": "BatchNorm statistics estimated once from the untrained network, then fixed; neg* random",
    "reestimate": "BatchNorm statistics estimated again after every epoch",
    "window": "each window's own batch statistics while training",
    "hardest": "neg* the hardest (nearest in descriptor space) true negative",
}
_ABLATION_PARTS = {
    "full": ("yes", "yes", "yes"),
    "no-dpr": ("no", "yes", "yes"),
    "no-fa": ("yes", "no", "yes"),
    "sum": ("yes", "yes", "no (sum)"),
}


def _validation_cell(best: dict) -> str:
    low, high = best["val_R@1_interval_95"]
    return f"{best['val_R@1']:.1f} [{low:.1f}, {high:.1f}]"


def _variants_over_seeds(r: Result, results_dir: Path) -> list[str]:
    """A --seeds study of benchmarks/tdfanet_variants.py: each variant's mean ± spread over the
    seeds at the scored epoch, and whether the paper's ranking holds (paired per seed)."""
    d = r.data
    m, summary, towns = d.get("machine", {}), d.get("summary", {}), d["towns"]
    out = [
        f"## TDFANet training choices and ablations over seeds: {d['card']}, {d['recipe']['epochs']} epochs of "
        f"{d['recipe']['tuples_per_epoch']} tuples",
        "",
        f"`benchmarks/tdfanet_variants.py`, {r.when}: {m.get('cpu', '?')}, {m.get('threads', '?')} threads. "
        f"`{d['command']}`. Every variant trained once per seed ({', '.join(map(str, d['seeds']))}) with the same "
        f"recipe on the design towns (seeds {towns['design']['seeds']}) and scored at its {d['score_epoch']} "
        f"epoch; ablations on the test towns (seeds {towns['test']['seeds']}), fp32 graph. Each cell: mean ± "
        f"sample standard deviation over the seeds [95 % t-interval of the mean]. JSON: {_link(r, results_dir)}.",
        "",
    ]
    rows = [
        [name, _VARIANT_TEXT.get(name, name), str(v["val R@1"]["n"]), _spread_cell(v["val R@1"])]
        for name in d["choices"]
        if (v := summary.get(name))
    ]
    if rows:
        out += ["### Training choices (validation, design towns)", ""]
        out += _table(["variant", "what", "seeds", "val R@1"], rows, ["---", "---", "---:", "---:"]) + [""]
    figures = ("R@1 at 5 m", "R@5 at 5 m", "R@10 at 5 m", "R@1 at 25 m")
    rows = [
        [label, *_ABLATION_PARTS[label], str(v["val R@1"]["n"])] + [_spread_cell(v[f]) for f in figures]
        for label, name in d["ablations"].items()
        if (v := summary.get(name)) and all(f in v for f in figures)
    ]
    if rows:
        out += ["### Ablations (test towns, fp32 graph)", ""]
        out += _table(["variant", "DPR", "FA", "pyramid + DA", "seeds", *figures], rows, ["---"] * 4 + ["---:"] * 5) + [
            ""
        ]
    rows = [
        [label, str(len(v["seeds"])), _spread_cell(v["full_minus"]), v["paper_ranking"]]
        for label, v in d.get("ranking", {}).items()
    ]
    if rows:
        out += [
            "The paper's ranking (its Table III: the full model above each ablation), tested per seed: test "
            "R@1 at 5 m of the full model minus the ablation's, paired by seed; it holds where the interval "
            "lies above 0, is reversed where below, and is not resolved where it holds 0.",
            "",
        ]
        out += _table(["ablation", "seeds", "full - ablation", "paper's ranking"], rows) + [""]
    return out


def variants_section(results: list[Result], results_dir: Path) -> list[str]:
    """TDFANet's training choices and ablations (benchmarks/tdfanet_variants.py)."""
    out = []
    for r in results:
        d = r.data
        if "seeds" in d:
            out += _variants_over_seeds(r, results_dir)
            continue
        towns, m, variants = d["towns"], d.get("machine", {}), d["variants"]
        out += [
            f"## TDFANet training choices and ablations: {d['card']}, {d['recipe']['epochs']} epochs of "
            f"{d['recipe']['tuples_per_epoch']} tuples",
            "",
            f"`benchmarks/tdfanet_variants.py`, {r.when}: {m.get('cpu', '?')}, {m.get('threads', '?')} threads. "
            f"`{d['command']}`. Every variant is trained the same way ({d['recipe']['epochs']} epochs of "
            f"{d['recipe']['tuples_per_epoch']} tuples) on the design towns (seeds {towns['design']['seeds']}), "
            f"used for {towns['design']['used_for']}; the test towns (seeds {towns['test']['seeds']}) for "
            f"{towns['test']['used_for']}. Validation Recall@1 at 5 m is the best epoch's, with its 95 % "
            f"bootstrap interval over validation queries. JSON: {_link(r, results_dir)}.",
            "",
        ]
        rows = [
            [
                name,
                _VARIANT_TEXT.get(name, name),
                str(v["best"]["epoch"]),
                _validation_cell(v["best"]),
                f"{v['best']['val_R@5']:.1f}",
                f"{v['train_seconds'] / 60:.1f}",
            ]
            for name in d["choices"]
            if (v := variants.get(name))
        ]
        if rows:
            out += ["### Training choices (validation, design towns)", ""]
            out += _table(
                ["variant", "what", "best epoch", "val R@1", "val R@5", "train min"],
                rows,
                ["---", "---", "---:", "---:", "---:", "---:"],
            ) + [""]
        rows = [
            [
                label,
                *_ABLATION_PARTS[label],
                _validation_cell(v["best"]),
                *(_recall_cell(v["test"], "5", n) for n in (1, 5, 10)),
                _recall_cell(v["test"], "25", 1),
                *(_direction_cell(v["test"]["5"].get("by_direction", {}).get(w)) for w in ("with", "against")),
                f"{v['train_seconds'] / 60:.1f}",
            ]
            for label, name in d["ablations"].items()
            if (v := variants.get(name)) and "test" in v
        ]
        if rows:
            out += ["### Ablations (test towns, fp32 graph)", ""]
            out += [
                "Recall@1 at 5 m is also split by the query's direction: with the database at its place, "
                "and against it (heading more than 90 degrees from the nearest database window's; "
                "- where the run predates the split).",
                "",
            ]
            out += _table(
                [
                    "variant",
                    "DPR",
                    "FA",
                    "pyramid + DA",
                    "val R@1",
                    "R@1 at 5 m",
                    "R@5 at 5 m",
                    "R@10 at 5 m",
                    "R@1 at 25 m",
                    "R@1 with",
                    "R@1 against",
                    "train min",
                ],
                rows,
                ["---", "---", "---", "---"] + ["---:"] * 8,
            ) + [""]
    return out


def trained_section(results: list[Result], trainings: list[Result], results_dir: Path) -> list[str]:
    """MAFF-Net on trained weights (benchmarks/maffnet_trained.py): fp32, int8 and the worst case,
    with each card's test mAP from its training result (benchmarks/maffnet_training.py)."""
    if not results:
        return []
    by_weights = {
        t.data["checkpoint_sha256"]: t
        for t in trainings
        if "test_trained" in t.data and t.data.get("checkpoint_sha256")
    }
    overview = []
    for r in results:
        d = r.data
        row = {x["graph"]: x for x in d.get("rows", [])}
        t = by_weights.get(d.get("checkpoint_sha256"))
        overview.append(
            [
                d.get("model"),
                d.get("cpu", "-"),
                _num(row.get("fp32", {}).get("fps")),
                _num(row.get("int8", {}).get("fps")),
                _num(row.get("worst case", {}).get("fps")),
                _num(_test_map(t, "onnxruntime"), ".2f"),
                _num(_test_map(t, "onnxruntime int8"), ".2f"),
            ]
        )
    out = [
        "## MAFF-Net on trained weights",
        "",
        "Each card's trained weights on the CPU of its row (frames per second compare only between rows of one "
        "CPU): frames per second of the fp32 graph, its int8 copy and "
        "the worst case (onnxruntime, 2 threads, real frames), and mean 3D AP over Car, Pedestrian and Cyclist "
        "(entire area) on the test split of the synthetic set, from the training result of the same checkpoint "
        "(joined by its sha256; '-' where no training result names that checkpoint).",
        "",
    ]
    out += _table(["card", "CPU", "fp32 FPS", "int8 FPS", "worst-case FPS", "test mAP fp32", "test mAP int8"], overview)
    out += [
        "",
        "`benchmarks/maffnet_trained.py`: a trained checkpoint on real frames of a labelled set, onnxruntime, "
        "fp32 / int8 / worst case timed in one alternating loop. The worst case is the same weights with every "
        "class logit raised by 30, so every anchor passes the score threshold and the NMS gets "
        "`post_processing.pre_max` candidates on every frame. Candidates: anchors above the threshold per frame "
        "(what the NMS is given, before the pre_max cap).",
        "",
    ]
    for r in results:
        d = r.data
        out += [
            f"### {d.get('model')}",
            "",
            f"{_stamp(r, d)}. Weights: `{d.get('checkpoint')}` (sha256 {str(d.get('checkpoint_sha256'))[:12]}...)"
            + (f", {d['note']}" if d.get("note") else "")
            + f". Frames: {len(d.get('frames', []))} of the "
            f"`{d.get('split')}` split of `{d.get('data')}` (median {_num(d.get('points_median'), '.0f')} points), "
            f"{d.get('passes')} passes. JSON: {_link(r, results_dir)}.",
            "",
        ]
        rows = [
            [
                row["graph"],
                _num(row.get("p50_ms")),
                _num(row.get("p90_ms")),
                _num(row.get("fps")),
                _num(100 * row["nms_share"] if row.get("nms_share") is not None else None),
                f"{_num(row.get('candidates_median'), '.0f')} / {row.get('candidates_max')}",
                _num(row.get("detections_median"), ".0f"),
            ]
            for row in d.get("rows", [])
        ]
        out += _table(
            ["graph", "p50 ms", "p90 ms", "FPS", "NMS share %", "candidates median / max", "detections median"], rows
        )
        out += [""] + _stage_table({row["graph"]: row["stage_ms"] for row in d.get("rows", []) if row.get("stage_ms")})
        out += [""]
    return out


def _spread_cell(v: dict) -> str:
    """``mean ± std [low, high]`` of a :func:`seed_stats.seed_summary` (just the mean for one seed)."""
    if v["std"] is None:
        return f"{v['mean']:.1f} (1 seed)"
    low, high = v["interval"]
    return f"{v['mean']:.1f} ± {v['std']:.1f} [{low:.1f}, {high:.1f}]"


def seeds_section(results: list[Result], results_dir: Path) -> list[str]:
    """A detector's test 3D AP and speed over several training seeds (benchmarks/detection_seeds.py):
    mean ± standard deviation over seeds with the 95 % t-interval of the mean, then each seed with
    its checkpoint's sha256, its bootstrap intervals and its speed."""
    out = []
    for r in results:
        d, summary = r.data, r.data["summary"]
        classes = ("Car", "Pedestrian", "Cyclist", "mAP")
        out += [
            f"## MAFF-Net across training seeds: {d['card']}",
            "",
            f"{r.when}: {d['machine'].get('cpu')}, onnxruntime on {d['timing']['threads']} threads. "
            f"{len(d['seeds'])} runs of `{d['command']}` (SEED: the seed), scored on the `{d['split']}` "
            f"split of `{d['data']}` ({d['seeds'][0]['frames']} frames; 3D AP, VoD's protocol, entire area). "
            f"Made by `{d['score_command']}`; JSON: {_link(r, results_dir)}.",
            "",
            "Over the seeds: mean ± sample standard deviation [95 % t-interval of the mean]; median ms per frame "
            f"on {d['timing']['frames']} test frames, {d['timing']['passes']} passes:",
            "",
        ]
        rows = [
            [graph] + [_spread_cell(summary[graph][c]) for c in classes] + [_spread_cell(summary["p50_ms"][graph])]
            for graph in ("fp32", "int8")
        ]
        rows.append(["int8 - fp32"] + [_spread_cell(summary["int8 - fp32"][c]) for c in classes] + ["-"])
        out += _table(["graph", *classes, "ms"], rows)
        out += ["", "Each seed (95 % bootstrap intervals over frames; int8 - fp32 paired):", ""]
        rows = [
            [
                str(s["seed"]),
                f"`{s['checkpoint_sha256'][:12]}`",
                str(s["epoch"]),
                _ap_cell(s["scores"]["onnxruntime"]["mAP"]),
                _ap_cell(s["scores"]["onnxruntime int8"]["mAP"]),
                _ap_cell(s["int8_minus_fp32"]["mAP"]),
                f"{s['speed']['fp32']['p50_ms']:.1f} / {s['speed']['int8']['p50_ms']:.1f}",
            ]
            for s in d["seeds"]
        ]
        out += _table(
            ["seed", "checkpoint sha256", "epoch", "fp32 mAP", "int8 mAP", "int8 - fp32", "ms fp32 / int8"], rows
        )
        out += [""]
    return out


def _ms_cell(v: dict) -> str:
    """``ms ± std (FPS)`` of a seed summary of median ms per frame."""
    spread = "" if v["std"] is None else f" ± {v['std']:.1f}"
    return f"{v['mean']:.1f}{spread} ms ({1000 / v['mean']:.1f} FPS)"


def _configuration_cell(c: dict | None) -> str:
    if not c:
        return "-"
    return f"{c['voxel_size_m']} m pillars, {c['layer_nums']} x {c['num_filters']}"


def _versus_sentence(v: dict) -> str:
    """One card against the reference, in words, from the trade-off file's comparison."""
    diff = v["fp32_mAP_difference"]
    if diff["interval"] is None:
        verdict = "with fewer than 2 seeds on a side there is no interval, so the sign is not resolved"
    else:
        low, high = diff["interval"]
        where = "below" if high < 0 else "above" if low > 0 else "not resolved from"
        verdict = f"95 % Welch interval [{low:.1f}, {high:.1f}]: {where} the reference's"
    share = "" if v["mAP_share"] is None else f", {100 * v['mAP_share']:.0f} % of its mean"
    return (
        f"- `{v['card']}` against `{v['reference']}`: fp32 test mAP {diff['mean']:+.1f} points{share} "
        f"({verdict}), at {v['fp32_speedup']:.1f}x its fp32 speed."
    )


def tradeoff_lines(r: Result) -> list[str]:
    """The trade-off table (benchmarks/detection_tradeoff.py): one row per card over its seeds,
    then every card against the reference card; shared by benchmarks/README.md and
    docs/models/maffnet.md."""
    d = r.data
    out = [
        f"{r.when}: test split of `{d['data']}` (3D AP, VoD's protocol, entire area), onnxruntime on "
        f"{d['timing']['threads']} threads of an {d['machine'].get('cpu')}, median ms per frame on "
        f"{d['timing']['frames']} test frames. Over each card's training seeds: mean ± sample standard "
        "deviation [95 % t-interval of the mean]; int8 - fp32 is paired by seed.",
        "",
    ]
    rows = [
        [
            f"`{row['card']}`",
            _configuration_cell(row["configuration"]),
            str(len(row["seeds"])),
            _spread_cell(row["fp32_mAP"]),
            _spread_cell(row["int8_mAP"]),
            _spread_cell(row["int8_minus_fp32_mAP"]),
            _ms_cell(row["fp32_ms"]),
            _ms_cell(row["int8_ms"]),
        ]
        for row in d["rows"]
    ]
    out += _table(
        [
            "card",
            "pillars, backbone (blocks x channels)",
            "seeds",
            "fp32 mAP",
            "int8 mAP",
            "int8 - fp32",
            "fp32",
            "int8",
        ],
        rows,
        ["---", "---"] + ["---:"] * 6,
    )
    out += [""]
    if d["versus_reference"]:
        out += [_versus_sentence(v) for v in d["versus_reference"]]
    else:
        out += [f"`{d['reference']}` has no seed study on this set yet, so no card is compared to it."]
    out += ["", "Each row's commands (SEED: the seed; its checkpoints' sha256 are in the source file):", ""]
    out += [
        f"- `{row['card']}` ({', '.join(map(str, row['seeds']))}; {row['source']}): `{row['command']}`, "
        f"scored by `{row['score_command']}`"
        for row in d["rows"]
    ]
    return out


def tradeoff_section(r: Result | None, results_dir: Path) -> list[str]:
    """benchmarks/README.md's trade-off section, when a trade-off file exists."""
    if r is None:
        return []
    return [
        "## MAFF-Net trade-off over training seeds",
        "",
        *tradeoff_lines(r),
        "",
        f"Made by `python benchmarks/detection_tradeoff.py`; JSON: {_link(r, results_dir)}.",
        "",
    ]


def _difference_cell(d: dict) -> str:
    """An int8 - fp32 difference with its paired interval: a class's 3D AP ({3d, 3d_interval})
    or a Recall@N ({value, interval})."""
    value, (low, high) = (d["3d"], d["3d_interval"]) if "3d" in d else (d["value"], d["interval"])
    return f"{value:+.2f} [{low:+.2f}, {high:+.2f}]"


def _method_label(method: str, row: dict) -> str:
    """A calibration method's name; a ``--qat`` fine-tune's row names its weights and says that
    its int8 graph is compared with the original weights' fp32 graph; the search's row names the
    layers it kept in fp32 and the data it chose them on."""
    if "search" in row:
        kept = ", ".join(f"`{m}`" for m in row["keep_fp32"]) or "none"
        return f"`quantize --search` from every layer int8 (kept fp32: {kept}; chosen on {row['search']['data']})"
    if "qat_fp32" not in row:
        return f"`{method}`"
    return f"`train --qat` (weights `{row['checkpoint_sha256'][:12]}`; int8 vs the original fp32)"


def _method_rows(card: str, methods: dict, columns: list[str]) -> list[list[str]]:
    """A row per calibration method (int8 - fp32 per column, verdict, command); a --qat row is
    followed by its control's two rows when it has one."""

    def row(label: str, differences: dict, verdict: str, command: str) -> list[str]:
        return [label] + [_difference_cell(differences[c]) for c in columns] + [verdict, f"`{command}`"]

    rows = []
    for m, v in methods.items():
        rows.append(row(_method_label(m, v), v["int8_minus_fp32"], v["verdict"], v["export_command"]))
        if "control" in v:
            c = v["control"]
            sha = c["checkpoint_sha256"][:12]
            label = f"control: fp32 fine-tune without `--qat` (weights `{sha}`; fp32 vs the original fp32)"
            command = f"radaredge export --model {card} --checkpoint CONTROL_WEIGHTS"
            rows.append(row(label, c["fp32_minus_original_fp32"], "(fp32)", command))
            label = "`train --qat` int8 vs the control's fp32"
            rows.append(row(label, c["qat_int8_minus_control_fp32"], c["verdict"], v["export_command"]))
    return rows


def _recall_score_cell(scores: dict, n: str) -> str:
    """Recall@``n`` [95 % interval] of a place_scores entry ({recall, recall_interval})."""
    low, high = scores["recall_interval"][n]
    return f"{scores['recall'][n]:.1f} [{low:.1f}, {high:.1f}]"


def _int8_places_lines(r: Result) -> list[str]:
    """An int8-methods file of a place recogniser: fp32 and no-learning Recall@N, then every
    method's int8 - fp32 Recall@N (paired 95 % interval over queries) and verdict."""
    d = r.data
    methods = d["methods"]
    first = next(iter(methods.values()))
    ns = list(first["fp32"]["recall"])
    out = [
        f"`{d['card']}`, weights `{d['checkpoint_sha256'][:12]}`, queries `{d['queries']}` against the database "
        f"`{d['database']}` ({first['queries']} evaluated queries, a true positive within {d['radius_m']:g} m; "
        f"{r.when}). fp32 Recall@N: "
        + ", ".join(f"@{n} {_recall_score_cell(first['fp32'], n)}" for n in ns)
        + f"; no learning (polar occupancy) @1 {_recall_score_cell(d['no_learning'], ns[0])}. int8 - fp32 in Recall@N "
        f"points, paired over queries [95 % interval]; budget -{d['budget_recall_points']:g} on Recall@1 (within: "
        "above it; meets: its interval not wholly below it):",
        "",
    ]
    columns = [f"R@{n}" for n in ns]
    renamed = {m: _renamed_recall_keys(v) for m, v in methods.items()}
    rows = _method_rows(d["card"], renamed, columns)
    out += _table(["method", *columns, "verdict", "command"], rows, ["---"] + ["---:"] * len(ns) + ["---", "---"])
    out += ["", *_int8_methods_made_by(d), ""]
    return out


def _renamed_recall_keys(row: dict) -> dict:
    """``row`` with its Recall@N differences keyed R@N (the table's columns), its control's too."""

    def keyed(differences: dict) -> dict:
        return {f"R@{n}": v for n, v in differences.items()}

    out = {**row, "int8_minus_fp32": keyed(row["int8_minus_fp32"])}
    if "control" in row:
        c = row["control"]
        out["control"] = {
            **c,
            "fp32_minus_original_fp32": keyed(c["fp32_minus_original_fp32"]),
            "qat_int8_minus_control_fp32": keyed(c["qat_int8_minus_control_fp32"]),
        }
    return out


def _int8_methods_made_by(d: dict) -> list[str]:
    """The commands behind an int8-methods file: the run that made it and each run added to it
    with ``--into`` (its rows, date and CPU)."""
    out = [f"Made by `{d['command']}`."]
    for run in d.get("added", []):
        rows = ", ".join(f"`{m}`" for m in run["methods"])
        machine = run["machine"]
        isa = machine.get("int8_dot_product")
        cpu = machine["cpu"] + ("" if isa is None else f" ({_int8_dot_product_text(isa)})")
        plural = "s" if len(run["methods"]) > 1 else ""
        out.append(f"The {rows} row{plural} added by `{run['command']}` ({run['date']}, {cpu}).")
    return out


def int8_methods_lines(r: Result) -> list[str]:
    """One int8-methods file (benchmarks/int8_methods.py): the fp32 graph's AP, then every
    calibration method's int8 - fp32 3D AP per class (paired 95 % interval) and verdict; a place
    recogniser's file in Recall@N (:func:`_int8_places_lines`)."""
    d = r.data
    if d.get("task") == "place recognition":
        return _int8_places_lines(r)
    methods = d["methods"]
    fp32 = next(iter(methods.values()))["fp32"]
    classes = [c for c in ("Car", "Pedestrian", "Cyclist", "mAP") if c in fp32]
    out = [
        f"`{d['card']}`, weights `{d['checkpoint_sha256'][:12]}`, {d['split']} split of `{d['data']}` "
        f"({next(iter(methods.values()))['frames']} frames; {r.when}). fp32 3D AP: "
        + ", ".join(f"{c} {_ap_cell(fp32[c])}" for c in classes)
        + f". int8 - fp32 in 3D AP points, paired over frames [95 % interval]; budget -{d['budget_ap_points']:g} "
        "per class (within: every class above it; meets: no class's interval wholly below it):",
        "",
    ]
    rows = _method_rows(d["card"], methods, classes)
    out += _table(["method", *classes, "verdict", "command"], rows, ["---"] + ["---:"] * len(classes) + ["---", "---"])
    out += ["", *_int8_methods_made_by(d), ""]
    return out


def int8_methods_section(results: list[Result], results_dir: Path) -> list[str]:
    """benchmarks/README.md's calibration-method comparisons, one per card and split."""
    if not results:
        return []
    out = ["## int8 calibration methods on trained weights", ""]
    for r in results:
        out += int8_methods_lines(r)[:-1] + [f"JSON: {_link(r, results_dir)}.", ""]
    return out


def _node_cell(node: list) -> str:
    name, op, ms = node
    return f"{op} `{name[:32]}` {ms:.1f}"


def int8_speed_lines(r: Result) -> list[str]:
    """One int8-speed file (benchmarks/int8_speed.py): per zoo card, fp32 and int8 median ms and
    their ratio (onnxruntime, OpenVINO when timed), then where the kernel time goes in each."""
    d = r.data
    m = d["machine"]
    out = [
        f"{r.when}: {m['cpu']} ({_int8_dot_product_text(m.get('int8_dot_product'))}), {m['threads']} threads, "
        f"median of {d['runs']} runs per backend (backends "
        "alternating, one run); the zoo's weights; kernel ms per run from onnxruntime's profiler.",
        "",
    ]
    rows = []
    for name, c in d["cards"].items():
        ms = c["median_ms"]
        ov = c.get("openvino_int8_vs_fp32")
        rows.append(
            [
                f"`{name}`",
                f"`{c['checkpoint_sha256'][:12]}`",
                _num(ms.get("onnxruntime")),
                _num(ms.get("onnxruntime int8")),
                f"{c['int8_vs_fp32']:.2f}x" if c.get("int8_vs_fp32") else "-",
                f"{ov:.2f}x" if ov else "-",
                _node_cell(c["fp32_heaviest_nodes"][0]),
                _node_cell(c["int8_heaviest_nodes"][0]),
            ]
        )
    out += _table(
        ["card", "weights", "fp32 ms", "int8 ms", "int8 / fp32 speed-up", "OpenVINO int8 / fp32",
         "heaviest fp32 node (ms)", "heaviest int8 node (ms)"],
        rows,
        ["---", "---", "---:", "---:", "---:", "---:", "---", "---"],
    )  # fmt: skip
    out.append("")
    for name, c in d["cards"].items():
        conv = ("Conv", "QLinearConv")
        fp32_conv = sum(v for k, v in c["fp32_ops_ms"].items() if k in conv)
        int8_conv = sum(v for k, v in c["int8_ops_ms"].items() if k in conv)
        qdq = [f"{k} {v:.1f} ms" for k, v in c["int8_ops_ms"].items() if k in ("QuantizeLinear", "DequantizeLinear")]
        out.append(
            f"- `{name}`: convolutions {fp32_conv:.1f} ms fp32, {int8_conv:.1f} ms int8 (QLinearConv and the "
            f"convs kept fp32); {', '.join(qdq) if qdq else 'no QuantizeLinear or DequantizeLinear'} among the "
            f"top {len(c['int8_ops_ms'])} int8 ops; top fp32 ops "
            + ", ".join(f"{k} {v:.1f}" for k, v in list(c["fp32_ops_ms"].items())[:4])
            + "; top int8 ops "
            + ", ".join(f"{k} {v:.1f}" for k, v in list(c["int8_ops_ms"].items())[:4])
            + "."
        )
    out += ["", f"Made by `{d['command']}`.", ""]
    return out


def int8_speed_section(rs: list[Result], results_dir: Path) -> list[str]:
    """benchmarks/README.md's int8 speed on the zoo's weights: the newest study of each kind of CPU."""
    if not rs:
        return []
    out = ["## int8 speed on the zoo's weights", ""]
    for r in rs:
        out += [*int8_speed_lines(r)[:-1], f"JSON: {_link(r, results_dir)}.", ""]
    return out


def _int8_dot_product_text(names: list[str] | None) -> str:
    """A CPU's int8 dot-product instruction sets (radaredge.benchmarking.timing.int8_dot_product)."""
    if names is None:
        return "int8 dot-product instructions not known"
    return f"int8 dot product: {', '.join(names)}" if names else "no int8 dot-product instructions"


class GeneratedBlock:
    """A table that render.py writes into a hand-written page of docs/, between two marker lines
    (``<!-- NAME: generated by benchmarks/render.py -->`` and ``<!-- end of the generated NAME -->``),
    from the newest results of one kind; main() rewrites it, tests/test_docs.py checks it."""

    def __init__(self, page: str, name: str, kind: str, lines: Callable[[list[Result]], list[str]]):
        self.page = page  # under docs/
        self.name = name
        self.kind = kind  # the results it is made of (:func:`_kind`)
        self.lines = lines  # the newest result of each key, oldest key first -> the block's lines

    @property
    def begin(self) -> str:
        return f"<!-- {self.name}: generated by benchmarks/render.py -->"

    @property
    def end(self) -> str:
        return f"<!-- end of the generated {self.name} -->"

    def fill(self, text: str, results: list[Result]) -> str:
        """``text`` with the block between the markers made from ``results`` (unchanged when there
        are none of this kind). ValueError when the markers are missing or out of order."""
        newest = newest_by_key(results, self.kind)
        if not newest:
            return text
        begin, end = text.find(self.begin), text.find(self.end)
        if begin < 0 or end < begin:
            raise ValueError(f"docs/{self.page}: expected the lines {self.begin!r} and {self.end!r}")
        return text[: begin + len(self.begin)] + "\n" + "\n".join(self.lines(newest)) + "\n" + text[end:]


GENERATED = (
    GeneratedBlock("models/maffnet.md", "trade-off", "tradeoff", lambda rs: tradeoff_lines(rs[-1])),
    GeneratedBlock(
        "quantization.md", "int8 methods", "int8-methods", lambda rs: [x for r in rs for x in int8_methods_lines(r)]
    ),
    GeneratedBlock(
        "quantization.md", "int8 speed", "int8-speed", lambda rs: [x for r in rs for x in int8_speed_lines(r)]
    ),
)


def _ap_cell(v: dict | None) -> str:
    if v is None:
        return "-"
    low, high = v["3d_interval"]
    return f"{v['3d']:.1f} [{low:.1f}, {high:.1f}]"


def _recall_cells(v: dict) -> list[str]:
    return [
        f"{v['recall'][n]:.1f} [{v['recall_interval'][n][0]:.1f}, {v['recall_interval'][n][1]:.1f}]"
        for n in ("1", "5", "10")
    ]


def _places_town(test: dict) -> str:
    """The make-benchmark command of a TDFANet zoo entry's test town, its queries and chance Recall@1."""
    if test.get("layout") == "network":
        town = f"`make-benchmark --layout network --route-km {test['route_km']:g} --seed {test['seed']}`"
    else:
        town = f"`make-benchmark --drives {test['drives']} --frames {test['frames']} --seed {test['seed']}`"
    chance = f", chance R@1 {test['chance_recall_1']:.2f} %" if "chance_recall_1" in test else ""
    return f"{town} ({test['queries']} queries{chance})"


def _with_seeded(entry: dict) -> dict:
    """An entry's test scores per backend, then the seeded (untrained) network's where recorded."""
    seeded = {"seeded weights, onnxruntime": entry["test"]["seeded"]} if entry["test"].get("seeded") else {}
    return {**entry["test"]["scores"], **seeded}


def zoo_section(zoo_dir: Path) -> list[str]:
    """The weights zoo (zoo/<card>/entry.json, benchmarks/zoo.py): each entry's task metric on
    held-out data with its 95 % interval, torch reference / fp32 graph / int8 graph, its weights
    and the command that made them."""
    entries = [json.loads(p.read_text()) for p in sorted(Path(zoo_dir).glob("*/entry.json"))]
    if not entries:
        return []
    out = [
        "## The weights zoo",
        "",
        "Trained weights in the repository (`zoo/<card>/`, written by `benchmarks/zoo.py`; synthetic scenes only), "
        "each metric with its 95 % bootstrap interval; `make test` re-scores each export on its regression set "
        "(tests/test_zoo.py).",
        "",
    ]
    detectors = [e for e in entries if "mAP" in next(iter(e["test"]["scores"].values()))]
    places = [e for e in entries if e not in detectors]
    if detectors:
        out += [
            "3D AP (entire area, VoD's protocol) on the test split of the synthetic detection set they trained "
            "on (over frames):",
            "",
        ]
        rows = [
            [e.get("name", e["card"]), f"`{e['weights_sha256'][:12]}`", str(e["epoch"]), backend]
            + [_ap_cell(row.get(c)) for c in ("Car", "Pedestrian", "Cyclist", "mAP")]
            for e in detectors
            for backend, row in _with_seeded(e).items()
        ]
        out += _table(["entry", "weights sha256", "epoch", "backend", "Car", "Pedestrian", "Cyclist", "mAP"], rows)
        out += [""]
    if places:
        out += [
            "Recall@N (%, 5 m, over queries) on each entry's held-out test town, beside the no-learning "
            "polar_occupancy descriptor and the seeded (untrained) network:",
            "",
        ]
        rows = [
            [e["card"], f"`{e['weights_sha256'][:12]}`", str(e["epoch"]), backend] + _recall_cells(row)
            for e in places
            for backend, row in _with_seeded(e).items()
        ]
        out += _table(["card", "weights sha256", "epoch", "backend", "R@1", "R@5", "R@10"], rows)
        out += [""]
    for e in entries:
        reg, machine = e["regression"], e["machine"]
        where = f"{machine.get('cpu')}, {machine.get('threads')} threads"
        if e in detectors:
            regression = (
                f"`make-benchmark --task detection --version {reg['version']} --drives {reg['drives']} "
                f"--frames {reg['frames']} --seed {reg['seed']}`, split {reg['split']}, fp32 mAP "
                f"{_ap_cell(reg['scores']['mAP'])}"
            )
        else:
            regression = (
                f"`make-benchmark --drives {reg['drives']} --frames {reg['frames']} --seed {reg['seed']}`, "
                f"fp32 R@1 {_recall_cells(reg['scores'])[0]}"
            )
            regression = f"{regression}. Test town: {_places_town(e['test'])}"
        out += [
            f"- {e.get('name', e['card'])}: `{e['command']}` (training seed {e['training_seed']}; scored on {where}). "
            f"Regression set: {regression}."
        ]
    return out + [""]


def render(results_dir: Path = RESULTS_DIR, zoo_dir: Path = ZOO_DIR) -> str:
    """The whole of benchmarks/README.md, built from the JSON files in ``results_dir``."""
    results_dir = Path(results_dir)
    results = load(results_dir)
    suites = newest_by_key(results, "suite")
    benches = newest_by_key(results, "bench")
    compares = newest_by_key(results, "compare")
    capacity = (newest_by_key(results, "capacity") or [None])[-1]
    cfa = (newest_by_key(results, "cfa") or [None])[-1]
    train_step = (newest_by_key(results, "train-step") or [None])[-1]
    fleet = (newest_by_key(results, "fleet") or [None])[-1]
    trainings = newest_by_key(results, "training")
    trained = newest_by_key(results, "trained")
    seeds = newest_by_key(results, "seeds")
    tradeoff = (newest_by_key(results, "tradeoff") or [None])[-1]
    int8_methods = newest_by_key(results, "int8-methods")
    places = newest_by_key(results, "places")
    variants = newest_by_key(results, "variants")
    real = (newest_by_key(results, "real") or [None])[-1]
    int8_speeds = newest_by_key(results, "int8-speed")
    out = [
        "# Benchmarks",
        "",
        "Generated by `python benchmarks/render.py` from the JSON files in [results/](results/); do not edit "
        "it by hand. `make bench` writes a new `suite-<date>.json` and regenerates this page; the other "
        "studies write their own files (see each section), after which `python benchmarks/render.py` "
        "rewrites the page. The speed suite times the zoo's trained weights for the cards the zoo holds (NMS "
        "and proposals depend on the scores) and seeded weights for the others; its table says which. The "
        "speed figures measure what the deployed pipeline costs, not a trained model's accuracy; the "
        "training section measures that.",
        "",
    ]
    if suites:
        out += suite_section(suites[-1], results_dir)
    out += bench_section(benches, results_dir)
    out += compare_section(compares, results_dir)
    out += capacity_section(capacity, results_dir)
    out += cfa_section(cfa, results_dir)
    out += real_data_section(real, results_dir)
    out += fleet_section(fleet, results_dir)
    out += zoo_section(zoo_dir)
    out += tradeoff_section(tradeoff, results_dir)
    out += int8_methods_section(int8_methods, results_dir)
    out += int8_speed_section(int8_speeds, results_dir)
    out += seeds_section(seeds, results_dir)
    out += trained_section(trained, trainings, results_dir)
    out += places_section(places, results_dir)
    out += variants_section(variants, results_dir)
    out += training_section(trainings, results_dir)
    out += train_step_section(train_step, results_dir)
    shown = suites + benches + compares + trainings + trained + seeds + places + variants + int8_methods + int8_speeds
    rendered = {r.path for r in shown} | {
        r.path for r in (capacity, cfa, real, fleet, train_step, tradeoff) if r is not None
    }
    out += history_section(results, rendered, results_dir)
    others = [r for r in results if r.kind == "other"]
    if others:
        out += ["## Other files", ""] + [f"- {_link(r, results_dir)}" for r in others] + [""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    README.write_text(render(RESULTS_DIR))
    print(f"wrote {README}")
    results = load(RESULTS_DIR)
    for block in GENERATED:
        page = DOCS / block.page
        page.write_text(block.fill(page.read_text(), results))
        print(f"wrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
