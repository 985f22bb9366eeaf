"""The documentation stays true: README.md is short, undated and lists every command;
benchmarks/README.md is exactly what benchmarks/render.py makes of the committed JSON; every
relative link in README.md and docs/ points at a file (and heading) that exists. Fast, no torch."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DATE = re.compile(r"20\d\d-\d\d-\d\d")
# [text](target) and ![alt](target); the target ends at whitespace or ')'.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
CODE_FENCE = re.compile(r"^(```|~~~)")


def _render_module():
    spec = importlib.util.spec_from_file_location("benchmarks_render", ROOT / "benchmarks" / "render.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _doc_files() -> list[Path]:
    return [README] + sorted((ROOT / "docs").rglob("*.md"))


def _unfenced(text: str) -> list[str]:
    """The lines of ``text`` outside fenced code blocks."""
    out, fenced = [], False
    for line in text.splitlines():
        if CODE_FENCE.match(line.strip()):
            fenced = not fenced
        elif not fenced:
            out.append(line)
    return out


def _prose(text: str) -> str:
    """``text`` without code blocks and inline code, where brackets are not links."""
    return "\n".join(re.sub(r"`[^`]*`", "", line) for line in _unfenced(text))


def _slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    anchors, seen = set(), {}
    for line in _unfenced(path.read_text()):
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*$", line)
        if m:
            slug = _slug(m.group(1))
            n = seen.get(slug, 0)
            anchors.add(slug if n == 0 else f"{slug}-{n}")
            seen[slug] = n + 1
    return anchors


def test_readme_is_short_and_undated():
    lines = README.read_text().splitlines()
    assert len(lines) < 250, f"README.md has {len(lines)} lines; move detail to docs/"
    dated = [f"{i}: {line}" for i, line in enumerate(lines, 1) if DATE.search(line)]
    assert not dated, "README.md must not carry dated measurements:\n" + "\n".join(dated)


def test_readme_lists_every_command():
    from radaredge.cli import main

    text = README.read_text()
    missing = [name for name in main.commands if not re.search(rf"radaredge {re.escape(name)}\b", text)]
    assert not missing, f"README.md does not show `radaredge <command>` for: {missing}"


def test_benchmarks_readme_is_generated_from_results():
    render = _render_module()
    expected = render.render(ROOT / "benchmarks" / "results")
    committed = (ROOT / "benchmarks" / "README.md").read_text()
    assert committed == expected, (
        "benchmarks/README.md differs from the committed JSON's rendering; "
        "run `python benchmarks/render.py` (never edit it by hand)"
    )


def test_generated_tables_in_docs_are_the_results_rendering():
    """docs/models/maffnet.md's trade-off and docs/quantization.md's int8 methods are what
    benchmarks/render.py makes of the newest committed results between the page's markers."""
    render = _render_module()
    results = render.load(ROOT / "benchmarks" / "results")
    for block in render.GENERATED:
        committed = (ROOT / "docs" / block.page).read_text()
        assert block.begin in committed and block.end in committed, block.page
        assert committed == block.fill(committed, results), (
            f"docs/{block.page}: {block.name} differs from the committed JSON's rendering; "
            "run `python benchmarks/render.py`"
        )


