"""The ``bench`` verb: every backend of a model timed in one run on THREADS cores, one row each.

By default each graph's whole pipeline is timed in the torch reference, the torch export
formulation, onnxruntime fp32, onnxruntime int8 (when an int8 copy exists) and OpenVINO (when
installed); a model may time something else through its entry in
:data:`radaredge.benchmarking.tasks.BENCH_TASKS` (Des4Pos: queries and cell encoding). A backend that
fails is a row with status ``error``, not an abort. Beside the tables: the onnxruntime per-stage split and top ops
from a separately profiled session, the peak memory of a numpy + onnxruntime process per graph,
and OpenVINO's largest output difference from onnxruntime.
"""

from __future__ import annotations

import datetime as _dt
import shutil
import statistics
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import onnx
import torch

from .. import artifacts, atomic
from .. import runtime as rt
from ..cards import ModelCard
from ..errors import ConfigError
from ..exporting.graphs import write_export
from ..exporting.quantize import Int8Options, make_int8_copies
from ..models.spec import BenchTask
from ..runtime.openvino import openvino_installed
from ..runtime.runners import lazy_runner
from .profiling import onnxruntime_peak_rss_mb, profile_runs, stage_times_from_profile, top_nodes, top_ops
from .timing import (
    BackendResult,
    benchmark,
    cpu_name,
    format_differences,
    int8_dot_product,
    int8_dot_product_text,
    output_differences,
    pinned,
    results_table,
)


@dataclass(frozen=True)
class BenchOptions:
    """What a model's bench tasks (:mod:`radaredge.benchmarking.tasks`) are told: threads, timed runs,
    warm-up runs, whether to time the torch reference, whether to add OpenVINO (None: when
    installed), each graph's int8 copy, and where progress lines go."""

    threads: int = 2
    runs: int = 20
    warmup: int = 3
    reference: bool = True
    openvino: bool | None = None
    int8: dict = field(default_factory=dict)
    log: Callable[[str], None] = lambda line: None


@dataclass
class TaskResult:
    """One timed table: its rows (one per backend) and the ratios read from them."""

    name: str
    title: str
    rows: list[BackendResult]
    baseline: str
    items_per_case: int | None = None
    item_unit: str = ""
    facts: dict = field(default_factory=dict)

    def row(self, backend: str) -> BackendResult | None:
        return next((r for r in self.rows if r.backend == backend and r), None)

    @property
    def onnxruntime_speedup(self) -> dict[str, float]:
        """onnxruntime p50 speed-up over each torch backend."""
        ort = self.row("onnxruntime")
        return {r.backend: r.p50_ms / ort.p50_ms for r in self.rows if r and ort and r.backend.startswith("torch")}

    @property
    def int8_vs_fp32(self) -> float | None:
        ort, int8 = self.row("onnxruntime"), self.row("onnxruntime int8")
        return ort.p50_ms / int8.p50_ms if ort and int8 else None

    @property
    def openvino_vs_onnxruntime(self) -> float | None:
        ort, ov = self.row("onnxruntime"), self.row("openvino")
        return ort.p50_ms / ov.p50_ms if ort and ov else None

    def to_dict(self) -> dict:
        return {
            "title": self.title,
            "baseline": self.baseline,
            "rows": [asdict(r) for r in self.rows],
            "onnxruntime_speedup": self.onnxruntime_speedup,
            "int8_vs_fp32": self.int8_vs_fp32,
            "openvino_vs_onnxruntime": self.openvino_vs_onnxruntime,
            **({"items_per_case": self.items_per_case, "item_unit": self.item_unit} if self.items_per_case else {}),
            **self.facts,
        }


@dataclass
class GraphExtras:
    """Per graph: stage split (ms), top onnxruntime ops and nodes (kernel ms per run) of the graph
    and of its int8 copy when one is timed, peak RSS (MiB) of an onnxruntime-only process,
    OpenVINO's largest output difference from onnxruntime."""

    stage_ms: dict | None = None
    top_ops: list | None = None
    top_nodes: list | None = None
    int8_top_ops: list | None = None
    int8_top_nodes: list | None = None
    peak_rss_mib: float | None = None
    openvino_max_abs: dict | None = None
    profiled_runs: int = 0


