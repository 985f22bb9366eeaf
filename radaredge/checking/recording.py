"""Parity cases from the user's own recording instead of the synthetic generator (``--data DIR``).

``radaredge parity-check --model M --onnx G --data DIR`` feeds graph and reference the scans of
a recording, chosen as below, and judges them with the same comparators as the synthetic cases
(:func:`radaredge.checking.check.check_graph`). What ``DIR`` may be, tried in this order:

- **a drive**: ``DIR/scans/`` + ``DIR/gps.csv`` (or TransLoc4D's ``pointclouds/`` + gps.csv),
  as :func:`radaredge.data.sequences.load_sequence` reads it; **a directory of drives** (at any
  depth, e.g. what ``radaredge make-benchmark`` writes): every drive under it, by path;
- **a KITTI layout** (View-of-Delft, TJ4DRadSet): ``DIR/training/velodyne/*.bin``, or VoD's
  top folder holding the card's ``radar``/``radar_3frames``/``radar_5frames``; ``split`` picks
  the frames of ``ImageSets/<split>.txt``, every frame otherwise. A card whose ``input.crop`` is
  ``camera_fov`` gets each scan cropped to the camera's view (``calib/``, the image size from
  ``image_2/`` or the dataset's), as ``radaredge eval`` does; without ``calib/`` the scans are
  fed whole, and the report says so. Labels are not read;
- **a folder of scan files**: ``DIR/*.bin`` / ``*.npy`` (or ``DIR/scans/`` without gps.csv),
  frames in file-name order with numbers compared as numbers, e.g. TJ4DRadSet's
  ``training/velodyne/``.

A graph that takes one scan (MAFF-Net) gets one case a scan; one that takes K consecutive scans
(TDFANet) one case a window of K consecutive scans of one drive or folder (never across two
drives). Window times come from gps.csv where there is one, else from the card's
``frame_rate`` (the report says which). Of all frames or windows, ``frames`` are checked
(default :data:`DEFAULT_FRAMES`), **spread evenly** over the recording, the first and the last
included (every one when there are at most ``frames``), so a long drive is sampled from start to
end rather than only at its start. Scan formats are as :mod:`radaredge.data.readers` reads
them, inferred from the files unless ``fmt`` is given; every scan is checked as the runtime
checks an input (:class:`radaredge.runtime.FrameFeeds`), and a scan that cannot be read or fed
is an InputError naming its file.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cards import ModelCard
from ..data.kitti_detection import (
    LAYOUTS,
    DetectionSet,
    camera_fov_mask,
    check_image_size,
    read_calibration,
    read_image_size,
)
from ..data.readers import FILE_SUFFIX, check_points, read_scan, scan_format
from ..data.sequences import POINTCLOUDS, frame_order, load_sequence
from ..errors import CapacityError, ConfigError, InputError
from ..models.spec import GraphSpec
from ..runtime import FrameFeeds

DEFAULT_FRAMES = 20  # frames (windows) checked when none are asked for: the synthetic default's cost
EXPECTED = (
    "a drive (scans/ + gps.csv) or a directory of drives, a KITTI layout (training/velodyne/: View-of-Delft, "
    "TJ4DRadSet), or a folder of scan files (.bin or .npy, one per frame in file-name order)"
)


@dataclass
class Stream:
    """Consecutive scans of one drive or folder: ``paths`` in frame order, their gps.csv
    ``timestamps`` (s) when the recording has them, and the KITTI ``root`` for the camera crop."""

    label: str
    paths: list[Path]
    timestamps: np.ndarray | None = None
    kitti_root: Path | None = None
    fmt: str = ""


@dataclass
class Recording:
    """The recording a parity run was fed (``cases``: [(name, feeds)] in recording order) and
    how its frames were chosen, for the report."""

    directory: str
    kind: str  # "drive", "drives", "kitti", "folder"
    fmt: str
    scans: int  # scan files in the recording (in the split)
    available: int  # frames (windows) that could be checked
    window: int  # scans a case takes (K)
    timestamps: str  # where window times came from ("" for a one-scan graph)
    split: str | None = None
    notes: list[str] = field(default_factory=list)
    cases: list = field(default_factory=list)
    files: dict = field(default_factory=dict)  # case name -> its scan files

    @property
    def unit(self) -> str:
        return "window" if self.window > 1 else "frame"

    def to_dict(self) -> dict:
        return {
            "directory": self.directory,
            "kind": self.kind,
            "format": self.fmt,
            "scans": self.scans,
            "unit": self.unit,
            "window": self.window,
            "available": self.available,
            "checked": len(self.cases),
            "selection": "spread evenly, first and last included",
            "timestamps": self.timestamps or None,
            "split": self.split,
            "notes": list(self.notes),
            "files": dict(self.files),
        }

    def lines(self) -> list[str]:
        kinds = {
            "drive": "a drive: scans/ + gps.csv",
            "drives": "drives with gps.csv",
            "kitti": "KITTI layout" + (f", ImageSets/{self.split}.txt" if self.split else ", every frame"),
            "folder": "a folder of scan files",
        }
        what = f"{self.window} consecutive scans" if self.window > 1 else "one scan"
        out = [
            f"recording: {self.directory} ({kinds[self.kind]}; {self.scans} {self.fmt} scans); "
            f"{len(self.cases)} of {self.available} {self.unit}s of {what}, spread evenly (first and last included)"
        ]
        if self.timestamps:
            out.append(f"window times: {self.timestamps}")
        out += [f"note: {n}" for n in self.notes]
        return out


# ----------------------------------------------------------------------------- finding the scans


def _has_gps_drive(path: Path) -> bool:
    """``path`` is a drive with positions: scans/ or TransLoc4D's pointclouds/, and gps.csv."""
    return ((path / "scans").is_dir() or (path / POINTCLOUDS).is_dir()) and (path / "gps.csv").is_file()


