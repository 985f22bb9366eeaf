"""The Python API: the verbs the command line calls, one code path for every model.

    import radaredge
    res = radaredge.export("tdfanet", output="export/tdfanet.onnx")          # -> ExportResult
    report = radaredge.parity("tdfanet", "export/tdfanet.onnx", cases=20)     # bool(report): the verdict
    bench = radaredge.bench("tdfanet", threads=2, runs=20)                    # -> BenchReport, a row per backend

A model is 1..n graphs (:mod:`radaredge.models.spec`), exported as a bundle
(:mod:`radaredge.artifacts`); each verb resolves the card's spec once, builds the model once
and loops over the graphs. What a verb needs of a particular model (comparators, int8 plan,
bench tasks, evaluation, training recipe) is declared in that model's spec.
``card`` is a :class:`ModelCard`, a shipped card's name or a card YAML path.

Importing this module loads neither torch nor an optional extra: each verb imports the machinery
it needs when it is called (torch for export, parity, bench, evaluate, train and
card_from_openpcdet; onnx for inspect's targets; faiss and tokenizers for locate; Ray for run
and the maps). That is radaredge's one lazy boundary: the command line imports this module and
calls its verbs, and a runtime-only install (numpy and onnxruntime) runs ``list``, ``inspect``
and ``locate``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from . import artifacts, atomic
from . import runtime as rt
from .atomic import Staging
from .cards import ModelCard, parse_card, resolve_card
from .cards.openpcdet import Conversion, describe_source, load_openpcdet_config, maffnet_card, render_card
from .config import check_count, check_writable_dir, checked_arguments, refuse_overwriting_inputs
from .errors import ConfigError, InputError, RadarEdgeError
from .registry import model_spec

__all__ = [
    "export",
    "parity",
    "bench",
    "evaluate",
    "train",
    "card_from_openpcdet",
    "run",
    "map_build",
    "map_query",
    "make_benchmark",
    "make_city",
    "locate",
    "inspect",
    "ExportResult",
    "resolve_card",
    "EXPORT_OPTIONS",
]


MAX_CASES = 10_000  # parity cases are built before the first run: bound them
MAX_BENCH_RUNS = 100_000  # timed and warm-up runs per backend
KEEP_FP32_STARTS = ("card", "none")  # quantize: the card's keep_fp32, or every layer int8
MIN_OPSET = 7  # the oldest opset onnx's version converter writes


def _calibrated(spec) -> bool:
    """The model's int8 plan takes calibration data."""
    return spec.int8.calibrated


# Every export option that depends on another option or on the model, checked by one generic
# function (Ultralytics' export_formats() table): (option, the option it needs, what to say when
# that is missing, whether the model takes it, what to say when it does not).
EXPORT_OPTIONS = (
    (
        "--calibration",
        "--quantize",
        "int8 calibration options need --quantize int8",
        _calibrated,
        "its int8 copy is quantised dynamically (weights only, no calibration)",
    ),
    (
        "--calibration-windows",
        "--quantize",
        "int8 calibration options need --quantize int8",
        _calibrated,
        "its int8 copy is quantised dynamically (weights only, no calibration)",
    ),
    (
        "--calibration-method",
        "--quantize",
        "int8 calibration options need --quantize int8",
        _calibrated,
        "its int8 copy is quantised dynamically (weights only, no calibration)",
    ),
    (
        "--calibration-format",
        "--calibration",
        "the format of a --calibration recording; add --calibration DIR",
        _calibrated,
        "its int8 copy is quantised dynamically (weights only, no calibration)",
    ),
)


def check_export_options(card: ModelCard, spec, given: dict) -> None:
    """ConfigError for an option of :data:`EXPORT_OPTIONS` given without the option it needs, or
    to a model that does not take it; ``given`` maps option names to values (None: not given)."""
    if given.get("--quantize") not in (None, "int8"):
        raise ConfigError(f"--quantize {given['--quantize']!r}: the one int8 format is 'int8'")
    for option, needs, missing, allowed, refused in EXPORT_OPTIONS:
        if given.get(option) is None:
            continue
        if given.get(needs) is None:
            raise ConfigError(f"{option}: {missing}")
        if not allowed(spec):
            raise ConfigError(f"{card.name}: {refused}; drop {option}")


@dataclass
class ExportResult:
    """What :func:`export` wrote: per graph the .onnx and its sidecar (and debug / int8 copies),
    a multi-graph model's directory and manifest, and the checkpoint load report."""

    model: str
    output: Path
    graphs: dict = field(default_factory=dict)  # graph name -> export.graphs.GraphExport
    debug: dict[str, Path] = field(default_factory=dict)
    int8: dict[str, Path] = field(default_factory=dict)
    manifest: Path | None = None
    checkpoint: object | None = None  # models.factory.LoadReport

    @property
    def path(self) -> Path:
        """The one graph's .onnx of a one-graph model."""
        if len(self.graphs) != 1:
            raise ConfigError(
                f"{self.model} exported {len(self.graphs)} graphs into {self.output}; use .graphs[name].path"
            )
        return next(iter(self.graphs.values())).path

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "output": str(self.output),
            "manifest": str(self.manifest) if self.manifest else None,
            "graphs": {
                n: {
                    **g.to_dict(),
                    "debug_onnx": str(self.debug[n]) if n in self.debug else None,
                    "int8_onnx": str(self.int8[n]) if n in self.int8 else None,
                }
                for n, g in self.graphs.items()
            },
            "checkpoint": None
            if self.checkpoint is None
            else {
                "path": self.checkpoint.path,
                "loaded": self.checkpoint.loaded,
                "dropped": self.checkpoint.dropped,
                "ignored": self.checkpoint.ignored,
            },
        }

    def lines(self) -> list[str]:
        out = []
        for name, g in self.graphs.items():
            top = ", ".join(f"{k} {v}" for k, v in list(g.op_histogram.items())[:12])
            out.append(
                f"wrote {g.path} ({g.size_bytes / 1e6:.2f} MB, {sum(g.op_histogram.values())} nodes) "
                f"and {g.sidecar.name}"
            )
            out.append(f"ops: {top}")
            if name in self.debug:
                out.append(f"debug graph: {self.debug[name]}")
            if name in self.int8:
                p = self.int8[name]
                out.append(f"int8 graph: {p} ({p.stat().st_size / 1e6:.2f} MB)")
        if self.manifest:
            out.append(f"wrote {self.manifest}")
        if self.int8:
            out.append(
                f"check the int8 copies with `radaredge parity-check --model {self.model} --quantized "
                f"--onnx {self.output}`"
            )
        return out


