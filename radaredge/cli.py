"""The ``radaredge`` command line: list, inspect, export, parity-check, bench."""

from __future__ import annotations

import datetime as _dt
import functools
import json
import sys
from pathlib import Path

import click

from .errors import ConfigError, RadarEdgeError
from .runners import RUNTIMES


def _friendly_errors(fn):
    """Turn radaredge errors into one clear line on stderr and exit code 2."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except RadarEdgeError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)
    return wrapper


def _progress(desc):
    from tqdm import tqdm
    return lambda it: tqdm(it, desc=desc, leave=False, file=sys.stderr, disable=not sys.stderr.isatty())


def _card(model: str, config: str | None):
    from .cards import load_card
    return load_card(config or model)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="radaredge")
def main():
    """radaredge: export 4D-radar perception models to one self-contained ONNX, prove parity
    against the PyTorch reference, and measure speed on 2 CPU cores."""


@main.command("list")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@_friendly_errors
def list_cmd(as_json):
    """The available model cards, one line each."""
    from .cards import available_cards, load_card
    cards = [load_card(n) for n in available_cards()]
    if as_json:
        click.echo(json.dumps([{"name": c.name, "model": c.model, "description": c.description} for c in cards], indent=2))
        return
    width = max((len(c.name) for c in cards), default=0)
    for c in cards:
        click.echo(f"{c.name:<{width}}  {c.description}")


@main.command()
@click.argument("onnx_path", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def inspect(onnx_path, as_json):
    """Show an exported graph's inputs, outputs, card and versions."""
    from . import runtime
    m = runtime.load(onnx_path)
    info = {
        "model": m.card.name, "features": m.features, "frames": m.frames,
        "inputs": {i.name: i.shape for i in m.session.get_inputs()},
        "outputs": {o.name: o.shape for o in m.session.get_outputs()},
        "weights_sha256": m.metadata.get("radaredge.weights_sha256"),
        "versions": json.loads(m.metadata.get("radaredge.versions", "{}")),
    }
    if as_json:
        click.echo(json.dumps(info, indent=2))
        return
    for k, v in info.items():
        click.echo(f"{k:>15}: {v}")


@main.command()
@click.option("--model", required=True, help="Model card name (see `radaredge list`).")
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of models/<model>.yaml.")
@click.option("--checkpoint", type=click.Path(dir_okay=False), help="state_dict .pth; default: seeded initialisation.")
@click.option("--output", type=click.Path(dir_okay=False), help="Where to write the .onnx (default export/<model>.onnx).")
@click.option("--opset", default=18, show_default=True, type=int)
@click.option("--debug", is_flag=True, help="Also write <output>.debug.onnx with intermediate tensors as outputs.")
@click.option("--quantize", type=click.Choice(["int8"]),
              help="Also write <output>.int8.onnx: static QDQ int8 of Conv/MatMul/Gemm, calibrated on synthetic "
                   "scenes or on --calibration.")
@click.option("--calibration", "calibration_dir", type=click.Path(file_okay=False),
              help="With --quantize int8: calibrate on this recording of your sensor (its scan files, .npy or "
                   ".bin, one per frame in file-name order, or a drive with scans/) instead of synthetic scenes.")
@click.option("--calibration-format", type=click.Choice(["vod", "tj4d", "transloc"]),
              help="Scan format of --calibration (default: inferred from the files).")
