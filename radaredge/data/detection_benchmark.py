"""A labelled synthetic 3D-detection set in View-of-Delft's layout (:mod:`radaredge.data.kitti_detection`).

Each drive is one seeded scene of :mod:`radaredge.data.synthetic` in its own town (static
world), with its own traffic and ego motion: moving cars, pedestrians and cyclists and parked
cars along the kerb; about 30 % of the pedestrians and cyclists move on the carriageway (1-4 m
from the ego lane's centre), so the driving corridor has some. Labelled frame ``DDKKK`` of drive
DD is scan 4 + KKK x stride, so that the 4 scans before it exist::

    OUT/radar/training/velodyne/DDKKK.bin          the scan alone (VoD's 7 columns, time 0)
    OUT/radar_5frames/training/velodyne/DDKKK.bin  it and the 4 scans before it, moved into its
                                                   frame, time = scan index 0, -1, ..., -4 (VoD's)
    OUT/<both>/training/label_2/DDKKK.txt          KITTI labels in the camera frame
    OUT/<both>/training/calib/DDKKK.txt            P2, R0_rect, Tr_velo_to_cam (radar -> camera)
    OUT/<both>/ImageSets/{train,val,test}.txt      split by drive (no drive or town in two splits)
    OUT/benchmark.json                             the parameters, each drive's town and radar
                                                   mounting, and the objects per class and split

Two versions. **1**: drives of consecutive 10 Hz frames, 10 % of them test drives; points sit on
box faces by a fixed budget, with isotropic noise; parked cars and traffic moving at constant
speed along their lanes; one calibration. **2** (the default) is built to rank detectors: the
scenes' radar physics (:data:`PHYSICS_V2`, :mod:`radaredge.data.radar_physics`) has occlusion by
nearer objects, points per object from the radar equation (falling with range, by class and
aspect), noise in range, azimuth and (larger) elevation, micro-Doppler of walkers and cyclists,
multipath ghosts that keep a mover's Doppler, false alarms, traffic that speeds up, slows down,
swerves and crosses the road; each drive's radar has its own mounting error (up to 1 deg in
pitch, roll and yaw, 5 cm in height), written into its calibration; labelled frames are 0.5 s
apart; half the drives (20 by default) are the test split.

Labels follow VoD's annotation rules: every object within 50 m of the sensor and at least
partly inside the camera's view is labelled, whether or not the radar saw it (VoD annotates
on the LiDAR); classes Car, Pedestrian, Cyclist. The camera (1936 x 1216 px, focal 1495 px:
VoD's +-32.9 deg) sits 0.6 m above and 0.2 m behind the radar, pitched 2 deg down, so rotation
about the camera's axis and the radar's differ as on VoD's vehicle. Occlusion is measured:
the share of the object hidden from the radar by nearer objects, 0 below 10 %, 1 below 50 %,
else 2 (version 1: of its azimuth interval; version 2: of its radar-facing surface, by ray
casting in azimuth and elevation, the same test that removes its hidden points). Truncation is
0 (VoD does not use it).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import atomic
from ..errors import ConfigError
from .kitti_detection import Calibration, camera_box_corners, radar_boxes_to_labels
from .radar_physics import occluded_share
from .synthetic import CLASS_NAMES, SceneConfig, generate_sequence, tj4d_table, vod_accumulated_table, vod_table

LABEL_NAMES = {"car": "Car", "pedestrian": "Pedestrian", "cyclist": "Cyclist"}
ANNOTATED_RANGE = 50.0  # m, VoD annotates objects within 50 m of the LiDAR
HISTORY = 4  # scans before a labelled frame (radar_5frames)
VRU_ON_ROAD = 0.3  # share of pedestrians and cyclists on the carriageway (the corridor has some)
SINGLE_DIR, ACCUMULATED_DIR = "radar", "radar_5frames"
VERSIONS = (1, 2)
DEFAULT_DRIVES = {1: 10, 2: 40}
FRAME_STRIDE = {1: 1, 2: 5}  # scans between labelled frames (10 Hz): version 2's are 0.5 s apart
PHYSICS_V2 = dict(  # SceneConfig fields of every version-2 drive
    points_model="radar",
    occlusion=True,
    position_noise=0.03,
    range_noise=0.05,
    azimuth_noise_deg=0.3,
    elevation_noise_deg=1.0,
    micro_doppler=1.0,
    clutter_points=15.0,
    moving_ghosts=True,
    ghost_fraction=0.04,
    traffic_accel_max=1.5,
    swerves=0.3,
    vru_crossing=0.15,
    vru_on_road=VRU_ON_ROAD,
)
MOUNT_JITTER_DEG, MOUNT_HEIGHT_JITTER = 1.0, 0.05  # version 2: |pitch|, |roll|, |yaw| (deg) and |height| (m)
NOMINAL_MOUNT_HEIGHT = 0.8  # m, SceneConfig's default


CAMERAS = {"vod": ((1936, 1216), 1495.0), "tj4d": ((1280, 960), 1110.0)}  # image (w, h) px, focal px


def synthetic_calibration(dataset: str = "vod", mount: np.ndarray | None = None) -> Calibration:
    """The benchmark's camera: the dataset's image size and focal length (principal point at the
    image centre), 0.6 m above and 0.2 m behind the radar as designed, pitched 2 deg down.
    ``mount`` [4, 4] maps the actual radar frame into the designed one (a mounting error)."""
    pitch = math.radians(2.0)
    axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # radar x fwd, y left, z up -> cam
    c, s = math.cos(pitch), math.sin(pitch)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])  # about the camera's x axis
    rotation = tilt @ axes
    camera_in_radar = np.array([-0.2, 0.0, 0.6])
    v2c = np.column_stack([rotation, -rotation @ camera_in_radar])
    if mount is not None:
        v2c = v2c @ np.asarray(mount, np.float64)
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
    corners = np.stack(
        [
            boxes[:, None, 0] + c[:, None] * sx * hx[:, None] - s[:, None] * sy * hy[:, None]
            for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1))
        ],
        1,
    )  # x only, [M, 4]
    cy = np.stack(
        [
            boxes[:, None, 1] + s[:, None] * sx * hx[:, None] + c[:, None] * sy * hy[:, None]
            for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1))
        ],
        1,
    )
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


def frame_labels(
    boxes: np.ndarray, labels: np.ndarray, calib: Calibration, image_size: tuple[int, int], version: int = 1
) -> tuple[list[str], np.ndarray]:
    """KITTI label lines of the annotated objects among radar-frame boxes [M, 7] (class index
    ``labels`` into synthetic.CLASS_NAMES): within 50 m and at least partly in the image; and
    the rows of ``boxes`` they label. Occlusion by :func:`_occlusion` (version 1) or by ray
    casting among all ``boxes`` (:func:`radaredge.data.radar_physics.occluded_share`, version 2)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    names = np.array([LABEL_NAMES[CLASS_NAMES[int(c)]] for c in labels], dtype=object)
    kitti = radar_boxes_to_labels(boxes, np.zeros(len(boxes)), names, calib, image_size)
    corners = camera_box_corners(kitti.location, kitti.dimensions, kitti.rotation_y)
    uv, depth = calib.rect_to_image(corners.reshape(-1, 3))
    uv, depth = uv.reshape(-1, 8, 2), depth.reshape(-1, 8)
    inside = (
        (depth > 0.1)
        & (uv[..., 0] >= 0)
        & (uv[..., 0] < image_size[0])
        & (uv[..., 1] >= 0)
        & (uv[..., 1] < image_size[1])
    ).any(1)
    keep = inside & (np.hypot(boxes[:, 0], boxes[:, 1]) <= ANNOTATED_RANGE)
    if version == 1:
        occluded = _occlusion(boxes[keep])
    else:
        share = occluded_share(boxes)[keep]
        occluded = np.where(share < 0.1, 0, np.where(share < 0.5, 1, 2))
    lines = []
    for k, i in enumerate(np.flatnonzero(keep)):
        length, h, w = kitti.dimensions[i]
        ry = (kitti.rotation_y[i] + np.pi) % (2 * np.pi) - np.pi
        alpha = (kitti.alpha[i] + np.pi) % (2 * np.pi) - np.pi
        values = [0.0, occluded[k], alpha, *kitti.bbox[i], h, w, length, *kitti.location[i], ry]
        lines.append(f"{names[i]} {values[0]:.0f} {values[1]:d} " + " ".join(f"{v:.6f}" for v in values[2:]))
    return lines, np.flatnonzero(keep)