@checked_arguments
def export(
    card: ModelCard | str | Path,
    output: str | Path | None = None,
    *,
    checkpoint: str | Path | None = None,
    model=None,
    opset: int | None = None,
    debug: bool = False,
    quantize: str | None = None,
    calibration: str | Path | None = None,
    calibration_format: str | None = None,
    calibration_windows: int | None = None,
    calibration_method: str | None = None,
    progress: Callable | None = None,
    log: Callable[[str], None] | None = None,
) -> ExportResult:
    """Export the card's whole pipeline: every graph to ``output`` (a one-graph model's .onnx,
    default ``export/<card>.onnx``; a multi-graph model's directory, default ``export/<card>/``)
    with a JSON sidecar each; ``debug`` adds each graph's debug copy, ``quantize="int8"`` the
    model's int8 copies (calibrated on ``calibration``, a recording of the user's sensor, or on
    synthetic scenes; ``calibration_windows`` windows; activation ranges by ``calibration_method``,
    default the card's ``quantization.calibration``, except those a ``radaredge train --qat``
    checkpoint learned). ``model`` reuses a built model (its
    weights must be the checkpoint's). ``log`` receives progress lines."""
    import onnx

    from .exporting.calibration import DEFAULT_WINDOWS, recorded_feeds
    from .exporting.graphs import write_export
    from .exporting.onnx_call import DEFAULT_OPSET
    from .exporting.quantize import Int8Options, calibration_method_of, check_qat_settings, make_int8_copies
    from .models.checkpoints import read_qat_entry
    from .models.factory import create_model
    from .runtime.model import FrameFeeds

    card = resolve_card(card)
    name, spec = card.name, model_spec(card)
    say = log or (lambda line: None)
    if opset is not None:
        check_count("--opset", opset, MIN_OPSET, onnx.defs.onnx_opset_version())
    check_export_options(
        card,
        spec,
        {
            "--quantize": quantize,
            "--calibration": calibration,
            "--calibration-format": calibration_format,
            "--calibration-windows": calibration_windows,
            "--calibration-method": calibration_method,
        },
    )
    if quantize and spec.int8.calibrated:
        calibration_method_of(card, calibration_method)  # an unknown method fails before the export
    if calibration is not None:  # a wrong recording fails before the export, not after it
        graph = spec.graph()
        recorded_feeds(
            FrameFeeds.of_card(card, graph.frame_inputs(card), graph.timestamps_input),
            calibration,
            calibration_windows or DEFAULT_WINDOWS,
            calibration_format,
        )
    if model is None:
        model = create_model(card, checkpoint, spec)  # card and checkpoint errors first, then the output's
    qat = read_qat_entry(checkpoint) if quantize and spec.int8.calibrated and checkpoint is not None else None
    if qat is not None:
        check_qat_settings(card, qat, str(checkpoint))
    graph_names = _graph_names(spec)
    bundle = artifacts.Bundle.for_output(name, graph_names, output)
    root, written, manifest = bundle.root, bundle.files(), bundle.manifest
    # before a long export
    check_writable_dir(root, "--output")
    refuse_overwriting_inputs(
        {"--output": [output, *written]},
        {"--config": card.path, "--checkpoint": checkpoint, "--calibration": calibration},
    )
    report = getattr(model, "checkpoint_report", None)
    if report is not None:
        say(report.summary())
    say(f"exporting {name}" + (f" ({', '.join(graph_names)}) to {bundle.path}/" if manifest else "") + " ...")
    int8 = None
    if quantize:

        def int8(paths):
            say(f"quantising {name} to int8 ...")
            return make_int8_copies(
                card,
                spec,
                paths,
                Int8Options(calibration_windows, calibration, calibration_format, calibration_method, qat),
            )

    graphs, int8_paths = write_export(
        card, spec, model, bundle, DEFAULT_OPSET if opset is None else opset, debug=debug, int8=int8, progress=progress
    )
    result = ExportResult(name, bundle.path, graphs, checkpoint=report, int8=int8_paths, manifest=manifest)
    result.debug = {n: artifacts.copy_path(g.path, artifacts.DEBUG) for n, g in graphs.items()} if debug else {}
    return result


def _graph_names(spec) -> tuple[str, ...]:
    return tuple(g.name for g in spec.graphs)