@click.option("--calibration-windows", type=click.IntRange(min=1),
              help="With --quantize int8: calibration windows, spread evenly over the recording, or synthetic "
                   "scenes  [default: 16]")
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def export(model, config, checkpoint, output, opset, debug, quantize, calibration_dir, calibration_format,
           calibration_windows, as_json):
    """Export the whole pipeline (raw points in, result out) to one .onnx and a JSON sidecar."""
    from .export import build_model, export_model
    card = _card(model, config)
    from .registry import is_bundle
    calibration = [name for name, value in (("--calibration", calibration_dir),
                                            ("--calibration-format", calibration_format),
                                            ("--calibration-windows", calibration_windows)) if value is not None]
    if calibration and not quantize:
        raise ConfigError(f"{', '.join(calibration)}: int8 calibration options need --quantize int8")
    if calibration_format and not calibration_dir:
        raise ConfigError("--calibration-format is the format of a --calibration recording; add --calibration DIR")
    if is_bundle(card):                 # several graphs: --output is a directory (default export/<model>/)
        if calibration:
            raise ConfigError(f"{card.name}'s int8 text encoder is quantised dynamically (weights only, no "
                              f"calibration); drop {', '.join(calibration)}")
        from .bundle import export_cmd
        return export_cmd(card, checkpoint, output, opset, quantize, as_json, _progress)
    output = Path(output or f"export/{card.name}.onnx")
    if calibration_dir:                 # a wrong recording fails before the export, not after it
        from .calibration import DEFAULT_WINDOWS, check_recording
        check_recording(calibration_dir, int(card.get("frames", 1)), calibration_windows or DEFAULT_WINDOWS,
                        calibration_format)
    net = build_model(card, checkpoint)
    if getattr(net, "checkpoint_report", None) is not None:
        click.echo(net.checkpoint_report.summary(), err=True)
    click.echo(f"exporting {card.name} ...", err=True)
    res = export_model(card, output, opset=opset, model=net)
    debug_path = int8_path = None
    if debug:
        debug_path = output.with_suffix(".debug.onnx")
        export_model(card, debug_path, opset=opset, debug=True, model=net)
    if quantize:
        from .quantize import quantize_int8
        click.echo(f"quantising {card.name} to int8 ...", err=True)
        int8_path = quantize_int8(card, res.path, output.with_suffix(".int8.onnx"), calibration_windows,
                                  calibration_dir=calibration_dir, calibration_format=calibration_format)
    if as_json:
        click.echo(json.dumps({"onnx": str(res.path), "sidecar": str(res.sidecar), "size_bytes": res.size_bytes,
                               "op_histogram": res.op_histogram, "debug_onnx": str(debug_path) if debug_path else None,
                               "int8_onnx": str(int8_path) if int8_path else None}, indent=2))
        return
    top = ", ".join(f"{k} {v}" for k, v in list(res.op_histogram.items())[:12])
    click.echo(f"wrote {res.path} ({res.size_bytes / 1e6:.2f} MB, {sum(res.op_histogram.values())} nodes) "
               f"and {res.sidecar}")
    click.echo(f"ops: {top}")
    if debug_path:
        click.echo(f"debug graph: {debug_path}")
    if int8_path:
        click.echo(f"int8 graph: {int8_path} ({int8_path.stat().st_size / 1e6:.2f} MB); "
                   f"check it with `radaredge parity-check --quantized --onnx {int8_path}`")


@main.command("parity-check")
@click.option("--model", required=True)
@click.option("--onnx", "onnx_path", required=True, type=click.Path(),
              help="The .onnx; for a multi-graph model (des4pos) the bundle directory.")
@click.option("--config", type=click.Path(dir_okay=False))
@click.option("--checkpoint", type=click.Path(dir_okay=False), help="Must be the weights the .onnx was exported with.")
@click.option("--cases", default=20, show_default=True, type=int)
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--quantized", is_flag=True,
              help="The .onnx is int8: descriptors need cosine >= 0.99 and top-1 agreement >= 98 %; "
                   "detections need matched-box recall >= 95 % at IoU 0.5 (recall of the boxes scored "
                   ">= 0.3 and >= 0.5 is reported); preprocessing outputs keep their fp32 tolerances.")
