"""Labelled 3D-detection sets in the KITTI layout that View-of-Delft and TJ4DRadSet use.

Layout (both datasets; ROOT is what ``--data`` names)::

    ROOT/ImageSets/{train,val,test}.txt     one frame id per line ("00042"); optional (below)
    ROOT/training/velodyne/<id>.bin         the radar scan (VoD: 7 float32 columns, TJ4D: 8)
    ROOT/training/label_2/<id>.txt          KITTI labels in the camera frame (VoD's example_set: <id>.json, below)
    ROOT/training/calib/<id>.txt            P2 (camera intrinsics), R0_rect, Tr_velo_to_cam (radar -> camera)
    ROOT/training/image_2/<id>.{jpg,png}    optional: only its size is read from its header (the 2D-box clip)

For View-of-Delft ROOT is ``radar/``, ``radar_3frames/`` or ``radar_5frames/`` (the devkit's
docs name them ``radar_3_scans/`` and ``radar_5_scans/``: both names are read); the dataset's
top folder works too and the card's ``input.scans_accumulated`` picks the subfolder. When the
top folder lacks that subfolder (VoD's published ``example_set/`` holds ``radar/`` only), the
folder of the nearest scan count is read and that is said (:func:`resolve_root`).

What is read without being asked is said once (the ``notes`` of :func:`list_frames`, each a
``warnings.warn`` from :class:`DetectionSet`): a folder whose scans a frame differ from the card's
``input.scans_accumulated``; a VoD time column in seconds rather than the devkit's scan index
(0 the current scan, -1 the one before, ...); no ``ImageSets/`` (TJ4DRadSet's published ``Sample/``): the split is
every frame of ``training/velodyne`` with a label, and how many; frames without an ``image_2``
file: the image size is the card's ``input.image_size`` or the dataset's camera.

VoD's annotation-tool JSON (``example_set/radar/training/label_2/<id>.json``, a list of objects
with ``className``, ``geometry`` {``center``, ``size`` {height, width, length}, ``quaternion``
{x, y, z, w}} and ``attributes``) is read into the KITTI labels the ``.txt`` files hold
(:func:`read_vod_json_labels`; on the example_set's 3 frames, 62 objects, it gives the
``lidar/training/label_2/*.txt`` labels to 1e-6 m).

Labels (VoD docs/ANNOTATION.md, KITTI devkit readme): one object a line, 15 fields (16 with a
score): class, truncated (VoD: unused, or a track id), occluded (0-2), alpha, 2D box left, top,
right, bottom (px), height, width, length (m), x, y, z (m, camera frame: the box's bottom
centre), rotation_y (rad). Into the radar frame as the devkits and OpenPCDet do it: centre =
the radar point of the bottom centre raised by h / 2, size (l, w, h), heading -(rotation_y +
pi / 2) (VoD defines rotation_y about the LiDAR's -Z axis). Radar frame: x forward, y left,
z up; metres, radians.

Every malformed file ends in an :class:`~radaredge.errors.InputError` naming the file and line.
Every file is bounded by its size (from its stat) before it is read: a label file at most
:data:`MAX_LABEL_BYTES`, a calibration :data:`MAX_CALIB_BYTES`, a split :data:`MAX_SPLIT_BYTES`,
an image :data:`MAX_IMAGE_BYTES` (only its header is read), a scan as
:mod:`radaredge.data.readers` bounds it. A frame's scan must hold points, all finite, with x, y,
z within :data:`radaredge.data.readers.MAX_COORDINATE` m (points outside the card's
point_cloud_range are left out later, as the graph does); a split lists each frame once.
"""

from __future__ import annotations

import json
import os
import re
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .readers import check_file, check_points, read_bounded, read_scan

DONT_CARE = "DontCare"

# Bounds on the files of a set, checked from their stat before they are read.
MAX_LABEL_BYTES = 4 * 2**20  # KITTI labels: one line of ~100-400 bytes an object, a frame a few thousand at most
MAX_CALIB_BYTES = 64 * 2**10  # KITTI calibration: 7 lines, about 1 KB
MAX_SPLIT_BYTES = 16 * 2**20  # ImageSets: one frame id a line (VoD: 8,693 frames; a million ids fit)
MAX_IMAGE_BYTES = 256 * 2**20  # a camera frame, even an uncompressed 8K 16-bit PNG (200 MB)
MAX_IMAGE_SIDE = 65535  # px: a JPEG's largest; a camera image is far smaller
_JPEG_HEADER_SPAN = 16 * 2**20  # bytes of JPEG segments searched for the frame header (EXIF APP1 <= 64 KiB each)
_JPEG_HEADER_SEGMENTS = 1024  # segments before it (a camera JPEG has a dozen) ...
_JPEG_FILL_BYTES = 64  # ... and 0xFF fill bytes before one marker


@dataclass(frozen=True)
class EvalClass:
    """One evaluated class: its label name, the minimum 3D / BEV IoU of a true positive, the
    minimum 2D-box IoU (the image metric and AOS), and the label names that count as neither hit
    nor miss for it (the devkits' "neighbouring" classes)."""

    name: str
    min_iou: float
    min_iou_image: float
    neighbours: tuple[str, ...] = ()


