"""int8 calibration on a recording of the user's sensor: scan discovery, format, window choice,
feeds checked like runtime input, and the calibrated graph's metadata and parity budget."""

import json

import numpy as np
import pytest
from conftest import invoke

import radaredge
from radaredge import runtime
from radaredge.data.synthetic import generate_sequence
from radaredge.errors import ConfigError, InputError
from radaredge.exporting.calibration import recorded_feeds, recorded_scan_paths, recording_format, window_starts
from radaredge.exporting.quantize import quantize_int8


def write_scans(directory, n=7, seed=3):
    """``n`` consecutive synthetic scans as transloc .npy files 000000.npy ... in ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    for i, scan in enumerate(generate_sequence(n, seed=seed)):
        np.save(directory / f"{i:06d}.npy", scan.points.astype(np.float32))
    return directory


@pytest.mark.parametrize(
    "num, k, n, expected",
    [
        (10, 3, 4, [0, 2, 5, 7]),  # evenly spread, first and last window included
        (10, 3, 8, [0, 1, 2, 3, 4, 5, 6, 7]),  # no more windows than there are
        (10, 3, 50, [0, 1, 2, 3, 4, 5, 6, 7]),
        (3, 3, 4, [0]),
        (9, 1, 3, [0, 4, 8]),
    ],
)
def test_window_starts(num, k, n, expected):
    assert window_starts(num, k, n).tolist() == expected


def test_window_starts_rejects_short_recordings_and_no_windows():
    with pytest.raises(InputError, match="holds 2 scan\\(s\\) but one window of this model takes 3"):
        window_starts(2, 3, 4)
    with pytest.raises(ConfigError, match="at least one window"):
        window_starts(10, 3, 0)


def test_scan_files_directly_or_under_scans(tmp_path):
    flat = write_scans(tmp_path / "flat", n=3)
    (flat / "notes.txt").write_text("ignored")
    assert [p.name for p in recorded_scan_paths(flat)] == ["000000.npy", "000001.npy", "000002.npy"]
    drive = write_scans(tmp_path / "drive" / "scans", n=4).parent
    assert len(recorded_scan_paths(drive)) == 4
    with pytest.raises(InputError, match="no .bin or .npy scan files"):
        recorded_scan_paths(tmp_path / "flat" / "..")
    with pytest.raises(InputError, match="is not a directory"):
        recorded_scan_paths(tmp_path / "missing")


def test_recording_format(tmp_path):
    npy = recorded_scan_paths(write_scans(tmp_path / "a", n=2))
    assert recording_format(npy) == "transloc"
    with pytest.raises(InputError, match="no .bin scan files in"):
        recorded_scan_paths(tmp_path / "a", "vod")
    with pytest.raises(ConfigError, match="calibration format 'pcd'"):
        recorded_scan_paths(tmp_path / "a", "pcd")
    bins = tmp_path / "b"
    bins.mkdir()
    np.zeros((5, 8), "<f4").tofile(bins / "000000.bin")  # 160 bytes: tj4d rows only
    np.zeros((3, 8), "<f4").tofile(bins / "000001.bin")
    assert recording_format(recorded_scan_paths(bins)) == "tj4d"
    np.zeros((7, 8), "<f4").tofile(bins / "000002.bin")  # 224 bytes fit vod and tj4d, the others only tj4d
    assert recording_format(recorded_scan_paths(bins)) == "tj4d"
    np.zeros((4, 7), "<f4").tofile(bins / "000003.bin")  # 112 bytes: vod only -> no layout fits all
    with pytest.raises(InputError, match="fit neither .*--calibration-format"):
        recording_format(recorded_scan_paths(bins))
    assert recording_format(recorded_scan_paths(bins, "tj4d"), "tj4d") == "tj4d"  # named: not inferred
    np.save(bins / "000004.npy", np.zeros((2, 5), np.float32))
    with pytest.raises(InputError, match="mixes .bin and .npy scan files"):
        recording_format(recorded_scan_paths(bins))
    assert [p.name for p in recorded_scan_paths(bins, "transloc")] == ["000004.npy"]  # a named format reads its own


def test_recorded_feeds_are_runtime_feeds(tiny_export, tmp_path):
    _, _, fp32, _ = tiny_export
    model = runtime.load(fp32)
    rec = write_scans(tmp_path / "rec", n=7)
    feeds, info = recorded_feeds(model, rec, 3)
    assert info == {"data": "recorded", "directory": str(rec), "format": "transloc", "scans": 7, "windows": 3}
    assert len(feeds) == 3 and set(feeds[0]) == set(model.input_names)
    # the last window is the last K scans, oldest first, in the card's feature columns
    for k in range(model.frames):
        scan = np.load(rec / f"{7 - model.frames + k:06d}.npy")
        np.testing.assert_array_equal(feeds[-1][f"points_{k}"], scan[:, : len(model.features)])
    np.testing.assert_allclose(feeds[-1]["timestamps"], np.arange(model.frames) / model.frame_rate)


def test_recorded_feeds_name_the_window_with_bad_data(tiny_export, tmp_path):
    _, _, fp32, _ = tiny_export
    rec = write_scans(tmp_path / "rec", n=4)
    scan = np.load(rec / "000003.npy")
    scan[2, 3] = np.nan
    np.save(rec / "000003.npy", scan)
    with pytest.raises(
        InputError,
        match="calibration window 000001.npy, 000002.npy, 000003.npy: frame 2: "
        "non-finite value nan at point 2, column 'v_r'",
    ):
        recorded_feeds(runtime.load(fp32), rec, 2)


def test_quantise_on_a_recording(tiny_export, tmp_path):
    """Calibrated on a recording, the int8 graph says so in its metadata and meets the budget."""
    card, model, fp32, _ = tiny_export
    rec = write_scans(tmp_path / "rec", n=8, seed=11)
    path = quantize_int8(card, fp32, tmp_path / "rec.int8.onnx", calibration_cases=4, calibration_dir=rec)
    calib = json.loads(runtime.load(path).metadata["radaredge.quantization"])["calibration"]
    assert calib == {
        "data": "recorded",
        "directory": str(rec),
        "format": "transloc",
        "scans": 8,
        "windows": 4,
        "method": "minmax",
    }
    report = radaredge.parity(card, path, model=model, cases=6, seed=4, quantized=True)
    assert report, report.to_dict()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--calibration", "REC"], "--calibration: int8 calibration options need --quantize int8"),
        (["--calibration-windows", "4"], "--calibration-windows: int8 calibration options need --quantize int8"),
        (["--calibration-method", "entropy"], "--calibration-method: int8 calibration options need --quantize int8"),
        (["--quantize", "int8", "--calibration-method", "kl"], "'kl' is not one of"),
        (["--quantize", "int8", "--calibration-format", "vod"], "add --calibration DIR"),
        (["--quantize", "int8", "--calibration", "MISSING"], "MISSING is not a directory"),
        (["--quantize", "int8", "--calibration", "REC", "--calibration-format", "vod"], "no .bin scan files"),
        (["--quantize", "int8", "--calibration", "SHORT"], "holds 2 scan(s) but one window of this model takes 3"),
    ],
)
def test_cli_calibration_options_fail_before_the_export(tmp_path, args, message):
    rec, short = write_scans(tmp_path / "rec", n=3), write_scans(tmp_path / "short", n=2)
    paths = {"REC": str(rec), "SHORT": str(short), "MISSING": str(tmp_path / "MISSING")}
    res = invoke("export", "--model", "tdfanet", "--output", tmp_path / "x.onnx", *[paths.get(a, a) for a in args])
    assert res.exit_code == 2 and message in res.output
    assert not (tmp_path / "x.onnx").exists()


def test_cli_calibration_does_not_apply_to_the_dynamic_text_encoder(tmp_path):
    res = invoke(
        "export", "--model", "des4pos", "--quantize", "int8", "--calibration-windows", "4", "--output", tmp_path / "d"
    )
    assert res.exit_code == 2 and "quantised dynamically" in res.output and "drop --calibration-windows" in res.output


def test_recorded_feeds_need_the_cards_columns(tmp_path):
    """A card whose columns the recording's format cannot serve (VoD's compensated Doppler from
    TransLoc4D-style scans) fails on the first window, naming it and the missing column."""

    class VodCardModel:
        frames, features = 1, ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"]

        def feeds(self, frames):
            raise AssertionError("not reached")

    rec = write_scans(tmp_path / "rec", n=2)
    with pytest.raises(
        InputError, match="calibration window 000000.npy: .*cannot provide feature\\(s\\) \\['v_r_comp', 'time'\\]"
    ):
        recorded_feeds(VodCardModel(), rec, 2)