@click.option("--runtime", "runtime_name", type=click.Choice(RUNTIMES), default="onnxruntime",
              show_default=True,
              help="Run the graph in onnxruntime or in OpenVINO's CPU plugin (pip install 'radaredge[openvino]').")
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def parity_check(model, onnx_path, config, checkpoint, cases, seed, quantized, runtime_name, as_json):
    """Run the ONNX in onnxruntime (or OpenVINO) and the reference formulation in torch on the
    same synthetic cases; PASSED/FAILED against per-output tolerances (exit 0/1)."""
    from . import runtime
    from .export import build_model, export_model, require_same_weights
    from .parity import run_parity
    card = _card(model, config)
    from .registry import is_bundle
    if is_bundle(card):
        from .bundle import parity_cmd
        sys.exit(parity_cmd(card, onnx_path, checkpoint, cases, seed, as_json, _print_parity, _progress, runtime_name))
    net = build_model(card, checkpoint)
    exported = runtime.load(onnx_path)
    require_same_weights(exported, net, checkpoint)
    if quantized and "radaredge.quantization" not in exported.metadata:
        raise ConfigError(f"{onnx_path} is not an int8 export; drop --quantized or pass the .int8.onnx")

    def debug_graph():
        """The debug export beside the .onnx, (re)written unless it holds these weights."""
        path = Path(onnx_path).with_suffix(".debug.onnx")
        if not path.exists() or runtime.load(path).weights_sha256 != exported.weights_sha256:
            export_model(card, path, debug=True, model=net)
        return path

    report = run_parity(card, onnx_path, net, cases, seed, progress=_progress("parity"), quantized=quantized,
                        debug_onnx=None if quantized else debug_graph, runtime=runtime_name)
    if as_json:
        click.echo(json.dumps(report.to_dict(), indent=2))
    else:
        _print_parity(report)
    sys.exit(0 if report.passed else 1)


def _print_parity(report):
    budget = " [int8 budget]" if report.quantized else ""
    click.echo(f"parity {report.model}: {Path(report.onnx).name} ({report.runtime}) vs reference (torch), "
               f"{len(report.cases)} cases{budget}")
    click.echo(f"{'output':<24}{'kind':<12}{'max abs':>11}{'max rel':>11}{'p99 abs':>11}{'min cos/IoU':>12}  verdict")
    for name, s in report.summary.items():
        cos = (f"{s['min_cosine']:.7f}" if s["min_cosine"] is not None else
               f"{s['min_iou']:.7f}" if s.get("min_iou") is not None else "-")
        click.echo(f"{name:<24}{s['kind']:<12}{s['max_abs']:>11.3g}{s['max_rel']:>11.3g}{s['p99_abs']:>11.3g}"
                   f"{cos:>12}  {'PASSED' if s['passed'] else 'FAILED'}  tol {s['tolerance']}")
        if s["kind"] == "boxes" and s.get("recall") is not None:
            click.echo(f"{'':<24}boxes: end to end vs the full reference; matched-box recall {s['recall'] * 100:.1f} % "
                       f"(needs >= {s['tolerance']['min_recall'] * 100:.0f} % at IoU >= {s['tolerance']['min_iou']}); "
                       f"max abs = score diff, max rel = box coordinate diff")
            bands = "; ".join(f">= {b}: {100 * m / n:.1f} % of {n}" if n else f">= {b}: no boxes"
                              for b, (m, n) in s.get("recall_by_score", {}).items())
            if bands:
                click.echo(f"{'':<24}recall by reference score (reported, not judged): {bands}")
        elif s["kind"] == "boxes":
            e = s.get("end_to_end")
            click.echo(f"{'':<24}boxes: the graph's NMS vs the reference NMS on the graph's anchor outputs; "
                       f"max abs = score diff, max rel = box coordinate diff, {s['mismatches']} unmatched")
            if e:
                click.echo(f"{'':<24}end to end vs the full reference: {e['boxes']} vs {e['reference_boxes']} boxes, "
                           f"{e['unmatched']} unmatched" + (" (decisions within float noise of a threshold)" if e["unmatched"] else ""))
    if report.retrieval_top1 is not None:
        click.echo(f"retrieval top-1 agreement over the case set: {report.retrieval_top1 * 100:.1f}% "
                   f"(needs >= {report.min_retrieval_top1 * 100:.0f}%)")
    if report.divergence:
        d = report.divergence
        if d["tensor"]:
            click.echo(f"first diverging intermediate (case {d['case']}): {d['tensor']} (max abs {d['max_abs']:.3g})")
        else:
            click.echo(f"no intermediate diverges beyond tolerance in case {d['case']}: "
                       "the difference arises in the final outputs")
    if report.runtime == "openvino" and not report.passed:
        click.echo("note: OpenVINO's CPU plugin has no float64 kernels; what the graph computes in float64 "
                   "(TDFANet's RANSAC ego velocity) carries float32 error there")
    click.echo("PASSED" if report.passed else "FAILED")