@dataclass(frozen=True)
class DetectionBenchmark:
    """What :func:`make_detection_benchmark` wrote: the root, frame ids per split, labels per
    class per split and distinct objects (one per object however many frames label it) per
    class per split."""

    out: Path
    splits: dict[str, list[str]]
    objects: dict[str, dict[str, int]]
    dataset: str = "vod"
    version: int = 2
    distinct: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "out": str(self.out),
            "dataset": self.dataset,
            "version": self.version,
            "frames": {k: len(v) for k, v in self.splits.items()},
            "objects": self.objects,
            "distinct_objects": self.distinct,
            "layouts": [SINGLE_DIR, ACCUMULATED_DIR] if self.dataset == "vod" else ["."],
        }

    def lines(self) -> list[str]:
        """What was written: frames per split with their labels and distinct objects per class."""
        where = (
            f"{self.out}/{SINGLE_DIR} and {self.out}/{ACCUMULATED_DIR}"
            if self.dataset == "vod"
            else f"{self.out} (TJ4DRadSet)"
        )
        out = [
            f"wrote {sum(len(v) for v in self.splits.values())} labelled frames to {where} (version {self.version}"
            f"); labels (distinct objects):"
        ]
        for split, ids in self.splits.items():
            counts = ", ".join(f"{n} ({self.distinct[split][c]}) {c}" for c, n in self.objects[split].items())
            out.append(f"  {split:<6}{len(ids):>5} frames   {counts}")
        return out


