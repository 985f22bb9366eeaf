"""Read raw radar scans as the datasets and sensors store them, into the model card's named columns.

A model card names its point columns (``features: [x, y, z, v_r, rcs]``); :func:`read_scan` and
:func:`iter_rosbag` return exactly those columns, in that order, as float32 [N, F]. Frames and
units as everywhere in radaredge: radar frame x forward, y left, z up; metres, m/s, seconds.

Scan files
----------
========  ==========================================  ==========================================
fmt       file layout (as the dataset names columns)  features served (canonical name <- column)
========  ==========================================  ==========================================
vod       View-of-Delft ``.bin``, little-endian       x, y, z, rcs, v_r, v_r_comp <- v_r_compensated,
          float32 x 7: x, y, z, rcs, v_r,             time
          v_r_compensated, time
tj4d      TJ4DRadSet ``.bin``, little-endian          x <- X, y <- Y, z <- Z, v_r <- V_r, range <- Range,
          float32 x 8: X, Y, Z, V_r, Range, Power,    power <- Power, snr <- Power (the MAFF-Net TJ4D
          Alpha, Beta                                 cards' name), alpha <- Alpha, beta <- Beta,
                                                      **rcs <- Power** (stand-in)
transloc  TransLoc4D-style ``.npy`` [N, 5], any       x, y, z, v_r <- v, intensity,
          integer or float dtype: x, y, z, v,         **rcs <- intensity** (stand-in)
          intensity
========  ==========================================  ==========================================

Stand-ins: TJ4DRadSet has no RCS column, so ``rcs`` is served from its Power (a received signal
strength, not dBsm); TransLoc4D-style files have an intensity instead of an RCS, so ``rcs`` is
served from it. A model trained on true RCS sees a different scale from these columns, so
:func:`read_scan` says so (:func:`stand_in_notes`, a ``UserWarning`` of the same text for every
file, which Python's default warning filter shows once per run).

``read_scan`` infers ``fmt`` from the file when it is not given: ``.npy`` is ``transloc``; a
``.bin`` is ``vod`` or ``tj4d`` only when its byte size is a whole number of rows of exactly one
of 7 or 8 float32 columns that its first rows agree with: TJ4D rows carry their own distance in
the Range column, so a file is ``tj4d`` only when they do and ``vod`` only when they do not (a
size that fits both is settled by the content; a truncated file of one layout whose size
happens to fit the other is refused). Otherwise pass ``fmt``.

ROS bags (fmt ``rosbag``)
-------------------------
:func:`iter_rosbag` reads ROS 1 ``.bag`` files and ROS 2 bags (a directory with
``metadata.yaml``, or one ``.db3``/``.mcap`` file) through ``rosbags``, one scan per message of
``sensor_msgs/msg/PointCloud2`` or ``sensor_msgs/msg/PointCloud``. Each feature is looked up
among the message's PointCloud2 fields or PointCloud channels (x, y, z come from a PointCloud's
points), by the first of these names present (case-insensitive):

=======  ==========================================
feature  names tried
=======  ==========================================
x, y, z  x, y, z
v_r      v_r, doppler, velocity, radial_velocity, v
rcs      rcs, power, intensity, snr
other    its own name
=======  ==========================================

``field_map`` overrides this per feature with a field/channel name (str) or index (int, into
PointCloud2 ``fields`` or PointCloud ``channels``). Example: NTU4DRadLM publishes
``/radar_enhanced_pcl`` as a PointCloud whose channel 0 is the Doppler velocity and channel 2
the power, so ``field_map={"v_r": 0, "rcs": 2}`` reads it (its power is then the ``rcs``
stand-in).
"""

from __future__ import annotations

import contextlib
import os
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np

from ..errors import InputError

FORMATS = ("vod", "tj4d", "transloc", "rosbag")
VOD_COLUMNS = ("x", "y", "z", "rcs", "v_r", "v_r_compensated", "time")
TJ4D_COLUMNS = ("X", "Y", "Z", "V_r", "Range", "Power", "Alpha", "Beta")
TRANSLOC_COLUMNS = ("x", "y", "z", "v", "intensity")

FieldMap = Mapping[str, str | int]


