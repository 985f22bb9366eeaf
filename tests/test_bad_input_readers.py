"""The bad-input catalogue of the file readers, by class: every reader radaredge hands a user's
file to, crossed with every way a file goes bad, so that a new reader added to READERS inherits
every class at once.

Readers (each read as the verbs read it): a camera image's header (image_2 PNG/JPEG), a
labelled set's scan (.bin), a drive's scan (.npy), a KITTI label file, a KITTI calibration file,
an ImageSets split, a model card (YAML), a checkpoint (.pth), a drive's gps.csv.

Corruptions: empty (0 bytes), truncated (the good file cut short), huge (a sparse file of 5 GiB
made with truncate(), which costs no disk: the reader must refuse it from its stat, not read
it), garbage (random bytes), a directory where the file belongs, and a NaN (or, where the file
holds no floats, an impossible number: a 0 x 0 image, a frame id that names no frame); and a few
classes of one reader (coordinates too far, a frame listed twice).

The promise, as tests/test_bad_input.py states it: through the library one RadarEdgeError with a
one-line message naming the file; on the command line exit code 2, exactly one ``error:`` line,
no traceback, and no file left behind. Every case runs under a memory limit (1 GiB more data
than at its start) and within MAX_SECONDS, so a reader that reads a huge file fails here rather
than on a user's machine. A label file that is empty is a frame without objects (the KITTI
convention), and reads; the command line refuses to train on a split where every label file is.
"""

from __future__ import annotations

import contextlib
import resource
import shutil
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch
from conftest import MAFFNET_TINY_CARD, assert_one_error_line, files_under, invoke

from radaredge.cards import load_card
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.data.kitti_detection import VOD, DetectionSet, read_calibration, read_labels
from radaredge.data.sequences import load_sequence, write_sequence
from radaredge.errors import RadarEdgeError
from radaredge.models.checkpoints import read_checkpoint

FEATURES_VOD = ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"]
FEATURES_DRIVE = ["x", "y", "z", "v_r", "rcs"]
HUGE = 5 * 2**30  # bytes of every "huge" file: sparse, so it costs no disk
GARBAGE = 146 * 28  # bytes of random garbage: whole View-of-Delft rows, so the size alone passes
MAX_SECONDS = 10.0
MEMORY_HEADROOM = 2**30  # bytes of data a case may allocate beyond what the process held at its start

JPEG = (
    b"\xff\xd8"
    + b"\xff\xe0\x00\x04ab"
    + b"\xff\xc0\x00\x11\x08"
    + (960).to_bytes(2, "big")
    + (1280).to_bytes(2, "big")
    + b"\x03"
    + b"\x00" * 9
)


def png(width: int, height: int) -> bytes:
    return b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\rIHDR" + struct.pack(">II", width, height) + b"\x08\x02\x00\x00\x00"


# ----------------------------------------------------------------------------- resource guard


def _data_bytes() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmData:"))


@contextlib.contextmanager
def bounded():
    """At most MEMORY_HEADROOM more data (RLIMIT_DATA: an attempt to read a huge file is a
    MemoryError, not a machine that swaps) and MAX_SECONDS while active."""
    soft, hard = resource.getrlimit(resource.RLIMIT_DATA)
    limit = _data_bytes() + MEMORY_HEADROOM
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_DATA, (limit, hard))
    start = time.perf_counter()
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_DATA, (soft, hard))
    seconds = time.perf_counter() - start
    assert seconds < MAX_SECONDS, f"took {seconds:.1f} s"


# ----------------------------------------------------------------------------- the readers


@pytest.fixture(scope="module")
def kitti(tmp_path_factory) -> Path:
    """A small labelled View-of-Delft-layout set (3 drives of 2 frames: train 2 drives, val 1)."""
    out = tmp_path_factory.mktemp("kitti") / "set"
    make_detection_benchmark(out, drives=3, frames=2, seed=1)
    return out / "radar"


def _set_copy(kitti: Path, tmp: Path) -> tuple[Path, str]:
    root = tmp / "set"
    shutil.copytree(kitti, root)
    return root, (root / "ImageSets" / "val.txt").read_text().split()[0]