def split_drives(drives: int, version: int = 1) -> dict[str, list[int]]:
    """Drive indices per split. Version 1: about 20 % val and 10 % test (at least one val drive),
    the rest train. Version 2: half the drives test (none below 4 drives); of the others about
    20 % val (at least one), the rest train."""
    if version == 1:
        n_val = max(1, round(0.2 * drives))
        n_test = round(0.1 * drives) if drives >= 4 else 0
    else:
        n_test = drives // 2 if drives >= 4 else 0
        n_val = max(1, round(0.2 * (drives - n_test)))
    n_train = drives - n_val - n_test
    return {
        "train": list(range(n_train)),
        "val": list(range(n_train, n_train + n_val)),
        "test": list(range(n_train + n_val, drives)),
    }


def _drive_mounts(drives: int, seed: int) -> list[dict]:
    """Version 2: each drive's radar mounting error, SceneConfig fields (uniform within
    +-MOUNT_JITTER_DEG and +-MOUNT_HEIGHT_JITTER of the design), from its own stream."""
    rng = np.random.default_rng([seed, 2])
    angles = rng.uniform(-MOUNT_JITTER_DEG, MOUNT_JITTER_DEG, (drives, 3))
    heights = NOMINAL_MOUNT_HEIGHT + rng.uniform(-MOUNT_HEIGHT_JITTER, MOUNT_HEIGHT_JITTER, drives)
    return [
        dict(
            mount_pitch_deg=round(float(p), 4),
            mount_roll_deg=round(float(r), 4),
            mount_yaw_deg=round(float(y), 4),
            mount_height=round(float(h), 4),
        )
        for (p, r, y), h in zip(angles, heights)
    ]


def _radar_in_vehicle(mount: dict) -> np.ndarray:
    """[4, 4] map from a drive's actual radar frame into the designed one (the vehicle's)."""
    rotation = SceneConfig(**mount).mount_rotation
    out = np.eye(4)
    out[:3, :3] = np.eye(3) if rotation is None else rotation
    out[2, 3] = mount["mount_height"] - NOMINAL_MOUNT_HEIGHT
    return out


def _drive_traffic(rng: np.random.Generator, drives: int, version: int) -> list[dict]:
    """Each drive's traffic (SceneConfig fields); version 2 has more road users, for the test
    split's distinct-object counts."""
    if version == 1:
        return [
            dict(
                num_cars=int(rng.integers(4, 11)),
                num_pedestrians=int(rng.integers(3, 9)),
                num_cyclists=int(rng.integers(2, 7)),
                static_points=int(rng.integers(250, 500)),
                vru_on_road=VRU_ON_ROAD,
            )
            for _ in range(drives)
        ]
    return [
        dict(
            num_cars=int(rng.integers(6, 13)),
            num_pedestrians=int(rng.integers(8, 16)),
            num_cyclists=int(rng.integers(6, 12)),
            static_points=int(rng.integers(250, 500)),
        )
        for _ in range(drives)
    ]