@dataclass(frozen=True)
class _Layout:
    """One scan-file layout: its columns as the dataset names them, and the features it serves."""

    title: str
    columns: tuple[str, ...]
    features: dict[str, int]  # canonical feature name -> column index


_LAYOUTS = {
    "vod": _Layout(
        "View-of-Delft radar", VOD_COLUMNS, {"x": 0, "y": 1, "z": 2, "rcs": 3, "v_r": 4, "v_r_comp": 5, "time": 6}
    ),
    "tj4d": _Layout(
        "TJ4DRadSet radar",
        TJ4D_COLUMNS,
        {"x": 0, "y": 1, "z": 2, "v_r": 3, "range": 4, "power": 5, "snr": 5, "alpha": 6, "beta": 7, "rcs": 5},
    ),
    "transloc": _Layout(
        "TransLoc4D-style radar", TRANSLOC_COLUMNS, {"x": 0, "y": 1, "z": 2, "v_r": 3, "intensity": 4, "rcs": 4}
    ),
}
_BIN_FORMATS = ("vod", "tj4d")
# Features a format serves from a column that measures another quantity: fmt -> feature -> what the
# column is (a stand-in, said by read_scan).
STAND_INS = {
    "tj4d": {"rcs": "its Power column (the signal-to-noise ratio in dB, not a radar cross-section in dBsm)"},
    "transloc": {"rcs": "its intensity column (not a radar cross-section in dBsm)"},
}
FILE_SUFFIX = {"vod": ".bin", "tj4d": ".bin", "transloc": ".npy"}  # scan-file formats and their suffix


# ----------------------------------------------------------------------------- bounded files


def check_file(path: str | os.PathLike, what: str, limit: int, why: str, error: type = InputError) -> int:
    """The byte size of the regular file ``path``, from its stat, before anything reads it.
    ``error`` (InputError by default) naming the file when it is missing, a directory or another
    kind of file (a FIFO, a device), cannot be stat-ed, or holds more than ``limit`` bytes;
    ``what`` names the file's kind with its article ("a KITTI label file"), ``why`` the reason
    for the bound, both as the message shows them."""
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise error(f"{path}: no such file; expected {what}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror or type(exc).__name__})") from None
    if stat.S_ISDIR(info.st_mode):
        raise error(f"{path} is a directory, not {what}")
    if not stat.S_ISREG(info.st_mode):
        raise error(f"{path} is not a regular file; expected {what}")
    if info.st_size > limit:
        raise error(f"{path}: {info.st_size:,} bytes, more than {what} can hold ({limit:,} bytes at most: {why})")
    return info.st_size


def read_bounded(path: str | os.PathLike, what: str, limit: int, why: str, error: type = InputError) -> bytes:
    """The bytes of ``path`` after :func:`check_file`, read up to ``limit`` bytes and no further
    (a file that grows while it is read is refused the same way)."""
    check_file(path, what, limit, why, error)
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror or type(exc).__name__})") from None
    if len(data) > limit:
        raise error(f"{path}: more than {limit:,} bytes, more than {what} can hold ({why})")
    return data


# Scan files hold at most this many points: the largest ``max_points_per_frame`` a card can
# declare (radaredge.cards.TOP_LEVEL_NUMBERS); a radar scan holds a few hundred to a few thousand.
MAX_SCAN_POINTS = 2**24
_NPY_HEADER_BYTES = 1 << 16  # room for a .npy header (NumPy reads headers of at most 10,000 bytes)
# x, y, z of a radar point (m): far beyond any radar's reach (automotive radars see a few hundred
# metres). Points outside a card's point_cloud_range are left out by its graph; a coordinate
# beyond this is no measurement (a damaged scan), and far beyond it float32 arithmetic breaks
# (voxel indices overflow near 1e37 m; the eval report's pictures fail near 1e17 m).
MAX_COORDINATE = 1.0e6
COORDINATES = ("x", "y", "z")


