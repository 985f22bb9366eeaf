"""The bad-input catalogue: every surface a user feeds (command-line options, model cards,
checkpoints, .onnx files, scans, gps.csv, KITTI360Pose pickles, ROS bags, runtime frames and
timestamps), each case asserting what radaredge promises on bad input:

- on the command line: exit code 2, exactly one line on stderr, starting with ``error:``, no
  traceback, and no file left behind in the working directory;
- through the library and the runtime: a :class:`radaredge.errors.RadarEdgeError` with a
  one-line message, never another exception;
- every case within 60 s and 2 GB of memory growth (sampled while it runs).

The README states the guarantee and the case count (``tests/test_docs.py`` checks the count).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
import yaml
from conftest import TINY_CARD, invoke

from radaredge import runtime
from radaredge.cards.des4pos import CellConfig, TextConfig
from radaredge.config import field_range
from radaredge.data.readers import read_rosbag, read_scan
from radaredge.data.sequences import load_sequence
from radaredge.errors import InputError, RadarEdgeError
from radaredge.models.des4pos.model import FineConfig, SubmapConfig
from radaredge.models.maffnet.fuser import CafConfig
from radaredge.models.maffnet.model import BackboneConfig, SpaConfig
from radaredge.models.maffnet.rcnn import KeypointConfig, ProposalConfig, RoiHeadConfig, SAConfig, VsaConfig
from radaredge.models.tdfanet.model import TDFANetConfig
from radaredge.ops.dbscan import DbscanConfig
from radaredge.ops.ego_velocity import RansacConfig
from radaredge.ops.grid_density import GridDensityConfig
from radaredge.ops.nms import NmsConfig
from radaredge.ops.pillars import PillarConfig
from radaredge.runtime.kitti360pose import TEXT2LOC_MODULE, read_cells, read_poses

MAFF_TINY = Path(__file__).parent / "cards" / "maffnet-tiny.yaml"
MAFF_DBSCAN = Path(__file__).parent / "cards" / "maffnet-tiny-full-dbscan.yaml"
DES4POS_TINY = Path(__file__).parent / "cards" / "des4pos-tiny.yaml"
MAX_SECONDS = 60.0
MAX_GROWTH_BYTES = 2 * 1024**3


# ----------------------------------------------------------------------------- resource guard


class _PeakRss:
    """Samples this process's resident memory every 10 ms while active."""

    def __init__(self):
        self.page = os.sysconf("SC_PAGE_SIZE")

    def rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self.page

    def __enter__(self):
        self.start, self.peak, self.stop = self.rss(), 0, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        self.t0 = time.perf_counter()
        return self

    def _run(self):
        while not self.stop.wait(0.01):
            self.peak = max(self.peak, self.rss())

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0
        self.stop.set()
        self.thread.join()
        self.peak = max(self.peak, self.rss())


@pytest.fixture(autouse=True)
def bounded():
    """Every case: at most MAX_SECONDS and MAX_GROWTH_BYTES more resident memory than at its start."""
    with _PeakRss() as guard:
        yield
    assert guard.seconds < MAX_SECONDS, f"took {guard.seconds:.1f} s"
    assert guard.peak - guard.start < MAX_GROWTH_BYTES, f"grew by {(guard.peak - guard.start) / 1e9:.2f} GB"


# ----------------------------------------------------------------------------- fixtures: files to break


@pytest.fixture(scope="module")
def files(tmp_path_factory, tiny_export):
    """One directory of bad and good inputs, shared by the command-line cases (read-only for them)."""
    d = tmp_path_factory.mktemp("bad-inputs")
    _, model, onnx_path, _ = tiny_export
    shutil.copy(onnx_path, d / "tiny.onnx")
    (d / "random.bin").write_bytes(np.random.default_rng(0).bytes(4000))
    (d / "random.onnx").write_bytes(np.random.default_rng(1).bytes(4000))
    (d / "empty.onnx").write_bytes(b"")
    (d / "truncated.onnx").write_bytes(onnx_path.read_bytes()[:5000])
    proto = onnx.load(str(onnx_path))
    del proto.metadata_props[:]
    onnx.save(proto, str(d / "no-metadata.onnx"))
    for name, card_text in (
        ("bad-yaml", "name: [unclosed"),
        ("python-tag", "!!python/object/apply:os.system ['true']"),
        ("alias-bomb", "a: &a [x, x]\nb: &b [*a, *a]\nc: [*b, *b]"),
        ("not-a-card", "just text"),
    ):
        proto = onnx.load(str(onnx_path))
        for prop in proto.metadata_props:
            if prop.key == "radaredge.card":
                prop.value = card_text
        onnx.save(proto, str(d / f"card-{name}.onnx"))
    state = model.state_dict()
    torch.save(state, d / "good.pth")
    (d / "truncated.pth").write_bytes((d / "good.pth").read_bytes()[:3000])
    torch.save([1, 2, 3], d / "list.pth")
    torch.save({**state, "vfe.pfn_layers.0.linear.weight": torch.zeros(3, 3)}, d / "wrong-shape.pth")
    torch.save({k: v for k, v in state.items() if not k.startswith("mlp.")}, d / "missing-keys.pth")
    torch.save({**state, "extra.weight": torch.zeros(2)}, d / "unexpected-key.pth")
    torch.save({**state, "gem.p": "three"}, d / "non-tensor.pth")
    torch.save(
        {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v for k, v in state.items()},
        d / "nan-weights.pth",
    )
    torch.save({k: v + 1 if v.is_floating_point() else v for k, v in state.items()}, d / "other-weights.pth")
    with open(d / "malicious.pth", "wb") as f:
        pickle.dump(_Exploit(), f)
    (d / "a-file").write_text("not a directory")
    (d / "garbage-run").mkdir()
    (d / "garbage-run" / "last.pth").write_bytes(b"\x00garbage" * 100)
    (d / "empty-dir").mkdir()
    (d / "binary.yaml").write_bytes(b"\xff\xfe\x00\x01" * 64)
    (d / "huge.yaml").write_text("# " + "x" * 300_000)
    town = d / "town"
    from radaredge.data.pr_benchmark import make_pr_benchmark

    make_pr_benchmark(town, drives=2, frames_per_drive=6, seed=0)
    far = d / "far-town"
    make_pr_benchmark(far, drives=2, frames_per_drive=6, seed=3)  # 30 km east of town
    nogps = d / "no-gps"
    shutil.copytree(town / "database" / "drive-00", nogps / "drive-00")
    (nogps / "drive-00" / "gps.csv").unlink()
    bingps = d / "binary-gps"
    shutil.copytree(town / "database" / "drive-00", bingps / "drive-00")
    (bingps / "drive-00" / "gps.csv").write_bytes(np.random.default_rng(2).bytes(500))
    (d / "random.npz").write_bytes(np.random.default_rng(3).bytes(900))
    cal = d / "recording"
    cal.mkdir()
    for i in range(6):
        np.random.default_rng(i).normal(size=(40, 7)).astype("<f4").tofile(cal / f"{i:06d}.bin")
    (cal / "000003.bin").write_bytes((cal / "000002.bin").read_bytes()[:50])
    nan = d / "nan-town"
    shutil.copytree(town, nan)
    scan = nan / "queries" / "drive-01" / "scans" / "000003.npy"
    values = np.load(scan)
    values[2, 3] = np.nan
    np.save(scan, values)
    return d


class _Exploit:
    def __reduce__(self):
        return (os.system, ("echo pwned > /tmp/radaredge-pwned",))


def _card_with(base: Path, dst: Path, edit) -> Path:
    data = yaml.safe_load(base.read_text())
    edit(data)
    dst.write_text(yaml.safe_dump(data, sort_keys=False))
    return dst


def assert_one_error_line(res, workdir: Path, before: set, expect: str = ""):
    err = res.stderr
    lines = [line for line in err.splitlines() if line.strip()]
    assert res.exit_code == 2, f"exit {res.exit_code}: {res.output}"
    assert "Traceback" not in res.output, res.output
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    assert expect in lines[0], f"{expect!r} not in {lines[0]!r}"
    assert set(p.relative_to(workdir) for p in workdir.rglob("*")) == before, "a file was left behind"


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


# ----------------------------------------------------------------------------- command-line options

