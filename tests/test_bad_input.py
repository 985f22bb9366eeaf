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

from radaredge import runtime
from radaredge.config import field_range
from radaredge.data.readers import read_rosbag, read_scan
from radaredge.data.sequences import load_sequence
from radaredge.data.kitti360pose import TEXT2LOC_MODULE, read_cells, read_poses
from radaredge.errors import RadarEdgeError
from radaredge.models.des4pos import FineConfig, SubmapConfig
from radaredge.models.des4pos_config import CellConfig, TextConfig
from radaredge.models.maffnet import BackboneConfig, SpaConfig
from radaredge.models.maffnet_rcnn import KeypointConfig, ProposalConfig, RoiHeadConfig, SAConfig, VsaConfig
from radaredge.models.maffnet_fuser import CafConfig
from radaredge.models.tdfanet import TDFANetConfig
from radaredge.ops.ego_velocity import RansacConfig
from radaredge.ops.dbscan import DbscanConfig
from radaredge.ops.grid_density import GridDensityConfig
from radaredge.ops.nms import NmsConfig
from radaredge.ops.pillars import PillarConfig

from conftest import TINY_CARD, invoke

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
    for name, card_text in (("bad-yaml", "name: [unclosed"), ("python-tag", "!!python/object/apply:os.system ['true']"),
                            ("alias-bomb", "a: &a [x, x]\nb: &b [*a, *a]\nc: [*b, *b]"), ("not-a-card", "just text")):
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
    torch.save({k: torch.full_like(v, float("nan")) if v.is_floating_point() else v for k, v in state.items()},
               d / "nan-weights.pth")
    torch.save({k: v + 1 if v.is_floating_point() else v for k, v in state.items()}, d / "other-weights.pth")
    with open(d / "malicious.pth", "wb") as f:
        pickle.dump(_Exploit(), f)
    (d / "a-file").write_text("not a directory")
    (d / "empty-dir").mkdir()
    (d / "binary.yaml").write_bytes(b"\xff\xfe\x00\x01" * 64)
    (d / "huge.yaml").write_text("# " + "x" * 300_000)
    town = d / "town"
    from radaredge.data.pr_benchmark import make_pr_benchmark
    make_pr_benchmark(town, drives=2, frames_per_drive=6, seed=0)
    far = d / "far-town"
    make_pr_benchmark(far, drives=2, frames_per_drive=6, seed=3)   # 30 km east of town
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
    ("export-calibration-windows-0", ["export", "--model", "tdfanet", "--quantize", "int8", "--calibration-windows", "0"],
     "--calibration-windows"),
    ("export-calibration-format", ["export", "--model", "tdfanet", "--calibration-format", "x"], "--calibration-format"),
    ("export-calibration-missing", ["export", "--model", "tdfanet", "--quantize", "int8", "--calibration",
                                    "{f}/nowhere"], "nowhere"),
    ("export-calibration-truncated-scan", ["export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD),
                                           "--quantize", "int8", "--calibration", "{f}/recording", "--calibration-format",
                                           "vod", "--calibration-windows", "4", "--output", "out/t.onnx"],
     "recording/000003.bin: 50 bytes"),
    ("export-output-under-file", ["export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output",
                                  "{f}/a-file/x.onnx"], "a-file"),
    ("export-config-missing", ["export", "--model", "x", "--config", "{f}/nowhere.yaml"], "nowhere.yaml"),
    ("export-config-binary", ["export", "--model", "x", "--config", "{f}/binary.yaml"], "not a text file"),
    ("export-config-huge", ["export", "--model", "x", "--config", "{f}/huge.yaml"], "at most"),
    ("parity-no-onnx", ["parity-check", "--model", "tdfanet"], "Missing option '--onnx'"),
    ("parity-cases-0", ["parity-check", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                        "--cases", "0"], "cases"),
    ("parity-cases-negative", ["parity-check", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                               "{f}/tiny.onnx", "--cases", "-3"], "cases"),
    ("parity-cases-huge", ["parity-check", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                           "{f}/tiny.onnx", "--cases", "100000000"], "cases"),
    ("parity-runtime", ["parity-check", "--model", "tdfanet", "--onnx", "x", "--runtime", "tensorrt"], "--runtime"),
    ("bench-runs-0", ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                      "--runs", "0"], "runs"),
    ("bench-warmup-negative", ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                               "{f}/tiny.onnx", "--warmup", "-1"], "warm"),
    ("bench-threads-0", ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                         "--threads", "0"], "threads"),
    ("bench-threads-huge", ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                            "--threads", "1000000"], "threads"),
    ("bench-save-under-file", ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                               "{f}/tiny.onnx", "--save", "{f}/a-file/b.json"], "a-file"),
    ("eval-no-onnx", ["eval", "--model", "tdfanet"], "Missing option '--onnx'"),
    ("eval-missing-database", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                               "{f}/tiny.onnx", "--database", "{f}/nowhere", "--queries", "{f}/town/queries"], "nowhere"),
    ("eval-empty-database", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                             "--database", "{f}/empty-dir", "--queries", "{f}/town/queries"], "no drives"),
    ("eval-no-gps", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                     "--database", "{f}/no-gps", "--queries", "{f}/town/queries"], "gps.csv"),
    ("eval-binary-gps", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                         "--database", "{f}/binary-gps", "--queries", "{f}/town/queries"], "not a text CSV"),
    ("eval-other-town", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                         "--database", "{f}/town/database", "--queries", "{f}/far-town/queries"], "within 5 m"),
    ("eval-nan-in-a-scan", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                            "--database", "{f}/nan-town/database", "--queries", "{f}/nan-town/queries"],
     "queries/drive-01/scans/000003.npy: non-finite value nan at point 2, column 'v_r'"),
    ("eval-radius-0", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                       "--database", "{f}/town/database", "--queries", "{f}/town/queries", "--radius", "0"], "radius"),
    ("eval-radius-nan", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                         "--database", "{f}/town/database", "--queries", "{f}/town/queries", "--radius", "nan"], "radius"),
    ("eval-radius-inf", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx", "{f}/tiny.onnx",
                         "--database", "{f}/town/database", "--queries", "{f}/town/queries", "--radius", "inf"], "radius"),
    ("eval-report-under-file", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                                "{f}/tiny.onnx", "--database", "{f}/town/database", "--queries", "{f}/town/queries",
                                "--report", "{f}/a-file/r.json"], "a-file"),
    ("eval-plot-under-file", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                              "{f}/tiny.onnx", "--database", "{f}/town/database", "--queries", "{f}/town/queries",
                              "--plot", "{f}/a-file/p.png"], "a-file"),
    ("eval-map-for-tdfanet", ["eval", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                              "{f}/tiny.onnx", "--map", "{f}/random.npz"], "--database"),
    ("eval-maffnet", ["eval", "--model", "maffnet-tiny", "--config", str(MAFF_TINY), "--onnx", "{f}/tiny.onnx",
                      "--database", "{f}/town/database", "--queries", "{f}/town/queries"], "no evaluation"),
    ("make-benchmark-drives-0", ["make-benchmark", "--out", "b", "--drives", "0"], "drives"),
    ("make-benchmark-drives-1", ["make-benchmark", "--out", "b", "--drives", "1"], "drives"),
    ("make-benchmark-frames-0", ["make-benchmark", "--out", "b", "--frames", "0"], "frames"),
    ("make-benchmark-seed-negative", ["make-benchmark", "--out", "b", "--seed", "-1"], "seed"),
    ("make-benchmark-towns-0", ["make-benchmark", "--out", "b", "--towns", "0"], "towns"),
    ("make-benchmark-towns-huge", ["make-benchmark", "--out", "b", "--towns", "100000"], "--towns"),
    ("make-city-cities-0", ["make-city", "--out", "c", "--cities", "0"], "--cities"),
    ("make-city-cities-huge", ["make-city", "--out", "c", "--cities", "100000"], "--cities"),
    ("make-benchmark-out-under-file", ["make-benchmark", "--out", "{f}/a-file/b", "--frames", "2"], "a-file"),
    ("make-city-objects-0", ["make-city", "--out", "c.npz", "--objects", "0"], "objects"),
    ("make-city-poses-negative", ["make-city", "--out", "c.npz", "--poses", "-1"], "poses"),
    ("make-city-world-0", ["make-city", "--out", "c.npz", "--world", "0"], "world"),
    ("make-city-world-nan", ["make-city", "--out", "c.npz", "--world", "nan"], "world"),
    ("make-city-seed-negative", ["make-city", "--out", "c.npz", "--seed", "-2"], "seed"),
    ("make-city-for-tdfanet", ["make-city", "--out", "c.npz", "--model", "tdfanet"], "tdfanet"),
    ("make-city-out-under-file", ["make-city", "--out", "{f}/a-file/c.npz"], "a-file"),
    ("locate-no-dir", ["locate", "--onnx-dir", "{f}/nowhere", "--map", "{f}/random.npz", "--text", "x"], "nowhere"),
    ("locate-top-k-0", ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x",
                        "--top-k", "0"], "top"),
    ("locate-threads-0", ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x",
                          "--threads", "0"], "threads"),
    ("locate-threads-huge", ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x",
                             "--threads", "100000"], "threads"),
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
    ("train-missing-data", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/nowhere"],
     "nowhere"),
    ("train-data-is-file", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/a-file"],
     "a-file"),
    ("train-empty-data", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/empty-dir"],
     "no drives"),
    ("train-one-drive", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/no-gps"],
     "gps.csv"),
    ("train-epochs-0", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                        "--epochs", "0"], "--epochs"),
    ("train-lr-negative", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                           "--lr", "-1"], "--lr"),
    ("train-lr-nan", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                      "--lr", "nan"], "--lr"),
    ("train-batch-0", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                       "--batch-size", "0"], "--batch-size"),
    ("train-set-unknown", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                           "--set", "foo=1"], "foo"),
    ("train-set-text", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                        "--set", "negatives=many"], "--negatives"),
    ("train-set-no-value", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                            "--set", "negatives"], "KEY=VALUE"),
    ("train-set-list", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                        "--set", "negatives=[1, 2]"], "list"),
    ("train-hard-above-negatives", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data",
                                    "{f}/town", "--set", "hard_negatives=30"], "hard_negatives"),
    ("train-radii-swapped", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                             "--set", "negative_radius=2"], "negative_radius"),
    ("train-second-term", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                           "--set", "second_term=other"], "second_term"),
    ("train-unknown-validation", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data",
                                  "{f}/town", "--validation", "nope"], "nope"),
    ("train-device", ["train", "--model", "tdfanet", "--data", "x", "--device", "tpu"], "--device"),
    ("train-resume-without-state", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data",
                                    "{f}/town", "--output", "run", "--resume"], "last.pth"),
    ("train-resume-and-checkpoint", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data",
                                     "{f}/town", "--resume", "--checkpoint", "{f}/good.pth"], "--checkpoint"),
    ("train-field-map", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                         "--field-map", "v_r"], "--field-map"),
    ("train-maffnet", ["train", "--model", "maffnet-tiny", "--config", str(MAFF_TINY), "--data", "{f}/town"],
     "no training recipe"),
    ("train-output-under-file", ["train", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--data", "{f}/town",
                                 "--output", "{f}/a-file/run"], "a-file"),
]
CHECKPOINTS = ["truncated", "list", "wrong-shape", "missing-keys", "unexpected-key", "non-tensor", "nan-weights",
               "malicious", "random", "nowhere"]