def check_points(points: np.ndarray, features: Sequence[str], where) -> np.ndarray:
    """``points`` [N, F] (columns ``features``) unchanged; InputError naming ``where``, the point
    and the column for a value that is not finite, or an x, y or z beyond +-MAX_COORDINATE m."""
    bad = ~np.isfinite(points)
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        raise InputError(
            f"{where}: non-finite value {points[row, col]} at point {row}, column "
            f"{features[col]!r} ({int(bad.any(1).sum())} point(s) affected)"
        )
    coords = [i for i, f in enumerate(features) if f in COORDINATES]
    if coords and len(points):
        far = np.abs(points[:, coords]) > MAX_COORDINATE
        if far.any():
            row, k = (int(v) for v in np.argwhere(far)[0])
            raise InputError(
                f"{where}: point {row}, column {features[coords[k]]!r} is {points[row, coords[k]]:.3g} "
                f"m; a radar point lies within {MAX_COORDINATE:g} m ({int(far.any(1).sum())} point(s) "
                f"beyond). Points outside the card's point_cloud_range are left out, as its graph "
                f"does, but this is no measurement: a damaged scan?"
            )
    return points


# ----------------------------------------------------------------------------- scan files


def _check_features(features: Sequence[str]) -> list[str]:
    """``features`` as a list of names; a non-empty sequence of strings is required."""
    if isinstance(features, str) or not features or not all(isinstance(f, str) for f in features):
        raise InputError(
            f"features must be a non-empty list of column names such as ['x', 'y', 'z', 'v_r', 'rcs'], got {features!r}"
        )
    return list(features)


def _feature_columns(features: Sequence[str], fmt: str) -> list[int]:
    """Column index in a ``fmt`` file of each feature."""
    layout = _LAYOUTS[fmt]
    missing = [f for f in features if f not in layout.features]
    if missing:
        raise InputError(
            f"format {fmt!r} ({layout.title}) cannot provide feature(s) {missing}; "
            f"it provides {sorted(layout.features)}"
        )
    return [layout.features[f] for f in features]


def scan_features(fmt: str) -> tuple[str, ...]:
    """The feature names a scan file of ``fmt`` (vod, tj4d, transloc) can serve."""
    return tuple(_LAYOUTS[fmt].features)


def _bin_row_bytes(fmt: str) -> int:
    return 4 * len(_LAYOUTS[fmt].columns)


def scan_format(paths: Sequence[Path], fmt: str | None, where: str, option: str) -> str:
    """``fmt`` when given, else :func:`infer_format` of ``paths``, whose InputError (a folder that
    mixes .npy and .bin files, .bin sizes that do not tell vod from tj4d) is prefixed by ``where``
    and names the command-line ``option`` that sets the format."""
    if fmt is not None:
        return fmt
    try:
        return infer_format(paths)
    except InputError as exc:
        raise InputError(f"{where}: {exc} ({option})") from None


