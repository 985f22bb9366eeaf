"""The radaredge CLI end to end, including the full cards (export + parity on each)."""

import json
import shutil

import pytest
from click.testing import CliRunner
from conftest import TINY_CARD, assert_parses_in_tensorrt, summary_of

from radaredge import runtime
from radaredge.cli import main

TINY = str(TINY_CARD)


def invoke(*args):
    return CliRunner().invoke(main, list(args), catch_exceptions=False)


def test_help_lists_the_commands():
    res = invoke("--help")
    assert res.exit_code == 0
    for cmd in ("export", "parity-check", "bench", "list", "inspect"):
        assert cmd in res.output


def test_list_shows_the_shipped_cards():
    res = invoke("list", "--json")
    names = {c["name"] for c in json.loads(res.stdout)}
    assert {"tdfanet", "tdfanet-edge"} <= names


def test_unknown_model_is_a_clear_error():
    res = CliRunner().invoke(main, ["export", "--model", "nope"])
    assert res.exit_code == 2 and "no model card 'nope'" in res.output


@pytest.mark.parametrize("model", ["tdfanet", "tdfanet-edge"])
def test_full_card_export_and_parity(model, tmp_path):
    onnx = tmp_path / f"{model}.onnx"
    res = invoke("export", "--model", model, "--output", str(onnx))
    assert res.exit_code == 0, res.output
    side = json.loads(onnx.with_suffix(".json").read_text())
    assert side["model"] == model and side["op_histogram"]
    assert side["inputs"][0] == {"name": "points_0", "shape": ["num_points_0", 5]}
    assert side["inputs"][-1] == {"name": "timestamps", "shape": [3]}
    assert_parses_in_tensorrt(onnx)
    res = invoke("parity-check", "--model", model, "--onnx", str(onnx), "--cases", "4", "--json")
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert summary_of(report)["descriptor_normalized"]["min_cosine"] >= 0.9999
    assert summary_of(report)["ego_velocity"]["max_abs"] <= 1e-4


def test_parity_refuses_an_onnx_with_other_weights(tmp_path):
    onnx = tmp_path / "tiny.onnx"
    assert invoke("export", "--model", "tdfanet-tiny", "--config", TINY, "--output", str(onnx)).exit_code == 0
    res = CliRunner().invoke(main, ["parity-check", "--model", "tdfanet", "--onnx", str(onnx), "--cases", "1"])
    assert res.exit_code == 2 and "other weights" in res.output


def test_bench_json_reports_every_backend(tmp_path, tiny_export):
    saved = tmp_path / "results" / "tiny.json"
    res = invoke(
        "bench",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY,
        "--onnx",
        str(tiny_export[2]),
        "--runs",
        "3",
        "--warmup",
        "1",
        "--json",
        "--save",
        saved,
    )
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert json.loads(saved.read_text()) == out
    rows = out["tasks"]["tdfanet"]["rows"]
    assert [r["backend"] for r in rows] == ["torch reference", "torch export", "onnxruntime", "openvino"]
    assert all(r["fps"] > 0 and r["status"] == "ok" for r in rows)
    assert out["graphs"]["tdfanet"]["onnxruntime_peak_rss_mib"] > 0


def test_a_failing_backend_is_a_row_not_an_abort():
    """Ultralytics-style: the backend that raises gets status error and its reason; the rest are timed."""
    from radaredge.benchmarking.timing import benchmark, results_table

    def broken(case):
        raise RuntimeError("no kernel for this op\nsecond line")

    rows = benchmark({"good": lambda case: None, "bad": broken}, [{}], runs=2, warmup=1)
    assert [(r.backend, r.status) for r in rows] == [("good", "ok"), ("bad", "error")]
    assert rows[0] and not rows[1] and rows[1].error == "RuntimeError: no kernel for this op"
    assert rows[0].runs == 2 and rows[1].p50_ms is None
    assert "| bad | error: RuntimeError: no kernel for this op |" in results_table(rows, "good")


