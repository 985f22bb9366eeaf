"""The torch-free runtime: loads an export, validates input with clear errors, never imports torch."""

import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from conftest import TINY_CARD as TINY

from radaredge import runtime
from radaredge.cards import load_card
from radaredge.errors import InputError
from radaredge.models import model_spec


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
        print(m.card.name, out["descriptor_normalized"].shape,
              round(float(np.linalg.norm(out["descriptor_normalized"])), 4))
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["tdfanet-tiny", "(32,)", "1.0"]


def test_runtime_matches_session_outputs(onnx_path, frames):
    m = runtime.load(onnx_path)
    out = m.run(frames[0], frames[1])
    assert set(out) == {"descriptor", "descriptor_normalized", "ego_velocity", "ego_valid", "input_flags"}
    assert (
        out["input_flags"].shape == (3,)
        and m.card.name == "tdfanet-tiny"
        and m.features == ["x", "y", "z", "v_r", "rcs"]
    )


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda f: f[:2], "takes 3 frame"),
        (lambda f: [f[0], f[1][:, :4], f[2]], r"frame 1: expected shape \[N, 5\]"),
        (lambda f: [f[0], f[1], f[2].astype(str)], "frame 2: expected a numeric array"),
    ],
)
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
    for t0 in (1_732_500_000.123456, 1e6, 3.7e4):  # epoch seconds (a ROS stamp), time since boot
        stamps = t0 + np.array([0.0, 0.1, 0.2])
        out = m.run(frames[0], stamps)
        rel = m.run(frames[0], stamps - stamps[0])
        for k in out:
            np.testing.assert_array_equal(out[k], rel[k], err_msg=f"t0 = {t0}: {k}")
            np.testing.assert_allclose(out[k], exact[k], atol=1e-5, err_msg=f"t0 = {t0}: {k}")
    with pytest.raises(InputError, match="increase strictly"):  # checked in float64, at epoch scale too
        m.run(frames[0], 1e9 + np.array([0.0, 0.2, 0.1]))


def test_ros_epoch_stamps_straight_from_a_bag(onnx_path, frames, tmp_path):
    """Scans and header stamps read from a ROS bag go to the runtime as they come: the outputs are
    bitwise those of the same window with relative stamps."""
    from test_readers import ROS1, pointcloud2, write_bag

    stamps = [(1732500000, 123456789 + 100_000_000 * k) for k in range(3)]
    clouds = [
        pointcloud2(ROS1, st, {c: f[:, i] for i, c in enumerate(("x", "y", "z", "v_r", "rcs"))})
        for st, f in zip(stamps, frames[0])
    ]
    bag = write_bag(tmp_path / "drive.bag", True, {"/radar": ("sensor_msgs/msg/PointCloud2", clouds)})
    from radaredge.data.readers import read_rosbag

    read = read_rosbag(bag, "/radar", ["x", "y", "z", "v_r", "rcs"])
    t = np.array([s for s, _ in read])
    scans = [a for _, a in read]
    assert t[0] > 1.7e9
    m = runtime.load(onnx_path)
    out, rel = m.run(scans, t), m.run(scans, t - t[0])
    for k in out:
        np.testing.assert_array_equal(out[k], rel[k], err_msg=k)


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


def test_points_per_frame_are_capped_by_the_card(tiny_export, frames, tmp_path):
    """A frame beyond the card's max_points_per_frame (default 65,536) is a CapacityError naming
    the frame, before onnxruntime allocates for it."""
    from radaredge.errors import CapacityError

    m = runtime.load(tiny_export[2])
    big = np.zeros((65_537, 5), np.float32)
    with pytest.raises(
        CapacityError, match=r"frame 1: 65537 points; tdfanet-tiny takes at most max_points_per_frame = 65536"
    ):
        m.run([frames[0][0], big, frames[0][2]])
    m.inputs.max_points = 10
    with pytest.raises(CapacityError, match="frame 0"):
        m.run([np.zeros((11, 5), np.float32), frames[0][1], frames[0][2]])


@pytest.mark.parametrize(
    "text, message",
    [
        ("a: &x [1, 2]\nb: *x\n", "anchors and aliases are not allowed in a model card"),
        ("a: [1, 2\n", "invalid YAML"),
        ("a: !!python/object/apply:os.system ['true']\n", "invalid YAML"),
    ],
)
def test_card_yaml_is_safe_and_alias_free(tmp_path, text, message):
    from radaredge.cards import card_from_yaml, load_card
    from radaredge.errors import ConfigError

    path = tmp_path / "card.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_card(path)
    with pytest.raises(ConfigError, match=f"graph.onnx: the card in its metadata: .*{message}"):
        card_from_yaml(text, "graph.onnx: the card in its metadata")


def test_a_binary_or_huge_card_file_is_one_error(tmp_path):
    from radaredge.cards import load_card
    from radaredge.errors import ConfigError

    binary = tmp_path / "binary.yaml"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(ConfigError, match="binary.yaml: not a text file"):
        load_card(binary)
    huge = tmp_path / "huge.yaml"
    huge.write_text("a: " + "x" * 300_000)
    with pytest.raises(ConfigError, match="huge.yaml: 300003 bytes; a model card is at most 262144 bytes"):
        load_card(huge)


def test_a_graph_whose_metadata_card_is_an_alias_bomb_is_refused(tiny_export, tmp_path):
    import onnx

    model = onnx.load(str(tiny_export[2]))
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi")
    )
    for prop in model.metadata_props:
        if prop.key == "radaredge.card":
            prop.value = bomb
    path = tmp_path / "bomb.onnx"
    onnx.save(model, str(path))
    from radaredge.errors import ConfigError

    with pytest.raises(ConfigError, match="bomb.onnx: the card in its metadata: .*aliases are not allowed"):
        runtime.load(path)