CLI += [(f"export-checkpoint-{name}", ["export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD),
                                       "--checkpoint", f"{{f}}/{name}.{'bin' if name == 'random' else 'pth'}"],
         {"nan-weights": "not finite", "malicious": "runs no pickled code"}.get(name, "checkpoint"))
        for name in CHECKPOINTS]
CLI += [(f"parity-onnx-{name}", ["parity-check", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                                 f"{{f}}/{name}.onnx"], name)
        for name in ("random", "empty", "truncated", "no-metadata", "nowhere")]
CLI += [(f"parity-checkpoint-{name}", ["parity-check", "--model", "tdfanet-tiny", "--config", str(TINY_CARD),
                                       "--onnx", "{f}/tiny.onnx", "--checkpoint", f"{{f}}/{name}.pth"], expect)
        for name, expect in (("truncated", "checkpoint"), ("malicious", "runs no pickled code"),
                             ("other-weights", "exported with other weights"))]
CLI += [(f"bench-onnx-{name}", ["bench", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--onnx",
                                f"{{f}}/{name}.onnx", "--runs", "1", "--no-reference"], name)
        for name in ("random", "no-metadata", "card-bad-yaml")]
CLI += [("locate-map-missing", ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/nowhere.npz", "--text", "x"],
         "nowhere.npz"),
        ("locate-not-a-bundle", ["locate", "--onnx-dir", "{f}/empty-dir", "--map", "{f}/random.npz", "--text", "x"],
         "not a Des4Pos bundle")]


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
    values = [("nan", float("nan")), ("inf", float("inf")), ("-inf", float("-inf")), ("below", below),
              ("above", above), ("word", "many"), ("bool", True)]
    if isinstance(default, tuple):
        values = [(k, [v] * len(default)) for k, v in values] + [("scalar", 1.0), ("short", [])]
    else:
        values += [("list", [])]               # an empty list passed the per-number checks (fuzzing found it)
    return values