@dataclass(frozen=True)
class DetectionLayout:
    """What differs between the KITTI-style radar datasets: scan format, label classes, the
    evaluated classes with their IoU thresholds, the default camera image size and whether the
    driving-corridor area is evaluated."""

    name: str
    scan_format: str
    label_classes: tuple[str, ...]
    eval_classes: tuple[EvalClass, ...]
    image_size: tuple[int, int]  # (width, height) px, when no image_2 file is present
    corridor: bool
    accumulated_dirs: dict[int, str] = field(default_factory=dict)  # scans a frame -> its folder
    accumulated_aliases: dict[int, tuple[str, ...]] = field(default_factory=dict)  # other names of that folder
    title: str = ""

    def scan_folders(self) -> dict[int, tuple[str, ...]]:
        """Scans a frame -> every name of the folder holding such frames (the primary first)."""
        return {n: (d, *self.accumulated_aliases.get(n, ())) for n, d in self.accumulated_dirs.items()}

    def eval_class(self, name: str) -> EvalClass:
        for c in self.eval_classes:
            if c.name.lower() == name.lower():
                return c
        raise InputError(
            f"{self.name} has no evaluated class {name!r}; it evaluates {[c.name for c in self.eval_classes]}"
        )


# View-of-Delft: 13 annotated classes (docs/ANNOTATION.md), DontCare, and KITTI's Van /
# Person_sitting that the devkit's evaluation knows as neighbours of Car / Pedestrian.
VOD = DetectionLayout(
    "vod",
    "vod",
    (
        "Car",
        "Pedestrian",
        "Cyclist",
        "rider",
        "bicycle",
        "bicycle_rack",
        "human_depiction",
        "moped_scooter",
        "motor",
        "ride_other",
        "ride_uncertain",
        "truck",
        "vehicle_other",
        "Van",
        "Person_sitting",
        DONT_CARE,
    ),
    (
        EvalClass("Car", 0.5, 0.7, ("Van",)),
        EvalClass("Pedestrian", 0.25, 0.5, ("Person_sitting",)),
        EvalClass("Cyclist", 0.25, 0.5),
    ),
    (1936, 1216),
    True,
    {1: "radar", 3: "radar_3frames", 5: "radar_5frames"},
    {3: ("radar_3_scans",), 5: ("radar_5_scans",)},
    "View-of-Delft",
)  # the devkit's docs/GETTING_STARTED.md names

# TJ4DRadSet as TRV-Lab/MAFF-Net evaluates it (pcdet/datasets/TJ4DRadSet): Car, Pedestrian,
# Cyclist, Truck at 0.5 / 0.25 / 0.25 / 0.5, the entire annotated area only.
TJ4D = DetectionLayout(
    "tj4d",
    "tj4d",
    ("Car", "Pedestrian", "Cyclist", "Truck", "Other", "Bus", "Motorcycle", "Van", "Person_sitting", DONT_CARE),
    (
        EvalClass("Car", 0.5, 0.7, ("Van",)),
        EvalClass("Pedestrian", 0.25, 0.5, ("Person_sitting",)),
        EvalClass("Cyclist", 0.25, 0.5),
        EvalClass("Truck", 0.5, 0.7),
    ),
    (1280, 960),
    False,
    title="TJ4DRadSet",
)  # README: 'Car', 'Pedestrian', 'Cyclist', 'Truck', 'Other'

LAYOUTS = {"vod": VOD, "tj4d": TJ4D}


# ----------------------------------------------------------------------------- calibration


@dataclass(frozen=True)
class Calibration:
    """One frame's calibration: ``P2`` [3, 4] camera projection, ``R0`` [3, 3] rectification,
    ``V2C`` [3, 4] radar -> camera (``Tr_velo_to_cam``). Rect = R0 (V2C [p; 1])."""

    P2: np.ndarray
    R0: np.ndarray
    V2C: np.ndarray
    path: str = ""

    def radar_to_rect(self, xyz: np.ndarray) -> np.ndarray:
        """Radar-frame points [N, 3] (m) in the rectified camera frame [N, 3] (x right, y down, z forward)."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        return (xyz @ self.V2C[:, :3].T + self.V2C[:, 3]) @ self.R0.T

    def rect_to_radar(self, xyz: np.ndarray) -> np.ndarray:
        """Rectified camera points [N, 3] back in the radar frame [N, 3]."""
        ref = np.linalg.solve(self.R0, np.asarray(xyz, np.float64).reshape(-1, 3).T).T
        return np.linalg.solve(self.V2C[:, :3], (ref - self.V2C[:, 3]).T).T

    def rect_to_image(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [N, 2] (u right, v down) and depth [N] (m) of rectified points."""
        hom = np.column_stack([np.asarray(xyz, np.float64).reshape(-1, 3), np.ones(len(xyz))]) @ self.P2.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return hom[:, :2] / hom[:, 2:3], hom[:, 2] - self.P2[2, 3]


_CALIB_KEYS = {"P2": 12, "R0_rect": 9, "Tr_velo_to_cam": 12}