def infer_format(paths: Sequence[Path]) -> str:
    """The one scan format that reads every file of ``paths``: ``transloc`` when all are
    ``.npy``; for ``.bin`` files, ``vod`` or ``tj4d`` when the byte sizes and the content of the
    files' first rows (TJ4D rows hold their own distance) agree on one. InputError for another
    or mixed suffixes, when neither layout fits, and when size and content disagree or cannot
    tell (then the format must be given)."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise InputError("no scan files to infer a format from")
    suffixes = sorted({p.suffix for p in paths})
    where = str(paths[0]) if len(paths) == 1 else f"{len(paths)} scan files in {paths[0].parent}"
    if suffixes == [".npy"]:
        return "transloc"
    if len(suffixes) > 1:
        raise InputError(
            f"{paths[0].parent} mixes {' and '.join(suffixes)} scan files; keep one recording in one "
            f"format, or pass fmt= to read only the files of that format"
        )
    if suffixes != [".bin"]:
        raise InputError(
            f"{where}: cannot infer the scan format from suffix {suffixes[0]!r}; pass fmt= one of "
            f"{list(_LAYOUTS)} (ROS bags: iter_rosbag / read_rosbag)"
        )
    sizes = [p.stat().st_size for p in paths]
    fits = [fmt for fmt in _BIN_FORMATS if all(size % _bin_row_bytes(fmt) == 0 for size in sizes)]
    step = max(1, len(paths) // _SIGNATURE_FILES)
    votes = {p: _looks_like_tj4d(p) for p in paths[::step][:_SIGNATURE_FILES]}
    judged = {v for v in votes.values() if v is not None}
    if len(fits) == 2 and len(judged) == 1:
        fits = ["tj4d" if judged == {True} else "vod"]
    if len(fits) != 1:
        what = "both" if fits else "neither"
        size = f"{sizes[0]} bytes" if len(paths) == 1 else "their byte sizes"
        raise InputError(
            f"{where}: {size} fit {what} of the .bin layouts vod (7 float32 columns, "
            f"{_bin_row_bytes('vod')} bytes a row) and tj4d (8 float32 columns, "
            f"{_bin_row_bytes('tj4d')} bytes a row); pass fmt='vod' or fmt='tj4d'"
        )
    for p, tj4d_like in votes.items():
        if tj4d_like is None or tj4d_like == (fits[0] == "tj4d"):
            continue
        size = p.stat().st_size
        if fits[0] == "tj4d":
            raise InputError(
                f"{p}: {size} bytes fit the tj4d layout, but its Range column (5th of 8) is not the "
                f"points' distance sqrt(X^2 + Y^2 + Z^2): not a TJ4DRadSet scan (a truncated "
                f"View-of-Delft .bin?); pass fmt='vod' or fmt='tj4d'"
            )
        raise InputError(
            f"{p}: {size} bytes fit the vod layout, but its first rows read as TJ4DRadSet rows "
            f"(the 5th of 8 columns is the points' distance): a truncated tj4d file?; pass "
            f"fmt='vod' or fmt='tj4d'"
        )
    return fits[0]


_SIGNATURE_FILES = 16  # files of a recording whose content infer_format checks
_SIGNATURE_ROWS = 64  # rows read from the head of each


def _looks_like_tj4d(path: Path) -> bool | None:
    """Whether the head of ``path``, read as 8-column float32 rows, has a 5th column equal to
    each row's distance sqrt(X^2 + Y^2 + Z^2) (TJ4DRadSet's Range) within 1 % + 5 cm; None when
    it cannot tell (no whole row, or only zeros). The head survives truncation, so a cut TJ4D
    file is still recognised; View-of-Delft rows read at an 8-column stride do not match."""
    head = np.fromfile(path, dtype="<f4", count=8 * _SIGNATURE_ROWS)
    rows = head[: len(head) // 8 * 8].reshape(-1, 8).astype(np.float64)
    if not np.any(rows):
        return None
    with np.errstate(all="ignore"):
        dist = np.linalg.norm(rows[:, :3], axis=1)
        return bool(np.all(np.abs(rows[:, 4] - dist) <= 0.01 * dist + 0.05))


def _read_bin(path: Path, fmt: str) -> np.ndarray:
    """A little-endian float32 ``.bin`` of ``fmt``'s columns as float32 [N, C]."""
    layout = _LAYOUTS[fmt]
    row = _bin_row_bytes(fmt)
    size = check_file(
        path,
        f"a {layout.title} scan",
        MAX_SCAN_POINTS * row,
        f"{MAX_SCAN_POINTS:,} points of {row} bytes, the most a card's max_points_per_frame can take",
    )
    if size % row:
        raise InputError(
            f"{path}: {size} bytes is not a whole number of {layout.title} rows of "
            f"{len(layout.columns)} float32 columns {layout.columns}: expected a multiple of {row} "
            f"bytes (truncated file, or another format?)"
        )
    return np.fromfile(path, dtype="<f4").reshape(-1, len(layout.columns)).astype(np.float32)