def _set(data: dict, dotted: str, value):
    node = data
    parts = dotted.split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value


SECTION_FIELDS = []
for base, model, sections in (
        (TINY_CARD, "tdfanet-tiny", (("preprocess.ransac", RansacConfig), ("pillars", PillarConfig),
                                     ("network", TDFANetConfig))),
        (MAFF_TINY, "maffnet-tiny", (("spa", SpaConfig), ("cfa.grid", GridDensityConfig), ("caf", CafConfig),
                                     ("backbone_2d", BackboneConfig), ("post_processing", NmsConfig))),
        (MAFF_DBSCAN, "maffnet-tiny-full-dbscan",
         (("cfa.dbscan", DbscanConfig), ("stage_two.proposals", ProposalConfig), ("stage_two.keypoints", KeypointConfig),
          ("stage_two.vsa", VsaConfig), ("stage_two.vsa.sa_clusterpoints", SAConfig),
          ("stage_two.roi_head", RoiHeadConfig), ("stage_two.roi_head.roi_grid_pool", SAConfig),
          ("stage_two.post_processing", NmsConfig))),
        (DES4POS_TINY, "des4pos-tiny", (("cell", CellConfig), ("submap", SubmapConfig), ("text", TextConfig),
                                        ("fine", FineConfig)))):
    for path, cls in sections:
        for f in dataclasses.fields(cls):
            if field_range(cls, f.name) is None:
                continue
            for label, value in _bad_values(cls, f.name):
                SECTION_FIELDS.append((f"{model}-{path}.{f.name}-{label}", base, model, f"{path}.{f.name}", value))