def _stage_table(spec, net, cases, n: int, no_reference: bool, onnx_path=None, profile=None) -> dict | None:
    """Median ms per pipeline stage over ``n`` runs in torch (export and reference formulations)
    and, when the spec names its graph's stages, the mean ms per stage inside onnxruntime from
    ``profile``, the profile events of ``n`` runs of ``onnx_path`` in a session of its own (the
    timed runs are never profiled); printed."""
    if spec.stage_times is None:
        return None
    import statistics
    out = {}
    for label, ref in (("torch export", False), ("torch reference", True)):
        if ref and no_reference:
            continue
        laps = [spec.stage_times(net, cases[i % len(cases)], ref) for i in range(n)]
        out[label] = {k: statistics.median(l[k] for l in laps) * 1e3 for k in laps[0]}
    if spec.onnx_stages and profile is not None:
        import onnx

        from .ort_stages import stage_times_from_profile
        out["onnxruntime"] = stage_times_from_profile(
            profile, onnx.load(str(onnx_path), load_external_data=False),
            list(spec.onnx_stages), spec.onnx_post_outputs, n)
    names = list(dict.fromkeys(k for row in out.values() for k in row))
    click.echo("per-stage ms (torch: median; onnxruntime: mean from its profiler): " + " | ".join(names))
    for label, row in out.items():
        click.echo(f"  {label:<16}" + "".join(f"{row[k]:>14.1f}" if k in row else f"{'-':>14}" for k in names))
    return out


@main.command()
@click.option("--model", required=True)
@click.option("--onnx", "onnx_path", type=click.Path(),
              help="Default export/<model>.onnx (exported if missing); des4pos: the bundle directory.")
@click.option("--config", type=click.Path(dir_okay=False))
@click.option("--checkpoint", type=click.Path(dir_okay=False))
@click.option("--threads", default=2, show_default=True, type=int)
@click.option("--runs", default=50, show_default=True, type=int)
@click.option("--warmup", default=3, show_default=True, type=int)
@click.option("--no-reference", is_flag=True, help="Skip the (slow) torch reference backend.")
@click.option("--int8", "int8_path", type=click.Path(dir_okay=False),
              help="Also time this int8 graph (default: <onnx>.int8.onnx when it exists).")
@click.option("--profile", is_flag=True, help="Print onnxruntime's top ops by time.")
@click.option("--openvino/--no-openvino", default=None,
              help="Also time the graph(s) in OpenVINO's CPU plugin (default: when openvino is installed).")
