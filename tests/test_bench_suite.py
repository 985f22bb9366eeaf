"""The benchmark suite script end to end on the tiny card (few runs: this checks the plumbing,
the table and the chart, not speed), the MAC counter's extra formulas and the harness's idle
pause before each timed run."""

import importlib.util
import json
import shutil
from pathlib import Path

import torch

from radaredge.benchmarking import timing as bench
from radaredge.benchmarking.macs import count_macs

ROOT = Path(__file__).resolve().parent.parent


def test_mac_counter_counts_grid_sample_and_scatter():
    value = torch.rand(2, 3, 8, 8)
    grid = torch.rand(2, 5, 7, 2) * 2 - 1
    macs = count_macs(lambda: torch.nn.functional.grid_sample(value, grid, align_corners=False))
    assert macs["grid_sampler_2d"] == 4 * 2 * 3 * 5 * 7
    src = torch.rand(10, 4)
    idx = torch.randint(0, 6, (10,))
    macs = count_macs(lambda: torch.zeros(6, 4).index_add(0, idx, src))
    assert macs["index_add"] == 40
    macs = count_macs(lambda: torch.nn.functional.linear(torch.rand(3, 4), torch.rand(5, 4)))
    assert macs["total"] == 3 * 4 * 5


def test_suite_writes_table_json_and_chart(tmp_path, monkeypatch, tiny_export):
    monkeypatch.setenv("RADAREDGE_CARDS", str(ROOT / "tests" / "cards"))
    spec = importlib.util.spec_from_file_location("bench_suite", ROOT / "benchmarks" / "run.py")
    suite = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(suite)
    export_dir = tmp_path / "export"  # a copy: the suite adds an int8 graph beside it
    export_dir.mkdir()
    shutil.copy(tiny_export[2], export_dir / "tdfanet-tiny.onnx")
    assert (
        suite.main(
            [
                "--models",
                "tdfanet-tiny",
                "maffnet-tiny",
                "--runs",
                "2",
                "--export-dir",
                str(export_dir),
                "--out",
                str(tmp_path / "bench"),
            ]
        )
        == 0
    )
    table = (tmp_path / "bench" / "README.md").read_text()
    for model in ("tdfanet-tiny", "maffnet-tiny"):  # maffnet-tiny is exported and quantised by the suite
        for backend in ("torch reference", "torch export", "onnxruntime", "onnxruntime int8"):
            assert f"| {model} | {backend} |" in table
    assert (tmp_path / "bench" / "suite.png").stat().st_size > 1000
    data = json.loads(next((tmp_path / "bench" / "results").glob("suite-*.json")).read_text())
    row = data["models"][0]
    assert row["rows"][0]["gmacs"] > 0 and 0 < row["quantised_op_time_share"] < 1
    assert data["gemm_peak_gflops"] > 0
    # the tiny cards are timed seeded; a card the zoo holds with the zoo's trained weights
    assert [m["weights"] for m in data["models"]] == ["seeded", "seeded"] and "| tdfanet-tiny | seeded |" in table
    assert suite.zoo_weights("maffnet-vod-edge") == ROOT / "zoo" / "maffnet-vod-edge" / "weights.pth"
    assert suite.zoo_weights("tdfanet-tiny") is None


def test_every_timed_run_starts_after_the_settle_pause(monkeypatch):
    """The previous backend's spinning worker threads must not be timed into the next one."""
    events = []
    monkeypatch.setattr(bench.time, "sleep", lambda s: events.append(("sleep", s)))
    backends = {"a": lambda feeds: events.append("a"), "b": lambda feeds: events.append("b")}
    results = bench.benchmark(backends, [{}], runs=2, warmup=1)
    assert [r.runs for r in results] == [2, 2]
    pause = ("sleep", bench.SETTLE_S)
    assert bench.SETTLE_S > 0
    # warm-up a, b without pauses; then run 0 (a, b) and run 1 (b first: rotation), each paused
    assert events == ["a", "b", pause, "a", pause, "b", pause, "b", pause, "a"]


def test_int8_dot_product_instructions_are_read_from_cpuinfo():
    """The int8 dot-product sets that decide whether int8 pays, from x86 flags and Arm features."""
    x86 = "processor\t: 0\nmodel name\t: cpu\nflags\t\t: fpu avx2 avx512f avx512_vnni avx_vnni\n"
    assert bench.int8_dot_product(x86) == ["AVX-512 VNNI", "AVX-VNNI"]
    assert bench.int8_dot_product("flags\t\t: fpu avx2 fma\n") == []
    assert bench.int8_dot_product("Features\t: fp asimd asimddp\n") == ["Arm dot product"]
    assert bench.int8_dot_product_text([]) == "no int8 dot-product instructions"
    assert bench.int8_dot_product_text(None) == "int8 dot-product instructions not known"  # no /proc/cpuinfo