TOP_LEVEL = [(f"tdfanet-tiny-{key}-{label}", TINY_CARD, "tdfanet-tiny", key, value)
             for key, values in (("frames", (0, 1, 65, "three", 2.5, None)), ("frame_rate", (0, -10, "fast")),
                                 ("seed", (-1, 2**40, "x")), ("max_points_per_frame", (0, -5, 2**30, 2**24)),
                                 ("features", ([], "xyz", ["y", "x", "z"], ["x", "y", "z", "x"], [1, 2, 3])),
                                 ("name", ("", 5)), ("model", ("", "nope", 3)), ("network", ("deep", [1])),
                                 ("pillars", (3,)), ("classes", ("car",)))
             for label, value in ((str(v), v) for v in values)]


@pytest.mark.parametrize("case, base, model, field, value", SECTION_FIELDS + TOP_LEVEL,
                         ids=[c[0] for c in SECTION_FIELDS + TOP_LEVEL])
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


FRAMES = ["count:0", "count:2", "count:4", *[f"nan:{c}" for c in range(5)], *[f"inf:{c}" for c in range(5)],
          "columns:4", "columns:6", "columns:0", "ndim:1", "ndim:3", "dtype:complex64", "dtype:U3", "dtype:bool",
          "object", "text", "none", "ragged", "huge"]


