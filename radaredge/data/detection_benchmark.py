"""A labelled synthetic 3D-detection set in View-of-Delft's layout (:mod:`radaredge.data.kitti_detection`).

Each drive is one seeded scene of :mod:`radaredge.data.synthetic` (its own traffic, ego motion
and town): moving cars, pedestrians and cyclists in their lanes and parked cars along the
kerb; about 30 % of the pedestrians and cyclists move on the carriageway (1-4 m from the
ego lane's centre), so the driving corridor has some. Frame ``DDKKK`` is scan KKK + 4 of
drive DD, so that the 4 scans before it exist::

    OUT/radar/training/velodyne/DDKKK.bin          the scan alone (VoD's 7 columns, time 0)
    OUT/radar_5frames/training/velodyne/DDKKK.bin  it and the 4 scans before it, moved into its
                                                   frame, time <= 0 s (VoD's radar_5frames)
    OUT/<both>/training/label_2/DDKKK.txt          KITTI labels in the camera frame
    OUT/<both>/training/calib/DDKKK.txt            P2, R0_rect, Tr_velo_to_cam (radar -> camera)
    OUT/<both>/ImageSets/{train,val,test}.txt      split by drive (no drive in two splits)
    OUT/benchmark.json                             the parameters and the objects per class and split

Labels follow VoD's annotation rules: every object within 50 m of the sensor and at least
partly inside the camera's view is labelled, whether or not the radar saw it (VoD annotates
on the LiDAR); classes Car, Pedestrian, Cyclist. The camera (1936 x 1216 px, focal 1495 px:
VoD's +-32.9 deg) sits 0.6 m above and 0.2 m behind the radar, pitched 2 deg down, so rotation
about the camera's axis and the radar's differ as on VoD's vehicle. Occlusion is measured:
the share of an object's azimuth interval (seen from the radar) that nearer labelled objects
cover, 0 below 10 %, 1 below 50 %, else 2. Truncation is 0 (VoD does not use it).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import atomic
from ..errors import ConfigError
from .kitti_detection import Calibration, camera_box_corners, radar_boxes_to_labels
from .synthetic import CLASS_NAMES, generate_sequence, tj4d_table, vod_accumulated_table, vod_table

LABEL_NAMES = {"car": "Car", "pedestrian": "Pedestrian", "cyclist": "Cyclist"}
ANNOTATED_RANGE = 50.0            # m, VoD annotates objects within 50 m of the LiDAR
HISTORY = 4                       # scans before a labelled frame (radar_5frames)
VRU_ON_ROAD = 0.3                 # share of pedestrians and cyclists on the carriageway (the corridor has some)
SINGLE_DIR, ACCUMULATED_DIR = "radar", "radar_5frames"


CAMERAS = {"vod": ((1936, 1216), 1495.0), "tj4d": ((1280, 960), 1110.0)}   # image (w, h) px, focal px


def synthetic_calibration(dataset: str = "vod") -> Calibration:
    """The benchmark's camera: the dataset's image size and focal length (principal point at the
    image centre), 0.6 m above and 0.2 m behind the radar, pitched 2 deg down."""
    pitch = math.radians(2.0)
    axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])    # radar x fwd, y left, z up -> cam
    c, s = math.cos(pitch), math.sin(pitch)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])            # about the camera's x axis
    rotation = tilt @ axes
    camera_in_radar = np.array([-0.2, 0.0, 0.6])
    v2c = np.column_stack([rotation, -rotation @ camera_in_radar])
    (width, height), f = CAMERAS[dataset]
    p2 = np.array([[f, 0.0, width / 2, 0.0], [0.0, f, height / 2, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return Calibration(p2, np.eye(3), v2c)


def calibration_text(calib: Calibration) -> str:
    """A KITTI calibration file of ``calib``."""
    def row(a):
        return " ".join(f"{v:.12e}" for v in np.asarray(a).ravel())
    lines = [f"P{k}: {row(calib.P2)}" for k in range(4)]
    lines += [f"R0_rect: {row(calib.R0)}", f"Tr_velo_to_cam: {row(calib.V2C)}", "Tr_imu_to_velo: "]
    return "\n".join(lines) + "\n"


def _occlusion(boxes: np.ndarray) -> np.ndarray:
    """Occlusion level 0/1/2 of each radar-frame box [M, 7] from the share of its azimuth
    interval that nearer boxes cover (BEV corners as seen from the origin)."""
    m = len(boxes)
    if m == 0:
        return np.zeros(0, np.int64)
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    hx, hy = boxes[:, 3] / 2, boxes[:, 4] / 2
    corners = np.stack([boxes[:, None, 0] + c[:, None] * sx * hx[:, None] - s[:, None] * sy * hy[:, None]
                        for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1))], 1)           # x only, [M, 4]
    cy = np.stack([boxes[:, None, 1] + s[:, None] * sx * hx[:, None] + c[:, None] * sy * hy[:, None]
                   for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1))], 1)
    az = np.arctan2(cy, corners)[..., 0]
    lo, hi = az.min(1), az.max(1)
    dist = np.hypot(boxes[:, 0], boxes[:, 1])
    levels = np.zeros(m, np.int64)
    for i in range(m):
        width = hi[i] - lo[i]
        if width <= 0:
            continue
        grid = np.linspace(lo[i], hi[i], 64)
        covered = np.zeros(64, bool)
        for j in np.flatnonzero(dist < dist[i]):
            covered |= (grid >= lo[j]) & (grid <= hi[j])
        share = covered.mean()
        levels[i] = 0 if share < 0.1 else 1 if share < 0.5 else 2
    return levels


def frame_labels(boxes: np.ndarray, labels: np.ndarray, calib: Calibration, image_size: tuple[int, int]) -> list[str]:
    """KITTI label lines of the annotated objects among radar-frame boxes [M, 7] (class index
    ``labels`` into synthetic.CLASS_NAMES): within 50 m and at least partly in the image."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    names = np.array([LABEL_NAMES[CLASS_NAMES[int(c)]] for c in labels], dtype=object)
    kitti = radar_boxes_to_labels(boxes, np.zeros(len(boxes)), names, calib, image_size)
    corners = camera_box_corners(kitti.location, kitti.dimensions, kitti.rotation_y)
    uv, depth = calib.rect_to_image(corners.reshape(-1, 3))
    uv, depth = uv.reshape(-1, 8, 2), depth.reshape(-1, 8)
    inside = ((depth > 0.1) & (uv[..., 0] >= 0) & (uv[..., 0] < image_size[0]) & (uv[..., 1] >= 0)
              & (uv[..., 1] < image_size[1])).any(1)
    keep = inside & (np.hypot(boxes[:, 0], boxes[:, 1]) <= ANNOTATED_RANGE)
    occluded = _occlusion(boxes[keep])
    lines = []
    for k, i in enumerate(np.flatnonzero(keep)):
        length, h, w = kitti.dimensions[i]
        ry = (kitti.rotation_y[i] + np.pi) % (2 * np.pi) - np.pi
        alpha = (kitti.alpha[i] + np.pi) % (2 * np.pi) - np.pi
        values = [0.0, occluded[k], alpha, *kitti.bbox[i], h, w, length, *kitti.location[i], ry]
        lines.append(f"{names[i]} {values[0]:.0f} {values[1]:d} " + " ".join(f"{v:.6f}" for v in values[2:]))
    return lines