def test_render_handles_every_result_kind(tmp_path):
    """A minimal file of each kind renders, the newest of a kind is the one shown, older ones go
    to the history, and a failed backend row (status, no timing) does not break the table."""
    import json

    render = _render_module()
    res = tmp_path / "results"
    res.mkdir()
    row = {"backend": "onnxruntime", "p50_ms": 10.0, "p90_ms": 12.0, "p99_ms": 13.0, "fps": 100.0}
    suite = {
        "date": "2030-01-02 00:00 UTC",
        "cpu": "cpu",
        "threads": 2,
        "cores": [0, 1],
        "runs": 5,
        "gemm_peak_gflops": 50.0,
        "models": [
            {
                "model": "m",
                "rows": [{**row, "gmacs": 1.0, "peak_fraction": 0.5}],
                "ort_vs_reference": 2.0,
                "int8_vs_fp32": 1.0,
                "quantised_op_time_share": 0.3,
            }
        ],
    }
    (res / "suite-2030-01-01.json").write_text(json.dumps({**suite, "date": "2030-01-01 00:00 UTC"}))
    (res / "suite-2030-01-02.json").write_text(json.dumps(suite))
    failed = {
        "backend": "openvino",
        "runs": 0,
        "p50_ms": None,
        "p90_ms": None,
        "p99_ms": None,
        "mean_ms": None,
        "fps": None,
        "status": "error",
        "error": "not installed",
    }
    (res / "m-2030-01-02.json").write_text(
        json.dumps(
            {  # `radaredge bench --save`
                "model": "m",
                "threads": 2,
                "cores": [0, 1],
                "cpu": "cpu",
                "runs": 5,
                "date": "2030-01-02 00:00 UTC",
                "tasks": {
                    "m": {
                        "title": "",
                        "baseline": "torch reference",
                        "rows": [{**row, "status": "ok"}, failed],
                        "onnxruntime_speedup": {},
                        "int8_vs_fp32": None,
                        "openvino_vs_onnxruntime": None,
                    }
                },
                "graphs": {
                    "m": {
                        "stage_ms": {"onnxruntime": {"a": 1.0, "b": 2.0}},
                        "top_ops": [["Conv", 3.0]],
                        "onnxruntime_peak_rss_mib": 100.0,
                        "openvino_vs_onnxruntime_max_abs": None,
                    }
                },
            }
        )
    )
    (res / "m-2030-01-01.json").write_text(json.dumps({"model": "m", "date": "2030-01-01 00:00 UTC", "results": [row]}))
    (res / "compare-x-2030-01-01.json").write_text(
        json.dumps(
            {
                "model": "m",
                "cases": ["c"],
                "points": [3],
                "runs": 5,
                "threads": 2,
                "profile_rounds": 5,
                "date": "2030-01-01 00:00 UTC",
                "graphs": [
                    {"onnx": "a.onnx", "p50_ms": 1.0, "p90_ms": 2.0, "stage_ms": {"s": 1.0}},
                    {"onnx": "b.onnx", "p50_ms": 1.5, "p90_ms": 2.5, "stage_ms": {"s": 1.2}},
                ],
            }
        )
    )
    (res / "maffnet-capacity-2030-01-01.json").write_text(
        json.dumps(
            {
                "card": "m",
                "spa_capacity": 10,
                "dbscan_capacity": 20,
                "clouds": [{"seed": 0}, {"seed": 0}],
                "camera_fov": {"points": 8, "scan_points": 5, "pillars": 4},
                "no_crop": {"points": 9, "scan_points": 6, "pillars": 5},
                "date": "2030-01-01 00:00 UTC",
            }
        )
    )
    (res / "cfa-speedup-2030-01-01.json").write_text(
        json.dumps(
            {
                "card": "m",
                "date": "2030-01-01 00:00 UTC",
                "rows": [
                    {
                        "scans": 1,
                        "points": 3,
                        "part": "map",
                        "backend": "up",
                        "p50_ms": 2.0,
                        "speedup_vs_upstream": 1.0,
                    },
                    {
                        "scans": 1,
                        "points": 3,
                        "part": "map",
                        "backend": "ours",
                        "p50_ms": 1.0,
                        "speedup_vs_upstream": 2.0,
                    },
                ],
            }
        )
    )
    (res / "maffnet-train-step-2030-01-01.json").write_text(
        json.dumps(
            {
                "card": "m",
                "date": "2030-01-01 00:00 UTC",
                "cpu": "cpu",
                "threads": 2,
                "steps": 5,
                "batch_size": 4,
                "weights": "seeded",
                "rows": [
                    {"precision": "bf16", "formulation": "before", "median_s": 1.0, "p90_s": 1.1, "speedup": 1.0},
                    {"precision": "bf16", "formulation": "after", "median_s": 0.5, "p90_s": 0.6, "speedup": 2.0},
                ],
            }
        )
    )
    trained_row = {
        "p50_ms": 50.0,
        "p90_ms": 60.0,
        "fps": 20.0,
        "candidates_median": 12.0,
        "candidates_max": 40,
        "detections_median": 5.0,
    }
    (res / "maffnet-trained-m-2030-01-01.json").write_text(
        json.dumps(
            {
                "model": "m",
                "checkpoint": "best.pth",
                "checkpoint_sha256": "ab" * 32,
                "data": "set",
                "split": "test",
                "frames": ["00001"],
                "points_median": 900.0,
                "passes": 3,
                "date": "2030-01-01 00:00 UTC",
                "cpu": "cpu",
                "rows": [
                    {
                        **trained_row,
                        "graph": "fp32",
                        "stage_ms": {"NMS": 2.0, "backbone+head": 30.0},
                        "nms_share": 0.0625,
                    },
                    {**trained_row, "graph": "int8", "stage_ms": {}, "nms_share": None},
                    {**trained_row, "graph": "worst case", "stage_ms": {"NMS": 90.0}, "nms_share": 0.75},
                ],
            }
        )
    )
    ap = {"Car": {"3d": 50.0, "bev": 60.0, "num_gt": 10}, "Pedestrian": {"3d": 10.0, "bev": 12.0, "num_gt": 5}}
    report = {
        "ap": {"onnxruntime": {"entire_area": ap}, "onnxruntime int8": {"entire_area": ap}},
        "fps": {"onnxruntime": 20.0, "onnxruntime int8": 25.0},
        "frames": 8,
    }
    (res / "m-training-2030-01-01.json").write_text(
        json.dumps(
            {
                "date": "2030-01-01 00:00",
                "card": "m",
                "command": "radaredge train --model m --data set",
                "checkpoint_sha256": "ab" * 32,
                "machine": {"cpu": "cpu", "threads": 2},
                "train_seconds": 60.0,
                "test_trained": report,
                "test_seeded": report,
                "train": {
                    "best_epoch": 1,
                    "data": {"train_frames": 8},
                    "epochs": [
                        {"epoch": 0, "loss": float("nan"), "AP3d_Car": 0.0, "mAP3d": 0.0, "seconds": 1.0},
                        {"epoch": 1, "loss": 1.0, "AP3d_Car": 40.0, "mAP3d": 20.0, "seconds": 60.0},
                    ],
                },
            }
        )
    )
    later = json.loads((res / "m-training-2030-01-01.json").read_text())  # a second run that day
    later["date"], later["train_seconds"] = "2030-01-01 12:00", 90.0
    (res / "m-training-2030-01-01-1200.json").write_text(json.dumps(later))
    recall = {
        "evaluated": 90,
        "recall": {"1": 40.0, "5": 60.0, "10": 70.0},
        "interval_95": {"1": [30.0, 50.0], "5": [50.0, 70.0], "10": [60.0, 80.0]},
    }
    by_direction = {
        "with": {"evaluated": 80, "recall_at_1": 45.0, "interval_95": [35.0, 55.0]},
        "against": {"evaluated": 10, "recall_at_1": 0.0, "interval_95": [0.0, 0.0]},
    }
    chance = {
        "5": {"recall_at_1": 0.35, "database_within": 9.0, "database_scans": 2600, "query_scans": 2800},
        "25": {"recall_at_1": 2.1, "database_within": 55.0, "database_scans": 2600, "query_scans": 2800},
    }
    (res / "place-recognition-m-2030-01-01.json").write_text(
        json.dumps(
            {
                "date": "2030-01-01 00:00",
                "card": "m",
                "command": "python benchmarks/place_recognition.py --card m",
                "machine": {"cpu": "cpu", "threads": 2},
                "frames_per_window": 5,
                "checkpoint": "best.pth",
                "train_seconds": 600.0,
                "chance": {"town-1000": chance},
                "towns": {
                    "design": {"seeds": [1], "route_km": 1.0, "used_for": "training"},
                    "test": {"seeds": [1000], "route_km": 2.2, "used_for": "this table only"},
                },
                "rows": {
                    k: {"5": {**recall, "by_direction": by_direction}, "25": recall}
                    for k in ("no_learning", "seeded", "trained_fp32", "trained_int8")
                },
            }
        )
    )
    best = {
        "epoch": 2,
        "val_R@1": 50.0,
        "val_R@5": 70.0,
        "val_R@10": 80.0,
        "val_queries": 200,
        "val_R@1_interval_95": [43.0, 57.0],
    }
    variant = {"best": best, "train_seconds": 600.0, "test": {"5": recall, "25": recall}}
    (res / "tdfanet-variants-m-2030-01-01.json").write_text(
        json.dumps(
            {
                "date": "2030-01-01 00:00",
                "card": "m",
                "command": "python benchmarks/tdfanet_variants.py --card m",
                "machine": {"cpu": "cpu", "threads": 2},
                "recipe": {"epochs": 3, "tuples_per_epoch": 200},
                "towns": {
                    "design": {"seeds": [1], "route_km": 0.5, "used_for": "training"},
                    "test": {"seeds": [1000], "route_km": 2.2, "used_for": "the ablations"},
                },
                "choices": ["frozen", "window"],
                "ablations": {"full": "frozen", "sum": "sum"},
                "variants": {
                    "frozen": variant,
                    "sum": variant,
                    "window": {k: v for k, v in variant.items() if k != "test"},
                },
            }
        )
    )
    long = {"best": best, "train_seconds": 900.0, "test": {"5": {**recall, "by_direction": by_direction}, "25": recall}}
    (res / "tdfanet-variants-m-5x500-2030-01-01.json").write_text(
        json.dumps(
            {  # another recipe, ablations only
                "date": "2030-01-01 00:00",
                "card": "m",
                "command": "python benchmarks/tdfanet_variants.py --card m",
                "machine": {"cpu": "cpu", "threads": 2},
                "recipe": {"epochs": 5, "tuples_per_epoch": 500},
                "towns": {
                    "design": {"seeds": [1], "route_km": 0.5, "used_for": "training"},
                    "test": {"seeds": [1000], "route_km": 2.2, "used_for": "the ablations"},
                },
                "choices": ["frozen", "window"],
                "ablations": {"full": "frozen", "sum": "sum"},
                "variants": {"sum": long},
            }
        )
    )
    table = {"1": {"5": 30.0}}
    held = {
        "localization": table,
        "localization_interval": {"1": {"5": [25.0, 35.0]}},
        "localization_centre": {"1": {"5": 25.0}},
        "localization_centre_interval": {"1": {"5": [20.0, 30.0]}},
        "localization_gain": {"1": {"5": 5.0}},
        "localization_gain_interval": {"1": {"5": [1.0, 9.0]}},
        "retrieval": {"1": 50.0},
    }
    (res / "des4pos-training-2030-01-01.json").write_text(
        json.dumps(
            {
                "date": "2030-01-01 00:00",
                "card": "des4pos",
                "command": "radaredge train --model des4pos --data cities",
                "eval_command": "radaredge eval --model des4pos",
                "machine": {"cpu": "cpu", "threads": 2},
                "train_seconds": 60.0,
                "parity": {"trained": {"passed": True}, "seeded": {"passed": True}},
                "train": {
                    "stage_best": {"fine": 1},
                    "data": {"maps": 2},
                    "epochs": [{"stage": "fine", "epoch": 1, "loss": 0.2, "fine_error_m": 6.0, "seconds": 6.0}],
                },
                "heldout": {"cells": 98, "maps": ["a", "b"], "queries": 400, "trained": {"onnxruntime": held}},
            }
        )
    )
    text = render.render(res)
    current, history = text.split("## History")
    assert "| trained | onnxruntime | gain | +5.0 [1.0, 9.0] |" in current  # the paired gain, signed
    assert "| trained | onnxruntime | cell centre | 25.0 [20.0, 30.0] |" in current
    short, longer = current.split("## TDFANet training choices and ablations: m, ")[1:]
    assert short.startswith("3 epochs of 200 tuples") and longer.startswith("5 epochs of 500 tuples")
    assert "### Training choices" in short and "### Training choices" not in longer
    assert "| sum | yes | yes | no (sum) | 50.0 [43.0, 57.0] | 40.0 [30.0, 50.0] " in longer
    assert "| 40.0 [30.0, 50.0] | 45.0 [35.0, 55.0] | 0.0 [0.0, 0.0] | 15.0 |" in longer
    assert "## Place recognition on street-network towns: m" in current
    assert (
        "| window | each window's own batch statistics while training | 2 | 50.0 [43.0, 57.0] | 70.0 | 10.0 |"
    ) in current
    assert (
        "| sum | yes | yes | no (sum) | 50.0 [43.0, 57.0] | 40.0 [30.0, 50.0] | 60.0 [50.0, 70.0] "
        "| 70.0 [60.0, 80.0] | 40.0 [30.0, 50.0] | - | - | 10.0 |"
    ) in short
    assert (
        "| trained, int8 | 40.0 [30.0, 50.0] | 60.0 [50.0, 70.0] | 70.0 [60.0, 80.0] | 40.0 [30.0, 50.0] |"
    ) in current
    assert "| chance (random ranking) | 0.35 | - | - | 2.10 |" in current
    assert (
        "80 with, 10 against queries" in current and "| trained, int8 | 45.0 [35.0, 55.0] | 0.0 [0.0, 0.0] |" in current
    )
    assert "| m | cpu | 20.0 | 20.0 | 20.0 | 30.00 | 30.00 |" in current  # CPU, FPS beside the same weights' mAP
    assert "## MAFF-Net training: m" in current and "| trained, onnxruntime int8 | 50.00 (60.00) |" in current
    for heading in (
        "## Speed suite",
        "## Per-model benches",
        "## Graph comparisons",
        "## MAFF-Net capacity",
        "## Clustering stage",
        "## MAFF-Net on trained weights",
    ):
        assert heading in current
    assert "2030-01-02 00:00 UTC" in current
    assert "[suite-2030-01-01.json](results/suite-2030-01-01.json)" in history
    assert "[m-2030-01-01.json](results/m-2030-01-01.json)" in history
    assert "[m-training-2030-01-01.json](results/m-training-2030-01-01.json)" in history
    assert "m-training-2030-01-01-1200.json" in current and "m-training-2030-01-01-1200.json" not in history
    assert "| openvino | error: not installed | - |" in current
    assert "## MAFF-Net training step" in current and "| bf16 | after | 0.500 | 0.600 | 2.00x |" in current
    assert "2.0x" in current and "(1 cloud, each with and without the crop" in current
    assert render.render(res) == text  # deterministic
    other = json.loads((res / "maffnet-trained-m-2030-01-01.json").read_text())
    (res / "maffnet-trained-m-2030-01-01.json").write_text(json.dumps({**other, "checkpoint_sha256": "cd" * 32}))
    assert "| m | cpu | 20.0 | 20.0 | 20.0 | - | - |" in render.render(res)  # other weights: no mAP beside them


