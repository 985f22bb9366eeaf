"""The torch-free runtime: loads an export, validates input with clear errors, never imports torch."""

import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from radaredge import runtime
from radaredge.cards import load_card
from radaredge.errors import InputError
from radaredge.registry import model_spec

from conftest import TINY_CARD as TINY


@pytest.fixture(scope="module")
def onnx_path(tiny_export):
    return tiny_export[2]


@pytest.fixture(scope="module")
def frames():
    card = load_card(TINY)
    _, feeds = model_spec(card).graph().make_cases(card, 1, 2)[0]
    return [feeds[f"points_{k}"] for k in range(3)], feeds["timestamps"]


def test_runtime_runs_without_torch(onnx_path, frames, tmp_path):
    np.save(tmp_path / "f0.npy", frames[0][0])
    np.save(tmp_path / "f1.npy", frames[0][1])
    np.save(tmp_path / "f2.npy", frames[0][2])
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None          # any `import torch` now raises ImportError
        import numpy as np
        from radaredge import runtime
        m = runtime.load({str(onnx_path)!r})
        frames = [np.load({str(tmp_path)!r} + f"/f{{k}}.npy") for k in range(3)]
        out = m.run(frames)
        assert "torch" not in [k for k, v in sys.modules.items() if v is not None]
        print(m.card.name, out["descriptor_normalized"].shape, round(float(np.linalg.norm(out["descriptor_normalized"])), 4))
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["tdfanet-tiny", "(32,)", "1.0"]


def test_runtime_matches_session_outputs(onnx_path, frames):
    m = runtime.load(onnx_path)
    out = m.run(frames[0], frames[1])
    assert set(out) == {"descriptor", "descriptor_normalized", "ego_velocity", "ego_valid"}
    assert m.card.name == "tdfanet-tiny" and m.features == ["x", "y", "z", "v_r", "rcs"]


@pytest.mark.parametrize("mutate, message", [
    (lambda f: f[:2], "takes 3 frame"),
    (lambda f: [f[0], f[1][:, :4], f[2]], r"frame 1: expected shape \[N, 5\]"),
    (lambda f: [f[0], f[1], f[2].astype(str)], "frame 2: expected a numeric array"),
])
def test_bad_frames_get_specific_errors(onnx_path, frames, mutate, message):
    m = runtime.load(onnx_path)
    with pytest.raises(InputError, match=message):
        m.run(mutate(list(frames[0])))


def test_non_finite_value_names_frame_point_and_column(onnx_path, frames):
    m = runtime.load(onnx_path)
    f = [a.copy() for a in frames[0]]
    f[2][4, 3] = np.nan
    with pytest.raises(InputError, match=r"frame 2: non-finite value nan at point 4, column 'v_r'"):
        m.run(f)


def test_timestamps_are_checked(onnx_path, frames):
    m = runtime.load(onnx_path)
    with pytest.raises(InputError, match="increase strictly"):
        m.run(frames[0], [0.0, 0.2, 0.1])
    with pytest.raises(InputError, match="3 finite values"):
        m.run(frames[0], [0.0, 0.1])


def test_absolute_timestamps_give_the_outputs_of_relative_ones(onnx_path, frames):
    """ROS / Unix epoch stamps and time since boot are made relative in float64 before the graph
    sees float32: the outputs are bitwise those of the same stamps made relative by the caller,
    and match a window stamped exactly 0, 0.1, 0.2 s to float precision. In float32 the epoch
    stamps would have collapsed (a 0.1 s step is below float32's resolution at 1.7e9 s)."""
    m = runtime.load(onnx_path)
    exact = m.run(frames[0], [0.0, 0.1, 0.2])
    for t0 in (1_732_500_000.123456, 1e6, 3.7e4):           # epoch seconds (a ROS stamp), time since boot
        stamps = t0 + np.array([0.0, 0.1, 0.2])
        out = m.run(frames[0], stamps)
        rel = m.run(frames[0], stamps - stamps[0])
        for k in out:
            np.testing.assert_array_equal(out[k], rel[k], err_msg=f"t0 = {t0}: {k}")
            np.testing.assert_allclose(out[k], exact[k], atol=1e-5, err_msg=f"t0 = {t0}: {k}")
    with pytest.raises(InputError, match="increase strictly"):      # checked in float64, at epoch scale too
        m.run(frames[0], 1e9 + np.array([0.0, 0.2, 0.1]))


def test_empty_frames_are_valid_input(onnx_path, frames):
    m = runtime.load(onnx_path)
    out = m.run([np.zeros((0, 5), np.float32), frames[0][1], np.zeros((0, 5), np.float32)])
    assert np.isfinite(out["descriptor"]).all()


def test_load_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        runtime.load(tmp_path / "missing.onnx")
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(b"not a protobuf")
    with pytest.raises(InputError, match=r"truncated.onnx: onnxruntime cannot load it as a model \(.*Protobuf"):
        runtime.load(truncated)


def test_worker_threads_stop_spinning_when_a_run_returns(onnx_path, frames):
    """Between scans the cores belong to the app: onnxruntime's default keeps its worker threads
    spinning after a run (tens of ms of CPU on 2 threads); radaredge's sessions stop them."""
    model = runtime.load(onnx_path, threads=2)
    model.run(*frames)
    before = time.process_time()
    time.sleep(0.3)
    assert time.process_time() - before < 0.01, "onnxruntime's worker threads kept spinning after the run"