CLI = [
    # (id, args with {f} for the shared files directory, expected text in the error)
    ("no-command", ["nope"], "No such command"),
    ("export-unknown-option", ["export", "--model", "tdfanet", "--bogus"], "No such option"),
    ("export-no-model", ["export"], "Missing option '--model'"),
    ("export-unknown-model", ["export", "--model", "nope"], "no model card 'nope'"),
    ("export-opset-text", ["export", "--model", "tdfanet", "--opset", "abc"], "--opset"),
    ("export-opset-0", ["export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--opset", "0"], "opset"),
    ("export-opset-99", ["export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--opset", "99"], "opset"),
    ("export-quantize-int4", ["export", "--model", "tdfanet", "--quantize", "int4"], "--quantize"),
    ("export-calibration-alone", ["export", "--model", "tdfanet", "--calibration", "{f}/town"], "--quantize"),
    (
        "export-calibration-windows-0",
        ["export", "--model", "tdfanet", "--quantize", "int8", "--calibration-windows", "0"],
        "--calibration-windows",
    ),
    (
        "export-calibration-format",
        ["export", "--model", "tdfanet", "--calibration-format", "x"],
        "--calibration-format",
    ),
    (
        "export-calibration-missing",
        ["export", "--model", "tdfanet", "--quantize", "int8", "--calibration", "{f}/nowhere"],
        "nowhere",
    ),
    (
        "export-calibration-truncated-scan",
        [
            "export",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--quantize",
            "int8",
            "--calibration",
            "{f}/recording",
            "--calibration-format",
            "vod",
            "--calibration-windows",
            "4",
            "--output",
            "out/t.onnx",
        ],
        "recording/000003.bin: 50 bytes",
    ),
    (
        "export-output-under-file",
        ["export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output", "{f}/a-file/x.onnx"],
        "a-file",
    ),
    ("export-config-missing", ["export", "--model", "x", "--config", "{f}/nowhere.yaml"], "nowhere.yaml"),
    ("export-config-binary", ["export", "--model", "x", "--config", "{f}/binary.yaml"], "not a text file"),
    ("export-config-huge", ["export", "--model", "x", "--config", "{f}/huge.yaml"], "at most"),
    ("parity-no-onnx", ["parity-check", "--model", "tdfanet"], "Missing option '--onnx'"),
    (
        "parity-cases-0",
        [
            "parity-check",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--cases",
            "0",
        ],
        "cases",
    ),
    (
        "parity-cases-negative",
        [
            "parity-check",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--cases",
            "-3",
        ],
        "cases",
    ),
    (
        "parity-cases-huge",
        [
            "parity-check",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--cases",
            "100000000",
        ],
        "cases",
    ),
    ("parity-runtime", ["parity-check", "--model", "tdfanet", "--onnx", "x", "--runtime", "tensorrt"], "--runtime"),
    (
        "bench-runs-0",
        ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx", "--runs", "0"],
        "runs",
    ),
    (
        "bench-warmup-negative",
        ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx", "--warmup", "-1"],
        "warm",
    ),
    (
        "bench-threads-0",
        ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx", "--threads", "0"],
        "threads",
    ),
    (
        "bench-threads-huge",
        [
            "bench",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--threads",
            "1000000",
        ],
        "threads",
    ),
    (
        "bench-save-under-file",
        [
            "bench",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--save",
            "{f}/a-file/b.json",
        ],
        "a-file",
    ),
    ("eval-no-onnx", ["eval", "--model", "tdfanet"], "Missing option '--onnx'"),
    (
        "eval-missing-database",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/nowhere",
            "--queries",
            "{f}/town/queries",
        ],
        "nowhere",
    ),
    (
        "eval-empty-database",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/empty-dir",
            "--queries",
            "{f}/town/queries",
        ],
        "no drives",
    ),
    (
        "eval-no-gps",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/no-gps",
            "--queries",
            "{f}/town/queries",
        ],
        "gps.csv",
    ),
    (
        "eval-binary-gps",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/binary-gps",
            "--queries",
            "{f}/town/queries",
        ],
        "not a text CSV",
    ),
    (
        "eval-other-town",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/town/database",
            "--queries",
            "{f}/far-town/queries",
        ],
        "within 5 m",
    ),
    (
        "eval-nan-in-a-scan",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/nan-town/database",
            "--queries",
            "{f}/nan-town/queries",
        ],
        "queries/drive-01/scans/000003.npy: non-finite value nan at point 2, column 'v_r'",
    ),
    (
        "eval-radius-0",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/town/database",
            "--queries",
            "{f}/town/queries",
            "--radius",
            "0",
        ],
        "radius",
    ),
    (
        "eval-radius-nan",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/town/database",
            "--queries",
            "{f}/town/queries",
            "--radius",
            "nan",
        ],
        "radius",
    ),
    (
        "eval-radius-inf",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/town/database",
            "--queries",
            "{f}/town/queries",
            "--radius",
            "inf",
        ],
        "radius",
    ),
    (
        "eval-report-under-file",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/town/database",
            "--queries",
            "{f}/town/queries",
            "--report",
            "{f}/a-file/r.json",
        ],
        "a-file",
    ),
    (
        "eval-plot-under-file",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/town/database",
            "--queries",
            "{f}/town/queries",
            "--plot",
            "{f}/a-file/p.png",
        ],
        "a-file",
    ),
    (
        "eval-map-for-tdfanet",
        [
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--map",
            "{f}/random.npz",
        ],
        "--database",
    ),
    (
        "eval-maffnet",
        [
            "eval",
            "--model",
            "maffnet-tiny",
            "--config",
            str(MAFF_TINY),
            "--onnx",
            "{f}/tiny.onnx",
            "--database",
            "{f}/town/database",
            "--queries",
            "{f}/town/queries",
        ],
        "is evaluated by 3D-detection AP on --data; missing --data",
    ),
    ("make-benchmark-drives-0", ["make-benchmark", "--out", "b", "--drives", "0"], "drives"),
    ("make-benchmark-drives-1", ["make-benchmark", "--out", "b", "--drives", "1"], "drives"),
    ("make-benchmark-frames-0", ["make-benchmark", "--out", "b", "--frames", "0"], "frames"),
    ("make-benchmark-seed-negative", ["make-benchmark", "--out", "b", "--seed", "-1"], "seed"),
    ("make-benchmark-towns-0", ["make-benchmark", "--out", "b", "--towns", "0"], "towns"),
    ("make-benchmark-towns-huge", ["make-benchmark", "--out", "b", "--towns", "100000"], "--towns"),
    (
        "make-benchmark-seed-beyond-gps",
        ["make-benchmark", "--out", "b", "--seed", "2001", "--frames", "2"],
        "use seeds up to 1990",
    ),
    (
        "make-benchmark-towns-beyond-gps",
        ["make-benchmark", "--out", "b", "--seed", "1985", "--towns", "10", "--frames", "2"],
        "use seeds up to 1990",
    ),
    ("make-city-cities-0", ["make-city", "--out", "c", "--cities", "0"], "--cities"),
    ("make-city-cities-huge", ["make-city", "--out", "c", "--cities", "100000"], "--cities"),
    ("make-benchmark-out-under-file", ["make-benchmark", "--out", "{f}/a-file/b", "--frames", "2"], "a-file"),
    ("make-city-objects-0", ["make-city", "--out", "c.npz", "--objects", "0"], "objects"),
    (
        "make-city-poses-unbounded",
        ["make-city", "--out", "c", "--cities", "1000", "--poses", "100000"],
        "described poses; at most",
    ),
    ("make-city-poses-negative", ["make-city", "--out", "c.npz", "--poses", "-1"], "poses"),
    ("make-city-world-0", ["make-city", "--out", "c.npz", "--world", "0"], "world"),
    ("make-city-world-nan", ["make-city", "--out", "c.npz", "--world", "nan"], "world"),
    ("make-city-seed-negative", ["make-city", "--out", "c.npz", "--seed", "-2"], "seed"),
    ("make-city-for-tdfanet", ["make-city", "--out", "c.npz", "--model", "tdfanet"], "tdfanet"),
    ("make-city-out-under-file", ["make-city", "--out", "{f}/a-file/c.npz"], "a-file"),
    ("locate-no-dir", ["locate", "--onnx-dir", "{f}/nowhere", "--map", "{f}/random.npz", "--text", "x"], "nowhere"),
    (
        "locate-top-k-0",
        ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x", "--top-k", "0"],
        "top",
    ),
    (
        "locate-threads-0",
        ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x", "--threads", "0"],
        "threads",
    ),
    (
        "locate-threads-huge",
        ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x", "--threads", "100000"],
        "threads",
    ),
    ("locate-empty-text", ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", ""], "text"),
    ("inspect-missing", ["inspect", "{f}/nowhere.onnx"], "nowhere.onnx"),
    ("inspect-random", ["inspect", "{f}/random.onnx"], "random.onnx"),
    ("inspect-empty", ["inspect", "{f}/empty.onnx"], "empty.onnx"),
    ("inspect-truncated", ["inspect", "{f}/truncated.onnx"], "truncated.onnx"),
    ("inspect-no-metadata", ["inspect", "{f}/no-metadata.onnx"], "no-metadata.onnx"),
    ("inspect-empty-dir", ["inspect", "{f}/empty-dir"], "empty-dir"),
    ("inspect-card-bad-yaml", ["inspect", "{f}/card-bad-yaml.onnx"], "invalid YAML"),
    ("inspect-card-python-tag", ["inspect", "{f}/card-python-tag.onnx"], "python"),
    ("inspect-card-alias-bomb", ["inspect", "{f}/card-alias-bomb.onnx"], "aliases"),
    ("inspect-card-not-a-mapping", ["inspect", "{f}/card-not-a-card.onnx"], "mapping"),
    ("train-no-data", ["train", "--model", "tdfanet"], "Missing option '--data'"),
    (
        "train-missing-data",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/nowhere"],
        "nowhere",
    ),
    (
        "train-data-is-file",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/a-file"],
        "a-file",
    ),
    (
        "train-empty-data",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/empty-dir"],
        "no drives",
    ),
    (
        "train-one-drive",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/no-gps"],
        "gps.csv",
    ),
    (
        "train-epochs-0",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--epochs", "0"],
        "--epochs",
    ),
    (
        "train-lr-negative",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--lr", "-1"],
        "--lr",
    ),
    (
        "train-lr-nan",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--lr", "nan"],
        "--lr",
    ),
    (
        "train-batch-0",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--batch-size", "0"],
        "--batch-size",
    ),
    (
        "train-set-unknown",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--set", "foo=1"],
        "foo",
    ),
    (
        "train-set-text",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--set",
            "negatives=many",
        ],
        "--negatives",
    ),
    (
        "train-set-no-value",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--set", "negatives"],
        "KEY=VALUE",
    ),
    (
        "train-set-list",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--set",
            "negatives=[1, 2]",
        ],
        "list",
    ),
    (
        "train-hard-above-negatives",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--set",
            "hard_negatives=30",
        ],
        "hard_negatives",
    ),
    (
        "train-radii-swapped",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--set",
            "negative_radius=2",
        ],
        "negative_radius",
    ),
    (
        "train-second-term",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--set",
            "second_term=other",
        ],
        "second_term",
    ),
    (
        "train-unknown-validation",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--validation", "nope"],
        "nope",
    ),
    ("train-device", ["train", "--model", "tdfanet", "--data", "x", "--device", "tpu"], "--device"),
    (
        "train-resume-without-state",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--output",
            "run",
            "--resume",
        ],
        "last.pth",
    ),
    (
        "train-resume-garbage-state",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--output",
            "{f}/garbage-run",
            "--resume",
        ],
        "not a readable torch checkpoint",
    ),
    (
        "train-resume-and-checkpoint",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--resume",
            "--checkpoint",
            "{f}/good.pth",
        ],
        "--checkpoint",
    ),
    (
        "train-field-map",
        ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town", "--field-map", "v_r"],
        "--field-map",
    ),
    (
        "train-maffnet",
        ["train", "--model", "maffnet-tiny", "--config", str(MAFF_TINY), "--data", "{f}/town"],
        "no training/ folder",
    ),
    (
        "train-output-under-file",
        [
            "train",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--data",
            "{f}/town",
            "--output",
            "{f}/a-file/run",
        ],
        "a-file",
    ),
]
CHECKPOINTS = [
    "truncated",
    "list",
    "wrong-shape",
    "missing-keys",
    "unexpected-key",
    "non-tensor",
    "nan-weights",
    "malicious",
    "random",
    "nowhere",
]
CLI += [
    (
        f"export-checkpoint-{name}",
        [
            "export",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--checkpoint",
            f"{{f}}/{name}.{'bin' if name == 'random' else 'pth'}",
        ],
        {"nan-weights": "not finite", "malicious": "runs no pickled code"}.get(name, "checkpoint"),
    )
    for name in CHECKPOINTS
]
CLI += [
    (
        f"parity-onnx-{name}",
        ["parity-check", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", f"{{f}}/{name}.onnx"],
        name,
    )
    for name in ("random", "empty", "truncated", "no-metadata", "nowhere")
]
CLI += [
    (
        f"parity-checkpoint-{name}",
        [
            "parity-check",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            "{f}/tiny.onnx",
            "--checkpoint",
            f"{{f}}/{name}.pth",
        ],
        expect,
    )
    for name, expect in (
        ("truncated", "checkpoint"),
        ("malicious", "runs no pickled code"),
        ("other-weights", "exported with other weights"),
    )
]
CLI += [
    (
        f"bench-onnx-{name}",
        [
            "bench",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--onnx",
            f"{{f}}/{name}.onnx",
            "--runs",
            "1",
            "--no-reference",
        ],
        name,
    )
    for name in ("random", "no-metadata", "card-bad-yaml")
]
CLI += [
    (
        "locate-map-missing",
        ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/nowhere.npz", "--text", "x"],
        "nowhere.npz",
    ),
    (
        "locate-not-a-bundle",
        ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x"],
        "not a Des4Pos bundle",
    ),
]


@pytest.mark.parametrize("case, args, expect", CLI, ids=[c[0] for c in CLI])
def test_command_line(files, workdir, case, args, expect):
    before = set(p.relative_to(workdir) for p in workdir.rglob("*"))
    res = invoke(*[a.replace("{f}", str(files)) for a in args])
    assert_one_error_line(res, workdir, before, expect)
    assert not Path("/tmp/radaredge-pwned").exists()


# ----------------------------------------------------------------------------- model cards, field by field


def _bad_values(cls, name: str):
    """NaN, infinities, both sides of the declared range, a word and a boolean for one numeric field."""
    rng = field_range(cls, name)
    default = next(f.default for f in dataclasses.fields(cls) if f.name == name)
    below = rng.low - 1 if rng.low - 1 < rng.low else -1e30
    above = rng.high * 2 + 1
    values = [
        ("nan", float("nan")),
        ("inf", float("inf")),
        ("-inf", float("-inf")),
        ("below", below),
        ("above", above),
        ("word", "many"),
        ("bool", True),
    ]
    if isinstance(default, tuple):
        values = [(k, [v] * len(default)) for k, v in values] + [("scalar", 1.0), ("short", [])]
    else:
        values += [("list", [])]  # an empty list passed the per-number checks (fuzzing found it)
    return values


def _set(data: dict, dotted: str, value):
    node = data
    parts = dotted.split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value


SECTION_FIELDS = []
for base, model, sections in (
    (
        TINY_CARD,
        "tdfanet-tiny",
        (("preprocess.ransac", RansacConfig), ("pillars", PillarConfig), ("network", TDFANetConfig)),
    ),
    (
        MAFF_TINY,
        "maffnet-tiny",
        (
            ("spa", SpaConfig),
            ("cfa.grid", GridDensityConfig),
            ("caf", CafConfig),
            ("backbone_2d", BackboneConfig),
            ("post_processing", NmsConfig),
        ),
    ),
    (
        MAFF_DBSCAN,
        "maffnet-tiny-full-dbscan",
        (
            ("cfa.dbscan", DbscanConfig),
            ("stage_two.proposals", ProposalConfig),
            ("stage_two.keypoints", KeypointConfig),
            ("stage_two.vsa", VsaConfig),
            ("stage_two.vsa.sa_clusterpoints", SAConfig),
            ("stage_two.roi_head", RoiHeadConfig),
            ("stage_two.roi_head.roi_grid_pool", SAConfig),
            ("stage_two.post_processing", NmsConfig),
        ),
    ),
    (
        DES4POS_TINY,
        "des4pos-tiny",
        (("cell", CellConfig), ("submap", SubmapConfig), ("text", TextConfig), ("fine", FineConfig)),
    ),
):
    for path, cls in sections:
        for f in dataclasses.fields(cls):
            if field_range(cls, f.name) is None:
                continue
            for label, value in _bad_values(cls, f.name):
                SECTION_FIELDS.append((f"{model}-{path}.{f.name}-{label}", base, model, f"{path}.{f.name}", value))

TOP_LEVEL = [
    (f"tdfanet-tiny-{key}-{label}", TINY_CARD, "tdfanet-tiny", key, value)
    for key, values in (
        ("frames", (0, 1, 65, "three", 2.5, None)),
        ("frame_rate", (0, -10, "fast")),
        ("seed", (-1, 2**40, "x")),
        ("max_points_per_frame", (0, -5, 2**30, 2**24)),
        ("features", ([], "xyz", ["y", "x", "z"], ["x", "y", "z", "x"], [1, 2, 3])),
        ("name", ("", 5)),
        ("model", ("", "nope", 3)),
        ("network", ("deep", [1])),
        ("pillars", (3,)),
        ("classes", ("car",)),
    )
    for label, value in ((str(v), v) for v in values)
]


@pytest.mark.parametrize(
    "case, base, model, field, value", SECTION_FIELDS + TOP_LEVEL, ids=[c[0] for c in SECTION_FIELDS + TOP_LEVEL]
)
def test_card_field(files, workdir, case, base, model, field, value):
    """Each numeric card field refuses non-finite, out-of-range and non-numeric values, naming the field."""
    card = _card_with(base, workdir / "card.yaml", lambda d: _set(d, field, value))
    before = set(p.relative_to(workdir) for p in workdir.rglob("*"))
    res = invoke("export", "--model", model, "--config", card, "--output", workdir / "out" / "x.onnx")
    assert_one_error_line(res, workdir, before, field.split(".")[-1] if field not in ("network", "pillars") else "")


# ----------------------------------------------------------------------------- the runtime: frames and timestamps


@pytest.fixture(scope="module")
def exported(tiny_export):
    model = runtime.load(tiny_export[2], threads=1)
    rng = np.random.default_rng(0)
    good = [rng.normal(size=(30, 5)).astype(np.float32) + np.float32([10, 0, 0, 0, 0]) for _ in range(3)]
    return model, good


def _mutate(good, how):
    f = [x.copy() for x in good]
    kind, _, arg = how.partition(":")
    if kind == "count":
        return f[: int(arg)] if int(arg) < 3 else f + f[:1]
    if kind == "nan":
        f[1][4, int(arg)] = np.nan
    elif kind == "inf":
        f[2][0, int(arg)] = np.inf
    elif kind == "columns":
        f[0] = np.zeros((5, int(arg)), np.float32)
    elif kind == "ndim":
        f[0] = np.zeros((5,) * int(arg), np.float32)
    elif kind == "dtype":
        f[1] = np.zeros((5, 5), dtype=arg)
    elif kind == "object":
        f[1] = np.array([[None] * 5] * 2, dtype=object)
    elif kind == "text":
        f[1] = "points"
    elif kind == "none":
        f[1] = None
    elif kind == "ragged":
        f[1] = [[1.0, 2.0], [3.0]]
    elif kind == "huge":
        f[2] = np.zeros((70_000, 5), np.float32)
    return f


FRAMES = [
    "count:0",
    "count:2",
    "count:4",
    *[f"nan:{c}" for c in range(5)],
    *[f"inf:{c}" for c in range(5)],
    "columns:4",
    "columns:6",
    "columns:0",
    "ndim:1",
    "ndim:3",
    "dtype:complex64",
    "dtype:U3",
    "dtype:bool",
    "object",
    "text",
    "none",
    "ragged",
    "huge",
]


@pytest.mark.parametrize("how", FRAMES)
def test_runtime_frames(exported, how):
    model, good = exported
    with pytest.raises(RadarEdgeError) as err:
        model.run(_mutate(good, how))
    assert "\n" not in str(err.value) and str(err.value)


TIMESTAMPS = [
    [0.0, 0.1],
    [0.0, 0.1, 0.2, 0.3],
    [0.0, 0.0, 0.1],
    [0.2, 0.1, 0.0],
    [0.0, np.nan, 0.2],
    [0.0, 0.1, np.inf],
    ["a", "b", "c"],
    [[0.0], [0.1], [0.2]],
    [1e300, -1e300, 0.0],
    [1e9, 1e9, 1e9],
]


@pytest.mark.parametrize("stamps", TIMESTAMPS, ids=[str(t) for t in TIMESTAMPS])
def test_runtime_timestamps(exported, stamps):
    model, good = exported
    with pytest.raises(RadarEdgeError) as err:
        model.run(good, stamps)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("threads", [0, -1, 10**6, 2.5, "two", True])
def test_runtime_threads(tiny_export, threads):
    with pytest.raises(RadarEdgeError):
        runtime.load(tiny_export[2], threads=threads)


# ----------------------------------------------------------------------------- scan files, drives, pickles, bags


def _scan(tmp: Path, kind: str) -> tuple[Path, dict]:
    p = tmp / "scan"
    if kind == "truncated-bin":
        p = p.with_suffix(".bin")
        p.write_bytes(np.zeros(7 * 4 * 3 + 5, np.uint8).tobytes())
    elif kind == "random-npy":
        p = p.with_suffix(".npy")
        p.write_bytes(np.random.default_rng(0).bytes(300))
    elif kind == "object-npy":
        p = p.with_suffix(".npy")
        np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    elif kind == "3d-npy":
        p = p.with_suffix(".npy")
        np.save(p, np.zeros((2, 3, 5), np.float32))
    elif kind == "columns-npy":
        p = p.with_suffix(".npy")
        np.save(p, np.zeros((4, 3), np.float32))
    elif kind == "text-npy":
        p = p.with_suffix(".npy")
        np.save(p, np.array([["a"] * 5]))
    elif kind == "huge-header-npy":
        p = p.with_suffix(".npy")
        header = "{'descr': '<f4', 'fortran_order': False, 'shape': (500000000000, 5), }"
        p.write_bytes(
            b"\x93NUMPY\x01\x00"
            + len(header.ljust(118) + "\n").to_bytes(2, "little")
            + (header.ljust(118) + "\n").encode()
        )
    elif kind == "suffix":
        p = p.with_suffix(".pcd")
        p.write_text("x")
    elif kind == "missing":
        p = p.with_suffix(".bin")
    elif kind == "directory":
        p.mkdir()
    elif kind == "fmt":
        p = p.with_suffix(".bin")
        p.write_bytes(np.zeros(35, np.float32).tobytes())
        return p, {"fmt": "lidar"}
    elif kind == "feature":
        p = p.with_suffix(".npy")
        np.save(p, np.zeros((4, 5), np.float32))
        return p, {"features": ["x", "y", "z", "doppler_spectrum"]}
    elif kind == "ambiguous-size":
        p = p.with_suffix(".bin")
        p.write_bytes(np.zeros(7 * 8, np.float32).tobytes())
    return p, {}


SCANS = [
    "truncated-bin",
    "random-npy",
    "object-npy",
    "3d-npy",
    "columns-npy",
    "text-npy",
    "huge-header-npy",
    "suffix",
    "missing",
    "directory",
    "fmt",
    "feature",
    "ambiguous-size",
]


@pytest.mark.parametrize("kind", SCANS)
def test_scan_files(tmp_path, kind):
    path, extra = _scan(tmp_path, kind)
    with pytest.raises(RadarEdgeError) as err:
        read_scan(path, extra.get("features", ["x", "y", "z", "v_r", "rcs"]), extra.get("fmt"))
    assert "\n" not in str(err.value)


GPS = [
    ("missing", None),
    ("empty", ""),
    ("header-only-wrong", "time,n,e\n0,0,0\n"),
    ("text-value", "timestamp,northing,easting\n0,a,0\n"),
    ("nan", "timestamp,northing,easting\n0,nan,0\n"),
    ("decreasing", "timestamp,northing,easting\n1,0,0\n0,0,0\n"),
    ("short-row", "timestamp,northing,easting\n0,0\n"),
    ("rows-vs-scans", "timestamp,northing,easting\n0,0,0\n1,0,0\n2,0,0\n"),
    ("binary", b"\x00\xff\xfe" * 30),
]


@pytest.mark.parametrize("kind, content", GPS, ids=[g[0] for g in GPS])
def test_gps_csv(tmp_path, kind, content):
    (tmp_path / "scans").mkdir()
    np.save(tmp_path / "scans" / "000000.npy", np.zeros((3, 5), np.float32))
    if isinstance(content, bytes):
        (tmp_path / "gps.csv").write_bytes(content)
    elif content is not None:
        (tmp_path / "gps.csv").write_text(content)
    with pytest.raises(RadarEdgeError) as err:
        load_sequence(tmp_path)
    assert "\n" not in str(err.value)


PICKLES = [
    ("cells-not-a-list", "cells", "dict"),
    ("cells-bbox-text", "cells", dict(bbox_w="abc")),
    ("cells-bbox-short", "cells", dict(bbox_w=np.zeros(3))),
    ("cells-bbox-nan", "cells", dict(bbox_w=np.full(6, np.nan))),
    ("cells-size-negative", "cells", dict(cell_size=-1.0)),
    ("cells-size-text", "cells", dict(cell_size="big")),
    ("cells-objects-dict", "cells", dict(objects={"a": 1})),
    ("cells-id-object", "cells", dict(id=[1, 2])),
    ("cells-xyz-shape", "cells", dict(object=dict(xyz=np.zeros((4, 2))))),
    ("cells-rgb-mismatch", "cells", dict(object=dict(rgb=np.zeros((3, 3))))),
    ("cells-label-list", "cells", dict(object=dict(label=[1]))),
    ("poses-not-a-list", "poses", "dict"),
    ("poses-pose-text", "poses", dict(pose_w="here")),
    ("poses-pose-short", "poses", dict(pose_w=np.zeros(1))),
    ("poses-descriptions-int", "poses", dict(descriptions=3)),
    ("poses-cell-id-list", "poses", dict(cell_id=[1])),
    ("poses-direction-none", "poses", dict(description=dict(direction=None))),
    ("random-bytes", "cells", "random"),
    ("truncated", "cells", "truncated"),
    ("exploit", "cells", "exploit"),
]


@pytest.fixture(scope="module")
def text2loc():
    """Classes named and placed like Text2Loc's, so pickle writes the dataset's global names."""
    import sys
    import types

    mod = types.ModuleType(TEXT2LOC_MODULE)
    for name in ("Cell", "Object3d", "Pose", "DescriptionPoseCell"):
        setattr(mod, name, type(name, (), {"__module__": TEXT2LOC_MODULE}))
    added = {n: types.ModuleType(n) for n in ("datapreparation", "datapreparation.kitti360pose")}
    added[TEXT2LOC_MODULE] = mod
    saved = {n: sys.modules.get(n) for n in added}
    sys.modules.update(added)
    yield mod
    for n, m in saved.items():
        if m is None:
            sys.modules.pop(n, None)
        else:
            sys.modules[n] = m


def _pickle_file(tmp: Path, mod, what: str, over) -> Path:
    """A cells/poses pickle of Text2Loc-named records, with the attributes in ``over`` replaced."""

    def make(name, attrs):
        obj = getattr(mod, name)()
        obj.__dict__.update(attrs)
        return obj

    path = tmp / f"{what}.pkl"
    if over == "random":
        path.write_bytes(np.random.default_rng(0).bytes(200))
    elif over == "exploit":
        path.write_bytes(pickle.dumps(_Exploit()))
    elif over == "dict":
        path.write_bytes(pickle.dumps({"a": 1}))
    else:
        over = dict(over) if isinstance(over, dict) else {}
        if what == "cells":
            obj = make(
                "Object3d", {**dict(xyz=np.zeros((4, 3)), rgb=np.zeros((4, 3)), label="car"), **over.pop("object", {})}
            )
            items = [
                make(
                    "Cell",
                    {
                        **dict(id="s_00001", scene_name="s", cell_size=30.0, bbox_w=np.arange(6.0), objects=[obj]),
                        **over,
                    },
                )
            ]
        else:
            desc = make(
                "DescriptionPoseCell",
                {**dict(direction="north", object_color_text="red", object_label="car"), **over.pop("description", {})},
            )
            items = [make("Pose", {**dict(pose_w=np.zeros(3), cell_id="s_00001", descriptions=[desc]), **over})]
        path.write_bytes(pickle.dumps(items))
    return path


@pytest.mark.parametrize("case, what, over", PICKLES, ids=[p[0] for p in PICKLES])
def test_kitti360pose_pickles(tmp_path, text2loc, case, what, over):
    path = _pickle_file(tmp_path, text2loc, what, {} if over == "truncated" else over)
    if over == "truncated":
        path.write_bytes(path.read_bytes()[:60])
    with pytest.raises(RadarEdgeError) as err:
        (read_cells if what == "cells" else read_poses)(path)
    assert "\n" not in str(err.value)
    assert not Path("/tmp/radaredge-pwned").exists()


BAGS = ["random-bag", "empty-file-bag", "empty-dir", "metadata-only", "missing-topic", "missing"]


@pytest.mark.parametrize("kind", BAGS)
def test_ros_bags(tmp_path, kind):
    if kind == "random-bag":
        path = tmp_path / "r.bag"
        path.write_bytes(np.random.default_rng(0).bytes(3000))
    elif kind == "empty-file-bag":
        path = tmp_path / "e.bag"
        path.write_bytes(b"")
    elif kind == "empty-dir":
        path = tmp_path / "bagdir"
        path.mkdir()
    elif kind == "metadata-only":
        path = tmp_path / "bag2"
        path.mkdir()
        (path / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    elif kind == "missing-topic":
        from test_readers import ROS1, pointcloud, write_bag

        path = write_bag(
            tmp_path / "t.bag",
            True,
            {
                "/other": (
                    "sensor_msgs/msg/PointCloud",
                    [pointcloud(ROS1, (1, 0), np.zeros((1, 3)), {"Doppler": [0.0]})],
                )
            },
        )
    else:
        path = tmp_path / "nowhere.bag"
    with pytest.raises(RadarEdgeError) as err:
        read_rosbag(path, "/radar_enhanced_pcl", ["x", "y", "z", "v_r"])
    assert "\n" not in str(err.value)


def test_a_good_pickle_reads(tmp_path, text2loc):
    """The catalogue's pickles differ from a readable one only in the broken field."""
    assert len(read_cells(_pickle_file(tmp_path, text2loc, "cells", {}))) == 1
    assert len(read_poses(_pickle_file(tmp_path, text2loc, "poses", {}))[0]) == 1


def test_the_catalogue_holds_at_least_250_cases():
    n = (
        len(CLI)
        + len(SECTION_FIELDS)
        + len(TOP_LEVEL)
        + len(FRAMES)
        + len(TIMESTAMPS)
        + 6
        + len(SCANS)
        + len(GPS)
        + len(PICKLES)
        + len(BAGS)
    )
    assert n >= 250, n


# ----------------------------------------------------------------------------- classes, by generator
# Each class of bad input below is generated: many variants of one mistake, rather than the one
# case somebody first tried (#35). The promise is the same as above.


def _cli(workdir, args, expect=""):
    before = set(p.relative_to(workdir) for p in workdir.rglob("*"))
    res = invoke(*args)
    assert_one_error_line(res, workdir, before, expect)
    return res


# -- output paths an export would have written wrongly (or over a good export)
OUTPUT_PATHS = [
    (
        f"single-{suffix or 'none'}",
        "tdfanet",
        suffix,
        "ending in .onnx" if suffix not in (".int8.onnx", ".debug.onnx") else "int8 and debug copies",
    )
    for suffix in (".json", ".txt", "", ".onnx.json", ".pth", ".int8.onnx", ".debug.onnx", ".yaml")
]
OUTPUT_PATHS += [
    ("bundle-over-a-file", "des4pos", "file", "exports 3 graphs into a directory"),
    ("bundle-as-onnx", "des4pos", ".onnx", "not one .onnx"),
]


@pytest.mark.parametrize("case, model, suffix, expect", OUTPUT_PATHS, ids=[c[0] for c in OUTPUT_PATHS])
def test_export_output_paths(files, workdir, case, model, suffix, expect):
    card = str(TINY_CARD) if model == "tdfanet" else str(DES4POS_TINY)
    target = workdir / f"out{suffix}"
    if suffix == "file":
        target = workdir / "taken"
        target.write_text("x")
    _cli(workdir, ["export", "--model", f"{model}-tiny", "--config", card, "--output", str(target)], expect)


# -- timestamps in another unit than seconds, at several epochs and frame rates
UNIT_STAMPS = [
    (unit, scale, epoch)
    for unit, scale in (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9))
    for epoch in (0.0, 1.7e9, 3.2e4)
] + [("too-close", 1e-3, 0.0), ("too-far", 50.0, 0.0)]


@pytest.mark.parametrize("unit, scale, epoch", UNIT_STAMPS, ids=[f"{u}-{e:g}" for u, _, e in UNIT_STAMPS])
def test_runtime_timestamps_in_other_units(exported, unit, scale, epoch):
    model, good = exported
    stamps = [epoch * (scale if scale > 1 else 1) + k * scale / model.frame_rate for k in range(3)]
    with pytest.raises(InputError) as err:
        model.run(good, stamps)
    message = str(err.value)
    assert "\n" not in message and "apart" in message
    if scale > 1 and unit.endswith("seconds"):
        assert f"they look like {unit}" in message


# -- gps.csv whose timestamps or positions are not seconds and metres
GPS_UNITS = [(f"stamps-{unit}", ("t", scale)) for unit, scale in (("ms", 1e3), ("us", 1e6), ("ns", 1e9))]
GPS_UNITS += [
    (f"latlon-{city}", ("latlon", lat, lon))
    for city, lat, lon in (
        ("delft", 52.0116, 4.3571),
        ("beijing", 39.9042, 116.4074),
        ("sydney", -33.8688, 151.2093),
        ("quito", -0.1807, -78.4678),
    )
]
GPS_UNITS += [("positions-beyond-the-earth", ("offset", 3e7)), ("positions-1e30", ("offset", 1e30))]


@pytest.mark.parametrize("case, how", GPS_UNITS, ids=[g[0] for g in GPS_UNITS])
def test_gps_units(files, tmp_path, case, how):
    drive = tmp_path / "drive"
    shutil.copytree(files / "town" / "database" / "drive-00", drive)
    rows = np.loadtxt(drive / "gps.csv", delimiter=",", skiprows=1)
    if how[0] == "t":
        rows[:, 0] = 1.7e9 * how[1] + (rows[:, 0] - rows[0, 0]) * how[1]
    elif how[0] == "latlon":
        rows[:, 1] = how[1] + (rows[:, 1] - rows[0, 1]) / 111_000
        rows[:, 2] = how[2] + (rows[:, 2] - rows[0, 2]) / 111_000
    else:
        rows[:, 1:] += how[1]
    (drive / "gps.csv").write_text("timestamp,northing,easting\n" + "".join(f"{t!r},{n!r},{e!r}\n" for t, n, e in rows))
    with pytest.raises(InputError) as err:
        load_sequence(drive)
    assert "\n" not in str(err.value) and "gps.csv" in str(err.value)


# -- checkpoints of the right shapes with values no layer can hold
def _state_edits():
    from radaredge.cards import load_card
    from radaredge.models import create_model

    state = create_model(load_card(TINY_CARD)).state_dict()
    bn = [k for k in state if k.endswith("running_var")]
    weights = [k for k, v in state.items() if k.endswith("weight") and v.dim() >= 2]
    edits = [(f"negative-var-{k}", k, "negvar") for k in bn[:: max(1, len(bn) // 6)]]
    edits += [(f"huge-{k}", k, "huge") for k in weights[:: max(1, len(weights) // 6)]]
    edits += [(f"complex-{k}", k, "complex") for k in weights[:2]]
    edits += [(f"gem-p-{v}", "gem.p", v) for v in (0.0, -1.0, -1e-9)]
    return edits


CHECKPOINT_VALUES = _state_edits()


@pytest.mark.parametrize("case, key, how", CHECKPOINT_VALUES, ids=[c[0] for c in CHECKPOINT_VALUES])
def test_checkpoint_values(files, workdir, case, key, how):
    state = torch.load(files / "good.pth")
    v = state[key]
    if how == "negvar":
        v = v.clone()
        v.view(-1)[0] = -0.5
    elif how == "huge":
        v = v * 1e7 + 1e7
    elif how == "complex":
        v = v.to(torch.complex64)
    else:
        v = torch.full_like(v, how)
    torch.save({**state, key: v}, workdir / "bad.pth")
    expect = "complex" if how == "complex" else key
    _cli(
        workdir,
        [
            "export",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(TINY_CARD),
            "--checkpoint",
            str(workdir / "bad.pth"),
            "--output",
            str(workdir / "out" / "x.onnx"),
        ],
        expect,
    )


# -- graphs whose radaredge metadata does not describe them
def _edit_metadata(src: Path, dst: Path, key: str, change) -> Path:
    proto = onnx.load(str(src))
    for prop in proto.metadata_props:
        if prop.key == key:
            prop.value = change(prop.value)
    onnx.save(proto, str(dst))
    return dst


def _inputs(change):
    import json

    def edit(text):
        d = json.loads(text)
        change(d)
        return json.dumps(d)

    return edit


METADATA = [
    ("input-renamed", "radaredge.inputs", _inputs(lambda d: d["names"].__setitem__(0, "scan_0"))),
    ("inputs-reordered", "radaredge.inputs", _inputs(lambda d: d["names"].reverse())),
    ("frame-not-an-input", "radaredge.inputs", _inputs(lambda d: d["frames"].__setitem__(1, "points_9"))),
    ("timestamps-not-an-input", "radaredge.inputs", _inputs(lambda d: d.__setitem__("timestamps", "time"))),
    ("timestamps-as-frame", "radaredge.inputs", _inputs(lambda d: d["frames"].__setitem__(2, "timestamps"))),
    ("output-renamed", "radaredge.outputs", lambda t: t.replace("descriptor_normalized", "embedding")),
    ("output-dropped", "radaredge.outputs", lambda t: t.replace(', "input_flags"', "")),
    ("output-added", "radaredge.outputs", lambda t: t.replace("]", ', "boxes"]')),
    ("features-reordered", "radaredge.features", lambda t: t.replace('"v_r", "rcs"', '"rcs", "v_r"')),
    ("features-extra", "radaredge.features", lambda t: t.replace("]", ', "snr"]')),
    ("input-errors-text", "radaredge.input_errors", lambda t: "many"),
]


@pytest.mark.parametrize("case, key, change", METADATA, ids=[m[0] for m in METADATA])
def test_graph_metadata_that_does_not_describe_the_graph(files, workdir, case, key, change):
    bad = _edit_metadata(files / "tiny.onnx", workdir / "bad.onnx", key, change)
    with pytest.raises(InputError) as err:
        runtime.load(bad)
    assert "\n" not in str(err.value)
    for args in (["bench", "--runs", "1"], ["parity-check", "--cases", "1"]):
        _cli(workdir, [args[0], "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", str(bad), *args[1:]])


def test_metadata_copied_onto_a_foreign_graph(files, workdir, tmp_path):
    """A MAFF-Net graph carrying the TDFANet graph's radaredge metadata."""
    import radaredge

    maff = radaredge.export(str(MAFF_TINY), tmp_path / "maff.onnx").path
    proto, donor = onnx.load(str(maff)), onnx.load(str(files / "tiny.onnx"))
    del proto.metadata_props[:]
    proto.metadata_props.extend(donor.metadata_props)
    onnx.save(proto, str(workdir / "foreign.onnx"))
    with pytest.raises(InputError, match="does not describe this graph"):
        runtime.load(workdir / "foreign.onnx")
    _cli(workdir, ["inspect", str(workdir / "foreign.onnx")], "does not describe this graph")


# -- Des4Pos bundles and maps
@pytest.fixture(scope="module")
def des4pos_bundle(tmp_path_factory):
    import radaredge
    from radaredge.cards import load_card
    from radaredge.data.text_city import make_city_for_card

    d = tmp_path_factory.mktemp("des4pos")
    radaredge.export(str(DES4POS_TINY), d / "bundle")
    make_city_for_card(load_card(DES4POS_TINY), seed=0, world=60.0, objects=30, poses=3).save(d / "city.npz")
    return d


def _map_edit(path: Path, dst: Path, how: str) -> Path:
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    if how == "no-cells":
        data = {k: (v[:0] if v.ndim and k not in ("pose_w", "pose_cell", "pose_text") else v) for k, v in data.items()}
    elif how == "nan-origin":
        data["origins"][1, 0] = np.nan
    elif how == "inf-origin":
        data["origins"][0, 1] = np.inf
    elif how == "float-mask":
        data["object_mask"] = data["object_mask"].astype(np.float32)
    elif how == "string-points":
        data["points"] = data["points"].astype(str)
    elif how == "int-ids":
        data["ids"] = np.arange(len(data["ids"]))
    elif how == "nan-pose":
        data["pose_w"][0, 0] = np.nan
    elif how == "short-pose-text":
        data["pose_text"] = data["pose_text"][:1]
    elif how == "zero-size":
        data["sizes"][0] = 0.0
    elif how.startswith(("nan-", "huge-")):  # every numeric array of the map, by class
        value = np.nan if how.startswith("nan-") else 1e30
        name, index = MAP_NUMBERS[how.split("-", 1)[1].removesuffix("-no-poses")]
        data[name] = data[name].astype(np.float64 if data[name].dtype == np.float64 else np.float32)
        data[name][index] = value
    if how.endswith("-no-poses"):
        data.update(pose_w=np.zeros((0, 2)), pose_cell=np.zeros(0, "<U1"), pose_text=np.zeros(0, "<U1"))
    np.savez(dst, **data)
    return dst


# A numeric array of a cell map -> the element a NaN or a huge value is written to (cell 0's first
# real object). A map without described poses (a locate database) is checked as fully as one with.
MAP_NUMBERS = {
    "origins": ("origins", (0, 0)),
    "sizes": ("sizes", 0),
    "xyz": ("points", (0, 0, 0, 1)),
    "rgb": ("points", (0, 0, 0, 4)),
    "num-points": ("num_points", (0, 0)),
    "pose": ("pose_w", (0, 1)),
}
MAPS = [
    "no-cells",
    "nan-origin",
    "inf-origin",
    "float-mask",
    "string-points",
    "int-ids",
    "nan-pose",
    "short-pose-text",
    "zero-size",
    *[
        f"{v}-{n}{tail}"
        for v in ("nan", "huge")
        for n in MAP_NUMBERS
        for tail in ("", "-no-poses")
        if not (n == "pose" and tail)
    ],
]


@pytest.mark.parametrize("how", MAPS)
def test_des4pos_maps(des4pos_bundle, workdir, how):
    bad = _map_edit(des4pos_bundle / "city.npz", workdir / "bad.npz", how)
    before = set(p.relative_to(workdir) for p in workdir.rglob("*"))
    res = invoke(
        "locate",
        "--model",
        "des4pos-tiny",
        "--onnx-dir",
        str(des4pos_bundle / "bundle"),
        "--map",
        str(bad),
        "--text",
        "The pose is north of a red box.",
        "--no-cache",
    )
    assert_one_error_line(res, workdir, before)


@pytest.mark.parametrize("how", [m for m in MAPS if m.startswith(("nan-", "huge-")) and not m.endswith("no-poses")])
def test_des4pos_maps_evaluated(des4pos_bundle, workdir, how):
    """``eval --map`` refuses what locate refuses: never null positions and exit 0."""
    bad = _map_edit(des4pos_bundle / "city.npz", workdir / "bad.npz", how)
    before = set(p.relative_to(workdir) for p in workdir.rglob("*"))
    res = invoke(
        "eval",
        "--model",
        "des4pos-tiny",
        "--config",
        str(DES4POS_TINY),
        "--onnx",
        str(des4pos_bundle / "bundle"),
        "--map",
        str(bad),
        "--no-reference",
        "--report",
        "r.json",
    )
    assert_one_error_line(res, workdir, before)


BUNDLES = [
    ("manifest-not-json", "bundle.json", b"{parts: nope"),
    ("manifest-list", "bundle.json", b"[1, 2]"),
    ("manifest-no-parts", "bundle.json", b'{"weights_sha256": "x"}'),
    ("manifest-parts-text", "bundle.json", b'{"weights_sha256": "x", "parts": "all"}'),
    (
        "manifest-onnx-escapes",
        "bundle.json",
        b'{"weights_sha256": "x", "parts": {"submap_encoder": {"onnx": "../x.onnx"}}}',
    ),
    ("manifest-binary", "bundle.json", b"\xff\xfe\x00" * 20),
    ("tokenizer-garbage", "tokenizer.json", b"{not a tokenizer"),
    ("tokenizer-empty", "tokenizer.json", b""),
    ("tokenizer-binary", "tokenizer.json", b"\x00\x01" * 50),
]


@pytest.mark.parametrize("case, name, content", BUNDLES, ids=[b[0] for b in BUNDLES])
def test_des4pos_bundles(des4pos_bundle, workdir, case, name, content):
    bundle = workdir / "bundle"
    shutil.copytree(des4pos_bundle / "bundle", bundle)
    (bundle / name).write_bytes(content)
    before = set(p.relative_to(workdir) for p in workdir.rglob("*"))
    res = invoke(
        "locate",
        "--model",
        "des4pos-tiny",
        "--onnx-dir",
        str(bundle),
        "--map",
        str(des4pos_bundle / "city.npz"),
        "--text",
        "The pose is north of a red box.",
        "--no-cache",
    )
    assert_one_error_line(res, workdir, before, name)


# -- generators asked for more than a machine holds
GENERATORS = [
    (f"make-benchmark-{opt}-{v}", ["make-benchmark", "--out", "b", opt, str(v)], opt)
    for opt, values in (
        ("--drives", (0, 1, 65, 10**9)),
        ("--frames", (0, -5, 20_001, 10**12)),
        ("--towns", (0, 1001, 10**9)),
    )
    for v in values
]
GENERATORS += [
    (f"make-city-{opt}-{v}", ["make-city", "--out", "c.npz", opt, str(v)], opt.lstrip("-"))
    for opt, values in (
        ("--world", (0, 0.5, 5001, 1e12, "nan", "inf")),
        ("--objects", (0, 100_001, 10**12)),
        ("--poses", (-1, 100_001, 10**12)),
        ("--cities", (0, 1001)),
    )
    for v in values
]
GENERATORS += [
    (
        "make-city-world-objects-budget",
        ["make-city", "--out", "c.npz", "--world", "5000", "--objects", "100000"],
        "--world",
    ),
    ("make-city-out-no-npz", ["make-city", "--out", "city"], "name it city.npz"),
    ("make-city-out-directory", ["make-city", "--out", "d/"], "a directory"),
    ("make-city-cities-out-file", ["make-city", "--out", "taken.npz", "--cities", "2"], "an existing file"),
]


@pytest.mark.parametrize("case, args, expect", GENERATORS, ids=[g[0] for g in GENERATORS])
def test_generators_are_bounded(workdir, case, args, expect):
    if "taken.npz" in args:
        (workdir / "taken.npz").write_text("x")
    _cli(workdir, args, expect)


# -- scan files whose names do not give one frame order
ORDERS = [["1.npy", "01.npy"], ["frame_2.npy", "frame_002.npy"], ["0.npy", "00.npy", "1.npy"], ["a7.npy", "a07.npy"]]


@pytest.mark.parametrize("names", ORDERS, ids=["+".join(n) for n in ORDERS])
def test_ambiguous_scan_names(tmp_path, names):
    (tmp_path / "scans").mkdir()
    for i, name in enumerate(names):
        np.save(tmp_path / "scans" / name, np.zeros((3, 5), np.float32))
    (tmp_path / "gps.csv").write_text(
        "timestamp,northing,easting\n" + "".join(f"{i * 0.1},{i},0\n" for i in range(len(names)))
    )
    with pytest.raises(InputError, match="name the same frame number"):
        load_sequence(tmp_path)


# -- KITTI360Pose pickles of shared references (a few kilobytes naming billions of numbers)
BOMBS = [(depth, width) for depth in (2, 3, 4) for width in (200, 1000)]


@pytest.mark.parametrize("depth, width", BOMBS, ids=[f"depth{d}-width{w}" for d, w in BOMBS])
def test_pickle_bombs(tmp_path, text2loc, depth, width):
    def make(name, attrs):
        obj = getattr(text2loc, name)()
        obj.__dict__.update(attrs)
        return obj

    nested = [0.5, 0.5, 0.5]
    for _ in range(depth):
        nested = [nested] * width
    obj = make("Object3d", dict(xyz=nested, rgb=nested, label="car"))
    cell = make(
        "Cell", dict(id="s_00001", scene_name="s", cell_size=30.0, bbox_w=np.arange(6.0), objects=[obj] * width)
    )
    path = tmp_path / "cells.pkl"
    path.write_bytes(pickle.dumps([cell] * width))
    assert path.stat().st_size < 200_000
    with pytest.raises(InputError) as err:
        read_cells(path)
    assert "\n" not in str(err.value)


# -- cards taken too loosely
def _card_text(edit: str) -> str:
    text = TINY_CARD.read_text()
    if edit == "duplicate-top":
        return text + "\nframes: 3\n"
    if edit == "repeated-section":
        return text + "\npillars:\n  out_channels: 8\n"
    if edit == "duplicate-nested":
        return (
            text.replace("pillars:\n", "pillars:\n  out_channels: 4\n", 1)
            if "out_channels" in text
            else text.replace("pillars:\n", "pillars:\n  bn_eps: 0.001\n  bn_eps: 0.01\n", 1)
        )
    if edit.startswith("misspelt-"):
        return text + f"\n{edit.split('-', 1)[1]}:\n  out_channels: 8\n"
    if edit.startswith("nested-"):
        depth = int(edit.split("-")[1])
        return text + "\nextra: " + "[" * depth + "]" * depth + "\n"
    if edit.startswith("digits-"):
        return text + "\nmax_points_per_frame: " + "9" * int(edit.split("-")[1]) + "\n"
    raise AssertionError(edit)


CARD_TEXTS = [
    ("duplicate-top", "given twice"),
    ("repeated-section", "given twice"),
    ("duplicate-nested", "given twice"),
    *[(f"misspelt-{name}", name) for name in ("pillarz", "netwrok", "preproces", "pilars", "quantisation")],
    *[(f"nested-{d}", "nested deeper") for d in (20, 200, 5000)],
    *[(f"digits-{n}", "digits") for n in (20, 400, 5000)],
]


@pytest.mark.parametrize("edit, expect", CARD_TEXTS, ids=[c[0] for c in CARD_TEXTS])
def test_cards_parsed_strictly(files, workdir, edit, expect):
    card = workdir / "card.yaml"
    card.write_text(_card_text(edit))
    _cli(
        workdir,
        ["export", "--model", "tdfanet-tiny", "--config", str(card), "--output", str(workdir / "o" / "x.onnx")],
        expect,
    )
    bad = _edit_metadata(files / "tiny.onnx", workdir / "carded.onnx", "radaredge.card", lambda t: _card_text(edit))
    _cli(workdir, ["inspect", str(bad)], expect)  # the card inside a graph, parsed the same way


GRIDS = [
    (
        "tdfanet-voxel-0.05",
        TINY_CARD,
        lambda d: d["pillars"].update(
            voxel_size=[0.05, 0.05, 5.0], point_cloud_range=[0, -40, -3, 70, 40, 2], out_channels=64
        ),
        "MiB BEV map",
    ),
    (
        "tdfanet-channels",
        TINY_CARD,
        lambda d: d["pillars"].update(
            point_cloud_range=[0, -40, -3, 70, 40, 2], voxel_size=[0.1, 0.1, 5.0], out_channels=512
        ),
        "MiB BEV map",
    ),
    (
        "tdfanet-voxel-0.016",
        TINY_CARD,
        lambda d: d["pillars"].update(voxel_size=[0.016, 0.016, 13.0]),
        "BEV maps per window",
    ),  # 4 M cells of 8 channels in 3 frames: the export needed 8 GB
    ("maffnet-cfa-map", MAFF_TINY, lambda d: d["cfa"]["grid"].update(map_h=4096, map_w=4096), "cells"),
    ("dbscan-map", MAFF_DBSCAN, lambda d: d["cfa"]["dbscan"].update(map_rows=2048, map_cols=2048), "cells"),
]


@pytest.mark.parametrize("case, base, edit, expect", GRIDS, ids=[g[0] for g in GRIDS])
def test_grids_the_runtime_cannot_allocate(workdir, case, base, edit, expect):
    card = _card_with(base, workdir / "card.yaml", edit)
    model = yaml.safe_load(card.read_text())["name"]
    _cli(
        workdir, ["export", "--model", model, "--config", str(card), "--output", str(workdir / "o" / "x.onnx")], expect
    )


def test_features_reordered_against_a_trained_checkpoint(files, workdir):
    """A training checkpoint records its card: a card that lists the same columns in another order
    is refused (the first layer's weights follow the column order)."""
    state = torch.load(files / "good.pth")
    data = yaml.safe_load(TINY_CARD.read_text())
    torch.save({"model_state": state, "card": data, "epoch": 1}, workdir / "trained.pth")
    card = _card_with(
        TINY_CARD, workdir / "card.yaml", lambda d: d.__setitem__("features", ["x", "y", "z", "rcs", "v_r"])
    )
    _cli(
        workdir,
        [
            "export",
            "--model",
            "tdfanet-tiny",
            "--config",
            str(card),
            "--checkpoint",
            str(workdir / "trained.pth"),
            "--output",
            str(workdir / "o" / "x.onnx"),
        ],
        "in that order",
    )


# -- one implausible value, column by column, on a card that refuses them
@pytest.fixture(scope="module")
def refusing(tmp_path_factory):
    import radaredge

    d = tmp_path_factory.mktemp("refusing")
    card = _card_with(MAFF_TINY, d / "maffnet-tiny.yaml", lambda c: c.__setitem__("implausible", "refuse"))
    return runtime.load(radaredge.export(str(card), d / "m.onnx").path, threads=1)


IMPLAUSIBLE_VALUES = [(c, v) for c in range(3, 7) for v in (1e4, -1e4, 3.4e38, -3.4e38, 101.0)]


@pytest.mark.parametrize("column, value", IMPLAUSIBLE_VALUES, ids=[f"col{c}-{v:g}" for c, v in IMPLAUSIBLE_VALUES])
def test_implausible_values_refused(refusing, column, value):
    points = np.zeros((20, 7), np.float32)
    points[:, 0] = np.linspace(1, 10, 20)
    points[7, column] = value
    if column == 6 and abs(value) == 101.0:
        points[7, column] = 11.0  # time: plausible within +-10 s
    with pytest.raises(InputError, match=f"point 7, column '{refusing.features[column]}'"):
        refusing.run(points)


# -- --json: one JSON document on stdout, also for a failure
JSON_FAILURES = [
    c
    for c in CLI
    if c[1]
    and c[1][0]
    in ("export", "parity-check", "bench", "eval", "inspect", "locate", "make-city", "make-benchmark", "train")
][:40]


@pytest.mark.parametrize("case, args, expect", JSON_FAILURES, ids=[c[0] for c in JSON_FAILURES])
def test_json_failures_print_a_json_document(files, workdir, case, args, expect):
    import json

    res = invoke(*[a.format(f=files) for a in args], "--json")
    assert res.exit_code == 2, res.output
    doc = json.loads(res.stdout)
    assert doc["exit_code"] == 2 and doc["error"]


# -- the Python API given values of the wrong type (None where a path is needed, an int, a generator)
def _api_cases():
    import inspect
    import typing

    from radaredge import api
    from radaredge.config import _accepts

    cases = []
    for verb in (
        "export",
        "parity",
        "bench",
        "evaluate",
        "quantize",
        "train",
        "card_from_openpcdet",
        "run",
        "map_build",
        "map_query",
    ):
        fn = getattr(api, verb)
        hints = typing.get_type_hints(fn.__wrapped__)
        for name, param in inspect.signature(fn).parameters.items():
            hint = hints.get(name)
            if hint is None or not _accepts(hint, "x"):
                continue  # counts, flags, callables: checked elsewhere
            for label, value in (("int", 5), ("generator", "gen"), ("none", None)):
                if value is None and _accepts(hint, None):
                    continue
                cases.append((verb, name, label))
    return cases


API_CASES = _api_cases()


@pytest.mark.parametrize("verb, name, label", API_CASES, ids=[f"{v}-{n}-{k}" for v, n, k in API_CASES])
def test_api_arguments_of_the_wrong_type(verb, name, label):
    """Every path or name argument of every API verb: a value of another type is a ConfigError naming
    the verb and the parameter, raised before any work (it was a TypeError from pathlib)."""
    import inspect

    from radaredge import api

    fn = getattr(api, verb)
    required = {
        n: "x"
        for n, p in inspect.signature(fn).parameters.items()
        if p.default is inspect.Parameter.empty and p.kind is not inspect.Parameter.VAR_KEYWORD
    }
    value = {"int": 5, "generator": (c for c in "ab"), "none": None}[label]
    with pytest.raises(RadarEdgeError, match=f"{verb}: {name}: expected"):
        fn(**{**required, name: value})