def _read_npy(path: Path, fmt: str) -> np.ndarray:
    """A 2-D numeric ``.npy`` of ``fmt``'s columns, as float32 [N, C]."""
    layout = _LAYOUTS[fmt]
    size = check_file(
        path,
        f"a {layout.title} .npy scan",
        _NPY_HEADER_BYTES + MAX_SCAN_POINTS * len(layout.columns) * 8,
        f"{MAX_SCAN_POINTS:,} points of {len(layout.columns)} float64 columns, the most a card's "
        f"max_points_per_frame can take",
    )
    with path.open("rb") as f:
        if f.read(len(np.lib.format.MAGIC_PREFIX)) != np.lib.format.MAGIC_PREFIX:
            raise InputError(f"{path}: not a readable .npy file (no NumPy array header)")
        f.seek(0)
        try:
            version = np.lib.format.read_magic(f)
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read_header(f)
        except (ValueError, SyntaxError) as exc:
            raise InputError(f"{path}: not a readable .npy file: {exc}") from None
    claimed = dtype.itemsize * float(np.prod(shape, dtype=np.float64))
    if claimed > size:  # checked before numpy allocates what the header claims
        raise InputError(
            f"{path}: its header claims shape {shape} of {dtype} ({claimed:.3g} bytes) but the file "
            f"holds {size} bytes (truncated or damaged)"
        )
    if len(shape) == 2 and shape[0] > MAX_SCAN_POINTS:
        raise InputError(
            f"{path}: its header claims {shape[0]:,} points; a scan holds at most {MAX_SCAN_POINTS:,} "
            f"(the most a card's max_points_per_frame can take)"
        )
    try:
        table = np.load(path, allow_pickle=False)
    except ValueError as exc:  # behind a valid header, a pickle is an object array
        if "pickle" in str(exc):
            raise InputError(
                f"{path}: holds a pickled object array, which is not loaded (allow_pickle=False); "
                f"save the scan as a numeric [N, {len(layout.columns)}] array"
            ) from exc
        raise InputError(f"{path}: not a readable .npy file: {exc}") from exc
    expected = f"a numeric [N, {len(layout.columns)}] array {layout.columns}"
    if table.dtype.kind not in "iuf":
        raise InputError(f"{path}: dtype {table.dtype} is not numeric; expected {expected}")
    if table.ndim != 2:
        raise InputError(f"{path}: array of shape {table.shape} is not 2-D; expected {expected}")
    if table.shape[1] != len(layout.columns):
        raise InputError(f"{path}: {table.shape[1]} columns, expected {expected}")
    return table.astype(np.float32)


def _read_table(path: str | os.PathLike, fmt: str) -> np.ndarray:
    """Every column of the scan file ``path`` in format ``fmt``, as float32 [N, C] in the file's
    own column order (``VOD_COLUMNS``, ``TJ4D_COLUMNS``, ``TRANSLOC_COLUMNS``), units as stored."""
    path = Path(path)
    if fmt not in _LAYOUTS:
        raise InputError(
            f"{path}: unknown scan format {fmt!r}; expected one of {list(_LAYOUTS)}"
            + (" (a ROS bag holds many scans: use iter_rosbag / read_rosbag)" if fmt == "rosbag" else "")
        )
    if not path.exists():
        raise InputError(f"{path}: no such {_LAYOUTS[fmt].title} file")
    return _read_bin(path, fmt) if fmt in _BIN_FORMATS else _read_npy(path, fmt)


def stand_in_notes(fmt: str, features: Sequence[str]) -> list[str]:
    """One sentence per feature of ``features`` (a card's ``features``) that a ``fmt`` file serves
    from a column measuring another quantity (:data:`STAND_INS`), naming both; none otherwise."""
    title = _LAYOUTS[fmt].title if fmt in _LAYOUTS else fmt
    return [
        f"{title} scans have no {feature!r} column: the card's features name {feature!r}, which is served "
        f"from {what}; a model trained on {feature} sees another quantity and scale"
        for feature, what in STAND_INS.get(fmt, {}).items()
        if feature in features
    ]


def read_scan(path: str | os.PathLike, features: Sequence[str], fmt: str | None = None) -> np.ndarray:
    """One scan: float32 [N, len(features)], the columns named by ``features`` in that order.

    ``features`` are the model card's canonical names (x, y, z in m in the radar frame, v_r in
    m/s, rcs, and per format those in the module docstring's table). ``fmt`` is one of ``vod``,
    ``tj4d``, ``transloc``; None infers it from the file (``.npy``: transloc; ``.bin``: by byte
    size). Raises :class:`InputError` for a missing or malformed file and for a feature the
    format cannot provide. A feature served from a column of another quantity (TJ4D's Power as
    ``rcs``) is said as a ``UserWarning`` (:func:`stand_in_notes`; the same text for every file).
    """
    features = _check_features(features)
    path = Path(path)
    if fmt is None:
        if not path.is_file():
            raise InputError(
                f"{path} is a directory, not a scan file" if path.is_dir() else f"{path}: no such scan file"
            )
        fmt = infer_format([path])
    table = _read_table(path, fmt)
    columns = _feature_columns(features, fmt)
    for note in stand_in_notes(fmt, features):
        warnings.warn(note, UserWarning, stacklevel=2)
    return np.ascontiguousarray(table[:, columns])