def read_calibration(path: str | os.PathLike) -> Calibration:
    """A KITTI calibration file's P2, R0_rect and Tr_velo_to_cam (other keys are ignored;
    a missing R0_rect is the identity). InputError naming the file and line for a missing key,
    a wrong number of values, a non-number, or a transform that cannot be inverted."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: calibration file missing (expected KITTI lines 'P2: ...', 'Tr_velo_to_cam: ...')")
    text = read_bounded(
        path, "a KITTI calibration file", MAX_CALIB_BYTES, "P2, R0_rect and Tr_velo_to_cam lines of about 1 KB in all"
    ).decode(errors="replace")
    found: dict[str, tuple[np.ndarray, int]] = {}
    for number, line in enumerate(text.splitlines(), 1):
        if ":" not in line:
            if line.strip():
                raise InputError(f"{path}:{number}: expected 'KEY: values', got {line.strip()[:60]!r}")
            continue
        key, values = line.split(":", 1)
        key = key.strip()
        if key not in _CALIB_KEYS:
            continue
        try:
            numbers = np.array([float(v) for v in values.split()], np.float64)
        except ValueError:
            raise InputError(f"{path}:{number}: {key} holds a value that is not a number") from None
        if numbers.size != _CALIB_KEYS[key] or not np.isfinite(numbers).all():
            raise InputError(f"{path}:{number}: {key} must hold {_CALIB_KEYS[key]} finite numbers, got {numbers.size}")
        found[key] = (numbers, number)
    for key in ("P2", "Tr_velo_to_cam"):
        if key not in found:
            raise InputError(
                f"{path}: no {key} line (KITTI calibration: P2 is the camera projection, "
                f"Tr_velo_to_cam the radar -> camera transform)"
            )
    r0, r0_line = found.get("R0_rect", (np.eye(3).ravel(), 0))
    calib = Calibration(
        found["P2"][0].reshape(3, 4), r0.reshape(3, 3), found["Tr_velo_to_cam"][0].reshape(3, 4), str(path)
    )
    for name, matrix, number in (
        ("Tr_velo_to_cam", calib.V2C[:, :3], found["Tr_velo_to_cam"][1]),
        ("R0_rect", calib.R0, r0_line),
    ):
        if abs(np.linalg.det(matrix)) < 1e-6:
            raise InputError(
                f"{path}:{number}: {name}'s 3 x 3 rotation part cannot be inverted (determinant "
                f"{np.linalg.det(matrix):.3g}); labels cannot be brought into the radar frame"
            )
    if abs(np.linalg.det(calib.P2[:, :3])) < 1e-9:
        raise InputError(f"{path}:{found['P2'][1]}: P2's 3 x 3 part cannot be inverted: not a camera projection")
    return calib


# ----------------------------------------------------------------------------- labels


@dataclass(frozen=True)
class Labels:
    """A frame's KITTI labels, the columns of the devkits' annotation dicts: ``name`` [M],
    ``truncated`` [M], ``occluded`` [M] int, ``alpha`` [M] rad, ``bbox`` [M, 4] px (left, top,
    right, bottom), ``dimensions`` [M, 3] m as (l, h, w), ``location`` [M, 3] m (camera frame,
    bottom centre), ``rotation_y`` [M] rad, ``score`` [M] (0 for ground truth)."""

    name: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray

    def __len__(self) -> int:
        return len(self.name)

    @staticmethod
    def empty() -> Labels:
        return Labels(
            np.zeros(0, dtype=object),
            np.zeros(0),
            np.zeros(0, np.int64),
            np.zeros(0),
            np.zeros((0, 4)),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros(0),
        )

    def select(self, keep: np.ndarray) -> Labels:
        return Labels(*(getattr(self, f)[keep] for f in Labels.__dataclass_fields__))

    def annotation(self) -> dict[str, np.ndarray]:
        """The devkits' annotation dict of these labels."""
        return {f: getattr(self, f) for f in Labels.__dataclass_fields__}


def read_labels(path: str | os.PathLike, classes: tuple[str, ...]) -> Labels:
    """A KITTI label file (15 fields a line, 16 with a score). InputError naming the file and
    line for a missing file, another field count, a non-number, a negative size, or a class not
    in ``classes``; and, from its stat before it is read, for a file over :data:`MAX_LABEL_BYTES`.
    An empty file is a frame without objects."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: label file missing (KITTI label_2: one object a line)")
    text = read_bounded(
        path,
        "a KITTI label file",
        MAX_LABEL_BYTES,
        "one line of about 100 bytes an object, and a frame holds at most a few thousand objects",
    ).decode(errors="replace")
    rows, names = [], []
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (15, 16):
            raise InputError(
                f"{path}:{number}: {len(fields)} fields; a KITTI label line has 15 (class, truncated, "
                f"occluded, alpha, 4 x bbox, h, w, l, x, y, z, rotation_y) or 16 (with a score)"
            )
        if fields[0] not in classes:
            raise InputError(
                f"{path}:{number}: unknown class {fields[0]!r}; this dataset's classes are {list(classes)}"
            )
        try:
            values = [float(v) for v in fields[1:]]
        except ValueError:
            raise InputError(f"{path}:{number}: a field after the class is not a number") from None
        if not np.isfinite(values).all():
            raise InputError(f"{path}:{number}: fields must be finite numbers")
        if fields[0] != DONT_CARE and min(values[7:10]) < 0:
            raise InputError(f"{path}:{number}: negative box size h, w, l = {values[7:10]}")
        names.append(fields[0])
        rows.append(values + [0.0] * (15 - len(values)))
    if not rows:
        return Labels.empty()
    v = np.array(rows, np.float64)
    return Labels(
        np.array(names, dtype=object),
        v[:, 0],
        v[:, 1].astype(np.int64),
        v[:, 2],
        v[:, 3:7],
        v[:, [9, 7, 8]],
        v[:, 10:13],
        v[:, 13],
        v[:, 14],
    )


def labels_to_radar_boxes(labels: Labels, calib: Calibration) -> np.ndarray:
    """OpenPCDet boxes [M, 7] (x, y, z centre, l, w, h, heading; radar frame) of the labels."""
    centre = calib.rect_to_radar(labels.location)
    length, h, w = labels.dimensions.T
    centre[:, 2] += h / 2
    return np.column_stack([centre, length, w, h, -(labels.rotation_y + np.pi / 2)]).reshape(-1, 7)


def camera_box_corners(location: np.ndarray, dims_lhw: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    """Corners [M, 8, 3] (rectified camera frame) of KITTI boxes: bottom centre ``location``,
    (l, h, w), rotation about the camera's y axis (pointing down)."""
    length, h, w = (dims_lhw[:, i : i + 1] for i in range(3))
    x = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * length / 2
    y = np.array([0, 0, 0, 0, -1, -1, -1, -1]) * h
    z = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * w / 2
    c, s = np.cos(rotation_y)[:, None], np.sin(rotation_y)[:, None]
    return np.stack([c * x + s * z, y, -s * x + c * z], -1) + location[:, None, :]