@dataclass
class BenchReport:
    """A whole ``bench`` run; true when every backend ran."""

    model: str
    threads: int
    cores: list | None
    cpu: str
    runs: int
    date: str
    tasks: dict[str, TaskResult] = field(default_factory=dict)
    graphs: dict[str, GraphExtras] = field(default_factory=dict)
    int8_dot_product: list[str] | None = None  # the CPU's (timing.int8_dot_product; None: not known)

    def __bool__(self) -> bool:
        return all(r for t in self.tasks.values() for r in t.rows)

    def save(self, path: str | Path) -> Path:
        """Write :meth:`to_dict` as JSON to ``path`` (parents created); return it."""
        return atomic.write_json(path, self.to_dict())

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "threads": self.threads,
            "cores": self.cores,
            "cpu": self.cpu,
            "int8_dot_product": self.int8_dot_product,
            "runs": self.runs,
            "date": self.date,
            "tasks": {n: t.to_dict() for n, t in self.tasks.items()},
            "graphs": {
                n: {
                    "stage_ms": g.stage_ms,
                    "top_ops": g.top_ops,
                    "top_nodes": g.top_nodes,
                    "int8_top_ops": g.int8_top_ops,
                    "int8_top_nodes": g.int8_top_nodes,
                    "onnxruntime_peak_rss_mib": g.peak_rss_mib,
                    "openvino_vs_onnxruntime_max_abs": g.openvino_max_abs,
                }
                for n, g in self.graphs.items()
            },
        }

    def lines(self) -> list[str]:
        out = [
            f"{self.model} on {self.threads} thread(s), cores {self.cores}, {self.cpu} "
            f"({int8_dot_product_text(self.int8_dot_product)}), {self.runs} runs, {self.date}"
        ]
        for t in self.tasks.values():
            if t.title:
                out.append(t.title + ":")
            out.append(results_table(t.rows, t.baseline, t.items_per_case, t.item_unit))
            if t.onnxruntime_speedup:
                out.append(
                    "onnxruntime speed-up: " + ", ".join(f"{v:.2f}x vs {k}" for k, v in t.onnxruntime_speedup.items())
                )
            if t.int8_vs_fp32 is not None:
                out.append(
                    f"int8 vs fp32: {t.int8_vs_fp32:.2f}x"
                    + ("  (int8 is SLOWER than fp32 on this CPU)" if t.int8_vs_fp32 < 1 else "")
                )
            extras = self.graphs.get(t.name)
            if t.openvino_vs_onnxruntime is not None and extras and extras.openvino_max_abs is not None:
                out.append(
                    f"openvino vs onnxruntime: {t.openvino_vs_onnxruntime:.2f}x; largest output difference on "
                    f"the bench inputs: {format_differences(extras.openvino_max_abs)} "
                    f"(`radaredge parity-check --runtime openvino` checks it against the reference)"
                )
        for name, g in self.graphs.items():
            label = f"{name}: " if len(self.graphs) > 1 else ""
            if g.stage_ms:
                names = list(dict.fromkeys(k for row in g.stage_ms.values() for k in row))
                out.append(
                    f"{label}per-stage ms (torch: median; onnxruntime: mean from its profiler): " + " | ".join(names)
                )
                for backend, row in g.stage_ms.items():
                    out.append(
                        f"  {backend:<16}" + "".join(f"{row[k]:>14.1f}" if k in row else f"{'-':>14}" for k in names)
                    )
            if g.peak_rss_mib is not None:
                out.append(
                    f"{label}onnxruntime peak RSS: {g.peak_rss_mib:.0f} MiB (a separate numpy + onnxruntime "
                    f"process running the bench inputs once)"
                )
            for kind, ops, nodes in (("", g.top_ops, g.top_nodes), ("int8 copy ", g.int8_top_ops, g.int8_top_nodes)):
                if ops:
                    out.append(
                        f"{label}{kind}onnxruntime top ops (kernel ms per run, from {g.profiled_runs} runs in a "
                        "separately profiled session; the profiler slows small ops):"
                    )
                    out += [f"  {op:<24}{ms:10.1f}" for op, ms in ops]
                if nodes:
                    out.append(f"{label}{kind}heaviest nodes (kernel ms per run):")
                    out += [f"  {node[:48]:<50}{op:<16}{ms:8.1f}" for node, op, ms in nodes]
        return out


BENCH_CASES, BENCH_SEED = 4, 1  # the inputs every backend is timed on: 4 synthetic cases, seed 1


def pipeline_backends(
    card: ModelCard, graph, module, onnx_path, options: BenchOptions, int8_path=None, openvino: bool = False
) -> dict[str, Callable]:
    """name -> fn(feeds) running one graph's pipeline: the torch reference (``options.reference``),
    the torch export formulation, onnxruntime fp32, onnxruntime on ``int8_path`` and, with
    ``openvino``, the same graph(s) in OpenVINO's CPU plugin. The sessions are never profiled
    (onnxruntime's profiler costs time in every node); profiles come from a session of their own.
    Graphs load on their first run, so one that fails to load is a failed row."""

    def torch_export(feeds):
        with torch.no_grad():
            graph.run_export(module, {k: torch.from_numpy(v) for k, v in feeds.items()}, None)

    def torch_reference(feeds):
        with torch.no_grad():
            graph.run_reference(module, feeds)

    backends = {}
    if options.reference:
        backends["torch reference"] = torch_reference
    backends["torch export"] = torch_export
    backends["onnxruntime"] = lazy_runner(onnx_path, "onnxruntime", options.threads)
    if int8_path is not None:
        backends["onnxruntime int8"] = lazy_runner(int8_path, "onnxruntime", options.threads)
    if openvino:
        backends["openvino"] = lazy_runner(onnx_path, "openvino", options.threads)
        if int8_path is not None:
            backends["openvino int8"] = lazy_runner(int8_path, "openvino", options.threads)
    return backends