def test_training_plot_draws_the_benchmark_run_and_every_variant(tmp_path):
    """benchmarks/plot_training.py draws the newest place-recognition run of a card and the
    newest variants file's runs, and says so when there is nothing to draw."""
    import json

    spec = importlib.util.spec_from_file_location("plot_training", ROOT / "benchmarks" / "plot_training.py")
    plot = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(plot)
    epochs = [{"epoch": 0, "loss": float("nan"), "val_R@1": 20.0}, {"epoch": 1, "loss": 0.2, "val_R@1": 40.0}]
    for day in ("2030-01-01", "2030-01-02"):
        (tmp_path / f"place-recognition-m-{day}.json").write_text(json.dumps({"train": {"epochs": epochs}}))
    (tmp_path / "tdfanet-variants-m-2030-01-01.json").write_text(
        json.dumps({"variants": {"frozen": {"history": epochs}, "sum": {"history": epochs[:1]}}})
    )
    assert [label for label, _, _ in plot.curves(tmp_path)] == ["m (benchmark run)", "m frozen", "m sum"]
    out = plot.draw(tmp_path, tmp_path / "curves.png")
    assert out.stat().st_size > 1000
    with pytest.raises(SystemExit, match="no place-recognition"):
        plot.draw(tmp_path / "empty", tmp_path / "none.png")