def radar_boxes_to_labels(
    boxes: np.ndarray, scores: np.ndarray, names: np.ndarray, calib: Calibration, image_size: tuple[int, int]
) -> Labels:
    """Detections (OpenPCDet boxes [M, 7] in the radar frame, scores [M], class names [M]) as
    KITTI labels in the camera frame, as OpenPCDet's ``generate_prediction_dicts`` writes them:
    bottom centre, (l, h, w), rotation_y = -heading - pi / 2, the 2D box of the projected
    corners clipped to the image (``image_size`` = width, height px), alpha = rotation_y -
    atan2 of the centre as seen from the radar."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    bottom = boxes[:, :3].copy()
    bottom[:, 2] -= boxes[:, 5] / 2
    location = calib.radar_to_rect(bottom)
    dims = boxes[:, [3, 5, 4]]
    rotation_y = -boxes[:, 6] - np.pi / 2
    corners = camera_box_corners(location, dims, rotation_y)
    uv, _ = calib.rect_to_image(corners.reshape(-1, 3))
    uv = uv.reshape(-1, 8, 2)
    width, height = image_size
    bbox = np.column_stack(
        [
            np.clip(uv[..., 0].min(1), 0, width - 1),
            np.clip(uv[..., 1].min(1), 0, height - 1),
            np.clip(uv[..., 0].max(1), 0, width - 1),
            np.clip(uv[..., 1].max(1), 0, height - 1),
        ]
    )
    alpha = -np.arctan2(-boxes[:, 1], boxes[:, 0]) + rotation_y
    n = len(boxes)
    return Labels(
        np.asarray(names, dtype=object).reshape(n),
        np.zeros(n),
        np.zeros(n, np.int64),
        alpha,
        bbox.reshape(n, 4),
        dims,
        location,
        rotation_y,
        np.asarray(scores, np.float64).reshape(n),
    )


# ----------------------------------------------------------------------------- VoD's annotation JSON


# The JSON's frame: VoD's example_set/radar/training/label_2/<id>.json gives box centres in the
# radar frame with y and z negated (x forward, y right, z down), whatever its "sensor" field says:
# with the radar calibration they reproduce lidar/training/label_2/<id>.txt exactly (3 frames, 62
# objects, 1e-6 m), with the LiDAR's they miss by 2.4 m.
_JSON_TO_RADAR = np.diag([1.0, -1.0, -1.0])
_JSON_RIDER_CLASS = {"bicycle": "Cyclist"}  # a bicycle with has_rider is the .txt's Cyclist


def _occlusion_level(text, where: str) -> int:
    """KITTI's occluded (0, 1, 2) of VoD's "spatial occlusion" percentage range: up to 10 % -> 0,
    up to 80 % -> 1, beyond -> 2 (0-10% -> 0, 10-40% and 41-80% -> 1, 80-100% -> 2, as the .txt)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*-\s*(\d+(?:\.\d+)?)\s*%\s*", str(text))
    if not m:
        raise InputError(
            f"{where}: attributes['spatial occlusion'] is {text!r}; expected a percentage range such as '10-40%'"
        )
    upper = float(m.group(2))
    return 0 if upper <= 10 else 1 if upper <= 80 else 2