@checked_arguments
def parity(
    card: ModelCard | str | Path,
    onnx: str | Path | None = None,
    *,
    checkpoint: str | Path | None = None,
    model=None,
    cases: int | None = None,
    seed: int | None = None,
    quantized: bool = False,
    runtime: str = "onnxruntime",
    data: str | Path | None = None,
    split: str | None = None,
    frames: int | None = None,
    data_format: str | None = None,
    progress: Callable[[str], Callable] | None = None,
):
    """Parity of every graph of the card's export at ``onnx`` (the bundle: a one-graph model's
    .onnx, a multi-graph model's directory; default the export path) run in ``runtime`` against
    the torch reference formulation, on ``cases`` synthetic cases (default 20) drawn with ``seed``
    (default 0), or with ``data`` on the user's own recording: ``frames`` frames (a model taking
    K scans: windows of K consecutive scans; default 20) spread evenly over the drive(s), KITTI
    layout (``split``: its ImageSets/<split>.txt, else every frame) or folder of scan files at
    ``data`` (scan format ``data_format``, default inferred), judged by the same comparators, with
    the graph's capacity outputs summarised over it (:mod:`radaredge.checking.recording`).
    ``quantized``: each graph's int8 copy (beside it; a one-graph model's may be named as
    ``onnx`` itself) is held to each output's int8 budget, and a graph the model's int8 policy
    keeps fp32 is checked as fp32. Returns a :class:`radaredge.checking.check.ParityReport`,
    whose truth value is the verdict."""
    from .checking.check import ParityReport, check_graph
    from .checking.recording import DEFAULT_FRAMES, recorded_cases
    from .eval.tasks import QUANTIZED_TASKS
    from .exporting.graphs import export_graph, require_same_weights
    from .models.factory import create_model

    if cases is not None:
        check_count("cases", cases, 1, MAX_CASES)
    if frames is not None:
        check_count("frames", frames, 1, MAX_CASES)
    card = resolve_card(card)
    spec = model_spec(card)
    if data is None:
        given = [o for o, v in (("--split", split), ("--frames", frames), ("--format", data_format)) if v is not None]
        if given:
            raise ConfigError(f"{', '.join(given)}: choose(s) the frames of a recording; add --data DIR")
    else:
        _check_recording_options(card, spec, cases, seed)
    onnx = Path(onnx) if onnx is not None else artifacts.Bundle.default(card.name, _graph_names(spec)).path
    targets = checked_graphs(card, spec, onnx, quantized)
    recordings = {}
    if data is not None:  # a wrong recording fails before the model is built
        recordings = {
            g.name: recorded_cases(card, g, data, frames or DEFAULT_FRAMES, split, data_format) for g in spec.graphs
        }
    if model is None:
        model = create_model(card, checkpoint, spec)
    report = ParityReport(card.name, str(onnx), runtime, quantized)
    report.data = next(iter(recordings.values()), None)
    for graph in spec.graphs:
        path, int8 = targets[graph.name]
        module = graph.module(model)
        exported = rt.load(path)
        require_same_weights(exported, module, checkpoint)
        if int8 and exported.info.quantization is None:
            raise ConfigError(
                f"{path} is not an int8 export; drop --quantized or write the int8 copy with "
                f"`radaredge export --quantize int8`"
            )

        def debug_graph(path=path, graph=graph, module=module, exported=exported):
            """The debug export beside the graph, (re)written unless it holds these weights."""
            debug_path = artifacts.copy_path(path, artifacts.DEBUG)
            if not _holds_weights(debug_path, exported.weights_sha256):
                with Staging(debug_path.parent) as stage:
                    export_graph(
                        card,
                        spec,
                        graph,
                        module,
                        stage.path(debug_path),
                        debug=True,
                        part=exported.info.part,
                        bundle_hash=exported.info.bundle_weights_sha256,
                    )
                    stage.commit()
            return debug_path

        wrap = progress(f"parity {graph.name}") if progress else None
        recorded = recordings[graph.name].cases if graph.name in recordings else None
        report.graphs[graph.name] = check_graph(
            card,
            graph,
            module,
            path,
            20 if cases is None else cases,
            0 if seed is None else seed,
            int8,
            runtime,
            debug_onnx=None if int8 else debug_graph,
            progress=wrap,
            recorded=recorded,
        )
    task = QUANTIZED_TASKS.get(spec.evaluation) if quantized and runtime == "onnxruntime" else None
    if task is not None:
        report.task = task(card, onnx, checkpoint)
    return report


def _check_recording_options(card: ModelCard, spec, cases, seed) -> None:
    """ConfigError for parity options that do not go with ``--data``: synthetic-case options, and
    a model whose graphs take no radar scans."""
    given = [o for o, v in (("--cases", cases), ("--seed", seed)) if v is not None]
    if given:
        raise ConfigError(
            f"{', '.join(given)} draw(s) synthetic cases; with --data the cases are the recording's "
            f"frames: --frames N picks N of them (windows, for a model taking several scans)"
        )
    scanless = [g.name for g in spec.graphs if not g.frame_inputs(card)]
    if scanless:
        raise ConfigError(
            f"--data: {card.name} takes no radar scans (its graph(s) {', '.join(scanless)} take "
            f"other inputs), so a recording of scans cannot feed it; check {card.name} on synthetic "
            f"cases (drop --data)"
        )