def default_tasks(card: ModelCard, spec, model, paths: dict[str, Path], options: BenchOptions) -> list[BenchTask]:
    """One task per graph: its pipeline in every backend (:func:`pipeline_backends`) on
    :data:`BENCH_CASES` synthetic cases."""
    openvino = openvino_installed() if options.openvino is None else options.openvino
    tasks = []
    for g in spec.graphs:
        cases = [feeds for _, feeds in g.make_cases(card, BENCH_CASES, BENCH_SEED)]
        backends = pipeline_backends(
            card, g, g.module(model), paths[g.name], options, options.int8.get(g.name), openvino
        )
        tasks.append(
            BenchTask(
                g.name,
                "" if len(spec.graphs) == 1 else f"{g.name}, {options.runs} runs",
                backends,
                cases,
                options.runs,
                options.warmup,
                baseline="torch reference" if options.reference else "torch export",
            )
        )
    return tasks


def _stage_ms(graph, module, cases, n: int, reference: bool, onnx_path, profile) -> dict | None:
    """Median ms per pipeline stage over ``n`` runs in torch (export and reference formulations)
    and, when the graph names its stages inside onnxruntime, the mean ms per stage from
    ``profile`` (the events of ``n`` profiled runs)."""
    if graph.stage_times is None:
        return None
    out = {}
    for label, ref in (("torch export", False), ("torch reference", True)):
        if ref and not reference:
            continue
        laps = [graph.stage_times(module, cases[i % len(cases)], ref) for i in range(n)]
        out[label] = {k: statistics.median(lap[k] for lap in laps) * 1e3 for k in laps[0]}
    if graph.onnx_stages and profile is not None:
        out["onnxruntime"] = stage_times_from_profile(
            profile,
            onnx.load(str(onnx_path), load_external_data=False),
            list(graph.onnx_stages),
            graph.onnx_post_outputs,
            n,
        )
    return out


def time_model(
    card: ModelCard,
    spec,
    model,
    onnx: str | Path | None,
    options: BenchOptions,
    int8: str | Path | bool | None = None,
    profile: bool = False,
    progress: Callable[[str], Callable] | None = None,
) -> BenchReport:
    """Time every backend of ``card``'s ``model`` (built from ``spec``) with ``options``: the
    process pinned to ``options.threads`` cores while it runs (restored afterwards), backends
    alternating every run. ``onnx`` (the bundle, default the export path) is exported first when
    missing. Each graph's int8 copy beside it is timed too when it exists; ``int8=True`` writes
    the copies first when missing (the model's int8 policy), and a path names one graph's int8
    copy (:func:`int8_copies`). ``profile`` adds onnxruntime's top ops and heaviest nodes, of the
    int8 copies too; the per-stage split is added for graphs that name their stages. The
    arguments are checked by
    :func:`radaredge.api.bench`, the verb that calls this."""
    say = options.log
    names = tuple(g.name for g in spec.graphs)
    bundle = artifacts.Bundle(Path(onnx), names) if onnx is not None else artifacts.Bundle.default(card.name, names)
    paths = bundle.graph_files()
    if not all(p.exists() for p in paths.values()):
        say(f"{bundle.path} missing: exporting it first")
        write_export(card, spec, model, bundle)
    for p in paths.values():  # a file that is no export of this card is bad input, not a failed backend
        exported = rt.load(p, threads=1)
        if exported.card.name != card.name:
            raise ConfigError(
                f"{p} is an export of card {exported.card.name!r}, not {card.name!r}; pass the "
                f"--model/--config it was exported with"
            )
    options = replace(options, int8=int8_copies(card, spec, paths, int8, say))
    with pinned(options.threads) as cores:
        return _timed_report(card, spec, model, paths, options, profile, progress, cores)