def _drive(tmp: Path) -> Path:
    rng = np.random.default_rng(0)
    scans = [(rng.normal(size=(20, 5)) * 5).astype(np.float32) for _ in range(3)]
    return write_sequence(tmp / "drive", scans, [0.0, 0.1, 0.2], np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]))


def _edit_bin(path: Path, row: int, col: int, value: float) -> None:
    table = np.fromfile(path, "<f4").reshape(-1, 7)
    table[row, col] = value
    table.tofile(path)


def _edit_npy(path: Path, row: int, col: int, value: float) -> None:
    table = np.load(path)
    table[row, col] = value
    np.save(path, table)


def _replace_field(path: Path, line: int, field_index: int, value: str) -> None:
    lines = path.read_text().splitlines()
    fields = lines[line].split()
    fields[field_index] = value
    lines[line] = " ".join(fields)
    path.write_text("\n".join(lines) + "\n")


@dataclass
class Reader:
    """One reader: ``setup(kitti, tmp)`` writes good inputs and returns (the file to break, a
    call that reads it as radaredge's verbs do); ``cut`` the good file's bytes cut short;
    ``nan`` writes a NaN (or an impossible number) into the file; ``named`` what the message
    shows of the file; ``accepts`` the corruptions this reader reads by design; ``extra`` its
    own classes."""

    setup: Callable
    cut: Callable[[bytes], bytes]
    nan: Callable[[Path], None]
    named: Callable[[Path], str] = str
    accepts: frozenset = frozenset()
    extra: dict = field(default_factory=dict)


def _image(kitti, tmp):
    root, fid = _set_copy(kitti, tmp)
    (root / "training" / "image_2").mkdir()
    path = root / "training" / "image_2" / f"{fid}.jpg"
    path.write_bytes(JPEG)
    return path, lambda: DetectionSet(root, "val", VOD).image_size(fid)


def _labelled_scan(kitti, tmp):
    root, fid = _set_copy(kitti, tmp)
    return root / "training" / "velodyne" / f"{fid}.bin", lambda: DetectionSet(root, "val", VOD).frame(0, FEATURES_VOD)


def _drive_scan(kitti, tmp):
    drive = _drive(tmp)
    return drive / "scans" / "000001.npy", lambda: load_sequence(drive).scan(1, FEATURES_DRIVE)


def _labels(kitti, tmp):
    root, fid = _set_copy(kitti, tmp)
    path = root / "training" / "label_2" / f"{fid}.txt"
    return path, lambda: DetectionSet(root, "val", VOD).frame(0, FEATURES_VOD).labels


def _calibration(kitti, tmp):
    root, fid = _set_copy(kitti, tmp)
    path = root / "training" / "calib" / f"{fid}.txt"
    return path, lambda: DetectionSet(root, "val", VOD).frame(0, FEATURES_VOD).calib


def _split(kitti, tmp):
    root, _ = _set_copy(kitti, tmp)
    return root / "ImageSets" / "val.txt", lambda: DetectionSet(root, "val", VOD)


def _card(kitti, tmp):
    path = tmp / "card.yaml"
    shutil.copy(MAFFNET_TINY_CARD, path)
    return path, lambda: load_card(path)


def _checkpoint(kitti, tmp):
    path = tmp / "weights.pth"
    torch.save({"w": torch.ones(4), "b": torch.zeros(2)}, path)
    return path, lambda: read_checkpoint(path)


def _gps(kitti, tmp):
    drive = _drive(tmp)
    return drive / "gps.csv", lambda: load_sequence(drive)


def _split_twice(path: Path) -> None:
    ids = path.read_text().split()
    path.write_text("\n".join(ids + [ids[0]]) + "\n")