def read_vod_bin(path: str | os.PathLike) -> np.ndarray:
    """Read a View-of-Delft radar ``.bin``: float32 [N, 7], columns ``VOD_COLUMNS``."""
    return _read_table(path, "vod")


def read_tj4d_bin(path: str | os.PathLike) -> np.ndarray:
    """Read a TJ4DRadSet radar ``.bin``: float32 [N, 8], columns ``TJ4D_COLUMNS``."""
    return _read_table(path, "tj4d")


# ----------------------------------------------------------------------------- ROS bags

_POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
_POINTCLOUD = "sensor_msgs/msg/PointCloud"
_XYZ = ("x", "y", "z")
_DEFAULT_NAMES = {
    "v_r": ("v_r", "doppler", "velocity", "radial_velocity", "v"),
    "rcs": ("rcs", "power", "intensity", "snr"),
}
_POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _pick(feature: str, names: list[str], field_map: FieldMap, kind: str, where: str) -> int:
    """Index in ``names`` (the message's fields or channels) of the source of ``feature``."""
    if feature in field_map:
        key = field_map[feature]
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            if 0 <= key < len(names):
                return int(key)
            raise InputError(
                f"{where}: field_map maps {feature!r} to {kind} index {key}, but the message has "
                f"{len(names)} {kind}s {names}"
            )
        if key in names:
            return names.index(key)
        raise InputError(
            f"{where}: field_map maps {feature!r} to {kind} {key!r}, which the message lacks; its {kind}s are {names}"
        )
    candidates = _DEFAULT_NAMES.get(feature, (feature,))
    lowered = [n.lower() for n in names]
    for name in candidates:
        if name in lowered:
            return lowered.index(name)
    raise InputError(
        f"{where}: cannot map feature {feature!r}: the message's {kind}s are {names}, none named "
        f"{list(candidates)}; pass field_map={{{feature!r}: <{kind} name or index>}}"
    )


def _cloud2_points(msg, where: str) -> np.ndarray:
    """The bytes of each point of a PointCloud2, uint8 [height * width, point_step]."""
    data = np.asarray(msg.data, dtype=np.uint8).ravel()
    height, width, step, row = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if row < width * step or data.size < height * row:
        raise InputError(
            f"{where}: PointCloud2 data holds {data.size} bytes; expected height {height} x row_step "
            f"{row} bytes with row_step >= width {width} x point_step {step}"
        )
    return data[: height * row].reshape(height, row)[:, : width * step].reshape(height * width, step)


def _cloud2_field(points: np.ndarray, field, big_endian: bool, where: str) -> np.ndarray:
    """One scalar PointField of every point, float32 [P]."""
    code = _POINTFIELD_DTYPES.get(int(field.datatype))
    if code is None:
        raise InputError(f"{where}: field {field.name!r} has unknown PointField datatype {field.datatype}")
    if int(field.count) != 1:
        raise InputError(f"{where}: field {field.name!r} has count {field.count}; only scalar fields can be mapped")
    dtype = np.dtype(code).newbyteorder(">" if big_endian else "<")
    start, stop = int(field.offset), int(field.offset) + dtype.itemsize
    if stop > points.shape[1]:
        raise InputError(
            f"{where}: field {field.name!r} (bytes {start}-{stop}) lies outside point_step {points.shape[1]}"
        )
    return np.ascontiguousarray(points[:, start:stop]).view(dtype).ravel().astype(np.float32)


def _decode_pointcloud2(msg, features: list[str], field_map: FieldMap, where: str) -> np.ndarray:
    """float32 [height * width, F] of a sensor_msgs/PointCloud2."""
    fields = list(msg.fields)
    chosen = [fields[_pick(f, [x.name for x in fields], field_map, "field", where)] for f in features]
    points = _cloud2_points(msg, where)
    columns = [_cloud2_field(points, field, bool(msg.is_bigendian), where) for field in chosen]
    return np.stack(columns, axis=1)