def _timed_report(card, spec, model, paths, options: BenchOptions, profile, progress, cores) -> BenchReport:
    tasks = (
        spec.bench_tasks(card, model, paths, options)
        if spec.bench_tasks is not None
        else default_tasks(card, spec, model, paths, options)
    )
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    report = BenchReport(
        card.name, options.threads, cores, cpu_name(), options.runs, stamp, int8_dot_product=int8_dot_product()
    )
    for t in tasks:
        rows = benchmark(
            t.backends, t.cases, t.runs, t.warmup, progress=progress(f"bench {t.name}") if progress else None
        )
        report.tasks[t.name] = TaskResult(t.name, t.title, rows, t.baseline, t.items_per_case, t.item_unit, t.facts)
    n_profiled = max(3, min(options.runs, 10))
    for g in spec.graphs:
        task = next((t for t in tasks if t.name == g.name), None)  # the graph's own pipeline task
        cases = task.cases if task is not None else [feeds for _, feeds in g.make_cases(card, BENCH_CASES, BENCH_SEED)]
        extras = GraphExtras(profiled_runs=n_profiled)
        rows = report.tasks[g.name].rows if g.name in report.tasks else []
        if sum(1 for r in rows if r and r.backend in ("openvino", "onnxruntime")) == 2:
            extras.openvino_max_abs = output_differences(task.backends["openvino"], task.backends["onnxruntime"], cases)
        # one profiled session serves the stage split and --profile: runs of its own, never timed
        wants = profile or (g.stage_times is not None and bool(g.onnx_stages))
        events = profile_runs(paths[g.name], cases, options.threads, n_profiled) if wants else None
        extras.stage_ms = _stage_ms(g, g.module(model), cases, n_profiled, options.reference, paths[g.name], events)
        extras.peak_rss_mib = onnxruntime_peak_rss_mb(paths[g.name], cases, options.threads)
        if profile:
            extras.top_ops, extras.top_nodes = top_ops(events, runs=n_profiled), top_nodes(events, runs=n_profiled)
            if g.name in (options.int8 or {}):
                int8_events = profile_runs(options.int8[g.name], cases, options.threads, n_profiled)
                extras.int8_top_ops = top_ops(int8_events, runs=n_profiled)
                extras.int8_top_nodes = top_nodes(int8_events, runs=n_profiled)
        report.graphs[g.name] = extras
    return report


def require_int8_copy(int8_path: Path, fp32) -> None:
    """ConfigError unless ``int8_path`` is an int8 copy of the graph ``fp32`` (a loaded
    :class:`radaredge.runtime.RadarModel`): quantised by radaredge, of the same card and
    weights, so a row labelled int8 times what its label says."""
    q = rt.load(int8_path, threads=1)
    if q.info.quantization is None:
        raise ConfigError(
            f"--int8 {int8_path} is not an int8 graph (no radaredge.quantization in its metadata); "
            f"write one with `radaredge export --quantize int8`"
        )
    if q.card.name != fp32.card.name or q.weights_sha256 != fp32.weights_sha256 or q.info.part != fp32.info.part:
        raise ConfigError(
            f"--int8 {int8_path} is the int8 copy of another graph ({q.card.name}, weights "
            f"{q.weights_sha256[:12]}) than {fp32.path} ({fp32.card.name}, weights "
            f"{fp32.weights_sha256[:12]}); export both from the same card and checkpoint"
        )


def int8_copies(card: ModelCard, spec, paths: dict[str, Path], int8, say) -> dict[str, Path]:
    """graph name -> the int8 copy ``bench`` times for it: the copy beside each graph when it
    exists (``int8=True``: written first by the model's int8 policy when missing), or the graph
    whose copy the path ``int8`` is; each checked to be the int8 copy of that graph."""
    fp32 = {name: rt.load(p, threads=1) for name, p in paths.items()}
    if int8 not in (None, True, False):
        q = rt.load(int8, threads=1)
        name = next((n for n, g in fp32.items() if g.info.part == q.info.part), None)
        if name is None:
            raise ConfigError(
                f"--int8 {int8} is not the int8 copy of a graph of {card.name} (its part "
                f"{q.info.part!r}; the graphs: {', '.join(paths)})"
            )
        require_int8_copy(Path(int8), fp32[name])
        return {name: Path(int8)}
    policy = spec.int8
    wanted = {name: artifacts.copy_path(p, artifacts.INT8) for name, p in paths.items() if policy.quantises(name)}
    if int8 is True and not all(c.exists() for c in wanted.values()):
        say(f"int8 copies missing: quantising {card.name} to int8 ...")
        write_int8_copies(card, spec, paths)
    found = {}
    for name, candidate in wanted.items():
        if candidate.exists():
            require_int8_copy(candidate, fp32[name])
            found[name] = candidate
    return found


def write_int8_copies(card: ModelCard, spec, paths: dict[str, Path]) -> None:
    """The model's int8 copies of the graphs at ``paths``, written beside them atomically (made
    from staged copies of the graphs, of which only the int8 files are moved into place)."""
    with atomic.Staging(next(iter(paths.values())).parent) as stage:  # every graph of a bundle is in one directory
        staged = {name: stage.path(p) for name, p in paths.items()}
        for name, p in paths.items():
            shutil.copyfile(p, staged[name])
        make_int8_copies(card, spec, staged, Int8Options())
        for p in staged.values():
            p.unlink()
        stage.commit()
