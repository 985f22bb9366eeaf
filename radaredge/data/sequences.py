"""Recorded drives as sequences of radar scans with a position per scan, and sliding windows over them.

Directory layout of one drive::

    DIR/
      scans/      one scan file per frame, frames in file-name order with the numbers in
                  names compared as numbers (0.npy, 1.npy, ..., 10.npy; 000000.npy, ...):
                  .npy for fmt "transloc" (the default),
                  .bin for fmt "vod" or "tj4d"; files with another suffix are ignored
      gps.csv     a header line naming at least the columns timestamp, northing, easting
                  (in any order; other columns are ignored), then one row per scan, in the
                  same order: timestamp in s (strictly increasing), northing and easting in m

A scan's columns are as :mod:`radaredge.data.readers` describes for its format (radar frame:
x forward, y left, z up; metres, m/s). Positions are planar (northing, easting) in metres, as
a GPS/UTM track gives them.

TransLoc4D layout. A directory with ``pointclouds/`` instead of ``scans/`` is read as TransLoc4D
writes its sets: each scan file is named by its timestamp (``pointclouds/1646303235123456.npy``)
and gps.csv rows are matched to files by that name, exactly (a row without its file is an
error; files without a row are ignored); rows come in timestamp order. Integer names are
TransLoc4D's microseconds since the epoch, names with a decimal point seconds. TransLoc4D's
released sets hold preprocessed clouds (normalised coordinates, a velocity column that is no
longer the Doppler in m/s); a model that reads metres and m/s needs the raw scans in this layout.

A window of k frames ending at frame t is the frames t-k+1 ... t, oldest first. Its time and
position are those of its last frame t, so windows and their positions line up one to one.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ConfigError, InputError
from .readers import FILE_SUFFIX, TJ4D_COLUMNS, TRANSLOC_COLUMNS, VOD_COLUMNS, check_points, read_bounded, read_scan

GPS_COLUMNS = ("timestamp", "northing", "easting")
MAX_GPS_BYTES = 64 * 2**20  # gps.csv: one row of ~50 bytes a scan; a million rows is a day of driving at 10 Hz
_FILE_COLUMNS = {"transloc": TRANSLOC_COLUMNS, "vod": VOD_COLUMNS, "tj4d": TJ4D_COLUMNS}


@dataclass
class RadarSequence:
    """One recorded drive.

    name        the drive's directory name
    scan_paths  the scan file of each frame, in frame order (a ROS bag: the bag, once per frame)
    timestamps  float64 [T], s, strictly increasing
    positions   float64 [T, 2], (northing, easting) m of each frame
    fmt         the scan file format: "transloc", "vod", "tj4d" or "rosbag"
    arrays      for a ROS bag, the scans read at load, float32 [N, F] with columns ``array_features``
    utm_zone    the UTM zone of ``positions`` when radaredge projected them from GNSS fixes
    """

    name: str
    scan_paths: list[Path]
    timestamps: np.ndarray
    positions: np.ndarray
    fmt: str
    arrays: list[np.ndarray] | None = None
    array_features: tuple[str, ...] = ()
    utm_zone: int | None = None

    def scan(self, i: int, features: Sequence[str]) -> np.ndarray:
        """Frame ``i``'s points: float32 [N, len(features)], the columns named by ``features``
        (radar frame x forward, y left, z up; m, m/s), read with :func:`read_scan`. InputError
        naming the file, the point and the column for a value that is not finite or a coordinate
        beyond :data:`radaredge.data.readers.MAX_COORDINATE` m (:func:`check_points`)."""
        if self.arrays is None:
            return check_points(read_scan(self.scan_paths[i], features, self.fmt), features, self.scan_paths[i])
        missing = [f for f in features if f not in self.array_features]
        if missing:
            raise InputError(
                f"{self.scan_paths[i]}: scans were read with the features {list(self.array_features)}, not {missing}"
            )
        return check_points(
            self.arrays[i][:, [self.array_features.index(f) for f in features]],
            features,
            f"{self.scan_paths[i]}: scan {i}",
        )

    def __len__(self) -> int:
        return len(self.timestamps)


def _check_fmt(fmt: str) -> str:
    if fmt not in FILE_SUFFIX:
        raise InputError(f"unknown sequence scan format {fmt!r}; expected one of {list(FILE_SUFFIX)}")
    return fmt


def _check_increasing(timestamps: np.ndarray, where: str) -> None:
    """Raise naming the first row whose timestamp is not after the previous row's."""
    bad = np.flatnonzero(np.diff(timestamps) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(
            f"{where}: timestamps must increase; row {i} has {float(timestamps[i])!r} s, "
            f"not after row {i - 1}'s {float(timestamps[i - 1])!r} s"
        )


def _natural_key(name: str) -> tuple:
    """``name`` split into text and numbers, numbers compared as numbers: 2.npy before 10.npy."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name) if part)


def frame_order(paths, where) -> list[Path]:
    """Scan files in frame order: by name, with the numbers in names compared as numbers (0.npy,
    1.npy, ..., 10.npy, not 0, 1, 10, 11, ..., 2); InputError naming both files when two names
    give the same order (1.npy and 01.npy), which leaves the frame order undefined."""
    paths = sorted(paths, key=lambda p: (_natural_key(p.name), p.name))
    for a, b in zip(paths, paths[1:]):
        if _natural_key(a.name) == _natural_key(b.name):
            raise InputError(
                f"{where}: {a.name} and {b.name} name the same frame number; name scans by frame "
                f"(000000{a.suffix}, 000001{a.suffix}, ...)"
            )
    return paths


def _scan_files(directory: Path, fmt: str) -> list[Path]:
    """The scan files in ``directory/scans``, in frame order (:func:`frame_order`)."""
    scans = directory / "scans"
    if not scans.is_dir():
        raise InputError(f"{directory}: no scans/ directory; expected one scan file per frame in {scans}")
    suffix = FILE_SUFFIX[fmt]
    folders = sorted(p.name for p in scans.iterdir() if p.suffix == suffix and p.is_dir())
    if folders:
        raise InputError(f"{scans / folders[0]} is a directory, not a scan file ({len(folders)} such in {scans})")
    paths = frame_order((p for p in scans.iterdir() if p.is_file() and p.suffix == suffix), scans)
    if not paths:
        found = sorted({p.suffix for p in scans.iterdir() if p.is_file()})
        raise InputError(
            f"{scans}: no {suffix} scan files for fmt {fmt!r}; suffixes present: {found} "
            f"(.npy scans are fmt 'transloc', .bin scans fmt 'vod' or 'tj4d')"
        )
    return paths


def _parse_value(text: str, row: int, column: str, where: str) -> float:
    """One finite number of gps.csv."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise InputError(f"{where}: row {row}, column {column!r}: cannot read {text!r} as a finite number")
    return value


def _read_gps(path: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(timestamps float64 [T] s, positions float64 [T, 2] northing, easting m, the timestamp
    cells as written) of gps.csv."""
    if not path.exists():
        raise InputError(
            f"{path}: no such file; expected a CSV with header {','.join(GPS_COLUMNS)} and one row per scan"
        )
    data = read_bounded(
        path,
        "a gps.csv",
        MAX_GPS_BYTES,
        "one row of about 50 bytes a scan, a day of driving at 10 Hz; split longer recordings into drives",
    )
    try:
        rows = [r for r in csv.reader(io.StringIO(data.decode("utf-8"), newline="")) if any(c.strip() for c in r)]
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(
            f"{path}: not a text CSV ({type(exc).__name__}: {str(exc)[:120]}); expected a header "
            f"line {','.join(GPS_COLUMNS)} and one row per scan"
        ) from None
    if not rows:
        raise InputError(f"{path}: empty; expected a header line {','.join(GPS_COLUMNS)} and one row per scan")
    header = [name.strip().lower() for name in rows[0]]
    missing = [name for name in GPS_COLUMNS if name not in header]
    if missing:
        raise InputError(
            f"{path}: header lacks column(s) {missing}; it has {header}, expected {', '.join(GPS_COLUMNS)}"
        )
    index = [header.index(name) for name in GPS_COLUMNS]
    values = np.zeros((len(rows) - 1, len(GPS_COLUMNS)))
    for row, cells in enumerate(rows[1:]):
        if len(cells) < len(header):
            raise InputError(f"{path}: row {row} has {len(cells)} values, the header has {len(header)} columns")
        values[row] = [_parse_value(cells[i], row, name, str(path)) for i, name in zip(index, GPS_COLUMNS)]
    _check_increasing(values[:, 0], str(path))
    return values[:, 0], values[:, 1:], [cells[index[0]].strip() for cells in rows[1:]]


POINTCLOUDS = "pointclouds"
_INTERVAL_RANGE = (1e-3, 10.0)  # s: plausible median intervals between radar frames


def is_drive(path: str | os.PathLike) -> bool:
    """``path`` holds a drive: ``scans/``, or ``pointclouds/`` in the TransLoc4D layout."""
    path = Path(path)
    return (path / "scans").is_dir() or (path / POINTCLOUDS).is_dir()


def drive_directories(path: str | os.PathLike) -> list[Path]:
    """``path`` itself if it is one drive (has ``scans/`` or ``pointclouds/``), else its sub-directories that are
    drives, sorted by name. InputError when there is none."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(f"{path} is not a directory; expected a drive (scans/ + gps.csv) or a directory of drives")
    if is_drive(path):
        return [path]
    drives = sorted(p for p in path.iterdir() if is_drive(p))
    if not drives:
        raise InputError(
            f"{path}: no drives found; expected {path}/scans/*.npy + {path}/gps.csv, or "
            f"sub-directories each holding scans/ + gps.csv (make one with `radaredge make-benchmark`)"
        )
    return drives


def _transloc_sequence(directory: Path, fmt: str | None) -> RadarSequence:
    """A drive in the TransLoc4D layout (module docstring)."""
    folder = directory / POINTCLOUDS
    suffixes = sorted({p.suffix for p in folder.iterdir() if p.is_file() and p.suffix in FILE_SUFFIX.values()})
    if not suffixes:
        raise InputError(f"{folder}: no scan files (.npy or .bin); expected one file per frame named by its timestamp")
    if len(suffixes) > 1:
        raise InputError(f"{folder}: mixes {suffixes} scan files; a drive holds one format")
    if fmt is None:
        if suffixes[0] != ".npy":
            raise InputError(
                f"{folder}: .bin scans can be View-of-Delft or TJ4DRadSet rows; pass the format (--format vod|tj4d)"
            )
        fmt = "transloc"
    fmt = _check_fmt(fmt)
    if FILE_SUFFIX[fmt] != suffixes[0]:
        raise InputError(f"{folder}: holds {suffixes[0]} files, but fmt {fmt!r} stores {FILE_SUFFIX[fmt]}")
    gps = directory / "gps.csv"
    _, positions, stamps = _read_gps(gps)
    paths = [folder / f"{stamp}{suffixes[0]}" for stamp in stamps]
    missing = [(row, p.name) for row, p in enumerate(paths) if not p.is_file()]
    if missing:
        row, name = missing[0]
        raise InputError(
            f"{gps}: row {row} (timestamp {stamps[row]}) has no scan {folder / name}; TransLoc4D-style "
            f"drives name each scan by its gps.csv timestamp ({len(missing)} row(s) without a file)"
        )
    micro = all(st.lstrip("-").isdigit() for st in stamps)
    seconds = np.array([int(st) / 1e6 if micro else float(st) for st in stamps], np.float64)
    if len(seconds) > 1:
        interval = float(np.median(np.diff(seconds)))
        lo, hi = _INTERVAL_RANGE
        if not lo <= interval <= hi:
            unit = "integer microseconds" if micro else "seconds (with a decimal point)"
            raise InputError(
                f"{gps}: read as {unit}, the timestamps put the frames {interval:g} s apart (median); "
                f"expected {lo:g}-{hi:g} s. TransLoc4D-style names are integer microseconds since the "
                f"epoch, or seconds with a decimal point"
            )
    check_positions(positions, str(gps))
    return RadarSequence(directory.name, paths, seconds, positions, fmt)


_UNITS = ((1e9, "nanoseconds"), (1e6, "microseconds"), (1e3, "milliseconds"))
MAX_POSITION = 2.0e7  # m: a UTM northing is below 1e7, a local frame far below
DEGREE_STEP = 1e-4  # a track whose moving steps are this small (median) is not in metres


def check_timestamps(timestamps: np.ndarray, where: str) -> None:
    """InputError unless gps.csv's timestamps are seconds: their median interval must lie in
    1 ms .. 10 s (one row per radar frame); the error names the unit they look like."""
    if len(timestamps) < 2:
        return
    interval = float(np.median(np.diff(timestamps)))
    lo, hi = _INTERVAL_RANGE
    if lo <= interval <= hi:
        return
    unit = next((u for f, u in _UNITS if lo * f <= interval <= hi * f), None)
    raise InputError(
        f"{where}: the timestamps put the frames {interval:g} s apart (median); expected {lo:g}-{hi:g} s "
        + (
            f"between radar frames: they look like {unit}; write seconds"
            if unit
            else "between radar frames; timestamps are seconds"
        )
    )


def check_positions(positions: np.ndarray, where: str) -> None:
    """InputError unless the positions are planar metres: within +-2e7 m, and not latitude and
    longitude in degrees (values within +-90 / +-180 whose moving steps are around 1e-5)."""
    if not len(positions):
        return
    big = np.flatnonzero(np.abs(positions).max(1) > MAX_POSITION)
    if big.size:
        raise InputError(
            f"{where}: row {int(big[0])} puts the frame at {positions[big[0]].tolist()}; northing and "
            f"easting are metres (UTM or a local frame), at most {MAX_POSITION:g} in size"
        )
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    moving = steps[steps > 0]
    in_degrees = (np.abs(positions[:, 0]) <= 90).all() and (np.abs(positions[:, 1]) <= 180).all()
    if in_degrees and moving.size and float(np.median(moving)) < DEGREE_STEP:
        raise InputError(
            f"{where}: the northing/easting columns look like latitude/longitude in degrees (values "
            f"within +-90/+-180 moving {float(np.median(moving)):.2g} per frame); radaredge reads "
            f"planar metres: project them to UTM first (radaredge.data.geodesy.utm_from_latlon)"
        )


def load_sequence(directory: str | os.PathLike, fmt: str | None = None) -> RadarSequence:
    """The drive stored in ``directory`` (layout in the module docstring) as a
    :class:`RadarSequence`; scans are read on demand by :meth:`RadarSequence.scan`.

    A directory with ``pointclouds/`` and no ``scans/`` is read in the TransLoc4D layout.
    ``fmt`` is the scan file format: None or "transloc" (.npy), "vod" or "tj4d" (.bin). gps.csv
    rows are numbered from 0, the first row after the header, i.e. by frame. Raises
    :class:`InputError` for a missing scans/ or gps.csv, a row count that differs from the scan
    count, a missing header column, a value that is not a finite number, or timestamps that do
    not increase.
    """
    directory = Path(directory)
    if not (directory / "scans").is_dir() and (directory / POINTCLOUDS).is_dir():
        return _transloc_sequence(directory, fmt)
    fmt = _check_fmt("transloc" if fmt is None else fmt)
    paths = _scan_files(directory, fmt)
    timestamps, positions, _ = _read_gps(directory / "gps.csv")
    check_timestamps(timestamps, str(directory / "gps.csv"))
    check_positions(positions, str(directory / "gps.csv"))
    if len(timestamps) != len(paths):
        raise InputError(
            f"{directory}: gps.csv has {len(timestamps)} rows but scans/ holds {len(paths)} "
            f"{FILE_SUFFIX[fmt]} scan files; expected one row per scan"
        )
    return RadarSequence(directory.name, paths, timestamps, positions, fmt)


def name_the_scan(sequence: RadarSequence, frames: np.ndarray, message: str) -> str:
    """An error ``message`` about one window (its frames ``frames`` of ``sequence``, oldest first)
    with a leading "frame k:" (the window's k-th scan, as the runtime numbers it) replaced by
    that scan's file, so the message names the drive and the file."""
    m = re.match(r"frame (\d+): (.*)", message, re.S)
    if m and int(m.group(1)) < len(frames):
        return f"{sequence.scan_paths[frames[int(m.group(1))]]}: {m.group(2)}"
    if any(message.startswith(f"{sequence.scan_paths[f]}:") for f in frames):  # it names the file already
        return message
    return f"{sequence.name}, window ending at frame {int(frames[-1])}: {message}"


def _check_window(k: int) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ConfigError(f"window length k must be a positive integer, got {k!r}")
    return int(k)


def windows(sequence: RadarSequence, k: int) -> list[np.ndarray]:
    """Every window of ``k`` consecutive frames: for each frame t >= k-1, the int64 frame indices
    [t-k+1, ..., t], oldest first. Empty when the sequence has fewer than k frames."""
    k = _check_window(k)
    return [np.arange(t - k + 1, t + 1) for t in range(k - 1, len(sequence))]


def window_positions(sequence: RadarSequence, k: int) -> np.ndarray:
    """Position of each window of :func:`windows` (that of its last frame): float64 [W, 2],
    (northing, easting) m."""
    return sequence.positions[_check_window(k) - 1 :]


def _check_scan(scan: np.ndarray, i: int, fmt: str) -> np.ndarray:
    """Scan ``i`` as a float32 [N, C] table of ``fmt``'s file columns."""
    columns = _FILE_COLUMNS[fmt]
    scan = np.asarray(scan)
    if scan.ndim != 2 or scan.shape[1] != len(columns) or scan.dtype.kind not in "iuf":
        raise InputError(
            f"scan {i}: {scan.dtype} array of shape {scan.shape}; fmt {fmt!r} stores numeric "
            f"[N, {len(columns)}] arrays with columns {columns}"
        )
    return scan.astype(np.float32)


def write_sequence(
    directory: str | os.PathLike,
    scans: Sequence[np.ndarray],
    timestamps: Sequence[float],
    positions: np.ndarray,
    fmt: str = "transloc",
) -> Path:
    """Write a drive in the layout of the module docstring and return ``directory``.

    ``scans`` are the T frames, each [N, C] in ``fmt``'s file columns: "transloc" x, y, z, v,
    intensity (.npy); "vod" and "tj4d" their 7 and 8 columns (little-endian float32 .bin; see
    :mod:`radaredge.data.readers`). ``timestamps`` [T] s, strictly increasing; ``positions``
    [T, 2] (northing, easting) m. Files are named 000000, 000001, ... Refuses a directory that
    already holds scans/ or gps.csv.
    """
    directory = Path(directory)
    fmt = _check_fmt(fmt)
    timestamps = np.asarray(timestamps, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64)
    if not len(scans):
        raise InputError("write_sequence needs at least one scan")
    if timestamps.shape != (len(scans),) or positions.shape != (len(scans), 2):
        raise InputError(
            f"{len(scans)} scans need timestamps of shape ({len(scans)},) and positions of shape "
            f"({len(scans)}, 2); got {timestamps.shape} and {positions.shape}"
        )
    if not (np.isfinite(timestamps).all() and np.isfinite(positions).all()):
        raise InputError("timestamps and positions must be finite")
    _check_increasing(timestamps, "write_sequence")
    tables = [_check_scan(scan, i, fmt) for i, scan in enumerate(scans)]
    for existing in (directory / "scans", directory / "gps.csv"):
        if existing.exists():
            raise InputError(f"{existing} already exists; write_sequence writes a new drive into an empty place")
    (directory / "scans").mkdir(parents=True)
    width = max(6, len(str(len(tables) - 1)))
    for i, table in enumerate(tables):
        path = directory / "scans" / f"{i:0{width}d}{FILE_SUFFIX[fmt]}"
        if fmt == "transloc":
            np.save(path, table)
        else:
            table.astype("<f4").tofile(path)
    with (directory / "gps.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(GPS_COLUMNS)
        writer.writerows([repr(float(t)), repr(float(n)), repr(float(e))] for t, (n, e) in zip(timestamps, positions))
    return directory
