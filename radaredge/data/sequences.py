"""Recorded drives as sequences of radar scans with a position per scan, and sliding windows over them.

Directory layout of one drive::

    DIR/
      scans/      one scan file per frame, frames in file-name order (zero-pad the numbers:
                  000000.npy, 000001.npy, ...): .npy for fmt "transloc" (the default),
                  .bin for fmt "vod" or "tj4d"; files with another suffix are ignored
      gps.csv     a header line naming at least the columns timestamp, northing, easting
                  (in any order; other columns are ignored), then one row per scan, in the
                  same order: timestamp in s (strictly increasing), northing and easting in m

A scan's columns are as :mod:`radaredge.data.readers` describes for its format (radar frame:
x forward, y left, z up; metres, m/s). Positions are planar (northing, easting) in metres, as
a GPS/UTM track gives them.

A window of k frames ending at frame t is the frames t-k+1 ... t, oldest first. Its time and
position are those of its last frame t, so windows and their positions line up one to one.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ConfigError, InputError
from .readers import FILE_SUFFIX, TJ4D_COLUMNS, TRANSLOC_COLUMNS, VOD_COLUMNS, read_scan

GPS_COLUMNS = ("timestamp", "northing", "easting")
_FILE_COLUMNS = {"transloc": TRANSLOC_COLUMNS, "vod": VOD_COLUMNS, "tj4d": TJ4D_COLUMNS}


@dataclass
class RadarSequence:
    """One recorded drive.

    name        the drive's directory name
    scan_paths  the scan file of each frame, in frame order
    timestamps  float64 [T], s, strictly increasing
    positions   float64 [T, 2], (northing, easting) m of each frame
    fmt         the scan file format: "transloc", "vod" or "tj4d"
    """

    name: str
    scan_paths: list[Path]
    timestamps: np.ndarray
    positions: np.ndarray
    fmt: str

    def scan(self, i: int, features: Sequence[str]) -> np.ndarray:
        """Frame ``i``'s points: float32 [N, len(features)], the columns named by ``features``
        (radar frame x forward, y left, z up; m, m/s), read with :func:`read_scan`."""
        return read_scan(self.scan_paths[i], features, self.fmt)

    def __len__(self) -> int:
        return len(self.scan_paths)


def _check_fmt(fmt: str) -> str:
    if fmt not in FILE_SUFFIX:
        raise InputError(f"unknown sequence scan format {fmt!r}; expected one of {list(FILE_SUFFIX)}")
    return fmt


def _check_increasing(timestamps: np.ndarray, where: str) -> None:
    """Raise naming the first row whose timestamp is not after the previous row's."""
    bad = np.flatnonzero(np.diff(timestamps) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"{where}: timestamps must increase; row {i} has {float(timestamps[i])!r} s, "
                         f"not after row {i - 1}'s {float(timestamps[i - 1])!r} s")


def _scan_files(directory: Path, fmt: str) -> list[Path]:
    """The scan files in ``directory/scans``, sorted by file name."""
    scans = directory / "scans"
    if not scans.is_dir():
        raise InputError(f"{directory}: no scans/ directory; expected one scan file per frame in {scans}")
    suffix = FILE_SUFFIX[fmt]
    paths = sorted((p for p in scans.iterdir() if p.is_file() and p.suffix == suffix), key=lambda p: p.name)
    if not paths:
        found = sorted({p.suffix for p in scans.iterdir() if p.is_file()})
        raise InputError(f"{scans}: no {suffix} scan files for fmt {fmt!r}; suffixes present: {found} "
                         f"(.npy scans are fmt 'transloc', .bin scans fmt 'vod' or 'tj4d')")
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


def _read_gps(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps float64 [T] s, positions float64 [T, 2] northing, easting m) of gps.csv."""
    if not path.is_file():
        raise InputError(f"{path}: no such file; expected a CSV with header {','.join(GPS_COLUMNS)} "
                         f"and one row per scan")
    with path.open(newline="") as f:
        rows = [r for r in csv.reader(f) if any(cell.strip() for cell in r)]
    if not rows:
        raise InputError(f"{path}: empty; expected a header line {','.join(GPS_COLUMNS)} and one row per scan")
    header = [name.strip().lower() for name in rows[0]]
    missing = [name for name in GPS_COLUMNS if name not in header]
    if missing:
        raise InputError(f"{path}: header lacks column(s) {missing}; it has {header}, "
                         f"expected {', '.join(GPS_COLUMNS)}")
    index = [header.index(name) for name in GPS_COLUMNS]
    values = np.zeros((len(rows) - 1, len(GPS_COLUMNS)))
    for row, cells in enumerate(rows[1:]):
        if len(cells) < len(header):
            raise InputError(f"{path}: row {row} has {len(cells)} values, the header has {len(header)} columns")
        values[row] = [_parse_value(cells[i], row, name, str(path)) for i, name in zip(index, GPS_COLUMNS)]
    _check_increasing(values[:, 0], str(path))
    return values[:, 0], values[:, 1:]


def load_sequence(directory: str | os.PathLike, fmt: str | None = None) -> RadarSequence:
    """The drive stored in ``directory`` (layout in the module docstring) as a
    :class:`RadarSequence`; scans are read on demand by :meth:`RadarSequence.scan`.

    ``fmt`` is the scan file format: None or "transloc" (.npy), "vod" or "tj4d" (.bin). gps.csv
    rows are numbered from 0, the first row after the header, i.e. by frame. Raises
    :class:`InputError` for a missing scans/ or gps.csv, a row count that differs from the scan
    count, a missing header column, a value that is not a finite number, or timestamps that do
    not increase.
    """
    directory = Path(directory)
    fmt = _check_fmt("transloc" if fmt is None else fmt)
    paths = _scan_files(directory, fmt)
    timestamps, positions = _read_gps(directory / "gps.csv")
    if len(timestamps) != len(paths):
        raise InputError(f"{directory}: gps.csv has {len(timestamps)} rows but scans/ holds {len(paths)} "
                         f"{FILE_SUFFIX[fmt]} scan files; expected one row per scan")
    return RadarSequence(directory.name, paths, timestamps, positions, fmt)


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
    return sequence.positions[_check_window(k) - 1:]


def _check_scan(scan: np.ndarray, i: int, fmt: str) -> np.ndarray:
    """Scan ``i`` as a float32 [N, C] table of ``fmt``'s file columns."""
    columns = _FILE_COLUMNS[fmt]
    scan = np.asarray(scan)
    if scan.ndim != 2 or scan.shape[1] != len(columns) or scan.dtype.kind not in "iuf":
        raise InputError(f"scan {i}: {scan.dtype} array of shape {scan.shape}; fmt {fmt!r} stores numeric "
                         f"[N, {len(columns)}] arrays with columns {columns}")
    return scan.astype(np.float32)


def write_sequence(directory: str | os.PathLike, scans: Sequence[np.ndarray], timestamps: Sequence[float],
                   positions: np.ndarray, fmt: str = "transloc") -> Path:
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
        raise InputError(f"{len(scans)} scans need timestamps of shape ({len(scans)},) and positions of shape "
                         f"({len(scans)}, 2); got {timestamps.shape} and {positions.shape}")
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