def test_bench_profile_comes_from_its_own_session(tmp_path, monkeypatch, tiny_export):
    """--profile: top ops per run from a profiled session, while the timed session is not profiled
    (onnxruntime's profiler slows every node); the profiler's JSON file is not left behind."""
    import tempfile

    import radaredge.runtime.session as ort_helpers

    opened = []
    real = ort_helpers.make_session

    def spy(path, threads=2, profile=False, **kw):
        opened.append(profile)
        return real(path, threads=threads, profile=profile, **kw)

    monkeypatch.setattr(ort_helpers, "make_session", spy)
    import radaredge.benchmarking.profiling

    monkeypatch.setattr(radaredge.benchmarking.profiling, "make_session", spy)
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    res = invoke(
        "bench",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY,
        "--onnx",
        str(tiny_export[2]),
        "--runs",
        "3",
        "--warmup",
        "1",
        "--no-reference",
        "--profile",
    )
    assert res.exit_code == 0, res.output
    assert opened[0] is False and True in opened, opened
    assert "kernel ms per run" in res.output
    res = invoke(
        "bench",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY,
        "--onnx",
        str(tiny_export[2]),
        "--runs",
        "3",
        "--warmup",
        "1",
        "--no-reference",
        "--profile",
        "--json",
    )
    top = json.loads(res.stdout)["graphs"]["tdfanet"]["top_ops"]
    assert top and all(ms > 0 for _, ms in top)
    assert list((tmp_path / "tmp").iterdir()) == []


def test_quantize_export_parity_and_bench(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    onnx = tmp_path / "tiny.onnx"
    res = invoke(
        "export", "--model", "tdfanet-tiny", "--config", TINY, "--output", str(onnx), "--quantize", "int8",
        "--calibration-method", "percentile",
    )  # fmt: skip
    assert res.exit_code == 0 and "int8 graph" in res.output
    int8 = tmp_path / "tiny.int8.onnx"
    assert json.loads(runtime.load(int8).metadata["radaredge.quantization"])["calibration"]["method"] == "percentile"
    res = invoke(
        "parity-check", "--model", "tdfanet-tiny", "--config", TINY, "--onnx", str(int8), "--cases", "4", "--quantized"
    )
    assert res.exit_code == 0 and "[int8 budget]" in res.output and "PASSED" in res.output
    # the fp32 graph with --quantized: its int8 copy beside it is checked, as for a multi-graph bundle
    res = invoke(
        "parity-check", "--model", "tdfanet-tiny", "--config", TINY, "--onnx", str(onnx), "--cases", "1", "--quantized"
    )
    assert res.exit_code == 0 and "tiny.int8.onnx" in res.output and "[int8 budget]" in res.output
    lone = tmp_path / "lone.onnx"
    shutil.copyfile(onnx, lone)
    res = CliRunner().invoke(
        main,
        [
            "parity-check",
            "--model",
            "tdfanet-tiny",
            "--config",
            TINY,
            "--onnx",
            str(lone),
            "--cases",
            "1",
            "--quantized",
        ],
    )
    assert res.exit_code == 2 and "lone.int8.onnx does not exist" in res.output
    shutil.copyfile(onnx, tmp_path / "lone.int8.onnx")  # an fp32 graph named like an int8 copy
    res = CliRunner().invoke(
        main,
        [
            "parity-check",
            "--model",
            "tdfanet-tiny",
            "--config",
            TINY,
            "--onnx",
            str(lone),
            "--cases",
            "1",
            "--quantized",
        ],
    )
    assert res.exit_code == 2 and "not an int8 export" in res.output
    res = invoke(
        "bench",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY,
        "--onnx",
        str(onnx),
        "--runs",
        "2",
        "--warmup",
        "1",
        "--no-reference",
    )
    assert res.exit_code == 0 and "| onnxruntime int8 |" in res.output and "int8 vs fp32" in res.output


def test_warnings_wait_for_success_and_never_precede_an_error(monkeypatch):
    """A RuntimeWarning raised while a command runs is printed after it succeeds, as one
    ``warning:`` line; when the command then fails, stderr holds the error line alone."""
    import warnings

    import radaredge.api
    from radaredge.errors import ConfigError

    def noisy(*args, **kwargs):
        warnings.warn("overflow encountered in multiply", RuntimeWarning)
        warnings.warn("overflow encountered in multiply", RuntimeWarning)
        raise ConfigError("the card is wrong")

    monkeypatch.setattr(radaredge.api, "export", noisy)
    res = CliRunner().invoke(main, ["export", "--model", "tdfanet-tiny", "--config", TINY])
    assert res.exit_code == 2 and res.stderr == "error: the card is wrong\n"
    res = CliRunner().invoke(main, ["export", "--model", "tdfanet-tiny", "--config", TINY, "--json"])
    assert res.exit_code == 2 and json.loads(res.stdout) == {"error": "the card is wrong", "exit_code": 2}


def test_json_documents_are_strict_json():
    """Non-finite numbers (a training metric before the first validation) become null."""
    from radaredge.atomic import dumps as _dumps

    text = _dumps({"loss": float("nan"), "recall": [float("inf"), 1.0], "n": 3})
    assert json.loads(text) == {"loss": None, "recall": [None, 1.0], "n": 3}
    assert "NaN" not in text and "Infinity" not in text
