"""Shared test helpers: export a module alone and run it in onnxruntime."""

from __future__ import annotations

import importlib.util
import os
import sys

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Before torch loads OpenMP: a test that asks for two torch threads shares the two cores with
    # the other worker, and OpenMP's default of spinning at every barrier then makes it about ten
    # times slower (a TDFANet ablation's training steps: 44 s against 6 s when the threads sleep).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from collections import OrderedDict
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pytest
import torch

from radaredge.exporting.onnx_call import export_onnx
from radaredge.runtime.session import make_session, run_session

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)  # `make test` runs two workers on two cores: one torch thread each


class OnnxRoundTrip:
    """Export ``module`` once, then run any number of input sets through torch and onnxruntime."""

    def __init__(
        self,
        tmp_path: Path,
        module: torch.nn.Module,
        example: Mapping[str, torch.Tensor],
        output_names: Sequence[str],
        dynamic_axes: Mapping[str, Mapping[int, str]] | None = None,
    ):
        self.module = module.eval()
        self.input_names = list(example)
        self.output_names = list(output_names)
        path = export_onnx(
            module,
            tuple(example.values()),
            tmp_path / f"{type(module).__name__}.onnx",
            self.input_names,
            self.output_names,
            dynamic_axes,
        )
        self.session = make_session(path, threads=1)

    def __call__(self, inputs: Mapping[str, torch.Tensor]):
        """Return (torch outputs, onnxruntime outputs), both as OrderedDicts of numpy arrays."""
        with torch.no_grad():
            out = self.module(*[inputs[n] for n in self.input_names])
        if not isinstance(out, (tuple, list)):
            out = (out,)
        ref = OrderedDict((n, o.detach().numpy()) for n, o in zip(self.output_names, out))
        got = run_session(self.session, {n: inputs[n].numpy() for n in self.input_names})
        return ref, OrderedDict((n, got[n]) for n in self.output_names)


@pytest.fixture
def onnx_roundtrip(tmp_path):
    def make(module, example, output_names, dynamic_axes=None):
        return OnnxRoundTrip(tmp_path, module, example, output_names, dynamic_axes)

    return make


def assert_close(a: np.ndarray, b: np.ndarray, atol: float = 1e-5, what: str = "") -> None:
    """Max-abs comparison with a message that says how far apart the arrays are."""
    a = np.asarray(a)
    b = np.asarray(b)
    assert a.shape == b.shape, f"{what}: shape {a.shape} != {b.shape}"
    if a.size == 0:
        return
    err = np.abs(a.astype(np.float64) - b.astype(np.float64)).max()
    assert err <= atol, f"{what}: max abs error {err:.3g} > {atol:g}"


TINY_CARD = Path(__file__).parent / "cards" / "tdfanet-tiny.yaml"


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory):
    """The tiny TDFANet card exported once per session: (card, model, onnx path, debug onnx path)."""
    import radaredge
    from radaredge.cards import load_card
    from radaredge.models import create_model

    card = load_card(TINY_CARD)
    model = create_model(card)
    d = tmp_path_factory.mktemp("tiny-export")
    radaredge.export(card, d / "tdfanet-tiny.onnx", model=model, debug=True)
    return card, model, d / "tdfanet-tiny.onnx", d / "tdfanet-tiny.debug.onnx"


MAFFNET_TINY_CARD = Path(__file__).parent / "cards" / "maffnet-tiny.yaml"
MAFFNET_TINY_FULL_CARD = Path(__file__).parent / "cards" / "maffnet-tiny-full.yaml"
MAFFNET_TINY_FULL_DBSCAN_CARD = Path(__file__).parent / "cards" / "maffnet-tiny-full-dbscan.yaml"


@pytest.fixture(scope="session")
def maffnet_tiny_export(tmp_path_factory):
    """The tiny MAFF-Net card exported once per session with its int8 copy: (card path, onnx path)."""
    import radaredge

    d = tmp_path_factory.mktemp("maffnet-tiny-export")
    radaredge.export(MAFFNET_TINY_CARD, d / "maffnet-tiny.onnx", quantize="int8")
    return MAFFNET_TINY_CARD, d / "maffnet-tiny.onnx"


def invoke(*args):
    """Run the radaredge CLI in-process (click's runner); exceptions propagate."""
    from click.testing import CliRunner

    from radaredge.cli import main

    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def one_error_line(res, *needles) -> None:
    """A CLI result that ended with exit code 2, exactly one ``error:`` line containing each of
    ``needles``, and no traceback."""
    lines = res.output.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert res.exit_code == 2 and len(errors) == 1 and "Traceback" not in res.output, res.output
    for n in needles:
        assert n in errors[0], (n, errors[0])


def files_under(workdir: Path) -> set:
    """Every path under ``workdir``, relative to it (what a failed command must leave as it was)."""
    return {p.relative_to(workdir) for p in Path(workdir).rglob("*")}


def assert_one_error_line(res, workdir: Path, before: set, expect: str = "") -> None:
    """The bad-input catalogue's promise on the command line: exit code 2, exactly one line on
    stderr, starting with ``error:`` and containing ``expect``, no traceback, and nothing
    written under ``workdir`` (``before`` is :func:`files_under` taken before the command)."""
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.exit_code == 2, f"exit {res.exit_code}: {res.output}"
    assert "Traceback" not in res.output, res.output
    assert len(lines) == 1 and lines[0].startswith("error:"), res.stderr
    assert expect in lines[0], f"{expect!r} not in {lines[0]!r}"
    assert files_under(workdir) == before, "a file was left behind"


def export_with_cli(out_dir: Path, model: str, config: Path) -> Path:
    """``radaredge export --model MODEL --config CONFIG`` into out_dir/MODEL.onnx; the path."""
    path = Path(out_dir) / f"{model}.onnx"
    res = invoke("export", "--model", model, "--config", config, "--output", path)
    assert res.exit_code == 0, res.output
    return path


def summary_of(report: dict, graph: str | None = None) -> dict:
    """The per-output summary of one graph in a parity report's JSON (the only graph by default)."""
    graphs = report["graphs"]
    return (graphs[graph] if graph is not None else next(iter(graphs.values())))["summary"]


def assert_parses_in_tensorrt(path: Path) -> None:
    """``radaredge inspect --targets tensorrt`` finds nothing TensorRT 10 refuses in the export."""
    res = invoke("inspect", str(path), "--targets", "tensorrt", "--json")
    import json

    info = json.loads(res.stdout)
    refused = [f for g in info["graphs"] for f in g["targets"]["tensorrt"] if f["level"] == "unsupported"]
    assert res.exit_code == 0 and not refused, refused


BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def benchmark_module(name: str):
    """benchmarks/<name>.py loaded as a module (the scripts import their neighbours by name, so
    benchmarks/ goes on sys.path)."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