@checked_arguments
def bench(
    card: ModelCard | str | Path,
    onnx: str | Path | None = None,
    *,
    checkpoint: str | Path | None = None,
    model=None,
    threads: int = 2,
    runs: int = 20,
    warmup: int = 3,
    reference: bool = True,
    int8: str | Path | bool | None = None,
    profile: bool = False,
    openvino: bool | None = None,
    save: str | Path | None = None,
    progress: Callable[[str], Callable] | None = None,
    log: Callable[[str], None] | None = None,
):
    """Time every backend of the card's model on ``threads`` pinned cores, ``runs`` timed runs
    after ``warmup``, backends alternating every run; returns a
    :class:`radaredge.benchmarking.harness.BenchReport`, a row per backend. The model is built
    from ``checkpoint`` unless given. ``onnx`` (the bundle, default the export path) is exported
    first when missing. Each graph's int8 copy beside it is timed too when it exists;
    ``int8=True`` writes the copies first when missing (the model's int8 policy), and a path
    names one graph's int8 copy. ``reference``: time the torch reference formulation too;
    ``openvino``: add OpenVINO rows (None: when installed); ``profile`` adds onnxruntime's top
    ops and heaviest nodes, of the int8 copies too. ``save``: the report is also written there as
    JSON (checked before the runs, never over an input)."""
    from .benchmarking.harness import BenchOptions, time_model
    from .models.factory import create_model
    from .runtime.session import checked_threads

    checked_threads(threads)
    check_count("runs", runs, 1, MAX_BENCH_RUNS)
    check_count("warmup", warmup, 0, MAX_BENCH_RUNS)
    card = resolve_card(card)
    spec = model_spec(card)
    if int8 not in (None, True, False) and not Path(int8).is_file():
        raise InputError(f"--int8 {int8} does not exist; write it with `radaredge export --quantize int8`")
    if save is not None:
        check_writable_dir(Path(save).parent, "--save")  # before the runs, not after them
        refuse_overwriting_inputs({"--save": save}, {"--onnx": onnx, "--config": card.path, "--checkpoint": checkpoint})
    say = log or (lambda line: None)
    options = BenchOptions(threads, runs, warmup, reference, openvino, log=say)
    model = create_model(card, checkpoint, spec) if model is None else model
    report = time_model(card, spec, model, onnx, options, int8, profile, progress)
    if save is not None:
        say(f"wrote {report.save(save)}")
    return report


def _holds_weights(path: Path, weights_sha256: str) -> bool:
    """Whether ``path`` is a graph that loads (contents as exported) and computes with these weights."""
    if not path.exists():
        return False
    try:
        return rt.load(path).weights_sha256 == weights_sha256
    except RadarEdgeError:  # edited or unreadable: rewritten like a stale one
        return False


def checked_graphs(card: ModelCard, spec, onnx: Path, quantized: bool) -> dict[str, tuple[Path, bool]]:
    """graph name -> (the file parity runs, whether it is judged as int8) for the bundle at
    ``onnx``: each graph itself, or with ``quantized`` its int8 copy where the model's int8
    policy makes one (a one-graph bundle named by its int8 copy is that copy)."""
    if spec.multi_graph and not artifacts.manifest_path(onnx).is_file():
        raise InputError(
            f"{onnx} is not a {card.name} export directory (no {artifacts.manifest_path(onnx).name}); "
            f"{card.name} exports as {len(spec.graphs)} graphs: pass the directory `radaredge export "
            f"--model {card.name}` wrote"
        )
    paths = artifacts.Bundle(onnx, _graph_names(spec)).graph_files()
    if not quantized:
        return {name: (p, False) for name, p in paths.items()}
    policy = spec.int8
    out = {}
    for name, p in paths.items():
        if artifacts.copy_kind(p) == artifacts.INT8 or not policy.quantises(name):
            out[name] = (p, policy.quantises(name))
            continue
        int8 = artifacts.copy_path(p, artifacts.INT8)
        if not int8.is_file():
            raise InputError(
                f"--quantized: {int8} does not exist; write the int8 copy with `radaredge export "
                f"--model {card.name} --quantize int8`"
            )
        out[name] = (int8, True)
    return out


@checked_arguments
def evaluate(
    card: ModelCard | str | Path,
    onnx: str | Path,
    database: str | Path | None = None,
    queries: str | Path | None = None,
    *,
    map_path: str | Path | None = None,
    data: str | Path | None = None,
    split: str = "val",
    dataset: str | None = None,
    checkpoint: str | Path | None = None,
    radius: float = 5.0,
    reference: bool = True,
    write: EvalFiles | None = None,
    progress: Callable[[str], Callable] | None = None,
):
    """The model's task metric on the export at ``onnx``, by the model's ``evaluate`` hook:
    TDFANet's place-recognition Recall@N (and the torch reference's) over the K-frame windows of
    ``queries`` drives against ``database`` drives, true positives within ``radius`` m
    (:func:`radaredge.eval.places.evaluate`); Des4Pos's localisation recall over the described
    poses of the cell map ``map_path`` (:func:`radaredge.eval.localisation.evaluate_localization`);
    MAFF-Net's 3D / BEV AP per class and area of the torch reference, the export, its int8 copy
    and OpenVINO over the ``split`` of the labelled set at ``data`` (VoD or TJ4D layout, or
    ``dataset``; :func:`radaredge.eval.detection.evaluate_detection`); the task is the model's
    spec's ``evaluation``, a name in :data:`radaredge.eval.tasks.EVALUATIONS`. With ``write``
    (:class:`EvalFiles`), the report's files are written too (their directories checked before
    the evaluation, the inputs never overwritten) and listed in the report's ``written``."""
    from .eval.tasks import EVALUATIONS, EvalInputs

    card = resolve_card(card)
    task = EVALUATIONS.get(model_spec(card).evaluation)
    if task is None:
        raise ConfigError(
            f"{card.name} ({card.model}) has no evaluation on recorded data in radaredge; "
            f"`radaredge parity-check` checks its export against the reference"
        )
    inputs = EvalInputs(
        database=str(database) if database else None,
        queries=str(queries) if queries else None,
        map=str(map_path) if map_path else None,
        data=str(data) if data else None,
        split=split,
        dataset=dataset,
        checkpoint=str(checkpoint) if checkpoint else None,
        radius=radius,
        reference=reference,
        progress=progress,
    )
    if write is None:
        return task(card, onnx, inputs)
    files = write.resolved(onnx)
    graph = Path(onnx)
    refuse_overwriting_inputs(
        dict(zip(("--report", "--plot", "--report-dir"), files)),
        {
            "--onnx": [graph, *(artifacts.copy_path(graph, k) for k in artifacts.COPY_KINDS)]
            if graph.suffix == artifacts.ARTIFACTS[artifacts.GRAPH].suffix
            else graph,
            "--database": database,
            "--queries": queries,
            "--map": map_path,
            "--data": data,
            "--config": card.path,
            "--checkpoint": checkpoint,
        },
    )
    report = task(card, onnx, inputs)
    report.written = write.write(report, files)
    return report