def _relative_links(path: Path):
    for target in LINK.findall(_prose(path.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#") and not target[1:]:
            continue  # http:, https:, mailto:, ...
        yield target


@pytest.mark.parametrize("doc", _doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc):
    broken = []
    for target in _relative_links(doc):
        file_part, _, anchor = target.partition("#")
        dest = (doc.parent / file_part).resolve() if file_part else doc
        if not dest.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and dest.is_file() and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target} (no heading #{anchor} in {dest.relative_to(ROOT)})")
    assert not broken, f"{doc.relative_to(ROOT)}: broken links: {broken}"


def test_readme_states_the_bad_input_catalogue_size():
    """The README's count of catalogued bad inputs is the catalogue's, tests/test_bad_input*.py
    (collected, not guessed)."""
    import subprocess
    import sys

    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "--collect-only",
            "-q",
            "-p",
            "no:cacheprovider",
            *map(str, sorted((ROOT / "tests").glob("test_bad_input*.py"))),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    cases = sum(
        1
        for line in out.stdout.splitlines()
        if "::test_" in line and "catalogue_holds" not in line and "good_pickle" not in line
    )
    stated = re.search(r"catalogue of (\d+) bad inputs", " ".join(README.read_text().split()))
    assert stated and int(stated.group(1)) == cases, (stated and stated.group(0), cases)


# "…/scratch/set" is a path result_file.py already shortened, not one of this machine's.
MACHINE_PATH = re.compile(r"(?<![\w.~/…-])/(?:tmp|work|root|home|scratch|Users|private)/[^\s\"'`,;()\[\]{}<>|]*")


def test_no_result_or_generated_page_holds_a_machine_path():
    """Result JSONs, the zoo's entries and the generated benchmarks page name paths relative to the repository or
    shortened (benchmarks/result_file.py); never this machine's directories."""
    files = [
        *sorted((ROOT / "benchmarks" / "results").glob("*.json")),
        *sorted((ROOT / "zoo").glob("*/*.json")),
        ROOT / "benchmarks" / "README.md",
    ]
    found = [f"{f.relative_to(ROOT)}: {m.group(0)}" for f in files for m in MACHINE_PATH.finditer(f.read_text())]
    assert not found, found[:10]


def test_results_are_written_portable(tmp_path):
    spec = importlib.util.spec_from_file_location("result_file", ROOT / "benchmarks" / "result_file.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    doc = {
        "checkpoint": "/work/scratch/mv12/run/best.pth",
        "data": "/tmp/set",
        "ours": str(ROOT / "export" / "a.onnx"),
        "command": "radaredge train --set coarse_weights=/work/x/run/best.pth --data set",
        "speed": "3 m/s",
        "link": "https://github.com/tudelft-iv/view-of-delft-dataset",
        "given": "runs/x/best.pth",
    }
    written = json.loads(module.write_result(tmp_path / "r.json", doc).read_text())
    assert written == {
        "checkpoint": "…/run/best.pth",
        "data": "…/set",
        "ours": "export/a.onnx",
        "command": "radaredge train --set coarse_weights=…/run/best.pth --data set",
        "speed": "3 m/s",
        "link": "https://github.com/tudelft-iv/view-of-delft-dataset",
        "given": "runs/x/best.pth",
    }
    rewritten = json.loads(module.write_result(tmp_path / "again.json", written).read_text())
    assert rewritten == written  # a path already shortened is left as it is


def test_int8_methods_render_the_qat_control_rows(tmp_path):
    """A --qat row with a --control-weights fine-tune renders two more rows: the control's fp32
    against the original fp32, and the QAT int8 graph against the control's fp32, each with its
    paired interval and, for the int8 one, its verdict."""
    render = _render_module()
    name = "int8-methods-maffnet-vod-edge-test-2026-12-07.json"
    doc = json.loads((ROOT / "benchmarks" / "results" / name).read_text())
    qat = doc["methods"]["qat"]

    def shifted(by: float) -> dict:
        return {
            c: {"3d": d["3d"] + by, "3d_interval": [bound + by for bound in d["3d_interval"]]}
            for c, d in qat["int8_minus_fp32"].items()
        }

    qat["control"] = {
        "checkpoint": "runs/fp32/best.pth",
        "checkpoint_sha256": "c" * 64,
        "fp32": qat["qat_fp32"],
        "fp32_minus_original_fp32": shifted(0.25),
        "qat_int8_minus_control_fp32": shifted(-3.0),
        "verdict": "fails",
    }
    (tmp_path / name).write_text(json.dumps(doc))
    lines = render.int8_methods_lines(render.Result(tmp_path / name))
    control = next(line for line in lines if line.startswith("| control: fp32 fine-tune"))
    assert "`cccccccccccc`" in control and "| (fp32) |" in control
    assert f"{qat['int8_minus_fp32']['Car']['3d'] + 0.25:+.2f}" in control
    versus = next(line for line in lines if line.startswith("| `train --qat` int8 vs the control's fp32"))
    assert f"{qat['int8_minus_fp32']['mAP']['3d'] - 3.0:+.2f}" in versus and "| fails |" in versus
    assert lines.index(versus) == lines.index(control) + 1


def test_int8_speed_renders_one_study_per_kind_of_cpu(tmp_path):
    """int8 speed depends on the CPU's int8 dot-product instructions, so a study on a CPU with
    them (int8-speed-avx-512-vnni-*) is shown beside the one without, each naming its CPU's; a
    newer run of one study replaces that study only."""
    import json

    render = _render_module()
    card = {
        "checkpoint": "zoo/m/weights.pth",
        "checkpoint_sha256": "ab" * 32,
        "median_ms": {"onnxruntime": 100.0, "onnxruntime int8": 80.0},
        "int8_vs_fp32": 1.25,
        "fp32_ops_ms": {"Conv": 60.0, "Transpose": 5.0},
        "int8_ops_ms": {"QLinearConv": 40.0, "DequantizeLinear": 2.0},
        "fp32_heaviest_nodes": [["conv_1", "Conv", 25.0]],
        "int8_heaviest_nodes": [["qconv_1", "QLinearConv", 15.0]],
    }

    def study(name, date, isa, int8_ms):
        doc = {
            "date": f"{date} 10:00 UTC",
            "command": "python benchmarks/int8_speed.py",
            "machine": {"cpu": "cpu", "int8_dot_product": isa, "threads": 2},
            "runs": 30,
            "cards": {"m": {**card, "median_ms": {"onnxruntime": 100.0, "onnxruntime int8": int8_ms}}},
        }
        (tmp_path / f"{name}-{date}.json").write_text(json.dumps(doc))

    study("int8-speed", "2030-01-01", [], 110.0)
    study("int8-speed-avx-512-vnni", "2030-01-01", ["AVX-512 VNNI", "AVX-VNNI"], 90.0)
    study("int8-speed-avx-512-vnni", "2030-01-02", ["AVX-512 VNNI", "AVX-VNNI"], 70.0)
    results = render.load(tmp_path)
    block = next(b for b in render.GENERATED if b.name == "int8 speed")
    text = block.fill(f"{block.begin}\n{block.end}\n", results)
    assert "cpu (no int8 dot-product instructions), 2 threads" in text
    assert "cpu (int8 dot product: AVX-512 VNNI, AVX-VNNI), 2 threads" in text
    assert "| 100.0 | 110.0 |" in text and "| 100.0 | 70.0 |" in text and "| 100.0 | 90.0 |" not in text
    readme = render.render(tmp_path)
    current, history = readme.split("## History")
    assert "int8-speed-2030-01-01.json" in current and "int8-speed-avx-512-vnni-2030-01-02.json" in current
    assert "int8-speed-avx-512-vnni-2030-01-01.json" in history