@click.option("--json", "as_json", is_flag=True, help="Also write benchmarks/results/<model>-<date>.json.")
@_friendly_errors
def bench(model, onnx_path, config, checkpoint, threads, runs, warmup, no_reference, int8_path, profile, openvino,
          as_json):
    """Frames per second and latency percentiles on THREADS cores, every backend in one run."""
    from .bench import (as_dicts, benchmark, cpu_name, format_differences, model_backends, onnxruntime_peak_rss_mb,
                        output_differences, pin_threads, profile_runs, results_table, top_ops, write_results_json)
    from .export import build_model, export_model
    from .openvino_runtime import openvino_installed
    from .registry import model_spec
    card = _card(model, config)
    from .registry import is_bundle
    if is_bundle(card):
        if openvino:
            raise ConfigError(f"--openvino times single-graph models; {card.name} is a bundle of graphs")
        from .models.des4pos_bench import bench_cmd
        return bench_cmd(card, onnx_path, checkpoint, threads, runs, warmup, no_reference, as_json, _progress)
    cores = pin_threads(threads)
    net = build_model(card, checkpoint)
    onnx_path = Path(onnx_path or f"export/{card.name}.onnx")
    if not onnx_path.exists():
        click.echo(f"{onnx_path} missing: exporting it first", err=True)
        export_model(card, onnx_path, model=net)
    spec = model_spec(card)
    cases = [feeds for _, feeds in spec.make_cases(card, 4, 1)]
    default_int8 = onnx_path.with_suffix(".int8.onnx")
    int8_path = int8_path or (default_int8 if default_int8.exists() else None)
    openvino = openvino_installed() if openvino is None else openvino
    backends = model_backends(card, net, onnx_path, threads, not no_reference, int8_path, openvino)
    results = benchmark(backends, cases, runs, warmup, progress=_progress("bench"))
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    click.echo(f"{card.name} on {threads} thread(s), cores {cores}, {cpu_name()}, {runs} runs, {stamp}")
    click.echo(results_table(results, "torch reference" if not no_reference else "torch export"))
    ort_r = next(r for r in results if r.backend == "onnxruntime")
    ratios = {r.backend: r.p50_ms / ort_r.p50_ms for r in results if r.backend.startswith("torch")}
    click.echo("onnxruntime speed-up: " + ", ".join(f"{v:.2f}x vs {k}" for k, v in ratios.items()))
    int8_r = next((r for r in results if r.backend == "onnxruntime int8"), None)
    if int8_r is not None:
        gain = ort_r.p50_ms / int8_r.p50_ms
        click.echo(f"int8 vs fp32: {gain:.2f}x" + ("  (int8 is SLOWER than fp32 on this CPU)" if gain < 1 else ""))
    openvino_diff = None
    if openvino:
        ov_r = next(r for r in results if r.backend == "openvino")
        openvino_diff = output_differences(backends["openvino"], backends["onnxruntime"], cases)
        click.echo(f"openvino vs onnxruntime: {ort_r.p50_ms / ov_r.p50_ms:.2f}x; largest output difference on the "
                   f"bench inputs: {format_differences(openvino_diff)} "
                   f"(`radaredge parity-check --runtime openvino` checks it against the reference)")
    # One profiled session serves the stage split and --profile: n runs of its own, never timed.
    n_profiled = max(3, min(runs, 10))
    wants_profile = profile or (spec.stage_times is not None and bool(spec.onnx_stages))
    profile_events = profile_runs(onnx_path, cases, threads, n_profiled) if wants_profile else None
    stages = _stage_table(spec, net, cases, n_profiled, no_reference, onnx_path, profile_events)
    peak_rss = onnxruntime_peak_rss_mb(onnx_path, cases, threads)
    click.echo(f"onnxruntime peak RSS: {peak_rss:.0f} MiB (a separate numpy + onnxruntime process running "
               f"the {len(cases)} bench inputs once)")
    prof = None
    if profile:
        prof = top_ops(profile_events, runs=n_profiled)
        click.echo(f"onnxruntime top ops (kernel ms per run, from {n_profiled} runs in a separately profiled session; "
                   "the profiler slows small ops):")
        for op, ms in prof:
            click.echo(f"  {op:<24}{ms:10.1f}")
    if as_json:
        path = write_results_json(card.name, {
            "model": card.name, "threads": threads, "cores": cores, "cpu": cpu_name(), "runs": runs, "date": stamp,
            "results": as_dicts(results), "onnxruntime_speedup": ratios, "top_ops": prof, "stage_ms": stages,
            "onnxruntime_peak_rss_mib": peak_rss, "openvino_vs_onnxruntime_max_abs": openvino_diff})
        click.echo(f"wrote {path}")


@main.command("make-benchmark")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Writes OUT/database/drive-00 and OUT/queries/drive-01 ...")
@click.option("--drives", default=3, show_default=True, type=int, help="Drive 0 is the database, the rest queries.")
@click.option("--frames", default=60, show_default=True, type=int, help="Scans per drive (10 Hz).")
@click.option("--seed", default=0, show_default=True, type=int, help="Seeds the town and every drive.")
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def make_benchmark(out_dir, drives, frames, seed, as_json):
    """Write a synthetic place-recognition benchmark: one town (static world) driven on several
    days with other traffic, ego speed and heading offset, and some parked cars moved."""
    from .data.pr_benchmark import make_pr_benchmark
    plan = make_pr_benchmark(out_dir, drives, frames, seed, progress=_progress("drives"))
    rows = [{"drive": str(Path(out_dir) / d.subdir), "role": d.role, "frames": d.frames,
             "speed_m_s": d.config.ego_speed_max, "parked_change": d.config.parked_change} for d in plan]
    if as_json:
        click.echo(json.dumps({"out": str(out_dir), "seed": seed, "drives": rows}, indent=2))
        return
    click.echo(f"wrote {len(plan)} drives of {frames} scans (seed {seed}) to {out_dir}:")
    for r in rows:
        click.echo(f"  {r['drive']:<32}{r['role']:<10}{r['speed_m_s']:5.1f} m/s, parked cars changed "
                   f"{r['parked_change'] * 100:.0f} %")