@checked_arguments
def quantize(
    card: ModelCard | str | Path,
    onnx: str | Path,
    *,
    data: str | Path | None = None,
    split: str = "val",
    dataset: str | None = None,
    database: str | Path | None = None,
    queries: str | Path | None = None,
    radius: float = 5.0,
    method: str | None = None,
    budget: float | None = None,
    search: bool = False,
    keep_fp32: str = "card",
    log: Callable[[str], None] | None = None,
):
    """Write the int8 copy of the fp32 graph at ``onnx`` beside it (``<name>.int8.onnx``), judged
    by the model's task metric on labelled data that is not the test split: a detector's 3D AP per
    class on the ``split`` of ``data``, a place recogniser's Recall@1 over ``queries`` drives
    against ``database`` drives (true positives within ``radius`` m). Activation ranges by
    ``method`` (default the card's ``quantization.calibration``); the layers in fp32 are those
    ``keep_fp32`` names ("card": the card's ``quantization.keep_fp32``; "none": every layer
    int8), or with ``search`` the fewest groups added to those that bring every metric's loss
    within ``budget`` points (default 1.0; :mod:`radaredge.quantizing.search`). Returns the
    :class:`radaredge.quantizing.search.QuantizeReport`, true when the written copy is within."""
    from .eval.tasks import EvalInputs
    from .exporting.quantize import calibration_method_of
    from .quantizing.search import DEFAULT_BUDGET, quantize_judged

    card = resolve_card(card)
    spec = model_spec(card)
    if not spec.int8.calibrated:
        raise ConfigError(f"{card.name}: its int8 copy is quantised dynamically (weights only); nothing to calibrate")
    if method is not None:
        calibration_method_of(card, method)
    budget = DEFAULT_BUDGET if budget is None else budget
    if not budget > 0:
        raise ConfigError(f"--budget {budget}: expected a positive number of metric points")
    if keep_fp32 not in KEEP_FP32_STARTS:
        raise ConfigError(f"--keep-fp32 {keep_fp32}: expected one of {', '.join(KEEP_FP32_STARTS)}")
    graph = Path(onnx)
    if not graph.is_file() or graph.suffix != artifacts.ARTIFACTS[artifacts.GRAPH].suffix:
        raise InputError(f"--onnx {graph}: expected an exported fp32 .onnx file (`radaredge export --checkpoint ...`)")
    if artifacts.graph_of_copy(graph) != graph:
        raise InputError(f"--onnx {graph} is a copy of {artifacts.graph_of_copy(graph)}; give the fp32 graph")
    exported = rt.load(graph, threads=1)
    if exported.card.name != card.name:
        raise ConfigError(f"{graph} is an export of card {exported.card.name!r}, not {card.name!r}")
    out = artifacts.copy_path(graph, artifacts.INT8)
    check_writable_dir(out.parent, "--onnx")
    inputs = EvalInputs(
        database=str(database) if database else None,
        queries=str(queries) if queries else None,
        data=str(data) if data else None,
        split=split,
        dataset=dataset,
        radius=radius,
    )
    keep = None if keep_fp32 == "card" else []
    return quantize_judged(card, graph, inputs, method, budget, search, log or (lambda line: None), keep)


@dataclass(frozen=True)
class EvalFiles:
    """Where :func:`evaluate` writes its report: the JSON ``report``, a place-recognition
    ``plot`` (PNG) and a detection ``directory`` (report.json, precision-recall plots, BEV
    pictures); each None: beside the graph, ``<onnx>.eval.json``, ``<onnx>.eval.png`` and
    ``<onnx>.eval/``."""

    report: str | Path | None = None
    plot: str | Path | None = None
    directory: str | Path | None = None

    def resolved(self, onnx: str | Path) -> tuple[Path, Path, Path]:
        """The three paths for the export at ``onnx``, their directories checked writable."""
        base = Path(onnx)
        graph_suffix = artifacts.ARTIFACTS[artifacts.GRAPH].suffix
        base = (
            base.with_name(base.name + ".eval.json") if base.suffix != graph_suffix else base.with_suffix(".eval.json")
        )
        paths = (
            Path(self.report or base),
            Path(self.plot or base.with_suffix(".png")),
            Path(self.directory or base.with_suffix("")),
        )
        for path, option in zip(paths, ("--report", "--plot", "--report-dir")):
            check_writable_dir(path.parent, option)
        return paths

    @staticmethod
    def write(report, paths: tuple[Path, Path, Path]) -> list[str]:
        """Writes what ``report`` has of the three files; what was written, as text."""
        written = [str(report.write_json(paths[0]))]
        if hasattr(report, "plot"):
            written.append(str(report.plot(paths[1])))
        if hasattr(report, "write_directory"):
            written.append(f"{paths[2]}/ ({len(report.write_directory(paths[2]))} files)")
        return written


