"""Recorded drives: write_sequence -> load_sequence round trip, windows and their positions, malformed gps.csv."""

import numpy as np
import pytest

from radaredge.data.sequences import RadarSequence, load_sequence, window_positions, windows, write_sequence
from radaredge.errors import ConfigError, InputError

T = 5
COLUMNS = {"transloc": 5, "vod": 7, "tj4d": 8}


def drive(fmt="transloc", n_frames=T, seed=0):
    """(scans in ``fmt``'s file columns, timestamps s, positions (northing, easting) m)."""
    rng = np.random.default_rng(seed)
    scans = [rng.normal(size=(int(rng.integers(0, 20)), COLUMNS[fmt])).astype(np.float32) for _ in range(n_frames)]
    timestamps = 1.7e9 + 0.1 * np.arange(n_frames) + rng.uniform(0, 0.01, n_frames)
    positions = np.column_stack([5.8e6 + np.cumsum(rng.uniform(0, 2, n_frames)), 3.3e5 + rng.normal(size=n_frames)])
    return scans, timestamps, positions


@pytest.fixture
def written(tmp_path):
    scans, timestamps, positions = drive()
    return write_sequence(tmp_path / "drive_01", scans, timestamps, positions), scans, timestamps, positions


@pytest.mark.parametrize("fmt", ["transloc", "vod", "tj4d"])
def test_round_trip(tmp_path, fmt):
    scans, timestamps, positions = drive(fmt)
    directory = write_sequence(tmp_path / "drive", scans, timestamps, positions, fmt=fmt)
    suffix = ".npy" if fmt == "transloc" else ".bin"
    assert sorted(p.name for p in (directory / "scans").iterdir()) == [f"{i:06d}{suffix}" for i in range(T)]
    seq = load_sequence(directory, fmt=None if fmt == "transloc" else fmt)
    assert isinstance(seq, RadarSequence) and seq.name == "drive" and seq.fmt == fmt and len(seq) == T
    assert seq.timestamps.dtype == np.float64 and seq.positions.shape == (T, 2)
    np.testing.assert_array_equal(seq.timestamps, timestamps)  # written exactly, not rounded
    np.testing.assert_array_equal(seq.positions, positions)
    for i, scan in enumerate(scans):
        np.testing.assert_array_equal(seq.scan(i, ["x", "y", "z", "v_r"]), scan[:, [0, 1, 2, 3 + (fmt == "vod")]])


def test_bin_sequence_needs_its_format(tmp_path):
    directory = write_sequence(tmp_path / "d", *drive("vod"), fmt="vod")
    with pytest.raises(InputError, match=r"no \.npy scan files.*\['\.bin'\].*'vod' or 'tj4d'"):
        load_sequence(directory)
    with pytest.raises(InputError, match="unknown sequence scan format 'rosbag'"):
        load_sequence(directory, fmt="rosbag")


def test_scans_sort_by_file_name_and_other_files_are_ignored(written):
    directory, scans, *_ = written
    (directory / "scans" / "README.txt").write_text("notes")
    seq = load_sequence(directory)
    assert [p.name for p in seq.scan_paths] == [f"{i:06d}.npy" for i in range(T)]


def test_gps_columns_in_any_order_and_extra_columns_ignored(written):
    directory, _, timestamps, positions = written
    lines = ["easting, altitude ,Timestamp,northing"]
    lines += [f"{e!r},12.5,{t!r},{n!r}" for t, (n, e) in zip(timestamps.tolist(), positions.tolist())]
    (directory / "gps.csv").write_text("\n".join(lines) + "\n\n")
    seq = load_sequence(directory)
    np.testing.assert_array_equal(seq.timestamps, timestamps)
    np.testing.assert_array_equal(seq.positions, positions)


def test_windows_and_their_positions(written):
    seq = load_sequence(written[0])
    got = windows(seq, 3)
    assert [w.tolist() for w in got] == [[0, 1, 2], [1, 2, 3], [2, 3, 4]]
    np.testing.assert_array_equal(window_positions(seq, 3), seq.positions[[w[-1] for w in got]])
    assert [w.tolist() for w in windows(seq, 1)] == [[t] for t in range(T)]
    np.testing.assert_array_equal(window_positions(seq, 1), seq.positions)
    assert windows(seq, T + 1) == [] and window_positions(seq, T + 1).shape == (0, 2)
    for k in (0, -1, 1.5, True):
        with pytest.raises(ConfigError, match="window length k"):
            windows(seq, k)
        with pytest.raises(ConfigError, match="window length k"):
            window_positions(seq, k)


def gps(*rows, header="timestamp,northing,easting"):
    return "\n".join([header, *rows]) + "\n"


FIVE = [f"{t},{10 + t},{20 + t}" for t in range(T)]


@pytest.mark.parametrize(
    "text, detail",
    [
        (gps(*FIVE[:4]), "gps.csv has 4 rows but scans/ holds 5 .npy scan files"),
        (gps(*FIVE, "5,0,0"), "gps.csv has 6 rows but scans/ holds 5"),
        (gps(*FIVE[:2], "1.0,0,0", *FIVE[3:]), r"timestamps must increase; row 2 has 1.0 s, not after row 1's 1.0 s"),
        (gps(*FIVE[::-1]), "row 1 has 3.0 s, not after row 0's 4.0 s"),
        (gps(*FIVE, header="timestamp,north,easting"), r"header lacks column\(s\) \['northing'\]"),
        (gps(*FIVE, header="time,northing,east"), r"\['timestamp', 'easting'\]"),
        (gps(*FIVE[:1], "1,abc,21", *FIVE[2:]), "row 1, column 'northing': cannot read 'abc' as a finite number"),
        (gps(*FIVE[:3], "3,13,nan", *FIVE[4:]), "row 3, column 'easting': cannot read 'nan'"),
        (gps(*FIVE[:3], "3,13", *FIVE[4:]), "row 3 has 2 values, the header has 3 columns"),
        ("", "gps.csv: empty"),
    ],
)
def test_malformed_gps_csv(written, text, detail):
    directory = written[0]
    (directory / "gps.csv").write_text(text)
    with pytest.raises(InputError, match=detail):
        load_sequence(directory)


def test_missing_gps_or_scans(written):
    directory = written[0]
    (directory / "gps.csv").unlink()
    with pytest.raises(InputError, match="gps.csv: no such file.*timestamp,northing,easting"):
        load_sequence(directory)
    with pytest.raises(InputError, match="no scans/ directory"):
        load_sequence(directory.parent / "elsewhere")


def test_write_sequence_checks_its_input(tmp_path, written):
    scans, timestamps, positions = drive()
    with pytest.raises(InputError, match="already exists"):
        write_sequence(written[0], scans, timestamps, positions)
    with pytest.raises(InputError, match=r"5 scans need timestamps of shape \(5,\)"):
        write_sequence(tmp_path / "a", scans, timestamps[:4], positions)
    with pytest.raises(InputError, match=r"row 3 has"):
        write_sequence(tmp_path / "a", scans, timestamps[[0, 1, 2, 2, 4]], positions)
    with pytest.raises(InputError, match=r"scan 0: float32 array of shape \(\d+, 5\); fmt 'vod' stores .*\[N, 7\]"):
        write_sequence(tmp_path / "a", scans, timestamps, positions, fmt="vod")
    with pytest.raises(InputError, match="at least one scan"):
        write_sequence(tmp_path / "a", [], [], np.zeros((0, 2)))
    with pytest.raises(InputError, match="finite"):
        write_sequence(tmp_path / "a", scans, timestamps, positions * np.nan)
    assert not (tmp_path / "a").exists()