def _drives_under(directory: Path) -> list[Path]:
    """Every drive with gps.csv under ``directory`` (not below a drive), by path."""
    found = []
    for here, dirs, _ in os.walk(directory):
        here_path = Path(here)
        for name in sorted(dirs):
            if _has_gps_drive(here_path / name):
                found.append(here_path / name)
        dirs[:] = sorted(d for d in dirs if not _has_gps_drive(here_path / d))
    return sorted(found)


def _scan_files(folder: Path, fmt: str | None) -> list[Path]:
    """The scan files directly in ``folder`` (.bin/.npy, or ``fmt``'s suffix), in frame order."""
    suffixes = {FILE_SUFFIX[fmt]} if fmt else set(FILE_SUFFIX.values())
    return frame_order((p for p in folder.iterdir() if p.suffix in suffixes and p.is_file()), folder)


def _format(paths: list[Path], fmt: str | None, where) -> str:
    """``fmt``, or the one format that reads every file (:func:`radaredge.data.readers.scan_format`)."""
    return scan_format(paths, fmt, f"--data {where}", "pass --format vod|tj4d|transloc")


def _kitti_root(directory: Path, card: ModelCard) -> Path | None:
    """The KITTI root of ``directory`` (it, or VoD's subfolder for the card's accumulated scans),
    None when it is no KITTI layout. InputError when it is VoD's top folder without the card's."""
    if (directory / "training" / "velodyne").is_dir():
        return directory
    scans = int(card.get("input.scans_accumulated", 1))
    names = {n: ds for layout in LAYOUTS.values() for n, ds in layout.scan_folders().items()}  # primary name first
    present = [d for ds in names.values() for d in ds if (directory / d / "training" / "velodyne").is_dir()]
    if not present:
        return None
    mine = [d for d in names.get(scans, ()) if d in present]
    if mine:
        return directory / mine[0]
    where = f", which View-of-Delft keeps in {' or '.join(d + '/' for d in names[scans])}" if scans in names else ""
    raise InputError(
        f"--data {directory}: {card.name} takes {scans} accumulated scan(s) a frame "
        f"(input.scans_accumulated){where}"
        f"; {directory} holds {', '.join(p + '/' for p in present)}: pass "
        f"{'it' if len(present) == 1 else 'one of them'} as --data to check on its scans"
    )