@checked_arguments
def train(
    card: ModelCard | str | Path,
    data: str | Path,
    output: str | Path | None = None,
    *,
    checkpoint: str | Path | None = None,
    device: str = "cpu",
    resume: bool = False,
    overwrite: bool = False,
    validation: tuple[str, ...] | list[str] | None = None,
    data_format: str | None = None,
    bag: dict | None = None,
    options: dict | None = None,
    progress: Callable | None = None,
    log: Callable[[str], None] | None = None,
):
    """Train the card's model with its paper's recipe on the data at ``data`` (TDFANet: drives
    of radar scans with positions; the model's ``train`` hook says what it reads) and write the
    run directory ``output`` (default ``runs/<card>/``): ``best.pth`` (for ``export
    --checkpoint``), ``last.pth`` (for ``resume``) and ``train-log.json``; a directory that holds
    a run already is continued with ``resume`` or replaced with ``overwrite``, never silently
    (:func:`radaredge.training.run.prepare_run_output`). ``checkpoint``
    initialises the weights (fine-tuning); ``options`` overrides recipe values by name (epochs,
    lr, batch_size, ...); ``bag`` says where ROS bag drives keep their radar scans and GNSS fixes
    (:class:`radaredge.data.bag_drives.BagSource` fields). Returns a
    :class:`radaredge.training.run.TrainReport`. The recipe is the model's entry in
    :data:`radaredge.training.recipes.RECIPES` its spec names."""
    from .models.factory import create_model
    from .training.recipes import RECIPES, TrainInputs
    from .training.run import prepare_run_output

    card = resolve_card(card)
    spec = model_spec(card)
    recipe = RECIPES.get(spec.recipe)
    if recipe is None:
        raise ConfigError(
            f"{card.name} ({card.model}): radaredge has no training recipe for this model; "
            f"train it upstream and pass the weights to `radaredge export --checkpoint`"
        )
    if resume and checkpoint is not None:
        raise ConfigError("--resume continues the run in --output from its last.pth; drop --checkpoint")
    output = Path(output) if output is not None else Path("runs") / card.name
    model = create_model(card, checkpoint, spec)  # card and checkpoint errors first
    prepare_run_output(
        output,
        resume,
        overwrite,
        {
            "--data": data,
            "--checkpoint": checkpoint,
            "--config": card.path,
            **{f"--set {k}": v for k, v in (options or {}).items() if isinstance(v, str) and v and Path(v).exists()},
        },
    )
    inputs = TrainInputs(
        str(output),
        str(checkpoint) if checkpoint is not None else None,
        device,
        resume,
        tuple(validation) if validation is not None else None,
        data_format,
        dict(bag or {}),
        dict(options or {}),
        progress,
        log,
    )
    return recipe(card, model, data, inputs)


CFA_CHOICES = ("dbscan", "grid_density")


@checked_arguments
def card_from_openpcdet(
    config: str | Path,
    out: str | Path | None = None,
    *,
    dataset_config: str | Path | None = None,
    name: str | None = None,
    stage_two: bool = True,
    cfa: str | None = None,
) -> Conversion:
    """A MAFF-Net card from an OpenPCDet config (TRV-Lab/MAFF-Net ``tools/cfgs``) and its
    ``_BASE_CONFIG_`` (``dataset_config`` replaces that file), written to ``out`` when given.

    Every key of the merged config is mapped, checked, training-only or ignored
    (:mod:`radaredge.cards.openpcdet`); the card is validated as ``export`` reads it (the model is
    built from it) before anything is written. ``stage_two`` False makes a stage-one card;
    ``cfa`` (``dbscan`` / ``grid_density``) overrides the clustering map the config names."""
    from .models.factory import create_model

    if cfa is not None and cfa not in CFA_CHOICES:
        raise ConfigError(f"cfa must be one of {list(CFA_CHOICES)}, got {cfa!r}")
    if out is not None:
        check_writable_dir(Path(out).parent, "--out")
    merged, files = load_openpcdet_config(config, dataset_config)
    refuse_overwriting_inputs(
        {"--out": out}, {"CONFIG": config, "--dataset-config": dataset_config, "_BASE_CONFIG_": files}
    )
    conversion = maffnet_card(merged, files, name=name, stage_two=stage_two, cfa=cfa)
    card = parse_card(conversion.card, Path(out) if out is not None else Path(f"{conversion.card['name']}.yaml"))
    create_model(card)
    if out is not None:
        atomic.write_text(out, render_card(conversion))
    return conversion


@checked_arguments
def run(
    onnx: str | Path,
    data: str | Path,
    out: str | Path,
    *,
    workers: int | None = None,
    threads: int = 1,
    backend: str = "onnxruntime",
    ray_address: str | None = None,
    shard_windows: int | None = None,
    fmt: str | None = None,
    progress: Callable | None = None,
):
    """Run the exported single-graph model ``onnx`` over every window (TDFANet) or frame
    (MAFF-Net) of every drive under ``data`` as a Ray Data pipeline, writing Parquet shards of its
    outputs with drive, frame, timestamp and pose to ``out``; resumable
    (:func:`radaredge.fleet.pipeline.run_graph`). Returns a ``RunReport``."""
    from .fleet.pipeline import run_graph

    check_writable_dir(Path(out), "--out")
    refuse_overwriting_inputs({"--out": out}, {"--onnx": onnx, "--data": data})
    return run_graph(
        onnx,
        data,
        out,
        workers=workers,
        threads=threads,
        backend=backend,
        ray_address=ray_address,
        shard_windows=shard_windows,
        fmt=fmt,
        progress=progress,
    )


@checked_arguments
def map_build(
    card: ModelCard | str | Path,
    onnx: str | Path,
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
):
    """A persistent place-recognition map of the drives under ``drives``: their windows described
    by ``onnx`` (an export of ``card``) on Ray, in a FAISS index (:mod:`radaredge.fleet.maps`)."""
    from .eval.places import check_export
    from .fleet.maps import build_map

    card = resolve_card(card)
    check_export(card, rt.load(onnx, threads=1))
    check_writable_dir(Path(out), "--out")
    refuse_overwriting_inputs({"--out": out}, {"--onnx": onnx, "--drives": drives, "--config": card.path})
    return build_map(
        onnx,
        drives,
        out,
        index=index,
        workers=workers,
        threads=threads,
        backend=backend,
        ray_address=ray_address,
        fmt=fmt,
        progress=progress,
    )