READERS = {
    "image-header": Reader(_image, lambda b: b[:14], lambda p: p.write_bytes(png(0, 0))),
    "scan-bin-in-a-set": Reader(
        _labelled_scan,
        lambda b: b[:-5],
        lambda p: _edit_bin(p, 3, 4, np.nan),
        extra={
            "far-coordinate": lambda p: _edit_bin(p, 3, 0, 1e30),
            "float32-overflow": lambda p: _edit_bin(p, 2, 1, 3e38),
            "infinite": lambda p: _edit_bin(p, 1, 2, -np.inf),
        },
    ),
    "scan-npy-in-a-drive": Reader(
        _drive_scan,
        lambda b: b[:-7],
        lambda p: _edit_npy(p, 2, 3, np.nan),
        extra={"far-coordinate": lambda p: _edit_npy(p, 4, 1, -1e30)},
    ),
    "label-txt": Reader(
        _labels,
        lambda b: b[: b.index(b"\n") // 2],
        lambda p: _replace_field(p, 0, 11, "nan"),
        accepts=frozenset({"empty"}),
    ),
    "calib-txt": Reader(_calibration, lambda b: b[:30], lambda p: _replace_field(p, 5, 1, "nan")),
    "imagesets-split": Reader(
        _split, lambda b: b[:3], lambda p: p.write_text("nan\n"), extra={"frame-twice": _split_twice}
    ),
    "card-yaml": Reader(
        _card, lambda b: b[:150], lambda p: p.write_text(p.read_text() + "frame_rate: .nan\n"), named=lambda p: p.name
    ),
    "checkpoint-pth": Reader(
        _checkpoint,
        lambda b: b[:200],
        lambda p: torch.save({"w": torch.full((4,), float("nan")), "b": torch.zeros(2)}, p),
    ),
    "gps-csv": Reader(
        _gps, lambda b: b[:-9], lambda p: p.write_text(p.read_text().replace("\n0.1,1.0,", "\n0.1,nan,"))
    ),
}


def _empty(path: Path, reader: Reader) -> None:
    path.write_bytes(b"")


def _truncated(path: Path, reader: Reader) -> None:
    path.write_bytes(reader.cut(path.read_bytes()))


def _huge(path: Path, reader: Reader) -> None:
    with open(path, "r+b") as f:  # the good file's head, then a hole: 5 GiB that occupy no disk
        f.truncate(HUGE)


def _garbage(path: Path, reader: Reader) -> None:
    path.write_bytes(np.random.default_rng(7).bytes(GARBAGE))


def _directory(path: Path, reader: Reader) -> None:
    path.unlink()
    path.mkdir()


def _nan(path: Path, reader: Reader) -> None:
    reader.nan(path)


CORRUPTIONS = {
    "empty": _empty,
    "truncated": _truncated,
    "huge": _huge,
    "garbage": _garbage,
    "directory": _directory,
    "nan": _nan,
}
CASES = [(r, c) for r in READERS for c in CORRUPTIONS] + [(r, c) for r, reader in READERS.items() for c in reader.extra]


@pytest.mark.parametrize("reader_name, corruption", CASES, ids=[f"{r}-{c}" for r, c in CASES])
def test_every_reader_refuses_every_corruption_naming_the_file(kitti, tmp_path, reader_name, corruption):
    reader = READERS[reader_name]
    path, read = reader.setup(kitti, tmp_path)
    read()  # the good file reads
    if corruption in CORRUPTIONS:
        CORRUPTIONS[corruption](path, reader)
    else:
        reader.extra[corruption](path)
    with bounded():
        if corruption in reader.accepts:
            assert len(read()) == 0  # an empty label file: a frame without objects
            return
        with pytest.raises(RadarEdgeError) as err:
            read()
    message = str(err.value)
    assert "\n" not in message, message
    assert reader.named(path) in message, f"{reader.named(path)} not in {message!r}"


# ----------------------------------------------------------------------------- what each refusal says


def test_a_split_that_lists_a_frame_twice_names_both_lines(kitti, tmp_path):
    root, fid = _set_copy(kitti, tmp_path)
    split = root / "ImageSets" / "val.txt"
    ids = split.read_text().split()
    split.write_text("\n".join(ids + [ids[0]]) + "\n")
    with pytest.raises(
        RadarEdgeError,
        match=rf"val.txt:{len(ids) + 1}: frame {fid} is listed again \(first on "
        rf"line 1\)",
    ):
        DetectionSet(root, "val", VOD)


@pytest.mark.parametrize("cut", range(JPEG.index(b"\xff\xc0") + 9))  # every cut before the frame header's width ends
def test_a_jpeg_cut_anywhere_before_its_size_is_one_error(kitti, tmp_path, cut):
    path, read = _image(kitti, tmp_path)
    path.write_bytes(JPEG[:cut])
    with pytest.raises(RadarEdgeError, match="not a readable PNG or JPEG header"):
        read()


@pytest.mark.parametrize("filler", [b"\xff\xd0", b"\xff" * 4096 + b"\xd0", b"\xff\xe0\x00\x02"])
def test_a_jpeg_without_a_frame_header_is_searched_within_bounds(kitti, tmp_path, filler):
    """Markers without a length, runs of fill bytes, empty segments: the search for the frame
    header stops after a bounded number of segments and bytes."""
    path, read = _image(kitti, tmp_path)
    path.write_bytes(b"\xff\xd8" + filler * (4 * 2**20 // len(filler)))
    with bounded(), pytest.raises(RadarEdgeError, match="not a readable PNG or JPEG header"):
        read()


@pytest.mark.parametrize("width, height", [(0, 0), (1936, 0), (0, 1216), (70000, 1216), (2**32 - 1, 2**32 - 1)])
def test_an_image_header_with_an_impossible_size_is_refused(kitti, tmp_path, width, height):
    path, read = _image(kitti, tmp_path)
    path.write_bytes(png(width, height))
    with pytest.raises(RadarEdgeError, match=rf"{width} x {height} px image; a camera image is 1 to 65535 px"):
        read()


def test_the_bounds_are_named_in_the_messages(kitti, tmp_path):
    """Each huge file's message says the bound and why it is one."""
    expect = {
        "label-txt": "a frame holds at most a few thousand objects",
        "checkpoint-pth": "2,147,483,648 bytes at most",
        "imagesets-split": "one frame id a line",
        "scan-bin-in-a-set": "the most a card's max_points_per_frame can take",
        "gps-csv": "one row of about 50 bytes a scan",
        "card-yaml": "a model card is at most 262144 bytes",
    }
    for name, says in expect.items():
        (tmp_path / name).mkdir()
        path, read = READERS[name].setup(kitti, tmp_path / name)
        _huge(path, READERS[name])
        with bounded(), pytest.raises(RadarEdgeError, match=says):
            read()


def test_far_points_are_left_to_the_card_but_no_measurement_is_read(kitti, tmp_path):
    """A point beyond the card's range but within radar reach reads (the graph leaves it out); a
    coordinate of 1e30 m is refused with the file, the point and the column."""
    path, read = _labelled_scan(kitti, tmp_path)
    _edit_bin(path, 3, 0, 900.0)
    assert read().points[3, 0] == 900.0
    _edit_bin(path, 3, 0, 1e30)
    with pytest.raises(RadarEdgeError, match=r"velodyne/\d+\.bin: point 3, column 'x' is 1e\+30 m"):
        read()


def test_an_empty_label_file_is_a_frame_without_objects(kitti, tmp_path):
    path, _ = _labels(kitti, tmp_path)
    path.write_text("")
    assert len(read_labels(path, VOD.label_classes)) == 0


def test_a_calibration_of_nan_names_the_line(kitti, tmp_path):
    path, _ = _calibration(kitti, tmp_path)
    _replace_field(path, 5, 1, "nan")
    with pytest.raises(RadarEdgeError, match=r":6: Tr_velo_to_cam must hold 12 finite numbers"):
        read_calibration(path)


def test_a_checkpoint_that_is_not_a_zip_or_pickle_is_refused_before_torch_reads_it(tmp_path, monkeypatch):
    path = tmp_path / "w.pth"
    path.write_bytes(b"GGUF" + bytes(100))
    monkeypatch.setattr(torch, "load", lambda *a, **k: pytest.fail("torch.load ran"))
    with pytest.raises(RadarEdgeError, match=r"begins with bytes b'GGUF', not the zip archive"):
        read_checkpoint(path)


# ----------------------------------------------------------------------------- the command line


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return work


def _all_labels_empty(root: Path) -> None:
    for label in (root / "training" / "label_2").iterdir():
        label.write_text("")


def _cli_case(case: str, root: Path, fid: str, tmp: Path) -> tuple[list[str], str]:
    """(extra train arguments, expected text of the error line) after breaking ``root`` for ``case``."""
    images = root / "training" / "image_2"
    images.mkdir(exist_ok=True)
    scan, label = root / "training" / "velodyne" / f"{fid}.bin", root / "training" / "label_2" / f"{fid}.txt"
    if case == "truncated-jpeg":
        (images / f"{fid}.jpg").write_bytes(JPEG[:12])
        return [], f"image_2/{fid}.jpg: not a readable PNG or JPEG header"
    if case == "zero-png":
        (images / f"{fid}.png").write_bytes(png(0, 0))
        return [], f"image_2/{fid}.png: its header gives a 0 x 0 px image"
    if case == "empty-scan":
        scan.write_bytes(b"")
        return [], f"velodyne/{fid}.bin: an empty scan (0 bytes)"
    if case == "far-scan":
        _edit_bin(scan, 2, 0, 1e30)
        return [], f"velodyne/{fid}.bin: point 2, column 'x' is 1e+30 m"
    if case == "overflowing-scan":
        _edit_bin(scan, 2, 2, -3e38)
        return [], f"velodyne/{fid}.bin: point 2, column 'z' is -3e+38 m"
    if case == "nan-scan":
        _edit_bin(scan, 2, 4, np.nan)
        return [], f"velodyne/{fid}.bin: non-finite value nan at point 2, column 'v_r'"
    if case == "huge-label":
        with open(label, "r+b") as f:
            f.truncate(HUGE)
        return [], f"label_2/{fid}.txt: {HUGE:,} bytes, more than a KITTI label file can hold"
    if case == "frame-twice":
        split = root / "ImageSets" / "train.txt"
        split.write_text(split.read_text() + f"{fid}\n")
        return [], f"train.txt:{len(split.read_text().split())}: frame {fid} is listed again (first on line 1)"
    if case == "no-labelled-object":
        _all_labels_empty(root)
        return (
            [],
            "train.txt: none of the 4 training frames read has a labelled object of the card's classes "
            "['Car', 'Pedestrian', 'Cyclist']",
        )
    if case == "other-classes-only":
        for path in (root / "training" / "label_2").iterdir():
            path.write_text(
                "".join(
                    line.replace("Car ", "truck ", 1)
                    .replace("Pedestrian ", "truck ", 1)
                    .replace("Cyclist ", "truck ", 1)
                    + "\n"
                    for line in path.read_text().splitlines()
                )
            )
        return [], "their labels name only ['truck']"
    if case == "huge-checkpoint":
        ckpt = tmp / "huge.pth"
        with open(ckpt, "wb") as f:
            f.write(b"PK\x03\x04")
            f.truncate(HUGE)
        return ["--checkpoint", str(ckpt)], f"{ckpt}: {HUGE:,} bytes, more than a torch checkpoint"
    if case == "garbage-checkpoint":
        ckpt = tmp / "garbage.pth"
        ckpt.write_bytes(np.random.default_rng(3).bytes(5000).replace(b"\x80", b"\x00").replace(b"PK", b"pk"))
        return ["--checkpoint", str(ckpt)], f"checkpoint {ckpt} is not a readable torch checkpoint"
    if case == "huge-card":
        card = tmp / "card.yaml"
        shutil.copy(MAFFNET_TINY_CARD, card)
        with open(card, "r+b") as f:
            f.truncate(4 * 2**30)
        return ["--config", str(card)], "card.yaml: 4294967296 bytes; a model card is at most 262144 bytes"
    raise AssertionError(case)


CLI_CASES = [
    "truncated-jpeg",
    "zero-png",
    "empty-scan",
    "far-scan",
    "overflowing-scan",
    "nan-scan",
    "huge-label",
    "frame-twice",
    "no-labelled-object",
    "other-classes-only",
    "huge-checkpoint",
    "garbage-checkpoint",
    "huge-card",
]


@pytest.mark.parametrize("case", CLI_CASES)
def test_train_on_a_broken_set_is_one_error_line(kitti, tmp_path, workdir, case):
    root, _ = _set_copy(kitti, tmp_path)
    fid = (root / "ImageSets" / "train.txt").read_text().split()[0]
    extra, expect = _cli_case(case, root, fid, tmp_path)
    if "--config" not in extra:
        extra += ["--config", str(MAFFNET_TINY_CARD)]
    before = files_under(workdir)
    with bounded():
        res = invoke("train", "--model", "maffnet-tiny", "--data", root, "--epochs", "1", "--output", "run", *extra)
    assert_one_error_line(res, workdir, before, expect)