def _kitti_streams(root: Path, card: ModelCard, split: str | None, fmt: str | None, notes: list[str]):
    velodyne = root / "training" / "velodyne"
    if split is None:
        paths = _scan_files(velodyne, fmt or "vod")  # KITTI layouts store .bin
    else:
        if not (root / "ImageSets" / f"{split}.txt").is_file():
            have = sorted(p.stem for p in (root / "ImageSets").glob("*.txt")) if (root / "ImageSets").is_dir() else []
            raise InputError(
                f"--split {split}: {root / 'ImageSets' / (split + '.txt')} does not exist"
                + (f"; ImageSets has {have}" if have else "; without ImageSets, drop --split to check every frame")
            )
        dataset = _format(_scan_files(velodyne, fmt), fmt, root)
        if dataset not in LAYOUTS:
            raise InputError(f"--data {root}: a KITTI layout holds View-of-Delft or TJ4DRadSet scans, not {dataset}")
        the_set = DetectionSet(
            root,
            split,
            LAYOUTS[dataset],
            int(card.get("input.scans_accumulated", 1)),
            card.get("input.image_size"),
            say=False,
        )
        paths = [the_set.scan_path(fid) for fid in the_set.frame_ids]
    accumulated = {d: n for layout in LAYOUTS.values() for n, ds in layout.scan_folders().items() for d in ds}
    want = int(card.get("input.scans_accumulated", 1))
    if root.name in accumulated and accumulated[root.name] != want:
        notes.append(
            f"{root.name}/ holds {accumulated[root.name]} accumulated scan(s) a frame; {card.name} takes "
            f"{want} (input.scans_accumulated): parity holds on any cloud, the capacity figures are of "
            f"these clouds"
        )
    crop = None
    if card.get("input.crop", "none") == "camera_fov":
        if (root / "training" / "calib").is_dir():
            crop = root
            notes.append(
                "input.crop camera_fov: each scan cropped to the camera's view (training/calib/), as "
                "`radaredge eval` feeds it"
            )
        else:
            notes.append(
                f"input.crop camera_fov not applied: {root / 'training'} has no calib/; the scans are fed whole"
            )
    return [Stream("", paths, None, crop)], velodyne


def find_streams(directory: Path, card: ModelCard, split: str | None, fmt: str | None):
    """(kind, streams, format, notes) of the recording at ``directory`` (module docstring)."""
    if not directory.exists():
        raise InputError(f"--data {directory}: no such directory; expected {EXPECTED}")
    if not directory.is_dir():
        raise InputError(f"--data {directory} is a file, not a directory; expected {EXPECTED}")
    if fmt is not None and fmt not in FILE_SUFFIX:
        raise ConfigError(f"--format {fmt!r}: expected one of {list(FILE_SUFFIX)}")
    notes: list[str] = []
    kitti = None if _has_gps_drive(directory) else _kitti_root(directory, card)
    if split is not None and kitti is None:
        raise InputError(
            f"--split {split}: {directory} is not a KITTI layout (ImageSets/ + training/velodyne/); "
            f"drop --split to check its scans"
        )
    if kitti is not None:
        streams, where = _kitti_streams(kitti, card, split, fmt, notes)
        kind = "kitti"
    else:
        drives = [directory] if _has_gps_drive(directory) else _drives_under(directory)
        if drives:
            read = [_drive_stream(d, directory, fmt) for d in drives]
            streams, fmts = [s for s, _ in read], sorted({f for _, f in read})
            kind, where = ("drive" if drives == [directory] else "drives"), directory
        else:
            folder = directory / "scans" if (directory / "scans").is_dir() else directory
            streams, kind, where = [Stream("", _scan_files(folder, fmt))], "folder", folder
    paths = [p for s in streams for p in s.paths]
    if not paths:
        kinds = " or ".join(sorted({FILE_SUFFIX[fmt]} if fmt else set(FILE_SUFFIX.values())))
        raise InputError(f"--data {where}: no scan files ({kinds}); expected {EXPECTED}")
    if kind in ("drive", "drives"):
        return kind, streams, "/".join(fmts), notes
    fmt = _format(paths, fmt, where)
    for s in streams:
        s.fmt = fmt
    return kind, streams, fmt, notes


def _drive_stream(drive: Path, top: Path, fmt: str | None) -> tuple[Stream, str]:
    """A drive's scans and gps.csv times, and its format: inferred from its scans/ unless given."""
    if fmt is None and (drive / "scans").is_dir():
        files = [p for p in (drive / "scans").iterdir() if p.is_file() and p.suffix in FILE_SUFFIX.values()]
        if files:
            fmt = _format(files, None, drive / "scans")
    seq = load_sequence(drive, fmt)
    label = "" if drive == top else drive.relative_to(top).as_posix()
    return Stream(label, list(seq.scan_paths), np.asarray(seq.timestamps, np.float64), fmt=seq.fmt), seq.fmt