@checked_arguments
def map_query(
    map_dir: str | Path,
    drive: str | Path,
    *,
    onnx: str | Path | None = None,
    top_k: int = 10,
    radius: float = 5.0,
    threads: int = 2,
    backend: str = "onnxruntime",
):
    """Localise the windows of ``drive`` against a map made by :func:`map_build`: top-k map
    windows with poses and Recall@N (:func:`radaredge.fleet.maps.query_map`)."""
    from .fleet.maps import query_map

    return query_map(map_dir, drive, onnx=onnx, top_k=top_k, radius=radius, threads=threads, backend=backend)


@dataclass
class PlacesBenchmark:
    """What :func:`make_benchmark` wrote for place recognition: per drive its path, role, scans,
    top ego speed (m/s) and share of parked cars changed (a route drive: lane offset in m and
    share driven against the database's direction), and per town the chance Recall@1 at each
    radius (:func:`radaredge.eval.recall_stats.chance_of_benchmark`)."""

    out: Path
    seed: int
    towns: int
    layout: str
    drives: list[dict]
    chance: dict

    def to_dict(self) -> dict:
        return {
            "out": str(self.out),
            "seed": self.seed,
            "towns": self.towns,
            "layout": self.layout,
            "drives": self.drives,
            "chance_recall": self.chance,
        }

    def lines(self) -> list[str]:
        out = [
            f"wrote {len(self.drives)} drives ({self.towns} town(s), {self.layout} layout, seed {self.seed}) to "
            f"{self.out}:"
        ]
        for r in self.drives:
            route = (
                f", lane {r['lane_m']:+.2f} m, {r['against_database'] * 100:.0f} % against the database's direction"
                if "lane_m" in r
                else ""
            )
            out.append(
                f"  {r['drive']:<40}{r['role']:<10}{r['frames']:>6} scans {r['speed_m_s']:5.1f} m/s, parked "
                f"cars changed {r['parked_change'] * 100:.0f} %{route}"
            )
        for town, by_radius in self.chance.items():
            out.append(
                f"  chance Recall@1 ({town}): "
                + ", ".join(
                    f"{v['recall_at_1']:.2f} % at {r} m ({v['database_within']:.1f} database scans within it per query)"
                    for r, v in by_radius.items()
                )
            )
        return out


MAX_PLACES_DRIVES = 64


