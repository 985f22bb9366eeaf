"""The one exporter entry point: its constant-folding policy keeps tensor generators out of the file."""

import os
from pathlib import Path

import numpy as np
import onnx
import torch
from conftest import TINY_CARD, assert_close
from torch import nn

CELLS = 30000  # 30000 x 8 = 240k floats: under the optimiser's 262144-element folding limit


class ZeroCanvasScatter(nn.Module):
    """Points [N, 8] added into a zero canvas of CELLS cells, as a pillar scatter does."""

    def forward(self, cell: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
        return torch.zeros(CELLS, 8).index_add(0, cell, value)


def test_zero_canvas_is_not_stored_in_the_file(onnx_roundtrip, tmp_path):
    example = {"cell": torch.tensor([0, 5, 5, CELLS - 1]), "value": torch.randn(4, 8)}
    rt = onnx_roundtrip(ZeroCanvasScatter(), example, ["canvas"], {"cell": {0: "N"}, "value": {0: "N"}})
    path = tmp_path / "ZeroCanvasScatter.onnx"
    largest = max((int(np.prod(t.dims)) for t in onnx.load(str(path)).graph.initializer), default=0)
    assert largest < 100, f"a {largest}-element constant was folded into the file"
    assert path.stat().st_size < 20_000, f"{path.stat().st_size} bytes for a graph without weights"
    g = torch.Generator().manual_seed(0)
    feeds = {"cell": torch.randint(0, CELLS, (50,), generator=g), "value": torch.randn(50, 8, generator=g)}
    ref, got = rt(feeds)
    assert_close(got["canvas"], ref["canvas"], 1e-5, "onnxruntime vs torch")


class ConvWithoutBias(nn.Module):
    """A bias=False convolution followed by a batch norm, as the TDFANet pyramid builds them."""

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, 8, 3, padding=1, bias=False)
        self.bn = nn.BatchNorm2d(8).eval()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.bn(self.conv(x))


def test_a_bias_free_layer_reads_a_constant_zero_bias(onnx_roundtrip, tmp_path):
    """The exporter writes a bias=False layer's bias as Expand(0, [C]). That small fill folds,
    so the Conv reads a constant: onnxruntime's Conv+BatchNorm fusion and the int8 quantiser
    need one. Without the fold the bias stays a computed tensor (this test then finds the Expand)."""
    example = {"x": torch.randn(1, 3, 6, 5)}
    rt = onnx_roundtrip(ConvWithoutBias(), example, ["y"])
    graph = onnx.load(str(tmp_path / "ConvWithoutBias.onnx")).graph
    constants = {t.name for t in graph.initializer} | {
        o for n in graph.node if n.op_type == "Constant" for o in n.output
    }
    assert [n.op_type for n in graph.node if n.op_type in ("Expand", "ConstantOfShape", "Tile")] == []
    conv = next(n for n in graph.node if n.op_type == "Conv")
    assert len(conv.input) == 3 and conv.input[2] in constants
    ref, got = rt(example)
    assert_close(got["y"], ref["y"], 1e-5, "onnxruntime vs torch")


def test_the_graph_has_the_opset_asked_for_or_none_is_written(tmp_path):
    """A model the exporter can convert comes out at the requested opset; one it cannot (the
    tiny TDFANet at opset 17) is refused with the opset it kept, and no file is left claiming it."""
    from click.testing import CliRunner
    from conftest import TINY_CARD

    from radaredge.cli import main
    from radaredge.exporting.onnx_call import export_onnx

    class Double(nn.Module):
        def forward(self, x):
            return torch.relu(x) * 2

    path = export_onnx(Double(), (torch.ones(3),), tmp_path / "double.onnx", ["x"], ["y"], opset=17)
    assert [o.version for o in onnx.load(str(path)).opset_import if o.domain in ("", "ai.onnx")] == [17]
    out = tmp_path / "tiny.onnx"
    res = CliRunner().invoke(
        main, ["export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output", str(out), "--opset", "17"]
    )
    assert res.exit_code == 2
    assert "error: opset 17: torch's exporter could not convert this graph to it and kept opset 18" in res.output
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_exports_are_byte_identical_across_install_locations(tmp_path):
    """Two copies of radaredge in two directories export one card to the same bytes: no absolute
    path, stack trace or other provenance stays in the graph."""
    import hashlib
    import shutil
    import subprocess
    import sys

    import radaredge

    digests = []
    for where in ("one", "two/deeper"):
        src = tmp_path / where / "src"
        shutil.copytree(
            Path(radaredge.__file__).parent, src / "radaredge", ignore=shutil.ignore_patterns("__pycache__")
        )
        out = tmp_path / where / "tiny.onnx"
        code = "import sys; from radaredge.cli import main; sys.exit(main())"
        subprocess.run(
            [
                sys.executable,
                "-c",
                code,
                "export",
                "--model",
                "tdfanet-tiny",
                "--config",
                str(TINY_CARD),
                "--output",
                str(out),
            ],
            check=True,
            capture_output=True,
            cwd=tmp_path / where,
            env={**os.environ, "PYTHONPATH": str(src)},
        )
        digests.append(hashlib.sha256(out.read_bytes()).hexdigest())
        proto = onnx.load(str(out))
        assert {p.key for n in proto.graph.node for p in n.metadata_props} <= {"pkg.torch.onnx.name_scopes"}
        assert str(tmp_path).encode() not in out.read_bytes()
    assert digests[0] == digests[1]


class AnyOfPoints(nn.Module):
    """Whether any of N values is positive, per row of a [2, N] table and over all of it."""

    def forward(self, x: torch.Tensor):
        from radaredge.ops.reduce import any_true

        m = x > 0
        return any_true(m, 1), any_true(m)


def test_any_true_is_false_on_an_empty_axis_in_the_graph(onnx_roundtrip):
    """torch's ``any`` exports as a ReduceMax, which onnxruntime answers True over zero elements;
    ``any_true`` is False there, as in eager torch (an empty scan once set every input flag)."""
    rt = onnx_roundtrip(
        AnyOfPoints(), {"x": torch.tensor([[1.0, -1.0, 2.0], [-1.0, -2.0, -3.0]])}, ["rows", "all"], {"x": {1: "N"}}
    )
    for x in (torch.tensor([[1.0, -1.0], [-1.0, -2.0]]), torch.zeros(2, 0)):
        ref, got = rt({"x": x})
        assert got["rows"].tolist() == ref["rows"].tolist() and bool(got["all"]) == bool(ref["all"])