def read_vod_json_labels(
    path: str | os.PathLike, calib: Calibration, image_size: tuple[int, int], classes: tuple[str, ...] = ()
) -> Labels:
    """View-of-Delft's annotation-tool JSON labels of one frame (a list of objects: ``className``,
    ``geometry`` {``center`` {x, y, z}, ``size`` {height, width, length}, ``quaternion`` {x, y, z,
    w}}, ``attributes``) as the KITTI labels its ``.txt`` files hold, in the camera frame of
    ``calib`` (the frame's radar calibration):

    - class: ``className`` matched to ``classes`` ignoring case (car -> Car, pedestrian ->
      Pedestrian); a ``bicycle`` with ``has_rider`` is a ``Cyclist``;
    - location: the bottom centre, centre + h / 2 along the JSON's z (down), in the radar frame as
      (x, -y, -z) (module note above), then through Tr_velo_to_cam; size (l, h, w) from length,
      height, width;
    - rotation_y = yaw - pi / 2, yaw = atan2(R[1, 0], R[0, 0]) of the quaternion's rotation;
      alpha = rotation_y - atan2(x, z) of the location, in [-pi, pi);
    - 2D box: the projected KITTI box corners, clipped to the image (``image_size``, width and
      height px), as the devkit computed the .txt's;
    - occluded from ``spatial occlusion`` (0-10% 0, up to 80% 1, else 2); truncated (unused by
      VoD) 1 for ``activity: moving``, else 0, as in the .txt; score 0.

    InputError naming the file and the object for anything else; the message points at the
    KITTI ``.txt`` labels of the same objects (VoD's ``lidar/training/label_2/``)."""
    path = Path(path)
    pointer = (
        "; the KITTI .txt labels of the same objects are in the dataset's lidar/training/label_2/ (copy "
        "them into this folder's label_2/)"
    )
    raw = read_bounded(
        path,
        "a View-of-Delft JSON label file",
        MAX_LABEL_BYTES,
        "a JSON object of about 700 bytes a box, a frame holds at most a few thousand",
    )
    try:
        objects = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not readable JSON ({str(exc)[:120]}){pointer}") from None
    if not isinstance(objects, list):
        raise InputError(f"{path}: expected a JSON list of annotated objects, got {type(objects).__name__}{pointer}")
    lower = {c.lower(): c for c in classes}
    names, centres, sizes, yaws, occluded, truncated = [], [], [], [], [], []
    for i, obj in enumerate(objects):
        where = f"{path}: object {i}"
        try:
            g = obj["geometry"]
            centre = [float(g["center"][k]) for k in "xyz"]
            height, width, length = (float(g["size"][k]) for k in ("height", "width", "length"))
            qx, qy, qz, qw = (float(g["quaternion"][k]) for k in "xyzw")
            cls = str(obj["className"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(
                f"{where}: expected className and geometry.center {{x, y, z}}, geometry.size "
                f"{{height, width, length}} and geometry.quaternion {{x, y, z, w}} numbers "
                f"({type(exc).__name__}: {exc}){pointer}"
            ) from None
        values = [*centre, height, width, length, qx, qy, qz, qw]
        if not np.isfinite(values).all() or min(height, width, length) < 0:
            raise InputError(f"{where}: geometry holds a value that is not finite, or a negative size{pointer}")
        norm = qx * qx + qy * qy + qz * qz + qw * qw
        if not 0.5 < norm < 2.0:
            raise InputError(f"{where}: geometry.quaternion has squared norm {norm:.3g}; a rotation's is 1{pointer}")
        attributes = obj.get("attributes") or {}
        if not isinstance(attributes, dict):
            raise InputError(f"{where}: attributes must be a JSON object{pointer}")
        name = _JSON_RIDER_CLASS.get(cls.lower()) if attributes.get("has_rider") is True else None
        name = name or lower.get(cls.lower(), cls if not classes else None)
        if name is None:
            raise InputError(f"{where}: unknown className {cls!r}; this dataset's classes are {list(classes)}{pointer}")
        names.append(name)
        centres.append(centre)
        sizes.append((length, width, height))
        # the rotation's x axis in the JSON frame: R[0, 0] and R[1, 0] of the quaternion over its
        # squared norm (exact for a quaternion that is not of unit length too)
        r00, r10 = (qw * qw + qx * qx - qy * qy - qz * qz) / norm, 2.0 * (qx * qy + qw * qz) / norm
        yaws.append(float(np.arctan2(r10, r00)))
        occluded.append(_occlusion_level(attributes.get("spatial occlusion", "0-10%"), where))
        truncated.append(1.0 if attributes.get("activity") == "moving" else 0.0)
    if not names:
        return Labels.empty()
    lwh = np.array(sizes, np.float64)
    radar_centre = np.array(centres, np.float64) @ _JSON_TO_RADAR.T
    yaw = np.array(yaws)
    boxes = np.column_stack([radar_centre, lwh, -yaw])  # heading -yaw: the y axis is negated
    labels = radar_boxes_to_labels(boxes, np.zeros(len(boxes)), np.array(names, dtype=object), calib, image_size)
    alpha = labels.rotation_y - np.arctan2(labels.location[:, 0], labels.location[:, 2])
    alpha = (alpha + np.pi) % (2 * np.pi) - np.pi
    return Labels(
        labels.name,
        np.array(truncated),
        np.array(occluded, np.int64),
        alpha,
        labels.bbox,
        labels.dimensions,
        labels.location,
        yaw - np.pi / 2,
        labels.score,
    )


def camera_fov_mask(xyz: np.ndarray, calib: Calibration, image_size: tuple[int, int]) -> np.ndarray:
    """Points [N, 3] (radar frame) that project inside the image with depth >= 0 (OpenPCDet's
    ``get_fov_flag``, what ``FOV_POINTS_ONLY`` keeps)."""
    uv, depth = calib.rect_to_image(calib.radar_to_rect(xyz))
    width, height = image_size
    return (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height) & (depth >= 0)


# ----------------------------------------------------------------------------- the set


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) px of a PNG or JPEG from its header (a PNG's IHDR chunk, a JPEG's start of
    frame); None when the file is neither, or its header is cut short or damaged. Reads the
    header only: at most 1024 JPEG segments within the first 16 MiB."""
    with open(path, "rb") as f:
        head = f.read(32)
        if head[:8] == _PNG_MAGIC:
            if len(head) < 24 or head[12:16] != b"IHDR":
                return None
            return struct.unpack(">II", head[16:24])
        if head[:2] != b"\xff\xd8":
            return None
        f.seek(2)
        for _ in range(_JPEG_HEADER_SEGMENTS):
            if f.tell() >= _JPEG_HEADER_SPAN:
                return None
            marker = f.read(2)
            for _ in range(_JPEG_FILL_BYTES):  # fill bytes before a marker
                if marker != b"\xff\xff":
                    break
                marker = b"\xff" + f.read(1)
            if len(marker) < 2 or marker[0] != 0xFF or marker[1] == 0xFF:
                return None
            kind = marker[1]
            if kind in (0xD9, 0xDA):  # end of image, or scan data, before any frame header
                return None
            if 0xD0 <= kind <= 0xD8 or kind == 0x01:  # markers without a length (RSTn, SOI, TEM)
                continue
            length = f.read(2)
            if len(length) < 2:
                return None
            size = struct.unpack(">H", length)[0]
            if size < 2:  # a segment's length counts its own two bytes
                return None
            if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):  # a start of frame
                body = f.read(5)
                if len(body) < 5:
                    return None
                _, h, w = struct.unpack(">BHH", body)
                return w, h
            f.seek(size - 2, 1)
    return None


def read_image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) px of the PNG or JPEG ``path`` (:func:`image_size`); InputError naming
    the file when it is missing, a directory, over :data:`MAX_IMAGE_BYTES`, not a readable PNG
    or JPEG header, or gives a side of 0 or over :data:`MAX_IMAGE_SIDE` px."""
    path = Path(path)
    check_file(
        path,
        "a PNG or JPEG camera image",
        MAX_IMAGE_BYTES,
        "a camera frame, even an uncompressed 8K PNG, is smaller; only its header is read",
    )
    try:
        size = image_size(path)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the image ({exc.strerror or type(exc).__name__})") from None
    if size is None:
        raise InputError(
            f"{path}: not a readable PNG or JPEG header (damaged or cut short?); only the image's size is read from it"
        )
    width, height = (int(v) for v in size)
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise InputError(
            f"{path}: its header gives a {width} x {height} px image; a camera image is 1 to "
            f"{MAX_IMAGE_SIDE} px a side (its size clips the 2D boxes and the camera-view crop)"
        )
    return width, height


@dataclass(frozen=True)
class DetectionFrame:
    """One labelled frame: id, radar points [N, F] (the card's features), labels, calibration,
    the camera image size (width, height px) and where that size came from."""

    frame_id: str
    points: np.ndarray
    labels: Labels
    calib: Calibration
    image_size: tuple[int, int]


_FRAME_ID = re.compile(r"[0-9A-Za-z_-]+")
_IMAGE_SUFFIXES = (".jpg", ".png", ".jpeg")
_SCAN_SAMPLE_FRAMES = 4  # frames whose time column tells the scans a frame of an unnamed VoD folder


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def _scans_phrase(n: int) -> str:
    return "single scans" if n == 1 else f"{n} accumulated scans a frame"


def resolve_root(
    root: str | os.PathLike, layout: DetectionLayout, scans: int = 1
) -> tuple[Path, int | None, list[str]]:
    """(the set's folder, the scans a frame its name says or None, notes) for ``--data root``:
    ``root`` itself when it holds ``training/``; else its subfolder for ``scans`` accumulated
    scans (View-of-Delft: ``radar/``, ``radar_3frames/`` or ``radar_3_scans/``, ``radar_5frames/``
    or ``radar_5_scans/``); else, said in a note, the present subfolder of the nearest scan count
    (VoD's published example_set holds ``radar/`` only). InputError when there is none."""
    root = Path(root)
    folders = layout.scan_folders()
    named = {name: n for n, names in folders.items() for name in names}
    if (root / "training").is_dir():
        return root, named.get(root.name), []
    present = {
        n: next(d for d in names if (root / d / "training").is_dir())
        for n, names in folders.items()
        if any((root / d / "training").is_dir() for d in names)
    }
    if scans in present:
        return root / present[scans], scans, []
    wanted = "/ or ".join(folders.get(scans, ())) + "/" if scans in folders else ""
    if present:
        n = min(present, key=lambda k: (abs(k - scans), -k))
        note = (
            f"{root}: no {wanted or 'folder of ' + _scans_phrase(scans)} (the card's input.scans_accumulated = "
            f"{scans}); read {present[n]}/ ({_scans_phrase(n)}) instead"
        )
        return root / present[n], n, [note]
    subs = sorted({d for names in folders.values() for d in names if (root / d).is_dir()})
    raise InputError(
        f"{root}: no training/ folder"
        + (f" and no {wanted} for {scans} accumulated scans" if wanted else "")
        + (f" (found {subs} without training/)" if subs else "")
        + "; expected the KITTI layout [ImageSets/ +] training/{velodyne,label_2,calib}"
    )


def _read_split(split_file: Path, training: Path) -> list[str]:
    """The frame ids of an ImageSets split file, each checked (module docstring)."""
    text = read_bounded(
        split_file, "an ImageSets split file", MAX_SPLIT_BYTES, "one frame id a line; View-of-Delft lists 8,693 frames"
    ).decode(errors="replace")
    frame_ids: list[str] = []
    first_line: dict[str, int] = {}
    for number, line in enumerate(text.splitlines(), 1):
        token = line.strip()
        if not token:
            continue
        if not _FRAME_ID.fullmatch(token):
            raise InputError(f"{split_file}:{number}: {token[:40]!r} is not a frame id (one id such as 00042 a line)")
        if token in first_line:
            raise InputError(
                f"{split_file}:{number}: frame {token} is listed again (first on line "
                f"{first_line[token]}); a frame listed twice would be scored twice: list each "
                f"frame once"
            )
        first_line[token] = number
        scan = training / "velodyne" / f"{token}.bin"
        if not scan.is_file():
            raise InputError(
                f"{split_file}:{number}: frame {token} is listed but {scan} "
                + ("is a directory" if scan.is_dir() else "does not exist")
            )
        frame_ids.append(token)
    if not frame_ids:
        raise InputError(f"{split_file}: lists no frames")
    return frame_ids


def label_path(training: Path, frame_id: str) -> Path | None:
    """The frame's label file: ``label_2/<id>.txt`` (KITTI), else ``label_2/<id>.json`` (VoD's
    annotation tool); None when it has neither."""
    for suffix in (".txt", ".json"):
        p = training / "label_2" / f"{frame_id}{suffix}"
        if p.is_file():
            return p
    return None


def _every_labelled_frame(root: Path, training: Path, split: str) -> tuple[list[str], str]:
    """Every frame of ``training/velodyne`` with a label file, in name order, and the note that says so."""
    velodyne = training / "velodyne"
    if not velodyne.is_dir():
        raise InputError(f"{velodyne}: no such folder; expected the radar scans <id>.bin of the KITTI layout")
    scans = sorted(p.stem for p in velodyne.glob("*.bin") if p.is_file() and _FRAME_ID.fullmatch(p.stem))
    ids = [fid for fid in scans if label_path(training, fid) is not None]
    if not ids:
        raise InputError(
            f"{root}: no ImageSets/ folder, and none of the {len(scans)} scans in {velodyne} has a "
            f"label file in {training / 'label_2'} (<id>.txt or <id>.json)"
        )
    left = len(scans) - len(ids)
    note = (
        f"{root}: no ImageSets/ folder, so split {split!r} is every labelled frame of {training}: "
        f"{_plural(len(ids), 'frame')}"
        + (f" ({_plural(left, 'scan')} without a label_2 file left out)" if left else "")
        + f"; write ImageSets/{split}.txt (one frame id a line) to choose the frames"
    )
    return ids, note


def _time_column(training: Path, frame_ids: list[str]) -> tuple[int, float | None]:
    """From the time column of the first frames of a View-of-Delft folder (a scan index: 0 for
    the current scan, -1 the one before, ...): the scans a frame (the most distinct values), and
    a value that is no whole number (times in seconds, not the devkit's scan index), else None."""
    from .readers import read_scan as _read

    most, odd = 0, None
    for fid in frame_ids[:_SCAN_SAMPLE_FRAMES]:
        t = _read(training / "velodyne" / f"{fid}.bin", ["time"], fmt="vod")[:, 0]
        t = t[np.isfinite(t)]
        most = max(most, len(np.unique(t)))
        fractional = t[t != np.round(t)]
        if odd is None and len(fractional):
            odd = float(fractional[0])
    return most, odd


_BENCHMARK_FILE, _MAX_BENCHMARK_BYTES = "benchmark.json", 2**20


def _synthetic_set(root: Path, layout: DetectionLayout) -> bool:
    """Whether ``root`` is (part of) a set ``radaredge make-benchmark --task detection`` wrote for
    ``layout``: its benchmark.json beside ``training/`` or one folder up names the dataset. Its
    frames have no images; their camera is the dataset's (detection_benchmark.CAMERAS)."""
    for folder in (root, root.parent):
        path = folder / _BENCHMARK_FILE
        if not path.is_file():
            continue
        try:
            doc = json.loads(read_bounded(path, "a benchmark.json", _MAX_BENCHMARK_BYTES, "a set's summary"))
        except (InputError, ValueError):
            return False
        return isinstance(doc, dict) and doc.get("dataset") == layout.name and "layouts" in doc
    return False


@dataclass(frozen=True)
class FrameList:
    """The frames of one split of a KITTI-layout set (:func:`list_frames`): ``root`` the folder
    holding ``training/``, ``frame_ids`` in split order, ``split_file`` (None: no ImageSets/,
    every labelled frame), ``scans_per_frame`` (from the folder's name or VoD's time column, None
    when unknown), ``image_size`` (width, height px) for frames without an image_2 file and
    ``notes``: what was read without being asked, each a sentence to say once."""

    root: Path
    split: str
    frame_ids: list[str]
    split_file: Path | None
    scans_per_frame: int | None
    image_size: tuple[int, int]
    notes: list[str]

    @property
    def training(self) -> Path:
        return self.root / "training"


def check_image_size(value, where: str = "input.image_size") -> tuple[int, int] | None:
    """A card's ``input.image_size`` as (width, height) px; None when absent. InputError unless two
    whole numbers of 1 to MAX_IMAGE_SIDE px."""
    if value is None:
        return None
    try:
        width, height = (int(v) for v in value)
        ok = [width, height] == [float(v) for v in value]
    except (TypeError, ValueError):
        ok = False
    if not ok or not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise InputError(f"{where}: expected [width, height] in whole pixels (1 to {MAX_IMAGE_SIDE}), got {value!r}")
    return width, height


def list_frames(
    root: str | os.PathLike,
    split: str = "val",
    layout: DetectionLayout = VOD,
    scans_accumulated: int = 1,
    image_size=None,
) -> FrameList:
    """The frames of ``split`` of the KITTI-layout set at ``root`` (:func:`resolve_root`), with the
    notes a run says once (module docstring):

    - ``ImageSets/<split>.txt`` lists them; without an ``ImageSets/`` folder, every frame of
      ``training/velodyne`` with a ``label_2`` file (.txt or VoD's .json) is the split (noted, with
      how many). An ``ImageSets/`` without ``<split>.txt`` is an error naming the splits it has.
    - a folder whose scans a frame (its name, or for VoD the time column) differ from
      ``scans_accumulated`` (the card's ``input.scans_accumulated``) is noted, and so is a VoD
      time column that holds no scan index (a value that is no whole number: seconds);
    - frames without an ``image_2`` file take ``image_size`` (the card's ``input.image_size``),
      else the dataset camera's size: noted with the calibration's principal point."""
    resolved, named_scans, notes = resolve_root(root, layout, scans_accumulated)
    training = resolved / "training"
    image_sets = resolved / "ImageSets"
    split_file: Path | None = image_sets / f"{split}.txt"
    if split_file.exists():
        frame_ids = _read_split(split_file, training)
    elif image_sets.is_dir():
        have = sorted(p.stem for p in image_sets.glob("*.txt"))
        raise InputError(
            f"{split_file}: split file missing"
            + (
                f"; ImageSets has {have}"
                if have
                else "; expected ImageSets/{train,val,test}.txt with one frame id a line (or no ImageSets/ "
                "folder at all: every labelled frame is read)"
            )
        )
    else:
        frame_ids, note = _every_labelled_frame(resolved, training, split)
        notes.append(note)
        split_file = None
    scans, how = named_scans, f"its name: {resolved.name}/"
    if layout.scan_format == "vod" and frame_ids:
        counted, odd = _time_column(training, frame_ids)
        if scans is None:
            scans, how = counted, "distinct values of its time column"
        if odd is not None:
            notes.append(
                f"{training / 'velodyne'}: the time column holds {odd:g}, not a whole number: "
                f"View-of-Delft's time is the scan index (0 the current scan, -1 the one before, ...), "
                f"not seconds; a card trained on View-of-Delft reads the column as scans"
            )
    if scans is not None and scans != scans_accumulated:
        folders = layout.scan_folders().get(scans_accumulated)
        where = f" ({layout.title or layout.name}: {' or '.join(f + '/' for f in folders)})" if folders else ""
        notes.append(
            f"{resolved} holds {_scans_phrase(scans)} ({how}), but the card's input.scans_accumulated is "
            f"{scans_accumulated}{where}: the model sees {'fewer' if scans < scans_accumulated else 'more'} "
            f"points a frame than it takes, and its scores are not the card's"
        )
    size = check_image_size(image_size)
    without = [
        fid for fid in frame_ids if not any((training / "image_2" / f"{fid}{s}").exists() for s in _IMAGE_SUFFIXES)
    ]
    if without and size is None and _synthetic_set(resolved, layout):
        size = layout.image_size  # radaredge's own set: its camera is the dataset's, nothing to say
    elif without:
        source = (
            "the card's input.image_size"
            if size
            else f"{layout.title or layout.name}'s camera, radaredge's default; the card has no input.image_size"
        )
        size = size or layout.image_size
        try:
            p2 = read_calibration(training / "calib" / f"{without[0]}.txt").P2
            principal = f"; P2's principal point in calib/{without[0]}.txt is ({p2[0, 2]:.0f}, {p2[1, 2]:.0f}) px"
        except InputError:
            principal = ""
        notes.append(
            f"{_plural(len(without), 'frame')} of {len(frame_ids)} have no camera image in "
            f"{training / 'image_2'}: their image size is {size[0]} x {size[1]} px ({source}){principal}; "
            f"it clips the 2D boxes (KITTI's 40 px height rule) and the camera-view crop (input.crop)"
        )
    return FrameList(resolved, split, frame_ids, split_file, scans, size or layout.image_size, notes)


class DetectionSet:
    """The frames of one split of a KITTI-layout radar detection set (module docstring). The
    notes of :func:`list_frames` are in ``notes`` and said once each, as a warning, when the set
    is opened (``say=False``: kept in ``notes`` only)."""

    def __init__(
        self,
        root: str | os.PathLike,
        split: str,
        layout: DetectionLayout,
        scans_accumulated: int = 1,
        image_size=None,
        say: bool = True,
    ):
        self.layout = layout
        listed = list_frames(root, split, layout, scans_accumulated, image_size)
        self.root, self.split, self.frame_ids = listed.root, split, listed.frame_ids
        self.training = self.root / "training"
        self.split_file = listed.split_file if listed.split_file is not None else self.training / "velodyne"
        self.scans_per_frame = listed.scans_per_frame
        self.default_image_size = listed.image_size
        self.notes = listed.notes
        self._image_dir = self.training / "image_2"
        if say:
            for note in self.notes:
                warnings.warn(note, UserWarning, stacklevel=2)

    def __len__(self) -> int:
        return len(self.frame_ids)

    def image_size(self, frame_id: str) -> tuple[int, int]:
        """The frame's camera image size from the header of its image_2 file when present
        (:func:`read_image_size`), else the card's ``input.image_size`` or the dataset's (noted)."""
        for suffix in _IMAGE_SUFFIXES:
            p = self._image_dir / f"{frame_id}{suffix}"
            if p.exists():
                return read_image_size(p)
        return self.default_image_size

    def scan_path(self, frame_id: str) -> Path:
        """The radar scan file of frame ``frame_id``."""
        return self.training / "velodyne" / f"{frame_id}.bin"

    def labels(self, frame_id: str, calib: Calibration, image_size: tuple[int, int]) -> Labels:
        """The frame's labels: ``label_2/<id>.txt`` (:func:`read_labels`), else VoD's
        ``label_2/<id>.json`` (:func:`read_vod_json_labels`, with the frame's calibration and
        image size)."""
        path = label_path(self.training, frame_id)
        if path is None or path.suffix == ".txt":
            return read_labels(self.training / "label_2" / f"{frame_id}.txt", self.layout.label_classes)
        return read_vod_json_labels(path, calib, image_size, self.layout.label_classes)

    def frame(self, i: int, features: list[str]) -> DetectionFrame:
        """Frame ``i`` of the split with its scan in ``features`` columns. InputError naming the
        scan for an empty one (0 bytes: a labelled frame without its radar scan), a value that
        is not finite, or a coordinate beyond ``MAX_COORDINATE`` m (module docstring)."""
        fid = self.frame_ids[i]
        path = self.scan_path(fid)
        points = read_scan(path, features, fmt=self.layout.scan_format)
        if not len(points):
            raise InputError(
                f"{path}: an empty scan (0 bytes): a labelled frame needs its radar points (a failed "
                f"copy?); restore the file, or remove frame {fid} from {self.split_file}"
            )
        check_points(points, features, path)
        calib = read_calibration(self.training / "calib" / f"{fid}.txt")
        size = self.image_size(fid)
        labels = self.labels(fid, calib, size)
        return DetectionFrame(fid, points, labels, calib, size)