@checked_arguments
def make_benchmark(
    out: str | Path,
    task: str = "places",
    *,
    drives: int | None = None,
    frames: int | None = None,
    seed: int = 0,
    towns: int = 1,
    dataset: str | None = None,
    layout: str = "street",
    route_km: float | None = None,
    version: int | None = None,
    progress: Callable | None = None,
):
    """Write a synthetic benchmark to ``out``. ``task="places"``: one town (or ``towns`` towns of
    seeds ``seed``, ``seed + 1``, ...) driven on ``drives`` days (default 3; the first is the
    database) with other traffic, ego speed and heading offsets and some parked cars moved; the
    town is one street (``frames`` scans a drive, default 60) or with ``layout="network"`` a
    grid of streets driven along routes of ``route_km`` km (default 2.2); returns a
    :class:`PlacesBenchmark` with the chance Recall@1. ``task="detection"``: labelled frames in
    View-of-Delft's (or ``dataset="tj4d"``: TJ4DRadSet's) layout, ``drives`` drives of ``frames``
    frames (default 40) split train / val / test by drive, set ``version`` 2 (radar physics,
    default) or 1 (:func:`radaredge.data.detection_benchmark.make_detection_benchmark`)."""
    from .data.detection_benchmark import make_detection_benchmark
    from .data.pr_benchmark import make_pr_benchmark, make_pr_towns, make_route_benchmark
    from .eval.recall_stats import chance_of_benchmark

    if task not in ("places", "detection"):
        raise ConfigError(f"--task must be places or detection, got {task!r}")
    if task == "detection":
        given = [
            name
            for name, used in (
                ("--towns", towns != 1),
                ("--layout", layout != "street"),
                ("--route-km", route_km is not None),
            )
            if used
        ]
        if given:
            raise ConfigError(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for --task places")
        return make_detection_benchmark(
            out, drives, frames or 40, seed, progress=progress, dataset=dataset or "vod", version=version or 2
        )
    if dataset is not None or version is not None:
        raise ConfigError(f"{'--dataset' if dataset is not None else '--version'} is for --task detection")
    if layout not in ("street", "network"):
        raise ConfigError(f"--layout must be street or network, got {layout!r}")
    drives = drives or 3
    if drives > MAX_PLACES_DRIVES:
        raise ConfigError(f"--drives {drives}: a places benchmark has at most {MAX_PLACES_DRIVES} drives")
    if layout == "network":
        route_km = route_km or 2.2
        if frames is not None:
            raise ConfigError("--frames is for --layout street; a network drive's scans follow from --route-km")

        def make(path, town_seed):
            return make_route_benchmark(path, drives, route_km * 1000.0, town_seed, progress=progress)
    else:
        if route_km is not None:
            raise ConfigError("--route-km is for --layout network")
        frames = frames or 60

        def make(path, town_seed):
            return make_pr_benchmark(path, drives, frames, town_seed, progress=progress)

    plans = {"": make(Path(out), seed)} if towns == 1 else make_pr_towns(out, towns, seed, make)
    rows = [
        {
            "drive": str(Path(out) / town / d.subdir),
            "role": d.role,
            "frames": d.frames,
            "speed_m_s": d.config.ego_speed_max,
            "parked_change": d.config.parked_change,
            **({"lane_m": d.drive.lane, "against_database": d.against} if layout == "network" else {}),
        }
        for town, ds in plans.items()
        for d in ds
    ]
    chance = {town or ".": chance_of_benchmark(Path(out) / town) for town in plans}
    return PlacesBenchmark(Path(out), seed, towns, layout, rows, chance)


@dataclass
class CityReport:
    """What :func:`make_city` wrote: per map its path, cells, objects, described poses and its
    first description (with that pose's position, m)."""

    out: Path
    seed: int
    maps: list[dict]

    def to_dict(self) -> dict:
        rows = [{k: v for k, v in m.items() if k != "example_pose"} for m in self.maps]
        return rows[0] if len(rows) == 1 else {"out": str(self.out), "seed": self.seed, "maps": rows}

    def lines(self) -> list[str]:
        out = [
            f"wrote {m['map']}: {m['cells']} cells, {m['objects']} objects, {m['poses']} described poses"
            for m in self.maps
        ]
        first = self.maps[0]
        if first["example"] is not None:
            out.append(f"e.g. pose 0 at {first['example_pose']} m: {first['example']}")
        return out


@checked_arguments
def make_city(
    out: str | Path,
    card: ModelCard | str | Path = "des4pos",
    *,
    seed: int = 0,
    cities: int = 1,
    world: float = 90.0,
    objects: int = 70,
    poses: int = 40,
) -> CityReport:
    """Write a synthetic city for text-to-point-cloud localisation in the layout of a Des4Pos
    ``card``: cells of coloured objects and ``poses`` query poses with template descriptions ("The
    pose is north of a red box."), in a ``world`` m square; ``out`` a ``.npz`` map, or with
    ``cities`` > 1 a directory of ``city-<seed>.npz`` of seeds ``seed``, ``seed + 1``, ...
    (:mod:`radaredge.data.text_city`)."""
    from .data.text_city import check_city_output, check_city_work, make_city_for_card, write_cities

    card = resolve_card(card)
    check_city_output(out, cities)
    check_city_work(cities, poses)
    refuse_overwriting_inputs({"--out": out}, {"--config": card.path})
    if cities == 1:
        m = make_city_for_card(card, seed=seed, world=world, objects=objects, poses=poses)
        m.save(out)
        written = [(str(out), m)]
    else:
        written = write_cities(out, card, cities, seed=seed, world=world, objects=objects, poses=poses)
    return CityReport(
        Path(out),
        seed,
        [
            {
                "map": p,
                "cells": len(m),
                "objects": int(m.object_mask.sum()),
                "poses": len(m.pose_w),
                "example": str(m.pose_text[0]) if len(m.pose_text) else None,
                "example_pose": m.pose_w[0].round(1).tolist() if len(m.pose_text) else None,
            }
            for p, m in written
        ],
    )


@checked_arguments
def locate(
    onnx_dir: str | Path,
    map_path: str | Path,
    text: str,
    *,
    model: str | None = None,
    top_k: int = 3,
    threads: int = 2,
    int8_text: bool = False,
    cache: bool = True,
    progress: Callable | None = None,
):
    """Locate a described pose with a Des4Pos export: the map's cells encoded once (cached beside
    it with ``cache``), the top-k cells retrieved for ``text`` (FAISS), the fine stage's position
    in each with its score (:func:`radaredge.runtime.des4pos.locate_description`); numpy,
    onnxruntime, faiss and tokenizers only."""
    from .runtime.des4pos import locate_description

    return locate_description(
        onnx_dir, map_path, text, top_k, threads, int8_text, cache=cache, progress=progress, model=model
    )


@dataclass
class InspectReport:
    """What :func:`inspect` found: per graph its fields (:func:`radaredge.runtime.inspect_export`),
    whether every graph is what was exported (``ok``) and whether a deployment target refuses an op."""

    info: dict

    @property
    def refused(self) -> bool:
        """A deployment target asked about does not support an op of a graph."""
        return any(
            f["level"] == "unsupported" for g in self.info["graphs"] for fs in g.get("targets", {}).values() for f in fs
        )

    def __bool__(self) -> bool:
        return bool(self.info.get("ok", True)) and not self.refused

    def to_dict(self) -> dict:
        return self.info

    def lines(self) -> list[str]:
        out = []
        for i, graph in enumerate(self.info["graphs"]):
            if i:
                out.append("")
            out += [
                f"{k:>15}: {describe_source(v) if k == 'source' else v}" for k, v in graph.items() if k != "targets"
            ]
            for target, found in graph.get("targets", {}).items():
                bad = [f for f in found if f["level"] == "unsupported"]
                out.append(
                    f"{'target ' + target:>15}: "
                    + (
                        "unsupported: " + "; ".join(f"{f['op']} x{f['count']} ({f['message']})" for f in bad)
                        if bad
                        else "parses"
                    )
                    + "".join(
                        f"\n{'':>17}note: {f['op']} x{f['count']}: {f['message']}"
                        for f in found
                        if f["level"] == "note"
                    )
                )
        return out


@checked_arguments
def inspect(onnx: str | Path, targets: str | None = None) -> InspectReport:
    """An exported graph's (or a multi-graph export directory's) inputs, outputs, card, versions
    and whether its contents and embedded card check out; with ``targets`` (comma-separated from
    onnxruntime, tensorrt, openvino, ort-mobile, or all; needs the onnx package), the ops each
    deployment target does not support (:func:`radaredge.runtime.inspect_export`)."""
    chosen = ()
    if targets is not None:
        from .targets import parse_targets

        chosen = parse_targets(targets)
    return InspectReport(rt.inspect_export(onnx, chosen))