@main.command("eval")
@click.option("--model", required=True, help="Model card name (see `radaredge list`).")
@click.option("--onnx", "onnx_path", required=True, type=click.Path(dir_okay=False))
@click.option("--database", required=True, type=click.Path(file_okay=False),
              help="A drive (scans/ + gps.csv) or a directory of drives.")
@click.option("--queries", required=True, type=click.Path(file_okay=False),
              help="A drive (scans/ + gps.csv) or a directory of drives.")
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of models/<model>.yaml.")
@click.option("--checkpoint", type=click.Path(dir_okay=False), help="Must be the weights the .onnx was exported with.")
@click.option("--radius", default=5.0, show_default=True, type=float,
              help="m; a retrieved window this close to the query is a true positive (TDFANet: 5 m).")
@click.option("--no-reference", is_flag=True, help="Skip the torch reference formulation.")
@click.option("--report", "report_path", type=click.Path(dir_okay=False),
              help="JSON report path (default: <onnx>.eval.json beside the .onnx).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False),
              help="PNG with the trajectory and Recall@N curve (default: <onnx>.eval.png).")
@click.option("--json", "as_json", is_flag=True, help="Print the whole report as JSON.")
@_friendly_errors
def eval_cmd(model, onnx_path, database, queries, config, checkpoint, radius, no_reference, report_path, plot_path,
             as_json):
    """Place-recognition Recall@1/5/10 of the ONNX (onnxruntime) and the torch reference over the
    K-frame windows of query drives against database drives, and their top-1 agreement."""
    from .evaluation import evaluate
    card = _card(model, config)
    report = evaluate(card, onnx_path, database, queries, checkpoint, radius, not no_reference, _progress)
    report_path = report_path or Path(onnx_path).with_suffix(".eval.json")
    plot_path = plot_path or Path(onnx_path).with_suffix(".eval.png")
    written = [str(report.write_json(report_path)), str(report.plot(plot_path))]
    if as_json:
        click.echo(json.dumps(report.to_dict(), indent=2))
        return
    _print_eval(report)
    click.echo(f"wrote {', '.join(written)}")


def _print_eval(report):
    from .evaluation import BACKEND_LABELS, ONNX, RECALL_NS, REFERENCE
    q, db = report.queries, report.database
    click.echo(f"eval {report.model}: {len(q)} query windows from {len(q.sequences)} drive(s) vs {len(db)} database "
               f"windows from {len(db.sequences)} drive(s), K = {db.k}, true positive within {report.radius:g} m")
    click.echo(f"{report.evaluated} queries evaluated, {report.skipped} skipped (no database window within "
               f"{report.radius:g} m)")
    click.echo(f"{'backend':<18}" + "".join(f"{f'R@{n}':>9}" for n in RECALL_NS))
    for name in report.results:
        click.echo(f"{BACKEND_LABELS[name]:<18}" + "".join(f"{r:>9.2f}" for r in report.recall(name).values()))
    if report.agreement is not None:
        click.echo(f"top-1 agreement {BACKEND_LABELS[ONNX]} vs {BACKEND_LABELS[REFERENCE]}: "
                   f"{report.agreement * 100:.1f} % of {len(q)} queries the same window, "
                   f"{report.place_agreement * 100:.1f} % within {report.radius:g} m of each other")


