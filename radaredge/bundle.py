"""Multi-graph bundles (a card whose spec is a BundleSpec, e.g. Des4Pos) on the command line:
export, parity-check every part, dynamic int8 quantisation of a part, and the query benchmark.

``radaredge.cli`` hands a bundle card to these functions; single-graph cards never reach them.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from .cards import ModelCard
from .errors import ExportError, InputError


def quantize_dynamic_int8(fp32_path: str | Path, out_path: str | Path) -> Path:
    """onnxruntime dynamic quantisation: int8 weights of MatMul/Gemm, activations quantised at run
    time (no calibration). Metadata is copied and ``radaredge.quantization`` added."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic
    import tempfile
    fp32_path, out_path = Path(fp32_path), Path(out_path)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            # the exporter's intermediate value_info carries shapes that onnx's re-inference rejects
            # after quantisation rewrites the graph; drop it and let the quantiser infer afresh
            clean = onnx.load(str(fp32_path))
            del clean.graph.value_info[:]
            pre = Path(tmp) / "pre.onnx"
            onnx.save(clean, str(pre))
            quantize_dynamic(str(pre), str(out_path), weight_type=QuantType.QInt8,
                             op_types_to_quantize=["MatMul", "Gemm"])
    except Exception as exc:
        raise ExportError(f"dynamic int8 quantisation of {fp32_path} failed: {type(exc).__name__}: {exc}") from exc
    from .quantize import carry_metadata
    carry_metadata(fp32_path, out_path, {"format": "dynamic", "weights": "int8", "activations": "uint8 at run time",
                                         "ops": ["MatMul", "Gemm"]})
    return out_path


def export_cmd(card: ModelCard, checkpoint, output, opset: int, quantize, as_json: bool, progress) -> None:
    from .export import build_model, export_bundle
    out_dir = Path(output or f"export/{card.name}")
    net = build_model(card, checkpoint)
    click.echo(f"exporting {card.name} ({', '.join(card.get('parts', []))}) to {out_dir}/ ...", err=True)
    res = export_bundle(card, out_dir, net, opset=opset, progress=progress("export"))
    int8 = None
    if quantize:
        int8 = quantize_dynamic_int8(res.parts["text_encoder"].path, out_dir / "text_encoder.int8.onnx")
    if as_json:
        click.echo(json.dumps({"bundle": str(out_dir), "manifest": str(res.manifest),
                               "parts": {n: {"onnx": str(r.path), "size_bytes": r.size_bytes, "op_histogram": r.op_histogram}
                                         for n, r in res.parts.items()},
                               "text_encoder_int8": str(int8) if int8 else None}, indent=2))
        return
    for name, r in res.parts.items():
        top = ", ".join(f"{k} {v}" for k, v in list(r.op_histogram.items())[:8])
        click.echo(f"wrote {r.path} ({r.size_bytes / 1e6:.2f} MB, {sum(r.op_histogram.values())} nodes): {top}")
    click.echo(f"wrote {res.manifest} and {out_dir / 'tokenizer.json'}")
    if int8:
        click.echo(f"dynamic int8 text encoder: {int8} ({int8.stat().st_size / 1e6:.2f} MB)")


def parity_cmd(card: ModelCard, bundle_dir, checkpoint, cases: int, seed: int, as_json: bool, printer, progress,
               runtime_name: str = "onnxruntime") -> int:
    """Parity of every part run in ``runtime_name``; returns the exit code (0 PASSED, 1 FAILED)."""
    from . import runtime
    from .export import build_model, require_same_weights
    from .parity import run_parity
    from .registry import model_spec
    spec = model_spec(card)
    bundle_dir = Path(bundle_dir)
    if not (bundle_dir / "bundle.json").is_file():
        raise InputError(f"{bundle_dir} is not a bundle directory (no bundle.json); {card.name} exports as "
                         f"{len(spec.parts)} graphs: pass the directory `radaredge export --model {card.name}` wrote")
    net = build_model(card, checkpoint)
    reports = {}
    for name, pspec in spec.parts.items():
        part = spec.part_module(net, name)
        path = bundle_dir / f"{name}.onnx"
        require_same_weights(runtime.load(path), part, checkpoint)
        reports[name] = run_parity(card, path, part, cases, seed, progress=progress(f"parity {name}"), spec=pspec,
                                   runtime=runtime_name)
    passed = all(r.passed for r in reports.values())
    if as_json:
        click.echo(json.dumps({"model": card.name, "bundle": str(bundle_dir), "passed": passed,
                               "parts": {n: r.to_dict() for n, r in reports.items()}}, indent=2))
    else:
        for name, r in reports.items():
            click.echo(f"--- {name}")
            printer(r)
        click.echo(f"bundle {card.name}: {'PASSED' if passed else 'FAILED'} "
                   f"({sum(r.passed for r in reports.values())}/{len(reports)} parts)")
    return 0 if passed else 1