def _decode_pointcloud(msg, features: list[str], field_map: FieldMap, where: str) -> np.ndarray:
    """float32 [N, F] of a sensor_msgs/PointCloud: x, y, z from ``points``, the rest from ``channels``."""
    xyz = np.array([[p.x, p.y, p.z] for p in msg.points], dtype=np.float32).reshape(-1, 3)
    channels = list(msg.channels)
    names = [c.name for c in channels]
    columns = []
    for feature in features:
        if feature in _XYZ and feature not in field_map:
            columns.append(xyz[:, _XYZ.index(feature)])
            continue
        channel = channels[_pick(feature, names, field_map, "channel", f"{where} (x, y, z from points)")]
        values = np.asarray(channel.values, dtype=np.float32).ravel()
        if values.size != len(xyz):
            raise InputError(f"{where}: channel {channel.name!r} has {values.size} values for {len(xyz)} points")
        columns.append(values)
    return np.stack(columns, axis=1)


_DECODERS = {_POINTCLOUD2: _decode_pointcloud2, _POINTCLOUD: _decode_pointcloud}


def _stamp_seconds(msg) -> float:
    """The message's header stamp in seconds."""
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def iter_rosbag(
    path: str | os.PathLike, topic: str, features: Sequence[str], field_map: FieldMap | None = None
) -> Iterator[tuple[float, np.ndarray]]:
    """Each scan on ``topic`` of a ROS 1 or ROS 2 bag, in recording order: (header stamp in s,
    float32 [N, len(features)] with the columns named by ``features``, in the sensor's frame).

    ``topic`` must carry sensor_msgs/msg/PointCloud2 or sensor_msgs/msg/PointCloud. Fields are
    found by name as in the module docstring; ``field_map`` maps a feature to a field/channel name
    or index instead. A generator: the bag is opened, and problems (missing bag or topic,
    unsupported type, unmappable feature) raise :class:`InputError`, on the first iteration.
    """
    features = _check_features(features)
    field_map = dict(field_map or {})
    unknown = sorted(set(field_map) - set(features))
    if unknown:
        raise InputError(f"field_map key(s) {unknown} are not among the requested features {features}")
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such ROS bag")
    with bag_topic(path, topic, list(_DECODERS)) as (reader, connections):
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            decode = _DECODERS[connection.msgtype]
            yield _stamp_seconds(msg), decode(msg, features, field_map, f"{path}: topic {topic!r}")


@contextlib.contextmanager
def bag_topic(path: Path, topic: str, msgtypes: Sequence[str], what: str = ""):
    """(reader, connections) of ``topic`` in the ROS 1 or ROS 2 bag ``path`` (rosbags'
    ``AnyReader``), its message types among ``msgtypes``; a missing topic, another type, or a
    damaged bag anywhere while the caller reads it is one InputError naming the file. ``what``
    names the topic's role in the message ("GNSS ")."""
    # rosbags is imported here, not at module level, so reading scan files stays numpy-only.
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    try:
        # The default typestore decodes ROS 2 bags that were recorded without message definitions.
        with AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as reader:
            connections = [c for c in reader.connections if c.topic == topic]
            if not connections:
                present = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(reader.topics.items()))
                raise InputError(f"{path}: no {what}topic {topic!r}; the bag has: {present or 'no topics'}")
            unsupported = sorted({c.msgtype for c in connections} - set(msgtypes))
            if unsupported:
                raise InputError(
                    f"{path}: topic {topic!r} carries {', '.join(unsupported)}; expected {' or '.join(msgtypes)}"
                )
            yield reader, connections
    except InputError:
        raise
    except AnyReaderError as exc:
        raise InputError(f"{path}: cannot read the ROS bag: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - a damaged bag fails anywhere inside rosbags' parsers
        raise InputError(
            f"{path}: cannot read the ROS bag, it is damaged or not a bag ({type(exc).__name__}: {str(exc)[:200]})"
        ) from exc


def read_rosbag(
    path: str | os.PathLike, topic: str, features: Sequence[str], field_map: FieldMap | None = None
) -> list[tuple[float, np.ndarray]]:
    """Every scan on ``topic``, as :func:`iter_rosbag` yields them: [(stamp s, float32 [N, F])]."""
    return list(iter_rosbag(path, topic, features, field_map))