@main.command("make-city")
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False), help="The map to write (.npz).")
@click.option("--model", default="des4pos", show_default=True, help="Card whose object slots / points the map uses.")
@click.option("--config", type=click.Path(dir_okay=False), help="Card YAML to use instead of models/<model>.yaml.")
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--world", default=90.0, show_default=True, type=float, help="m, edge of the square city.")
@click.option("--objects", default=70, show_default=True, type=int)
@click.option("--poses", default=40, show_default=True, type=int, help="Query poses with descriptions.")
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def make_city_cmd(out_path, model, config, seed, world, objects, poses, as_json):
    """Write a synthetic city for text-to-point-cloud localisation: cells of coloured objects and
    query poses with template descriptions ("The pose is north of a red car.")."""
    from .data.text_city import make_city
    card = _card(model, config)
    c = card.get("cell", {})
    m = make_city(int(c.get("max_objects", 28)), int(c.get("points_per_object", 256)), seed=seed, world=world,
                  size=float(c.get("size", 30.0)), stride=float(c.get("stride", 10.0)), objects=objects, poses=poses)
    m.save(out_path)
    info = {"map": str(out_path), "cells": len(m), "objects": int(m.object_mask.sum()), "poses": len(m.pose_w),
            "example": str(m.pose_text[0]) if len(m.pose_text) else None}
    if as_json:
        click.echo(json.dumps(info, indent=2))
        return
    click.echo(f"wrote {out_path}: {info['cells']} cells, {info['objects']} objects, {info['poses']} described poses")
    if info["example"]:
        click.echo(f"e.g. pose 0 at {m.pose_w[0].round(1).tolist()} m: {info['example']}")


@main.command()
@click.option("--model", default="des4pos", show_default=True)
@click.option("--onnx-dir", "onnx_dir", required=True, type=click.Path(file_okay=False),
              help="The bundle `radaredge export --model des4pos` wrote.")
@click.option("--map", "map_path", required=True, type=click.Path(dir_okay=False),
              help="Cell map: .npz from `radaredge make-city`, or a KITTI360Pose cells/<scene>.pkl.")
@click.option("--text", required=True, help='The description, e.g. "The pose is north of a red car."')
@click.option("--top-k", default=3, show_default=True, type=int, help="Candidate cells for the fine stage.")
@click.option("--threads", default=2, show_default=True, type=int)
@click.option("--int8-text", is_flag=True, help="Use the dynamically quantised text_encoder.int8.onnx of the bundle.")
@click.option("--no-cache", is_flag=True, help="Re-encode the map's cells instead of reading the cached descriptors.")
@click.option("--json", "as_json", is_flag=True)
@_friendly_errors
def locate(model, onnx_dir, map_path, text, top_k, threads, int8_text, no_cache, as_json):
    """Locate a described pose: encode the map's cells once (cached), retrieve the top-k cells for the
    text (FAISS), run the fine stage in each and print the position estimates with their scores.
    Needs numpy, onnxruntime, faiss and tokenizers only (no torch, no network)."""
    import time
    from .locate import Des4PosBundle, MapIndex
    int8 = Path(onnx_dir) / "text_encoder.int8.onnx" if int8_text else None
    if int8 is not None and not int8.is_file():
        raise ConfigError(f"{int8} does not exist; export with `radaredge export --model {model} --quantize int8`")
    bundle = Des4PosBundle(onnx_dir, threads=threads, text_encoder=int8)
    if bundle.card.model != "des4pos" or (model != bundle.card.name and model != "des4pos"):
        raise ConfigError(f"{onnx_dir} holds {bundle.card.name}, not {model}")
    t0 = time.perf_counter()
    index = MapIndex.build(bundle, map_path, cache=not no_cache, progress=_progress("cells"))
    t1 = time.perf_counter()
    hits = bundle.locate(text, index, top_k)
    t2 = time.perf_counter()
    hints = bundle.tokenize(text)[0]
    if as_json:
        click.echo(json.dumps({"text": text, "hints": hints, "cells": len(index), "from_cache": index.from_cache,
                               "map_ms": (t1 - t0) * 1e3, "query_ms": (t2 - t1) * 1e3, "results": hits}, indent=2))
        return
    how = f"read from {index.cache.name}" if index.from_cache else "encoded" + (f", cached in {index.cache.name}"
                                                                               if index.cache else "")
    click.echo(f"map {map_path}: {len(index)} cells ({how}) in {(t1 - t0) * 1e3:.0f} ms")
    click.echo(f"query: {len(hints)} hint(s), text encode + search + fine stage in {(t2 - t1) * 1e3:.1f} ms")
    click.echo(f"{'rank':>4}  {'cell':<32}{'score':>8}  {'x (m)':>11}{'y (m)':>11}")
    for h in hits:
        click.echo(f"{h['rank']:>4}  {h['cell']:<32}{h['score']:>8.4f}  {h['position'][0]:>11.2f}{h['position'][1]:>11.2f}")


if __name__ == "__main__":
    main()