@dataclass(frozen=True)
class DetectionBenchmark:
    """What :func:`make_detection_benchmark` wrote: the root, frame ids per split and objects per
    class per split."""

    out: Path
    splits: dict[str, list[str]]
    objects: dict[str, dict[str, int]]
    dataset: str = "vod"

    def to_dict(self) -> dict:
        return {"out": str(self.out), "dataset": self.dataset, "frames": {k: len(v) for k, v in self.splits.items()},
                "objects": self.objects,
                "layouts": [SINGLE_DIR, ACCUMULATED_DIR] if self.dataset == "vod" else ["."]}


def split_drives(drives: int) -> dict[str, list[int]]:
    """Drive indices per split: about 20 % val and 10 % test (at least one val drive), the rest train."""
    n_val = max(1, round(0.2 * drives))
    n_test = round(0.1 * drives) if drives >= 4 else 0
    n_train = drives - n_val - n_test
    return {"train": list(range(n_train)), "val": list(range(n_train, n_train + n_val)),
            "test": list(range(n_train + n_val, drives))}


def make_detection_benchmark(out: str | os.PathLike, drives: int = 10, frames: int = 40, seed: int = 0,
                             progress: Callable | None = None, dataset: str = "vod") -> DetectionBenchmark:
    """Write the set (module docstring) to ``out``: ``drives`` drives of ``frames`` labelled
    frames. ``dataset`` "tj4d" writes TJ4DRadSet's layout instead: OUT/training and
    OUT/ImageSets directly, 8-column scans (one scan each), TJ4D's camera (1280 x 960 px)."""
    if dataset not in CAMERAS:
        raise ConfigError(f"dataset must be one of {sorted(CAMERAS)}, got {dataset!r}")
    if drives < 2 or drives > 100:
        raise ConfigError(f"drives must be 2..100 (at least one train and one val drive), got {drives}")
    if frames < 1 or frames > 996:
        raise ConfigError(f"frames must be 1..996 per drive (frame ids DDKKK), got {frames}")
    out = Path(out)
    subs = (SINGLE_DIR, ACCUMULATED_DIR) if dataset == "vod" else ("training", "ImageSets")
    taken = [str(out / sub) for sub in (*subs, "benchmark.json") if (out / sub).exists()]
    if taken:
        raise ConfigError(f"{', '.join(taken)} already exist(s); write the benchmark to a new --out directory")
    calib = synthetic_calibration(dataset)
    image_size = CAMERAS[dataset][0]
    calib_text = calibration_text(calib)
    rng = np.random.default_rng(seed)
    traffic = [dict(num_cars=int(rng.integers(4, 11)), num_pedestrians=int(rng.integers(3, 9)),
                    num_cyclists=int(rng.integers(2, 7)), static_points=int(rng.integers(250, 500)),
                    vru_on_road=VRU_ON_ROAD)
               for _ in range(drives)]
    parts = split_drives(drives)
    split_of = {d: name for name, ds in parts.items() for d in ds}
    splits: dict[str, list[str]] = {name: [] for name in parts}
    objects = {name: {n: 0 for n in LABEL_NAMES.values()} for name in parts}
    with atomic.Staging(out) as stage:
        roots = ({sub: stage.path(out / sub) for sub in subs} if dataset == "vod"
                 else {"tj4d": stage.path(out / "training").parent})
        for root in roots.values():
            for folder in ("velodyne", "label_2", "calib"):
                (root / "training" / folder).mkdir(parents=True, exist_ok=True)
            (root / "ImageSets").mkdir(parents=True, exist_ok=True)
        drive_iter = progress(range(drives)) if progress else range(drives)
        for d in drive_iter:
            scans = generate_sequence(frames + HISTORY, seed=seed * 1000 + d, **traffic[d])
            for k in range(frames):
                fid = f"{d:02d}{k:03d}"
                scan = scans[k + HISTORY]
                lines = frame_labels(scan.boxes, scan.box_labels, calib, image_size)
                for line in lines:
                    objects[split_of[d]][line.split()[0]] += 1
                if dataset == "vod":
                    tables = {SINGLE_DIR: vod_table(scan),
                              ACCUMULATED_DIR: vod_accumulated_table(scans[k:k + HISTORY + 1])}
                else:
                    tables = {"tj4d": tj4d_table(scan)}
                for sub, root in roots.items():
                    np.ascontiguousarray(tables[sub], "<f4").tofile(root / "training" / "velodyne" / f"{fid}.bin")
                    (root / "training" / "label_2" / f"{fid}.txt").write_text("".join(x + "\n" for x in lines))
                    (root / "training" / "calib" / f"{fid}.txt").write_text(calib_text)
                splits[split_of[d]].append(fid)
        for root in roots.values():
            for name, ids in splits.items():
                (root / "ImageSets" / f"{name}.txt").write_text("".join(f + "\n" for f in ids))
        result = DetectionBenchmark(out, splits, objects, dataset)
        atomic.write_json(stage.path(out / "benchmark.json"),
                          {**result.to_dict(), "seed": seed, "drives": drives, "frames_per_drive": frames,
                           "drives_per_split": parts, "traffic": traffic})
        stage.commit()
    return result
