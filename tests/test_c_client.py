"""examples/c: the C client built against the onnxruntime wheel's library, run on TDFANet and
MAFF-Net exports, bitwise equal to radaredge.runtime at 1 and 2 threads (an empty frame
included); the graph's input_flags seen from C and from Python; one AddressSanitizer and
UndefinedBehaviorSanitizer run. Building needs onnxruntime's C headers, which
examples/c/fetch_headers.sh downloads from Debian: when that fails, these tests fail and say so."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_CARD

import radaredge
from radaredge import runtime
from radaredge.cards import load_card
from radaredge.errors import CapacityError, InputError
from radaredge.models import create_model
from radaredge.runtime.flags import CAPACITY, IMPLAUSIBLE, NON_FINITE, OUT_OF_RANGE, TIME_ORDER
from radaredge.runtime.session import run_session

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "c"
MAFF_TINY = Path(__file__).parent / "cards" / "maffnet-tiny.yaml"


def _make(target: str, build: Path) -> Path:
    done = subprocess.run(
        ["make", "-C", str(EXAMPLE), f"BUILD={build}", f"PYTHON={sys.executable}", target],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, (
        f"building examples/c failed (onnxruntime's C headers come from Debian's "
        f"libonnxruntime-dev via examples/c/fetch_headers.sh):\n{done.stdout}\n{done.stderr}"
    )
    return build / ("radaredge_run" if target == "all" else "radaredge_run_asan")


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    return _make("all", tmp_path_factory.mktemp("c-build"))


@pytest.fixture(scope="module")
def graphs(tmp_path_factory, tiny_export):
    """The tiny TDFANet export and a tiny MAFF-Net export."""
    d = tmp_path_factory.mktemp("c-graphs")
    card = load_card(MAFF_TINY)
    maff = radaredge.export(card, d / "maffnet-tiny.onnx", model=create_model(card)).path
    return {"tdfanet": tiny_export[2], "maffnet": maff}


def _scans(tmp: Path, arrays: list[np.ndarray]) -> list[Path]:
    paths = []
    for i, a in enumerate(arrays):
        p = tmp / f"scan{i}.bin"
        np.ascontiguousarray(a, "<f4").tofile(p)
        paths.append(p)
    return paths


def _run(client: Path, onnx: Path, scans: list[Path], out: Path, *extra) -> subprocess.CompletedProcess:
    out.mkdir(parents=True, exist_ok=True)
    return subprocess.run(
        [str(client), *map(str, extra), "--out", str(out), str(onnx), *map(str, scans)], capture_output=True, text=True
    )


def _outputs(out: Path) -> dict[str, np.ndarray]:
    summary = json.loads((out / "summary.json").read_text())
    return {
        o["name"]: np.fromfile(out / f"{o['name']}.bin", np.dtype(o["dtype"])).reshape(o["shape"])
        for o in summary["outputs"]
    }


def _tdfanet_frames():
    card = load_card(TINY_CARD)
    feeds = radaredge.models.model_spec(card).graph().make_cases(card, 1, 0)[0][1]
    return [feeds["points_0"], np.zeros((0, 5), np.float32), feeds["points_2"]]


def _maffnet_frames():
    card = load_card(MAFF_TINY)
    feeds = radaredge.models.model_spec(card).graph().make_cases(card, 1, 0)[0][1]
    return [feeds["points"]]


@pytest.mark.parametrize("model", ["tdfanet", "maffnet"])
@pytest.mark.parametrize("threads", [1, 2])
def test_the_c_client_is_bitwise_the_python_runtime(client, graphs, tmp_path, model, threads):
    frames = _tdfanet_frames() if model == "tdfanet" else _maffnet_frames()
    stamps = [1732500000.1, 1732500000.2, 1732500000.3][: len(frames)]
    res = _run(
        client,
        graphs[model],
        _scans(tmp_path, frames),
        tmp_path / "out",
        "--threads",
        threads,
        "--timestamps",
        ",".join(repr(t) for t in stamps),
    )
    assert res.returncode == 0, res.stderr
    assert "card:" in res.stdout and "x, y, z" in res.stdout
    assert all(line.startswith("input_flags: frame") for line in res.stderr.splitlines())  # information only
    got = _outputs(tmp_path / "out")
    m = runtime.load(graphs[model], threads=threads)
    want = m.run(frames, stamps if m.inputs.timestamps_input else None)
    assert set(got) == set(want)
    for name, value in want.items():
        assert got[name].dtype == value.dtype and got[name].shape == value.shape, name
        assert got[name].tobytes() == value.tobytes(), f"{model} {name} differs from radaredge.runtime"


def test_the_c_client_refuses_bad_input_like_the_runtime(client, graphs, tmp_path):
    frames = _tdfanet_frames()
    frames[2] = frames[2].copy()
    frames[2][3, 4] = np.nan
    scans = _scans(tmp_path, frames)
    res = _run(client, graphs["tdfanet"], scans, tmp_path / "a")
    assert (
        res.returncode == 2
        and res.stderr.strip() == f"error: frame 2 ({scans[2]}): non-finite value nan at point 3, column 'rcs'"
    )
    (tmp_path / "short.bin").write_bytes(b"\0" * 13)
    res = _run(client, graphs["tdfanet"], [scans[0], scans[1], tmp_path / "short.bin"], tmp_path / "b")
    assert res.returncode == 2 and "13 bytes is not a whole number of rows of 5 float32 columns" in res.stderr
    res = _run(client, graphs["tdfanet"], scans[:2], tmp_path / "c")
    assert res.returncode == 2 and "takes 3 frame(s)" in res.stderr
    res = _run(client, graphs["tdfanet"], _scans(tmp_path, _tdfanet_frames()), tmp_path / "d", "--timestamps", "1,1,2")
    assert res.returncode == 2 and "timestamps must increase strictly" in res.stderr
    close = [0.0, 0.1, 0.100000001]  # increasing in float64, equal in the graph's float32
    res = _run(
        client,
        graphs["tdfanet"],
        _scans(tmp_path, _tdfanet_frames()),
        tmp_path / "e",
        "--timestamps",
        ",".join(map(repr, close)),
    )
    assert res.returncode == 2 and "frames 1 and 2 are 1e-09 s apart" in res.stderr
    with pytest.raises(InputError, match="frames 1 and 2 are 1e-09 s apart"):
        runtime.load(graphs["tdfanet"]).run(_tdfanet_frames(), close)
    for unit, scale in (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9)):  # not seconds
        stamps = [1732500000.0 * scale + k * 0.1 * scale for k in range(3)]
        res = _run(
            client,
            graphs["tdfanet"],
            _scans(tmp_path, _tdfanet_frames()),
            tmp_path / unit,
            "--timestamps",
            ",".join(map(repr, stamps)),
        )
        assert res.returncode == 2 and "off its period are refused" in res.stderr, res.stderr
        with pytest.raises(InputError, match=f"they look like {unit}: pass seconds"):
            runtime.load(graphs["tdfanet"]).run(_tdfanet_frames(), stamps)


def test_the_c_client_acts_on_the_declared_checks_like_the_runtime(client, graphs, tmp_path):
    """MAFF-Net declares spa_overflow an error (radaredge.checks): 600 points on distinct pillars
    overflow the tiny card's 256 sparse-attention slots; the runtime raises, the client fails
    with the same message and writes nothing; --no-checks writes the outputs."""
    rng = np.random.default_rng(0)
    pts = np.zeros((600, 7), np.float32)
    cells = rng.choice(1600, 600, replace=False)
    pts[:, 0] = (cells % 40) * 0.32 + 0.16
    pts[:, 1] = -6.4 + (cells // 40) * 0.32 + 0.16
    with pytest.raises(CapacityError) as raised:
        runtime.load(graphs["maffnet"]).run([pts])
    scans = _scans(tmp_path, [pts])
    res = _run(client, graphs["maffnet"], scans, tmp_path / "a")
    assert res.returncode == 2 and res.stderr.strip().splitlines()[-1] == f"error: {raised.value}"
    assert "600 non-empty pillars" in res.stderr and not (tmp_path / "a" / "summary.json").exists()
    res = _run(client, graphs["maffnet"], scans, tmp_path / "b", "--no-checks")
    assert res.returncode == 0 and _outputs(tmp_path / "b")["spa_overflow"].item()


def _flag_cases():
    """TDFANet frames with a NaN point (frame 1), a pillar holding more than max_points_per_pillar
    points (frame 2; the tiny card keeps 8), one point out of range and one with a radial velocity
    of 1e4 m/s, outside the card's plausible range (frame 0), plus timestamps that run backwards
    into frame 2."""
    rng = np.random.default_rng(1)

    def static_scan(xyz):  # a static world seen from a radar driving at 8 m/s
        v_r = -(xyz / np.linalg.norm(xyz, axis=1, keepdims=True)) @ np.array([8.0, 0.0, 0.0])
        return np.column_stack([xyz, v_r, np.full(len(xyz), 5.0)]).astype(np.float32)

    frames = [static_scan(rng.uniform([5, -12, -1], [30, 12, 1], size=(40, 3))) for _ in range(3)]
    frames[0][0, :3] = [500.0, 0.0, 0.0]
    frames[0][1, 3] = 1e4
    frames[1][7, 2] = np.nan
    frames[2][:12] = static_scan(np.column_stack([5.5 + 0.02 * np.arange(12), np.full(12, 0.5), np.zeros(12)]))
    return frames, [0.0, 0.1, 0.05]


def test_input_flags_from_c_and_from_python(client, graphs, tmp_path):
    frames, stamps = _flag_cases()
    res = _run(
        client,
        graphs["tdfanet"],
        _scans(tmp_path, frames),
        tmp_path / "out",
        "--no-checks",
        "--timestamps",
        ",".join(map(str, stamps)),
    )
    assert res.returncode == 1, res.stderr
    flags = _outputs(tmp_path / "out")["input_flags"]
    assert flags.tolist() == [OUT_OF_RANGE | IMPLAUSIBLE, NON_FINITE, TIME_ORDER | CAPACITY]
    assert "frame 1: bit 0 (1): non_finite" in res.stderr and "frame 2: bit 3 (8): capacity" in res.stderr
    assert "frame 0: bit 5 (32): implausible" in res.stderr
    meta = json.loads(runtime.load(graphs["tdfanet"]).metadata["radaredge.input_flags"])
    assert set(meta) == {"1", "2", "4", "8", "16", "32"}
    m = runtime.load(graphs["tdfanet"], threads=1)  # the graph itself, fed directly as a C app does
    raw = {f"points_{k}": f for k, f in enumerate(frames)}
    raw["timestamps"] = np.float32(stamps)
    assert run_session(m.session, raw)["input_flags"].tolist() == flags.tolist()
    raw["timestamps"] = np.float32([0.0, np.nan, 0.2])  # a NaN compares False: flagged, not taken as ordered
    assert [f & TIME_ORDER for f in run_session(m.session, raw)["input_flags"].tolist()] == [0, TIME_ORDER, TIME_ORDER]
    with pytest.raises(InputError, match="frame 1: non-finite value nan at point 7, column 'z'"):
        m.run(frames, stamps)  # the runtime refuses what the graph would mask
    frames[1][7, 2] = 0.0
    with pytest.raises(InputError, match="timestamps must increase strictly"):
        m.run(frames, stamps)
    assert m.run(frames)["input_flags"].tolist() == [OUT_OF_RANGE | IMPLAUSIBLE, 0, CAPACITY]


def test_sanitizers(graphs, tmp_path_factory, tmp_path):
    """AddressSanitizer and UndefinedBehaviorSanitizer: no error on a good run or a refused one."""
    asan = _make("asan", tmp_path_factory.mktemp("c-asan"))
    env = {
        **os.environ,
        "ASAN_OPTIONS": "detect_leaks=1:abort_on_error=0:exitcode=99",
        "LSAN_OPTIONS": f"suppressions={EXAMPLE / 'lsan.supp'}",
        "UBSAN_OPTIONS": "halt_on_error=1:exitcode=98",
    }
    scans = _scans(tmp_path, _tdfanet_frames())
    for extra, code in (((), 0), (("--timestamps", "3,2,1"), 2)):
        out = tmp_path / f"out{code}"
        out.mkdir()
        res = subprocess.run(
            [str(asan), *extra, "--out", str(out), str(graphs["tdfanet"]), *map(str, scans)],
            capture_output=True,
            text=True,
            env=env,
        )
        assert res.returncode == code, res.stderr[-3000:]
        assert "Sanitizer" not in res.stderr, res.stderr[-3000:]
    out = tmp_path / "maffnet"  # the declared checks' metadata read and applied
    out.mkdir()
    res = subprocess.run(
        [str(asan), "--out", str(out), str(graphs["maffnet"]), *map(str, _scans(out, _maffnet_frames()))],
        capture_output=True,
        text=True,
        env=env,
    )
    assert res.returncode == 0 and "Sanitizer" not in res.stderr, res.stderr[-3000:]
