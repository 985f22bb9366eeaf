"""Calibration windows for int8 quantisation: synthetic scenes, or scans recorded by the user's sensor.

onnxruntime's static quantisation sets each activation's int8 range from the values it sees on
calibration inputs. The default is synthetic scenes drawn from the model's own case generator.
A real sensor's value ranges (RCS scale, Doppler spread, point density, clutter) differ from
them, and an activation range that is too narrow clips a deployed model's activations, so
``radaredge export --quantize int8 --calibration DIR`` calibrates on the user's recordings:

    DIR/   one scan file per frame, frames in file-name order (zero-pad the numbers), either
           directly in DIR or in DIR/scans/ (a drive as ``radaredge eval`` reads it). Formats as
           in :mod:`radaredge.data.readers`: .npy (transloc) or .bin (vod / tj4d, told apart
           by byte size when every file fits exactly one of them, else pass the format).

A K-frame model is calibrated on windows of K consecutive files, spread evenly over the
recording (the first and the last window included), timestamped at the card's frame rate.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from onnxruntime.quantization import CalibrationDataReader

from .cards import ModelCard
from .data.readers import FILE_SUFFIX, infer_format, read_scan
from .errors import ConfigError, InputError
from .registry import model_spec
from .runtime import RadarModel


class FeedList(CalibrationDataReader):
    """onnxruntime calibration reader over a list of input-feed dicts, one window per call."""

    def __init__(self, feeds: list[dict[str, np.ndarray]]):
        self._feeds = iter(feeds)

    def get_next(self):
        return next(self._feeds, None)


def synthetic_feeds(card: ModelCard, n: int, seed: int) -> list[dict[str, np.ndarray]]:
    """The feeds of ``n`` synthetic cases of the card's model drawn with ``seed``."""
    return [feeds for _, feeds in model_spec(card).make_cases(card, n, seed)]


def recorded_scan_paths(directory: str | os.PathLike) -> list[Path]:
    """The scan files (.npy / .bin) of a recording, in file-name order: those directly in
    ``directory``, else those in ``directory``/scans. InputError when there are none."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"calibration: {directory} is not a directory; expected one holding a recording's "
                         f"scan files (.npy or .bin, one per frame) or a drive with scans/")
    suffixes = set(FILE_SUFFIX.values())
    for folder in (directory, directory / "scans"):
        if folder.is_dir():
            paths = sorted((p for p in folder.iterdir() if p.suffix in suffixes and p.is_file()), key=lambda p: p.name)
            if paths:
                return paths
    raise InputError(f"calibration: no .npy or .bin scan files in {directory} or {directory / 'scans'}")


def recording_format(paths: list[Path], fmt: str | None = None) -> str:
    """The scan format of the recording's files ``paths``: ``fmt`` when given, after checking
    that it reads their suffix, else :func:`radaredge.data.readers.infer_format`."""
    if fmt is None:
        try:
            return infer_format(paths)
        except InputError as exc:
            raise InputError(f"calibration: {exc} (radaredge export: --calibration-format)") from exc
    if fmt not in FILE_SUFFIX:
        raise ConfigError(f"calibration format {fmt!r}: expected one of {list(FILE_SUFFIX)}")
    wrong = [p.name for p in paths if p.suffix != FILE_SUFFIX[fmt]]
    if wrong:
        raise InputError(f"calibration: format {fmt!r} reads {FILE_SUFFIX[fmt]} files, but {wrong[0]} "
                         f"({len(wrong)} of {len(paths)} files) is not one")
    return fmt


def window_starts(num_scans: int, k: int, n: int) -> np.ndarray:
    """First-frame indices of ``n`` windows of ``k`` consecutive scans spread evenly over
    ``num_scans`` scans, the first and last window included; every window when there are at
    most ``n``. InputError when there are fewer than ``k`` scans."""
    if n < 1:
        raise ConfigError(f"calibration needs at least one window, got {n}")
    if num_scans < k:
        raise InputError(f"calibration: the recording holds {num_scans} scan(s) but one window of this model "
                         f"takes {k} consecutive frames")
    last = num_scans - k
    if last + 1 <= n:
        return np.arange(last + 1)
    return np.unique(np.round(np.linspace(0, last, n)).astype(np.int64))


def recorded_feeds(model: RadarModel, directory: str | os.PathLike, n: int,
                   fmt: str | None = None) -> tuple[list[dict[str, np.ndarray]], dict]:
    """Input feeds of ``n`` windows (:func:`window_starts`) of the recording in ``directory``,
    in ``model``'s feature columns and checked like any runtime input, plus a description for
    the int8 graph's metadata (directory, format, scans, windows). InputError names the file
    whose scan cannot be read or fed."""
    paths = recorded_scan_paths(directory)
    fmt = recording_format(paths, fmt)
    starts = window_starts(len(paths), model.frames, n)
    feeds = []
    for s in starts:
        window = paths[s:s + model.frames]
        try:
            feeds.append(model.feeds([read_scan(p, model.features, fmt) for p in window]))
        except InputError as exc:
            raise InputError(f"calibration window {', '.join(p.name for p in window)}: {exc}") from exc
    return feeds, {"data": "recorded", "directory": str(directory), "format": fmt, "scans": len(paths),
                   "windows": len(feeds)}