# ----------------------------------------------------------------------------- the cases


def spread(count: int, n: int) -> np.ndarray:
    """Indices of ``n`` of ``count`` items spread evenly, the first and (for ``n`` >= 2) the last
    included; all of them when ``count`` <= ``n``."""
    if count <= n:
        return np.arange(count)
    return np.unique(np.round(np.linspace(0, count - 1, n)).astype(np.int64))


def _frame_file(message: str, window: list[Path]) -> str:
    """An InputError message of the runtime's input checks, its "frame k:" replaced by the file."""
    m = re.match(r"frame (\d+): (.*)", message, re.S)
    if m and int(m.group(1)) < len(window):
        return f"{window[int(m.group(1))]}: {m.group(2)}"
    return f"{', '.join(p.name for p in window)}: {message}"


def _read(path: Path, card: ModelCard, fmt: str, kitti_root: Path | None) -> np.ndarray:
    """One scan in the card's columns, cropped to the camera's view when ``kitti_root`` is given."""
    points = check_points(read_scan(path, card.features, fmt), card.features, path)
    if kitti_root is None:
        return points
    training = kitti_root / "training"
    calib = read_calibration(training / "calib" / f"{path.stem}.txt")
    images = (training / "image_2" / f"{path.stem}{suffix}" for suffix in (".jpg", ".png", ".jpeg"))
    size = (
        next((read_image_size(p) for p in images if p.exists()), None)
        or check_image_size(card.get("input.image_size"))
        or LAYOUTS[fmt if fmt in LAYOUTS else "vod"].image_size
    )
    xyz = points[:, [card.features.index(c) for c in ("x", "y", "z")]]
    return points[camera_fov_mask(xyz, calib, size)]


def recorded_cases(
    card: ModelCard,
    graph: GraphSpec,
    directory: str | os.PathLike,
    frames: int = DEFAULT_FRAMES,
    split: str | None = None,
    fmt: str | None = None,
) -> Recording:
    """The parity cases of ``graph`` from the recording at ``directory`` (module docstring):
    ``frames`` frames (windows), spread evenly. InputError for a recording that is missing,
    holds no scans, too few for one window, or a scan that cannot be read or fed."""
    directory = Path(directory)
    k = len(graph.frame_inputs(card))
    if k > 1 and split is not None:
        raise ConfigError(
            f"--split picks labelled frames of a KITTI layout for a one-scan model; {card.name} takes "
            f"windows of {k} consecutive scans: drop --split and pass a drive or a folder of consecutive "
            f"scans"
        )
    kind, streams, fmt, notes = find_streams(directory, card, split, fmt)
    units = [(s, start) for s in streams for start in range(len(s.paths) - k + 1)]
    scans = sum(len(s.paths) for s in streams)
    if not units:
        raise InputError(
            f"--data {directory}: {scans} scan(s) per "
            f"{'drive' if kind.startswith('drive') else 'folder'} at most, but one window of {card.name} "
            f"takes {k} consecutive scans"
        )
    timed = graph.timestamps_input is not None
    if timed and all(s.timestamps is not None for s in streams):
        times = "gps.csv timestamps"
    elif timed:
        times = f"the card's frame_rate, {float(card.get('frame_rate', 10.0)):g} Hz (the recording has no gps.csv)"
    else:
        times = ""
    rec = Recording(str(directory), kind, fmt, scans, len(units), k, times, split, notes)
    feeder = FrameFeeds.of_card(card, graph.frame_inputs(card), graph.timestamps_input)
    for i in spread(len(units), frames):
        stream, start = units[int(i)]
        window = stream.paths[start : start + k]
        stamps = stream.timestamps[start : start + k] if stream.timestamps is not None and timed else None
        try:
            points = [_read(p, card, stream.fmt, stream.kitti_root) for p in window]
            feeds = feeder.feeds(points, stamps)
        except (InputError, CapacityError) as exc:  # named by the scan's file
            message = str(exc)
            if not any(message.startswith(str(p)) for p in window):
                message = _frame_file(message, window)
            raise type(exc)(message) from None
        stem = window[0].stem if k == 1 else f"{window[0].stem}-{window[-1].stem}"
        name = f"{stream.label}/{stem}" if stream.label else stem
        rec.cases.append((name, feeds))
        rec.files[name] = [str(p) for p in window]
    return rec
