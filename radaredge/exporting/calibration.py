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
recording (the first and, from two windows on, the last window included), timestamped at the
card's frame rate.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from onnxruntime.quantization import CalibrationDataReader

from ..cards import ModelCard
from ..data.readers import FILE_SUFFIX, read_scan, scan_format
from ..data.sequences import frame_order
from ..errors import ConfigError, InputError
from ..registry import model_spec
from ..runtime import FrameFeeds

DEFAULT_WINDOWS = 16  # calibration windows when none are asked for


class FeedList(CalibrationDataReader):
    """onnxruntime calibration reader over a list of input-feed dicts, one window per call."""

    def __init__(self, feeds: list[dict[str, np.ndarray]]):
        self._feeds = iter(feeds)

    def get_next(self):
        return next(self._feeds, None)


def synthetic_feeds(card: ModelCard, n: int, seed: int, graph=None) -> list[dict[str, np.ndarray]]:
    """The feeds of ``n`` synthetic cases drawn with ``seed`` of ``graph`` (a
    :class:`radaredge.models.spec.GraphSpec`; default the card's model's only graph)."""
    if graph is None:
        graph = model_spec(card).graph()
    return [feeds for _, feeds in graph.make_cases(card, n, seed)]


def recorded_scan_paths(directory: str | os.PathLike, fmt: str | None = None) -> list[Path]:
    """The scan files of a recording, in frame order (:func:`radaredge.data.sequences.frame_order`):
    those directly in ``directory``, else
    those in ``directory``/scans. Scan files are .npy and .bin, or only ``fmt``'s suffix when it
    is given. InputError when there are none."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(
            f"calibration: {directory} is not a directory; expected one holding a recording's "
            f"scan files (.npy or .bin, one per frame) or a drive with scans/"
        )
    if fmt is not None and fmt not in FILE_SUFFIX:
        raise ConfigError(f"calibration format {fmt!r}: expected one of {list(FILE_SUFFIX)}")
    suffixes = {FILE_SUFFIX[fmt]} if fmt else set(FILE_SUFFIX.values())
    for folder in (directory, directory / "scans"):
        if folder.is_dir():
            paths = frame_order((p for p in folder.iterdir() if p.suffix in suffixes and p.is_file()), folder)
            if paths:
                return paths
    kinds = " or ".join(sorted(suffixes))
    raise InputError(f"calibration: no {kinds} scan files in {directory} or {directory / 'scans'}")


def recording_format(paths: list[Path], fmt: str | None = None) -> str:
    """The scan format of the recording's files ``paths`` (:func:`recorded_scan_paths`):
    ``fmt`` when given, else inferred (:func:`radaredge.data.readers.scan_format`)."""
    return scan_format(paths, fmt, "calibration", "radaredge export: --calibration-format")


def check_recording(
    directory: str | os.PathLike, k: int, n: int, fmt: str | None = None
) -> tuple[list[Path], str, np.ndarray]:
    """The recording's scan files, their format and the first-frame indices of its ``n``
    calibration windows of ``k`` frames (:func:`window_starts`), before any scan is read, so
    that a wrong directory fails before an export. InputError / ConfigError as those say."""
    paths = recorded_scan_paths(directory, fmt)
    fmt = recording_format(paths, fmt)
    return paths, fmt, window_starts(len(paths), k, n)


def window_starts(num_scans: int, k: int, n: int) -> np.ndarray:
    """First-frame indices of ``n`` windows of ``k`` consecutive scans spread evenly over
    ``num_scans`` scans, the first and (for ``n`` >= 2) the last window included; every window
    when there are at most ``n``. InputError when there are fewer than ``k`` scans."""
    if n < 1:
        raise ConfigError(f"calibration needs at least one window, got {n}")
    if num_scans < k:
        raise InputError(
            f"calibration: the recording holds {num_scans} scan(s) but one window of this model "
            f"takes {k} consecutive frames"
        )
    last = num_scans - k
    if last + 1 <= n:
        return np.arange(last + 1)
    return np.unique(np.round(np.linspace(0, last, n)).astype(np.int64))


def recorded_feeds(
    model: FrameFeeds, directory: str | os.PathLike, n: int, fmt: str | None = None
) -> tuple[list[dict[str, np.ndarray]], dict]:
    """Input feeds of ``n`` windows (:func:`window_starts`) of the recording in ``directory``,
    built by ``model`` (a graph's :class:`radaredge.runtime.FrameFeeds`, or a loaded
    :class:`radaredge.runtime.RadarModel`) in its feature columns and checked like any runtime
    input, plus a description for
    the int8 graph's metadata (directory, format, scans, windows). InputError names the file
    whose scan cannot be read or fed."""
    paths, fmt, starts = check_recording(directory, model.frames, n, fmt)
    feeds = []
    for s in starts:
        window = paths[s : s + model.frames]
        try:
            feeds.append(model.feeds([read_scan(p, model.features, fmt) for p in window]))
        except InputError as exc:
            raise InputError(f"calibration window {', '.join(p.name for p in window)}: {exc}") from exc
    return feeds, {
        "data": "recorded",
        "directory": str(directory),
        "format": fmt,
        "scans": len(paths),
        "windows": len(feeds),
    }
