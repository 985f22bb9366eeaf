"""The Python API is the CLI's: verbs importable from the package, the CLI a thin layer over them,
one code path for one- and multi-graph models, and the runtime metadata contract."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import TINY_CARD, invoke

import radaredge
from radaredge.errors import CapacityError, InputError
from radaredge.runtime.metadata import GraphMetadata, OutputCheck

PKG = Path(radaredge.__file__).parent


def test_verbs_import_from_the_package_without_torch():
    """``radaredge.export(...)`` etc. are the API's verbs; their machinery lives in packages named
    for the work (exporting, checking, benchmarking, training), so no name is both; importing
    radaredge, its CLI and its runtime loads no torch."""
    import radaredge.exporting.graphs  # noqa: F401
    from radaredge import api, bench, evaluate, export, parity, train

    assert (export, parity, bench, evaluate, train) == (api.export, api.parity, api.bench, api.evaluate, api.train)
    assert radaredge.export is api.export and radaredge.exporting.__name__ == "radaredge.exporting"
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, radaredge, radaredge.cli, radaredge.runtime; "
            "print(sorted(m for m in ('torch', 'onnx', 'onnxscript') if m in sys.modules))",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert done.stdout.strip() == "[]"


class _Result:
    def __init__(self, passed=True):
        self.passed = passed

    def __bool__(self):
        return self.passed

    def to_dict(self):
        return {"stub": True}

    def lines(self):
        return ["stub result"]

    def write_json(self, path):  # eval also writes its report and plot
        return path

    plot = write_json


@pytest.mark.parametrize(
    "command, verb, extra",
    [
        ("export", "export", ()),
        ("parity-check", "parity", ("--onnx", "x.onnx")),
        ("bench", "bench", ()),
        ("eval", "evaluate", ("--onnx", "x.onnx", "--database", ".", "--queries", ".")),
        ("train", "train", ("--data", ".")),
        ("quantize", "quantize", ("--onnx", "x.onnx", "--data", ".")),
    ],
)
def test_the_cli_calls_the_library_verbs(monkeypatch, command, verb, extra):
    """Each command parses its options, calls radaredge.api.<verb> and renders what it returns."""
    from radaredge import api

    calls = []
    monkeypatch.setattr(api, verb, lambda *a, **kw: calls.append((a, kw)) or _Result())
    res = invoke(command, "--model", "tdfanet-tiny", "--config", TINY_CARD, *extra, "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout) == {"stub": True}
    assert len(calls) == 1 and calls[0][0][0].name == "tdfanet-tiny"


def _leaf_commands(group, prefix=""):
    """(name, command) of every command, those of a command group (``card``) included."""
    import click

    for name, cmd in group.commands.items():
        if isinstance(cmd, click.Group):
            yield from _leaf_commands(cmd, f"{prefix}{name} ")
        else:
            yield prefix + name, cmd


def test_every_command_has_json():
    from radaredge.cli import main

    names = []
    for name, cmd in _leaf_commands(main):
        names.append(name)
        assert any("--json" in p.opts for p in cmd.params), f"{name} has no --json"
    assert "card from-openpcdet" in names


def test_card_from_openpcdet_is_the_api_verb(monkeypatch, tmp_path):
    """`radaredge card from-openpcdet` calls radaredge.api.card_from_openpcdet; radaredge.card_from_openpcdet is it."""
    import radaredge
    from radaredge import api

    assert radaredge.card_from_openpcdet is api.card_from_openpcdet
    calls = []

    class Conversion:
        card = {"name": "x", "source": {"config": "c.yaml"}}
        notes, keys = [], []

        def counts(self):
            return {"mapped": 1}

    monkeypatch.setattr(api, "card_from_openpcdet", lambda *a, **kw: calls.append((a, kw)) or Conversion())
    res = invoke("card", "from-openpcdet", "c.yaml", "--out", tmp_path / "x.yaml", "--stage-one", "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["counts"] == {"mapped": 1}
    assert calls[0][0] == ("c.yaml", str(tmp_path / "x.yaml")) and calls[0][1]["stage_two"] is False


def test_the_layers_hold():
    """import-linter's contracts (pyproject.toml): the layers, torch-free runtime and core, and no
    import cycle anywhere in radaredge/. ``make test`` runs it too, before the suite."""
    lint = Path(sys.executable).parent / "lint-imports"
    res = subprocess.run([str(lint)], cwd=PKG.parent, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 broken" in res.stdout


def test_no_module_is_left_for_bundles():
    assert not (PKG / "bundle.py").exists() and not (PKG / "models" / "des4pos_bench.py").exists()


# ----------------------------------------------------------------------------- metadata contract


def _meta(**kw) -> GraphMetadata:
    base = dict(
        model="m",
        card_yaml="name: m",
        features=["x", "y", "z"],
        input_names=["points"],
        dynamic_axes={"points": {"0": "num_points"}},
        frame_inputs=["points"],
        timestamps_input=None,
        output_names=["flag", "count"],
        weights_sha256="abc",
    )
    return GraphMetadata(**{**base, **kw})


def test_metadata_round_trips_through_props():
    check = OutputCheck("flag", True, "error", "{count} too many")
    meta = _meta(checks=[check], part="p", bundle_weights_sha256="def", quantization={"format": "QDQ"})
    props = meta.to_props()
    assert all(k.startswith("radaredge.") for k in props)
    assert GraphMetadata.from_props(props, "x.onnx") == meta


def test_metadata_errors_name_the_file_and_key():
    with pytest.raises(InputError, match="x.onnx is not a radaredge export"):
        GraphMetadata.from_props({}, "x.onnx")
    props = _meta().to_props()
    del props["radaredge.inputs"]
    with pytest.raises(InputError, match="x.onnx: its metadata lacks radaredge.inputs; re-export"):
        GraphMetadata.from_props(props, "x.onnx")
    props = _meta().to_props()
    props["radaredge.inputs"] = "{not json"
    with pytest.raises(InputError, match="x.onnx: unreadable radaredge metadata"):
        GraphMetadata.from_props(props, "x.onnx")


def test_output_checks_raise_or_warn_with_the_run_values():
    error = OutputCheck("flag", True, "error", "the scan has {count} pillars; {unknown} stays")
    with pytest.raises(CapacityError, match="the scan has 7 pillars; {unknown} stays"):
        error.apply({"flag": np.array(True), "count": np.array(7)})
    error.apply({"flag": np.array(False), "count": np.array(7)})  # not failing: silent
    error.apply({"count": np.array(7)})  # output absent: silent
    warn = OutputCheck("converged", False, "warn", "did not converge")
    with pytest.warns(RuntimeWarning, match="did not converge"):
        warn.apply({"converged": np.array(False)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn.apply({"converged": np.array(True)})
    with pytest.raises(ValueError, match="severity"):
        OutputCheck("flag", True, "fatal", "x")


def test_exported_graph_carries_the_contract(tiny_export):
    from radaredge import runtime

    _, _, path, _ = tiny_export
    m = runtime.load(path)
    assert m.info.frame_inputs == ["points_0", "points_1", "points_2"] and m.info.timestamps_input == "timestamps"
    assert m.info.output_names == m.output_names and m.info.input_names == m.input_names
    assert m.info.checks == [] and m.info.part is None and m.info.quantization is None
    info = runtime.inspect_export(path)["graphs"][0]
    assert info["model"] == "tdfanet-tiny" and info["frames"] == m.info.frame_inputs


def test_a_missing_optional_package_is_one_line_with_the_extra_to_install(monkeypatch):
    from radaredge import api

    def needs_torch(*a, **kw):
        raise ModuleNotFoundError("No module named 'torch'", name="torch")

    monkeypatch.setattr(api, "export", needs_torch)
    res = invoke("export", "--model", "tdfanet-tiny", "--config", TINY_CARD)
    assert res.exit_code == 2
    assert res.output.strip() == (
        "error: this command needs torch, which the base install leaves out: pip install 'radaredge[export]'"
    )


def test_bench_takes_only_the_int8_copy_of_its_own_graph(tiny_export, tmp_path):
    """--int8 must be an int8 copy of the bench's graph (same card and weights), or the row
    labelled int8 would time something else: a missing file, a file that is no graph, the fp32
    graph itself and another card's int8 graph are each one error."""
    _, _, path, _ = tiny_export
    res = invoke(
        "bench",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        path,
        "--int8",
        tmp_path / "typo.int8.onnx",
        "--runs",
        1,
    )
    assert res.exit_code == 2 and "typo.int8.onnx does not exist" in res.output
    junk = tmp_path / "junk.int8.onnx"
    junk.write_bytes(b"not onnx")
    res = invoke(
        "bench",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        path,
        "--int8",
        junk,
        "--runs",
        2,
        "--warmup",
        1,
        "--no-reference",
        "--no-openvino",
        "--json",
    )
    assert res.exit_code == 2 and "onnxruntime cannot load it" in res.output
    assert json.loads(res.stdout)["exit_code"] == 2  # --json: a JSON error document on stdout
    res = invoke("bench", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", path, "--int8", path, "--runs", 1)
    assert res.exit_code == 2 and "is not an int8 graph" in res.output
    reseeded = tmp_path / "tdfanet-tiny.yaml"
    reseeded.write_text(yaml.safe_dump({**yaml.safe_load(Path(TINY_CARD).read_text()), "seed": 5}))
    other = radaredge.export(str(reseeded), tmp_path / "other.onnx", quantize="int8").int8["tdfanet"]
    res = invoke(
        "bench", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", path, "--int8", other, "--runs", 1
    )
    assert res.exit_code == 2 and "is the int8 copy of another graph" in res.output


def test_a_multi_graph_export_refuses_a_file_as_its_directory(tmp_path):
    target = tmp_path / "taken.onnx"
    target.write_text("x")
    res = invoke(
        "export",
        "--model",
        "des4pos-tiny",
        "--config",
        Path(__file__).parent / "cards" / "des4pos-tiny.yaml",
        "--output",
        target,
    )
    assert res.exit_code == 2 and "exports 3 graphs into a directory" in res.output


@pytest.mark.parametrize(
    "args, message",
    [
        (("bench", "--threads", 0), "threads: expected an integer from 1 to"),
        (("bench", "--threads", 10**6), "threads: expected an integer from 1 to"),
        (("bench", "--runs", 0), "runs: expected an integer from 1 to 100000, got 0"),
        (("bench", "--warmup", -1), "warmup: expected an integer from 0 to 100000, got -1"),
        (("parity-check", "--onnx", "x.onnx", "--cases", 0), "cases: expected an integer from 1 to 10000, got 0"),
    ],
)
def test_counts_are_bounded_before_any_work(args, message):
    res = invoke(*args[:1], "--model", "tdfanet-tiny", "--config", TINY_CARD, *args[1:])
    assert res.exit_code == 2 and message in res.output
    assert res.output.count("error:") == 1 and "Traceback" not in res.output


def test_runtime_threads_are_bounded(tiny_export):
    from radaredge import runtime
    from radaredge.errors import ConfigError
    from radaredge.runtime.session import usable_cores

    with pytest.raises(ConfigError, match="threads: expected an integer from 1 to"):
        runtime.load(tiny_export[2], threads=10**6)
    with pytest.raises(ConfigError, match="threads"):
        runtime.load(tiny_export[2], threads=0)
    with pytest.warns(RuntimeWarning, match="more than the .* usable cores"):
        runtime.load(tiny_export[2], threads=usable_cores() + 1)


@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf"])
def test_non_finite_card_numbers_are_refused_by_field(tmp_path, value):
    card = tmp_path / "bad.yaml"
    card.write_text(TINY_CARD.read_text().replace("inlier_threshold: 0.15", f"inlier_threshold: {value}"))
    res = invoke("export", "--model", "bad", "--config", card, "--output", tmp_path / "bad.onnx")
    assert res.exit_code == 2 and "preprocess.ransac.inlier_threshold: expected a finite number" in res.output
    assert not (tmp_path / "bad.onnx").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (("bench", "--nope"), "error: No such option '--nope'."),
        (
            ("export", "--model", "tdfanet", "--opset", "x"),
            "error: Invalid value for '--opset': 'x' is not a valid integer.",
        ),
        (("export",), "error: Missing option '--model'."),
        (("no-such-command",), "error: No such command 'no-such-command'."),
    ],
)
def test_usage_errors_are_one_line(args, message):
    from click.testing import CliRunner

    from radaredge.cli import main

    res = CliRunner().invoke(main, list(args))
    assert res.exit_code == 2 and res.output.startswith(message) and res.output.count("\n") == 1, res.output