@pytest.mark.parametrize("how", FRAMES)
def test_runtime_frames(exported, how):
    model, good = exported
    with pytest.raises(RadarEdgeError) as err:
        model.run(_mutate(good, how))
    assert "\n" not in str(err.value) and str(err.value)


TIMESTAMPS = [[0.0, 0.1], [0.0, 0.1, 0.2, 0.3], [0.0, 0.0, 0.1], [0.2, 0.1, 0.0], [0.0, np.nan, 0.2],
              [0.0, 0.1, np.inf], ["a", "b", "c"], [[0.0], [0.1], [0.2]], [1e300, -1e300, 0.0], [1e9, 1e9, 1e9]]


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
        p.write_bytes(b"\x93NUMPY\x01\x00" + len(header.ljust(118) + "\n").to_bytes(2, "little")
                      + (header.ljust(118) + "\n").encode())
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


SCANS = ["truncated-bin", "random-npy", "object-npy", "3d-npy", "columns-npy", "text-npy", "huge-header-npy",
         "suffix", "missing", "directory", "fmt", "feature", "ambiguous-size"]


@pytest.mark.parametrize("kind", SCANS)
def test_scan_files(tmp_path, kind):
    path, extra = _scan(tmp_path, kind)
    with pytest.raises(RadarEdgeError) as err:
        read_scan(path, extra.get("features", ["x", "y", "z", "v_r", "rcs"]), extra.get("fmt"))
    assert "\n" not in str(err.value)


GPS = [("missing", None), ("empty", ""), ("header-only-wrong", "time,n,e\n0,0,0\n"),
       ("text-value", "timestamp,northing,easting\n0,a,0\n"), ("nan", "timestamp,northing,easting\n0,nan,0\n"),
       ("decreasing", "timestamp,northing,easting\n1,0,0\n0,0,0\n"), ("short-row", "timestamp,northing,easting\n0,0\n"),
       ("rows-vs-scans", "timestamp,northing,easting\n0,0,0\n1,0,0\n2,0,0\n"),
       ("binary", b"\x00\xff\xfe" * 30)]


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
            obj = make("Object3d", {**dict(xyz=np.zeros((4, 3)), rgb=np.zeros((4, 3)), label="car"),
                                    **over.pop("object", {})})
            items = [make("Cell", {**dict(id="s_00001", scene_name="s", cell_size=30.0, bbox_w=np.arange(6.0),
                                          objects=[obj]), **over})]
        else:
            desc = make("DescriptionPoseCell", {**dict(direction="north", object_color_text="red",
                                                       object_label="car"), **over.pop("description", {})})
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
        path = write_bag(tmp_path / "t.bag", True, {"/other": ("sensor_msgs/msg/PointCloud", [
            pointcloud(ROS1, (1, 0), np.zeros((1, 3)), {"Doppler": [0.0]})])})
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
    n = len(CLI) + len(SECTION_FIELDS) + len(TOP_LEVEL) + len(FRAMES) + len(TIMESTAMPS) + 6 + len(SCANS) + len(GPS) \
        + len(PICKLES) + len(BAGS)
    assert n >= 250, n