def make_detection_benchmark(
    out: str | os.PathLike,
    drives: int | None = None,
    frames: int = 40,
    seed: int = 0,
    progress: Callable | None = None,
    dataset: str = "vod",
    version: int = 2,
) -> DetectionBenchmark:
    """Write the set (module docstring) of ``version`` to ``out``: ``drives`` drives (default 10
    for version 1, 40 for version 2) of ``frames`` labelled frames. ``dataset`` "tj4d" writes
    TJ4DRadSet's layout instead: OUT/training and OUT/ImageSets directly, 8-column scans (one
    scan each), TJ4D's camera (1280 x 960 px)."""
    if dataset not in CAMERAS:
        raise ConfigError(f"dataset must be one of {sorted(CAMERAS)}, got {dataset!r}")
    if version not in VERSIONS:
        raise ConfigError(f"version must be one of {list(VERSIONS)}, got {version!r}")
    drives = DEFAULT_DRIVES[version] if drives is None else drives
    if drives < 2 or drives > 100:
        raise ConfigError(f"drives must be 2..100 (at least one train and one val drive), got {drives}")
    if frames < 1 or frames > 996:
        raise ConfigError(f"frames must be 1..996 per drive (frame ids DDKKK), got {frames}")
    out = Path(out)
    subs = (SINGLE_DIR, ACCUMULATED_DIR) if dataset == "vod" else ("training", "ImageSets")
    taken = [str(out / sub) for sub in (*subs, "benchmark.json") if (out / sub).exists()]
    if taken:
        raise ConfigError(f"{', '.join(taken)} already exist(s); write the benchmark to a new --out directory")
    image_size = CAMERAS[dataset][0]
    stride = FRAME_STRIDE[version]
    traffic = _drive_traffic(np.random.default_rng(seed), drives, version)
    mounts = _drive_mounts(drives, seed) if version == 2 else [{} for _ in range(drives)]
    physics = PHYSICS_V2 if version == 2 else {}
    parts = split_drives(drives, version)
    split_of = {d: name for name, ds in parts.items() for d in ds}
    splits: dict[str, list[str]] = {name: [] for name in parts}
    objects = {name: {n: 0 for n in LABEL_NAMES.values()} for name in parts}
    seen: dict[str, dict[str, set]] = {name: {n: set() for n in LABEL_NAMES.values()} for name in parts}
    with atomic.Staging(out) as stage:
        roots = (
            {sub: stage.path(out / sub) for sub in subs}
            if dataset == "vod"
            else {"tj4d": stage.path(out / "training").parent}
        )
        for root in roots.values():
            for folder in ("velodyne", "label_2", "calib"):
                (root / "training" / folder).mkdir(parents=True, exist_ok=True)
            (root / "ImageSets").mkdir(parents=True, exist_ok=True)
        drive_iter = progress(range(drives)) if progress else range(drives)
        for d in drive_iter:
            calib = synthetic_calibration(dataset, _radar_in_vehicle(mounts[d]) if mounts[d] else None)
            calib_text = calibration_text(calib)
            scans = generate_sequence(
                (frames - 1) * stride + HISTORY + 1, seed=seed * 1000 + d, **{**traffic[d], **physics, **mounts[d]}
            )
            for k in range(frames):
                fid = f"{d:02d}{k:03d}"
                last = HISTORY + k * stride
                scan = scans[last]
                lines, rows = frame_labels(scan.boxes, scan.box_labels, calib, image_size, version)
                for line, row in zip(lines, rows):
                    name = line.split()[0]
                    objects[split_of[d]][name] += 1
                    seen[split_of[d]][name].add((d, int(scan.box_ids[row])))
                if dataset == "vod":
                    tables = {
                        SINGLE_DIR: vod_table(scan),
                        ACCUMULATED_DIR: vod_accumulated_table(scans[last - HISTORY : last + 1]),
                    }
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
        distinct = {split: {name: len(ids) for name, ids in per.items()} for split, per in seen.items()}
        result = DetectionBenchmark(out, splits, objects, dataset, version, distinct)
        towns = {name: [seed * 1000 + d for d in ds] for name, ds in parts.items()}  # each drive's own static world
        atomic.write_json(
            stage.path(out / "benchmark.json"),
            {
                **result.to_dict(),
                "seed": seed,
                "drives": drives,
                "frames_per_drive": frames,
                "frame_stride_scans": stride,
                "drives_per_split": parts,
                "towns_per_split": towns,
                "physics": physics,
                "traffic": traffic,
                "mounts": mounts,
            },
        )
        stage.commit()
    return result