def test_unwritable_outputs_and_impossible_cities_are_one_error_before_any_work(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = invoke("export", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--output", blocker / "x.onnx")
    assert res.exit_code == 2 and f"--output: cannot create {blocker}: {blocker} is not a directory" in res.output
    assert "exporting" not in res.output  # refused before the model is built
    res = invoke("make-city", "--out", blocker / "city.npz", "--poses", 2)
    assert res.exit_code == 2 and res.output.strip() == f"error: {blocker}: not a directory"
    res = invoke("make-city", "--out", tmp_path / "city.npz", "--objects", 0)
    assert res.exit_code == 2 and "Invalid value for '--objects'" in res.output


def test_the_command_line_only_parses_and_renders():
    """cli.py imports everything at its top (the verbs load their machinery lazily, in
    radaredge.api): no import inside a function, and every command calls a verb of radaredge.api."""
    import ast
    import inspect as pyinspect

    import radaredge.cli as cli
    from radaredge import api

    tree = ast.parse(pyinspect.getsource(cli))
    nested = [
        f"{fn.name}: line {node.lineno}"
        for fn in ast.walk(tree)
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
        for node in ast.walk(fn)
        if isinstance(node, (ast.Import, ast.ImportFrom))
    ]
    assert not nested, f"imports inside cli functions: {nested}"
    for verb in ("make_benchmark", "make_city", "locate", "inspect"):
        assert callable(getattr(api, verb)) and f"api.{verb}(" in pyinspect.getsource(cli)
