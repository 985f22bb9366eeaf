"""Seeded synthetic 4D-radar scenes: realistic scans and sequences with ground truth.

Frames and units, as everywhere in radaredge: the radar frame has x forward, y left, z up;
positions in metres, velocities in m/s, time in seconds, angles in radians unless the name
ends in ``_deg``, radar cross-section (RCS) in dBsm. World coordinates are a fixed right-handed
frame with z up in which the ego starts at the origin heading along +x.

The scene
---------
* **Road.** The ego lane's centreline is a circular arc of constant curvature (straight when
  the drawn yaw rate is 0; radius never below 60 m) with a constant grade. Road coordinates
  (s, d, h) are the arc length along the ego lane, the lateral offset to the left and the
  height above the road surface (m). By |d|: lanes at d = -3.5 (same direction), 0 (ego) and
  +3.5 (oncoming), bike lanes around 6 m, a parking strip around 8 m, sidewalks around 10 m
  with street trees and poles at their kerb side, then bushes and building facades (12-16 m).
* **Static world**, in world coordinates, built lazily in 20 m segments along the road, each
  from its own seeded stream, so a place looks the same in every frame and sequence of a seed:
  building facades, guard rails, poles, parked cars, bushes and tree crowns, and road-surface
  clutter, each a set of candidate reflector points with a fixed RCS and an outward surface
  normal (zero for scatterers that reflect in every direction).
* **Revisits.** ``world_seed`` seeds the static world alone, so several ``seed`` values with
  one ``world_seed`` are drives through one town on different days: other traffic, ego motion
  and measurement noise, and, with ``parked_change``, some parked cars gone or shifted. The road's
  curvature and grade are otherwise drawn with the ego motion (from ``seed``); give them all one
  ``road_curvature`` and ``ego_vertical_max`` = 0 (a flat road) to share one world frame.
* **Traffic.** Cars, pedestrians and cyclists move parallel to the road at constant speed in
  their lanes (with ``vru_on_road``, some pedestrians and cyclists on the carriageway). They live in
  a window from 30 m behind to 90 m ahead of the ego, both ends
  outside the field of view (FOV), and wrap around in it, so traffic keeps flowing through
  long sequences.
* **Ego.** The radar moves along the ego lane at a constant speed and yaw rate; a small
  constant yaw offset between radar and lane gives a lateral velocity, the road grade a
  vertical one.

One scan
--------
1. Static points: candidate reflectors inside the FOV whose surface faces the radar, a
   Poisson(``static_points``) sample weighted towards strong, near reflectors.
2. Dynamic points: ``round(n_static * f / (1 - f))`` with f = ``dynamic_fraction``, shared
   among the moving objects whose centre is in the FOV (by size, RCS and range) and drawn
   uniformly on their radar-facing box faces. f is therefore the fraction of moving-object
   points among the non-ghost points.
3. Position noise (isotropic Gaussian), then v_r = r̂·(v_obj - v_ego) for the reported
   position, with r̂ the unit vector from the radar to the point and v_obj = 0 for static
   points, all in the radar frame. The radar's rotation adds nothing (r̂·(ω×p) = 0), and
   objects translate (their yaw rate on a curve is ignored). Gaussian Doppler noise is the
   only departure from this relation.
4. Multipath ghosts: copies of real points mirrored across a vertical reflecting plane beyond
   them or seen at twice their range (double bounce), with v_r = -r̂·v_ego ± 0.5-3 m/s, so they
   are never consistent with the static world, and an RCS 3-10 dB below their source.
5. Points outside the FOV after noise are dropped and the order is shuffled.

Radar physics (``SceneConfig``'s fields from ``points_model`` on, all off by default;
:mod:`radaredge.data.radar_physics`): with ``points_model`` "radar" every car, pedestrian and
cyclist, parked or moving, gets Poisson(radar-equation mean) points on its radar-facing faces
instead of step 2's budget; ``occlusion`` drops points behind nearer objects; range, azimuth
and elevation noise, micro-Doppler, false alarms and ghosts that keep a mover's Doppler join
steps 3-4; movers may change speed, swerve or cross the road; the radar may sit with a
mounting error. The detection benchmark's version 2 turns them all on.

What an estimator can reach: with the defaults (300 static points, 0.05 m/s Doppler noise)
least squares on the true static points has errors of about 0.005 m/s on v_x and v_y and
0.035 m/s (1 sigma) on v_z, which the +-15 deg elevation FOV observes poorly because most
points lie near the horizon; the RANSAC of ``radaredge.ops.ego_velocity`` keeps the error
norm below 0.1 m/s on about 99 % of scans, even at dynamic_fraction 0.4.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..atomic import atomic_path
from ..errors import ConfigError, InputError
from . import radar_physics

COLUMNS = ("x", "y", "z", "v_r", "rcs")
CLASS_NAMES = ("car", "pedestrian", "cyclist")
RCS_CLASSES = CLASS_NAMES + ("wall", "pole", "guard_rail", "vegetation", "ground")

_DEFAULT_RCS_DBSM = {  # (mean, std) of one reflector point, dBsm
    "car": (8.0, 6.0),
    "pedestrian": (-6.0, 4.0),
    "cyclist": (-1.0, 4.0),
    "wall": (5.0, 6.0),
    "pole": (5.0, 4.0),
    "guard_rail": (3.0, 5.0),
    "vegetation": (-8.0, 5.0),
    "ground": (-12.0, 5.0),
}

# Road layout: |d| (m) from the ego lane centre; pairs are (low, high) ranges of object centres.
_LANE = 3.5
_ROAD_EDGE = 5.25
_BIKE_LANE = (5.7, 6.3)
_GUARD_RAIL = 5.6
_PARKING = (7.7, 8.1)
_POLE = 9.2
_TREE = 9.4
_SIDEWALK = (9.6, 11.0)
_VEGETATION = (11.2, 16.0)
_FACADE = (11.8, 16.0)
_SEGMENT = 20.0  # m of road per static-world segment
_MIN_CURVE_RADIUS = 60.0  # m
_TRAFFIC_WINDOW = (-30.0, 90.0)  # m of arc length relative to the ego
_GHOST_DOPPLER = (0.5, 3.0)  # m/s, |v_r offset| of a ghost from the static world
_DIMS = {  # (low, high) of length, width, height in m
    "car": ((3.9, 4.9), (1.7, 1.95), (1.4, 1.7)),
    "pedestrian": ((0.5, 0.8), (0.5, 0.7), (1.55, 1.9)),
    "cyclist": ((1.6, 1.9), (0.5, 0.7), (1.6, 1.9)),
}
_FACE_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=float)
_STREAM_EGO, _STREAM_WORLD, _STREAM_TRAFFIC, _STREAM_FRAME, _STREAM_PARKING, _STREAM_MANOEUVRE = range(6)
_CROSSING_SPAN = 11.0  # m, crossing pedestrians and cyclists walk |d| <= 11 m and wrap
_PARKED_SHIFT = (0.3, 0.8)  # m, |shift| of a moved parked car along its axis (slot gaps are >= 1.6 m)

_LIMITS = {  # field: (lowest value, highest value or None, lowest value itself allowed)
    "seed": (0, None, True),
    "frame_rate": (0.0, None, False),
    "ego_speed_min": (0.0, None, True),
    "ego_speed_max": (0.0, None, True),
    "ego_lateral_max": (0.0, None, True),
    "ego_vertical_max": (0.0, None, True),
    "max_yaw_rate": (0.0, None, True),
    "mount_height": (0.0, None, True),
    "min_range": (0.0, None, True),
    "max_range": (0.0, None, False),
    "max_azimuth_deg": (0.0, 90.0, False),
    "max_elevation_deg": (0.0, 90.0, False),
    "static_points": (0, None, True),
    "num_cars": (0, None, True),
    "num_pedestrians": (0, None, True),
    "num_cyclists": (0, None, True),
    "dynamic_fraction": (0.0, 0.9, True),
    "doppler_noise": (0.0, None, True),
    "position_noise": (0.0, None, True),
    "ghost_fraction": (0.0, 0.5, True),
    "parked_change": (0.0, 1.0, True),
    "vru_on_road": (0.0, 1.0, True),
    "range_noise": (0.0, None, True),
    "azimuth_noise_deg": (0.0, 10.0, True),
    "elevation_noise_deg": (0.0, 10.0, True),
    "micro_doppler": (0.0, 1.0, True),
    "clutter_points": (0.0, 1000.0, True),
    "traffic_accel_max": (0.0, 5.0, True),
    "swerves": (0.0, 1.0, True),
    "vru_crossing": (0.0, 1.0, True),
    "mount_pitch_deg": (-5.0, 5.0, True),
    "mount_roll_deg": (-5.0, 5.0, True),
    "mount_yaw_deg": (-5.0, 5.0, True),
}
POINTS_MODELS = ("budget", "radar")


@dataclass(frozen=True)
class SceneConfig:
    """Everything that shapes a synthetic scene; every field has a default.

    Build from a model-card style mapping with ``radaredge.config.config_from_dict``. Invalid
    values raise :class:`~radaredge.errors.ConfigError` naming the field. ``rcs_dbsm`` may name
    only some classes; the others keep their defaults.
    """

    seed: int = 0  # seeds the traffic, the ego motion, every frame, and the world
    world_seed: int | None = None  # seeds the static world instead of ``seed`` (revisits of one town)
    frame_rate: float = 10.0  # Hz; frame k is at t = k / frame_rate s
    ego_speed_min: float = 3.0  # m/s along the road
    ego_speed_max: float = 15.0  # m/s along the road
    ego_lateral_max: float = 0.3  # m/s, |v_y| of the radar (radar frame), at most half the speed
    ego_vertical_max: float = 0.15  # m/s, |v_z| of the radar from the road grade (grade <= 10 %)
    max_yaw_rate: float = 0.05  # rad/s; 0 gives a straight road
    road_curvature: float | None = None  # 1/m (> 0 turns left, |.| <= 1/60) instead of the drawn yaw rate
    mount_height: float = 0.8  # m, radar above the road surface
    min_range: float = 1.0  # m
    max_range: float = 70.0  # m
    max_azimuth_deg: float = 60.0  # |atan2(y, x)| limit
    max_elevation_deg: float = 15.0  # |atan2(z, hypot(x, y))| limit
    static_points: int = 300  # mean number of static points per scan (Poisson)
    num_cars: int = 4  # moving cars in the traffic window
    num_pedestrians: int = 3  # moving pedestrians in the traffic window
    num_cyclists: int = 2  # moving cyclists in the traffic window
    dynamic_fraction: float = 0.15  # target fraction of non-ghost points on moving objects, [0, 0.9]
    doppler_noise: float = 0.05  # m/s, std of the Gaussian noise on v_r
    position_noise: float = 0.1  # m, std of the isotropic Gaussian noise on x, y, z
    ghost_fraction: float = 0.03  # expected fraction of multipath ghosts among all points, [0, 0.5]
    parked_change: float = 0.0  # chance per parked car to be gone (half) or shifted 0.3-0.8 m
    # along its axis (half) in this drive, drawn from ``seed``, [0, 1]
    vru_on_road: float = 0.0  # chance per pedestrian / cyclist to move on the carriageway
    # (|d| 1-4 m, with the traffic) instead of its sidewalk or bike lane, [0, 1]
    rcs_dbsm: Mapping[str, tuple[float, float]] = field(default_factory=lambda: dict(_DEFAULT_RCS_DBSM))
    # (mean, std) in dBsm of one reflector point per class of RCS_CLASSES
    # --- radar physics (radaredge.data.radar_physics); the defaults give the plain scenes above
    points_model: str = "budget"  # "budget": objects share dynamic_fraction of the points and parked
    # cars compete with the static world; "radar": every car, pedestrian
    # and cyclist gets Poisson(density x projected area / range x detection
    # probability) points on its radar-facing faces (radar equation)
    occlusion: bool = False  # drop points whose line of sight passes through a nearer object box
    range_noise: float = 0.0  # m, std of the range noise (on top of position_noise)
    azimuth_noise_deg: float = 0.0  # deg, std of the azimuth noise
    elevation_noise_deg: float = 0.0  # deg, std of the elevation noise (4D radars: several x the azimuth's)
    micro_doppler: float = 0.0  # [0, 1]: spread of walkers' legs and cyclists' wheels and pedals
    clutter_points: float = 0.0  # mean CFAR false alarms a scan, uniform over the FOV, random Doppler
    moving_ghosts: bool = False  # multipath ghosts of moving objects keep their source's Doppler
    traffic_accel_max: float = 0.0  # m/s^2, peak acceleration of each mover's sinusoidal speed change
    swerves: float = 0.0  # chance per car and cyclist of one swerve (0.5-1.5 m) in the first 20 s
    vru_crossing: float = 0.0  # chance per pedestrian / cyclist to cross the road (heading across it)
    mount_pitch_deg: float = 0.0  # deg, the radar's mounting error about its y axis (nose down > 0)
    mount_roll_deg: float = 0.0  # deg, about its x axis
    mount_yaw_deg: float = 0.0  # deg, about its z axis

    @property
    def static_seed(self) -> int:
        """The seed of the static world: ``world_seed``, or ``seed`` when it is None."""
        return self.seed if self.world_seed is None else self.world_seed

    def __post_init__(self):
        for f in dataclasses.fields(self):
            if f.name in _LIMITS:
                integer = isinstance(f.default, int)
                value = _check_number(f.name, getattr(self, f.name), integer, *_LIMITS[f.name])
                object.__setattr__(self, f.name, int(value) if integer else float(value))
        if self.world_seed is not None:
            world_seed = _check_number("world_seed", self.world_seed, True, 0, None, True)
            object.__setattr__(self, "world_seed", int(world_seed))
        if self.road_curvature is not None:
            curvature = _check_number(
                "road_curvature", self.road_curvature, False, -1 / _MIN_CURVE_RADIUS, 1 / _MIN_CURVE_RADIUS, True
            )
            object.__setattr__(self, "road_curvature", float(curvature))
        if self.ego_speed_min > self.ego_speed_max:
            raise ConfigError(
                f"SceneConfig.ego_speed_min ({self.ego_speed_min} m/s) must be <= "
                f"ego_speed_max ({self.ego_speed_max} m/s)"
            )
        if self.min_range >= self.max_range:
            raise ConfigError(f"SceneConfig.min_range ({self.min_range} m) must be < max_range ({self.max_range} m)")
        object.__setattr__(self, "rcs_dbsm", _merge_rcs(self.rcs_dbsm))
        if self.points_model not in POINTS_MODELS:
            raise ConfigError(f"SceneConfig.points_model must be one of {POINTS_MODELS}, got {self.points_model!r}")
        for name in ("occlusion", "moving_ghosts"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ConfigError(f"SceneConfig.{name}: expected true or false, got {getattr(self, name)!r}")

    @property
    def mount_rotation(self) -> np.ndarray | None:
        """Rotation [3, 3] from the radar's frame into the frame it was meant to have (mounting
        error: yaw, then pitch, then roll), or None when there is none."""
        if not (self.mount_pitch_deg or self.mount_roll_deg or self.mount_yaw_deg):
            return None
        yaw, pitch, roll = (math.radians(v) for v in (self.mount_yaw_deg, self.mount_pitch_deg, self.mount_roll_deg))
        cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
        about_y = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
        about_x = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        return _rot_z(yaw) @ about_y @ about_x


def _check_number(name: str, value, integer: bool, low, high, low_allowed: bool):
    """Return ``value`` if it is a finite number within [low, high]; else raise ConfigError."""
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"SceneConfig.{name}: expected {kind}, got {value!r}")
    if not math.isfinite(value) or (integer and not float(value).is_integer()):
        raise ConfigError(f"SceneConfig.{name}: expected {kind}, got {value!r}")
    if value < low or (value == low and not low_allowed) or (high is not None and value > high):
        wanted = f"{'>=' if low_allowed else '>'} {low}" + (f" and <= {high}" if high is not None else "")
        raise ConfigError(f"SceneConfig.{name} must be {wanted}, got {value!r}")
    return value


def _merge_rcs(table) -> dict[str, tuple[float, float]]:
    """Default per-class RCS table updated with ``table``; unknown classes or bad pairs raise."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"SceneConfig.rcs_dbsm: expected a mapping class -> (mean, std) in dBsm, got {table!r}")
    unknown = sorted(set(table) - set(RCS_CLASSES))
    if unknown:
        raise ConfigError(f"SceneConfig.rcs_dbsm: unknown class(es) {unknown}; expected some of {list(RCS_CLASSES)}")
    merged = dict(_DEFAULT_RCS_DBSM)
    for name, value in table.items():
        try:
            mean, std = (float(v) for v in value)
        except (TypeError, ValueError):
            raise ConfigError(f"SceneConfig.rcs_dbsm.{name}: expected (mean, std) in dBsm, got {value!r}") from None
        if not (math.isfinite(mean) and math.isfinite(std) and std >= 0):
            raise ConfigError(f"SceneConfig.rcs_dbsm.{name}: need a finite mean and a std >= 0, got {value!r}")
        merged[name] = (mean, std)
    return merged


@dataclass
class RadarScan:
    """One radar scan and its ground truth. Radar frame unless stated otherwise.

    points          float32 [N, 5], columns ``COLUMNS``: x, y, z (m), v_r (m/s, positive =
                    moving away), rcs (dBsm)
    dynamic         bool [N], the point lies on a moving object
    ghost           bool [N], the point is a multipath ghost or a false alarm (never dynamic)
    object_index    int64 [N], row of ``boxes`` the point lies on, -1 for none (static world
                    other than parked cars, and ghosts)
    ego_velocity    float64 [3], m/s, velocity of the radar w.r.t. the world
    yaw_rate        float, rad/s, of the radar w.r.t. the world (positive = turning left)
    pose            float64 [4, 4], radar-to-world transform
    timestamp       float, s, frame index / frame_rate
    boxes           float32 [M, 7]: x, y, z centre (m), length, width, height (m), yaw (rad,
                    about z from the x axis) of every object whose centre is in the FOV or that
                    has a point in this scan
    box_labels      int64 [M], index into ``CLASS_NAMES``
    box_velocities  float32 [M, 3], m/s, object velocity w.r.t. the world
    box_dynamic     bool [M], the object moves (False for parked cars)
    box_num_points  int64 [M], points of this scan on the object
    box_ids         int64 [M], the object's identity within its sequence (a parked car keeps its
                    id in every frame; movers are 1,000,000 + their row in the traffic)
    """

    points: np.ndarray
    dynamic: np.ndarray
    ghost: np.ndarray
    object_index: np.ndarray
    ego_velocity: np.ndarray
    yaw_rate: float
    pose: np.ndarray
    timestamp: float
    boxes: np.ndarray
    box_labels: np.ndarray
    box_velocities: np.ndarray
    box_dynamic: np.ndarray
    box_num_points: np.ndarray
    box_ids: np.ndarray

    def column(self, name: str) -> np.ndarray:
        """Column ``name`` (one of ``COLUMNS``) of ``points``, float32 [N]."""
        if name not in COLUMNS:
            raise InputError(f"unknown point column {name!r}; RadarScan.points has columns {COLUMNS}")
        return self.points[:, COLUMNS.index(name)]


# ----------------------------------------------------------------------------- geometry


def _rng(seed: int, stream: int, index: int = 0) -> np.random.Generator:
    """Independent generator for one stream (ego, world, traffic, frame) and index."""
    return np.random.default_rng([seed, stream, index % 2**32])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def _unit(xyz: np.ndarray) -> np.ndarray:
    """Unit vectors [N, 3] from the radar to the points ``xyz`` [N, 3]."""
    return xyz / np.maximum(np.linalg.norm(xyz, axis=1, keepdims=True), 1e-9)


def _to_radar(pose: np.ndarray, xyz_world: np.ndarray) -> np.ndarray:
    """World points [N, 3] (m) into the radar frame of the radar-to-world ``pose``."""
    return (xyz_world - pose[:3, 3]) @ pose[:3, :3]


def _in_fov(xyz: np.ndarray, config: SceneConfig) -> np.ndarray:
    """bool [N]: radar-frame points within the range, azimuth and elevation limits."""
    r = np.linalg.norm(xyz, axis=1)
    azimuth = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    return (
        (r >= config.min_range)
        & (r <= config.max_range)
        & (np.abs(azimuth) <= config.max_azimuth_deg)
        & (np.abs(elevation) <= config.max_elevation_deg)
    )


def _faces_radar(normal: np.ndarray, xyz_world: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """bool [N]: surface points whose outward normal (world) does not point away from the radar."""
    return np.einsum("ij,ij->i", normal, xyz_world - origin) <= 0


def _detection_weight(rcs: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Relative chance (> 0) that a reflector of ``rcs`` dBsm at range ``r`` m is detected."""
    return 10.0 ** (rcs / 20.0) / (1.0 + (r / 12.0) ** 2)


class _RoadFrame:
    """Directions and velocities in road coordinates (arc length ``s``, ``d`` to the left, m) of
    a road that gives ``heading(s)``, ``curvature_at(s)`` and ``grade``."""

    def to_world_direction(self, s, along, left) -> np.ndarray:
        """World vectors [..., 3] with components ``along`` and ``left`` of the road at ``s``."""
        s, along, left = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (s, along, left)))
        theta = self.heading(s)
        return np.stack(
            [
                along * np.cos(theta) - left * np.sin(theta),
                along * np.sin(theta) + left * np.cos(theta),
                np.zeros_like(s),
            ],
            axis=-1,
        )

    def velocity(self, s, d, s_dot) -> np.ndarray:
        """World velocity [..., 3] (m/s) of a point at (s, d) moving with ds/dt = ``s_dot``."""
        s, d, s_dot = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (s, d, s_dot)))
        v = self.to_world_direction(s, s_dot * (1.0 - self.curvature_at(s) * d), 0.0)
        v[..., 2] = s_dot * self.grade
        return v


@dataclass(frozen=True)
class _Road(_RoadFrame):
    """The ego lane: constant ``curvature`` (1/m, positive turns left) and ``grade`` (dz/ds)."""

    curvature: float
    grade: float

    def curvature_at(self, s) -> float:
        """Curvature (1/m, positive turns left) at arc length ``s`` (m): constant."""
        return self.curvature

    def heading(self, s) -> np.ndarray:
        """World yaw (rad) of the road at arc length ``s`` (m)."""
        return self.curvature * np.asarray(s, dtype=float)

    def to_world(self, s, d, h) -> np.ndarray:
        """World points [..., 3] (m) of road coordinates (s, d, h), broadcast together."""
        s, d, h = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (s, d, h)))
        theta = self.heading(s)
        x = s * np.sinc(theta / np.pi) - d * np.sin(theta)  # sin(ks)/k - d sin
        y = 0.5 * theta * s * np.sinc(theta / (2 * np.pi)) ** 2 + d * np.cos(theta)  # (1-cos ks)/k + d cos
        return np.stack([x, y, self.grade * s + h], axis=-1)


@dataclass(frozen=True)
class _Ego:
    """The radar's motion: ``speed`` (m/s) along the ego lane, ``lateral`` v_y (m/s, radar frame)."""

    road: _Road
    speed: float
    lateral: float
    mount_height: float
    mount: np.ndarray | None = None  # SceneConfig.mount_rotation

    @property
    def slip(self) -> float:
        """Yaw (rad) of the radar relative to the road heading, which makes v_y = ``lateral``."""
        return -math.asin(self.lateral / self.speed) if self.speed > 0 else 0.0

    def yaw_rate_at(self, t: float) -> float:
        """Yaw rate (rad/s, positive = turning left) of the radar at time ``t`` (s)."""
        return float(self.road.curvature_at(self.speed * t)) * self.speed

    def velocity(self) -> np.ndarray:
        """Radar velocity w.r.t. the world in the radar frame, m/s [3] (constant)."""
        velocity = np.array([self.speed * math.cos(self.slip), self.lateral, self.road.grade * self.speed])
        return velocity if self.mount is None else self.mount.T @ velocity

    def pose(self, t: float) -> np.ndarray:
        """Radar-to-world transform [4, 4] at time ``t`` (s)."""
        s = self.speed * t
        pose = np.eye(4)
        pose[:3, :3] = _rot_z(float(self.road.heading(s)) + self.slip)
        if self.mount is not None:
            pose[:3, :3] = pose[:3, :3] @ self.mount
        pose[:3, 3] = self.road.to_world(s, 0.0, self.mount_height)
        return pose


def _draw_ego(config: SceneConfig) -> _Ego:
    """Speed, lateral and vertical velocity and yaw rate of the ego, constant per seed."""
    rng = _rng(config.seed, _STREAM_EGO)
    speed = rng.uniform(config.ego_speed_min, config.ego_speed_max)
    lateral = rng.uniform(-1, 1) * min(config.ego_lateral_max, 0.5 * speed)
    vertical = rng.uniform(-1, 1) * min(config.ego_vertical_max, 0.1 * speed)
    yaw_rate = rng.uniform(-1, 1) * config.max_yaw_rate
    if config.road_curvature is not None:
        curvature = config.road_curvature
    elif speed > 0:
        curvature = float(np.clip(yaw_rate / speed, -1 / _MIN_CURVE_RADIUS, 1 / _MIN_CURVE_RADIUS))
    else:
        curvature = 0.0
    grade = vertical / speed if speed > 0 else 0.0
    return _Ego(_Road(curvature, grade), float(speed), float(lateral), config.mount_height, config.mount_rotation)


# ----------------------------------------------------------------------------- world


@dataclass(frozen=True)
class _Boxes:
    """Objects in world coordinates: centre [M, 3] (m), dims [M, 3] (length, width, height, m),
    yaw [M] (rad), label [M] (index into CLASS_NAMES), velocity [M, 3] (m/s), ident [M] (the
    object's id in the scene, RadarScan.box_ids)."""

    centre: np.ndarray
    dims: np.ndarray
    yaw: np.ndarray
    label: np.ndarray
    velocity: np.ndarray
    ident: np.ndarray

    def __len__(self) -> int:
        return len(self.label)

    @staticmethod
    def concat(parts: Sequence[_Boxes]) -> _Boxes:
        parts = [_NO_BOXES, *parts]
        return _Boxes(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(_Boxes)))


_NO_BOXES = _Boxes(
    np.zeros((0, 3)),
    np.zeros((0, 3)),
    np.zeros(0),
    np.zeros(0, dtype=np.int64),
    np.zeros((0, 3)),
    np.zeros(0, dtype=np.int64),
)
_MOVER_ID = 1_000_000  # RadarScan.box_ids of movers start here; parked cars: 16 (segment + 4096) + slot


@dataclass(frozen=True)
class _Reflectors:
    """Static candidate reflectors in world coordinates: xyz [K, 3] (m), outward unit normal
    [K, 3] (zero for scatterers seen from everywhere), rcs [K] (dBsm), owner [K] (row of the
    parked-car boxes the point lies on, -1 for none)."""

    xyz: np.ndarray
    normal: np.ndarray
    rcs: np.ndarray
    owner: np.ndarray

    @staticmethod
    def concat(parts: Sequence[_Reflectors], owner_offsets: Sequence[int]) -> _Reflectors:
        """All ``parts`` in one; the owners of part i are shifted by ``owner_offsets[i]``."""
        owner = [np.zeros(0, dtype=np.int64)] + [
            np.where(p.owner >= 0, p.owner + o, -1) for p, o in zip(parts, owner_offsets)
        ]
        return _Reflectors(
            np.concatenate([np.zeros((0, 3))] + [p.xyz for p in parts]),
            np.concatenate([np.zeros((0, 3))] + [p.normal for p in parts]),
            np.concatenate([np.zeros(0)] + [p.rcs for p in parts]),
            np.concatenate(owner),
        )


@dataclass(frozen=True)
class _Surface:
    """Roadside reflector points in road coordinates (m); ``facing`` = +1/-1 if the surface
    faces left/right (towards +d/-d), 0 if it scatters in every direction."""

    s: np.ndarray
    d: np.ndarray
    h: np.ndarray
    facing: float
    kind: str


def _draw_rcs(rng: np.random.Generator, config: SceneConfig, kind: str, n: int) -> np.ndarray:
    mean, std = config.rcs_dbsm[kind]
    return rng.normal(mean, std, n)


def _draw_dims(rng: np.random.Generator, labels: np.ndarray) -> np.ndarray:
    """Length, width, height [M, 3] (m) for objects of class ``labels``."""
    bounds = np.array([_DIMS[CLASS_NAMES[c]] for c in labels]).reshape(-1, 3, 2)
    return rng.uniform(bounds[..., 0], bounds[..., 1])


def _facade(rng: np.random.Generator, s0: float, side: float, offset: float) -> _Surface:
    """A building facade at |d| = ``offset``, a jittered 0.5 m x 0.7 m grid of points."""
    start, end = s0 + rng.uniform(0, 3), s0 + _SEGMENT - rng.uniform(0, 3)
    s, h = np.meshgrid(np.arange(start, end, 0.5), np.arange(0.3, rng.uniform(4, 15), 0.7))
    s = s.ravel() + rng.uniform(-0.15, 0.15, s.size)
    h = h.ravel() + rng.uniform(-0.2, 0.2, h.size)
    return _Surface(s, np.full(s.size, side * offset), h, -side, "wall")


def _guard_rail(rng: np.random.Generator, s0: float, side: float) -> _Surface:
    s = np.arange(s0, s0 + _SEGMENT, 0.3) + rng.uniform(-0.05, 0.05)
    h = rng.uniform(0.55, 0.75) + rng.uniform(-0.05, 0.05, s.size)
    return _Surface(s, np.full(s.size, side * _GUARD_RAIL), h, -side, "guard_rail")


def _road_clutter(rng: np.random.Generator, s0: float) -> _Surface:
    """Road-surface scatterers (kerb stones, road studs, manhole covers): about one per 2 m^2
    of road, near the surface. They give the near, below-horizon returns of real scans."""
    n = rng.poisson(_SEGMENT * 2 * _ROAD_EDGE / 2)
    s = s0 + rng.uniform(0, _SEGMENT, n)
    return _Surface(s, rng.uniform(-_ROAD_EDGE, _ROAD_EDGE, n), rng.uniform(0.0, 0.15, n), 0.0, "ground")


def _pole(rng: np.random.Generator, s0: float, side: float) -> _Surface:
    h = np.arange(0.2, rng.uniform(4, 8), 0.25)
    return _Surface(np.full(h.size, s0 + rng.uniform(0, _SEGMENT)), np.full(h.size, side * _POLE), h, 0.0, "pole")


def _clusters(
    rng: np.random.Generator, centres: np.ndarray, spread: tuple[float, float], size: tuple[int, int]
) -> np.ndarray:
    """Gaussian point clusters [K, 3] around road-coordinate ``centres`` [C, 3] (m)."""
    parts = [c + rng.normal(0, rng.uniform(*spread), (rng.integers(*size), 3)) for c in centres]
    return np.concatenate([np.zeros((0, 3))] + parts)


def _vegetation(rng: np.random.Generator, s0: float, side: float, far: float) -> _Surface:
    """Bushes between the sidewalk and |d| = ``far``, and street-tree crowns (4-7 m up) over the
    sidewalk's kerb side: Gaussian point clusters."""
    n_bush, n_tree = rng.poisson(2), rng.poisson(1.5)
    bushes = np.column_stack(
        [
            s0 + rng.uniform(0, _SEGMENT, n_bush),
            side * rng.uniform(_VEGETATION[0], far, n_bush),
            rng.uniform(0.5, 1.5, n_bush),
        ]
    )
    trees = np.column_stack(
        [s0 + rng.uniform(0, _SEGMENT, n_tree), np.full(n_tree, side * _TREE), rng.uniform(4.0, 7.0, n_tree)]
    )
    pts = np.concatenate([_clusters(rng, bushes, (0.25, 0.7), (15, 40)), _clusters(rng, trees, (0.8, 1.5), (40, 100))])
    return _Surface(pts[:, 0], pts[:, 1], np.maximum(pts[:, 2], 0.1), 0.0, "vegetation")


def _parked_cars(rng: np.random.Generator, road: _Road, s0: float, side: float) -> _Boxes:
    """Cars in up to three 6.5 m parking slots of the segment, facing either way."""
    slots = np.flatnonzero(rng.random(3) < 0.45)
    s = s0 + 3.5 + 6.5 * slots + rng.uniform(-0.5, 0.5, slots.size)
    label = np.zeros(s.size, dtype=np.int64)
    dims = _draw_dims(rng, label)
    centre = road.to_world(s, side * rng.uniform(*_PARKING, s.size), dims[:, 2] / 2)
    yaw = road.heading(s) + np.pi * rng.integers(0, 2, s.size)
    return _Boxes(centre, dims, yaw, label, np.zeros((s.size, 3)), np.zeros(s.size, dtype=np.int64))


def _surface_reflectors(rng: np.random.Generator, config: SceneConfig, road: _Road, surface: _Surface) -> _Reflectors:
    n = surface.s.size
    normal = road.to_world_direction(surface.s, 0.0, surface.facing)
    return _Reflectors(
        road.to_world(surface.s, surface.d, surface.h),
        normal,
        _draw_rcs(rng, config, surface.kind, n),
        np.full(n, -1, dtype=np.int64),
    )


def _box_surface(rng: np.random.Generator, dims: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform on the five outer faces (no bottom) of a box of ``dims`` (l, w, h, m)
    centred on its own frame's origin, x along the length: (points [n, 3], outward normals [n, 3])."""
    length, width, height = dims
    area = np.array([width * height, width * height, length * height, length * height, length * width])
    normal = _FACE_NORMALS[rng.choice(5, size=n, p=area / area.sum())]
    unit = np.where(normal != 0, 0.5 * normal, rng.uniform(-0.5, 0.5, (n, 3)))
    return unit * dims, normal


def _box_points_world(boxes: _Boxes, i: int, local: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals [n, 3] from box ``i``'s frame into world coordinates."""
    rot = _rot_z(float(boxes.yaw[i]))
    return boxes.centre[i] + local @ rot.T, normal @ rot.T


def _box_reflectors(rng: np.random.Generator, config: SceneConfig, boxes: _Boxes, density: float) -> _Reflectors:
    """About ``density`` candidate reflectors per m^2 on every box's outer faces."""
    parts = []
    for i in range(len(boxes)):
        l, w, h = boxes.dims[i]
        local, normal = _box_surface(rng, boxes.dims[i], round(density * (l * w + 2 * (l + w) * h)))
        xyz, normal = _box_points_world(boxes, i, local, normal)
        parts.append(
            _Reflectors(
                xyz,
                normal,
                _draw_rcs(rng, config, CLASS_NAMES[boxes.label[i]], len(xyz)),
                np.full(len(xyz), i, dtype=np.int64),
            )
        )
    return _Reflectors.concat(parts, [0] * len(parts))


def _change_parking(
    rng: np.random.Generator, cars: _Boxes, reflectors: _Reflectors, change: float
) -> tuple[_Boxes, _Reflectors]:
    """This drive's parked cars: each with chance ``change`` gone (half of them) or shifted by
    0.3-0.8 m along its own horizontal axis, forwards or backwards (the other half), together
    with its reflectors (``owner`` = row of ``cars``). Rows are renumbered after removals."""
    n = len(cars)
    changed = rng.random(n) < change
    kept = ~(changed & (rng.random(n) < 0.5))
    shift = np.where(changed & kept, rng.choice([-1.0, 1.0], n) * rng.uniform(*_PARKED_SHIFT, n), 0.0)
    offset = shift[:, None] * np.column_stack([np.cos(cars.yaw), np.sin(cars.yaw), np.zeros(n)])
    on_kept = kept[reflectors.owner]
    owner = reflectors.owner[on_kept]
    row = np.cumsum(kept) - 1
    return (
        _Boxes(
            cars.centre[kept] + offset[kept],
            cars.dims[kept],
            cars.yaw[kept],
            cars.label[kept],
            cars.velocity[kept],
            cars.ident[kept],
        ),
        _Reflectors(
            reflectors.xyz[on_kept] + offset[owner], reflectors.normal[on_kept], reflectors.rcs[on_kept], row[owner]
        ),
    )


def _build_segment(config: SceneConfig, road: _Road, index: int, s0: float) -> tuple[_Reflectors, _Boxes]:
    """Static reflectors and parked cars of the road segment s in [``s0``, ``s0`` + 20) m of
    ``road``, drawn from the world's stream ``index``; the parking of this drive
    (``parked_change``) from the stream of ``seed``."""
    rng = _rng(config.static_seed, _STREAM_WORLD, index)
    surfaces, parked = [_road_clutter(rng, s0)], []
    for side in (-1.0, 1.0):
        facade = rng.uniform(*_FACADE) if rng.random() < 0.7 else None
        if rng.random() < 0.3:
            surfaces.append(_guard_rail(rng, s0, side))
        else:
            parked.append(_parked_cars(rng, road, s0, side))
        if facade is not None:
            surfaces.append(_facade(rng, s0, side, facade))
        if rng.random() < 0.6:
            surfaces.append(_pole(rng, s0, side))
        surfaces.append(_vegetation(rng, s0, side, _VEGETATION[1] if facade is None else facade - 0.5))
    cars = _Boxes.concat(parked)
    cars = dataclasses.replace(cars, ident=16 * (index + 4096) + np.arange(len(cars), dtype=np.int64))
    parts = [_surface_reflectors(rng, config, road, s) for s in surfaces]
    car_reflectors = _box_reflectors(rng, config, cars, density=3.0)
    if config.parked_change > 0:
        cars, car_reflectors = _change_parking(
            _rng(config.seed, _STREAM_PARKING, index), cars, car_reflectors, config.parked_change
        )
    return _Reflectors.concat(parts + [car_reflectors], [0] * (len(parts) + 1)), cars


class _StaticWorld:
    """The static world of one seed, built lazily per road segment and cached."""

    def __init__(self, config: SceneConfig, road: _Road):
        self._config = config
        self._road = road
        self._segments: dict[int, tuple[_Reflectors, _Boxes]] = {}

    def between(self, s_low: float, s_high: float) -> tuple[_Reflectors, _Boxes]:
        """Reflectors and parked cars of every segment overlapping arc lengths [s_low, s_high] m."""
        indices = range(math.floor(s_low / _SEGMENT), math.floor(s_high / _SEGMENT) + 1)
        for i in indices:
            if i not in self._segments:
                self._segments[i] = _build_segment(self._config, self._road, i, i * _SEGMENT)
        segments = [self._segments[i] for i in indices]
        offsets = np.cumsum([0] + [len(cars) for _, cars in segments[:-1]])
        return (_Reflectors.concat([r for r, _ in segments], offsets), _Boxes.concat([cars for _, cars in segments]))

    def visible(self, s_ego: float, position: np.ndarray) -> tuple[_Reflectors, _Boxes]:
        """Reflectors and parked cars a radar at arc length ``s_ego`` (m) may see: one segment
        behind it to twice the maximum range ahead (``position`` is not needed on one street)."""
        return self.between(s_ego - _SEGMENT, s_ego + 2 * self._config.max_range)


@dataclass(frozen=True)
class _Manoeuvres:
    """How movers depart from constant speed along their lane, per mover [M]: a sinusoidal speed
    change of ``amplitude`` m/s at ``omega`` rad/s from ``phase``; one lateral move of ``shift`` m
    (a swerve) starting at ``start`` s and lasting ``duration`` s (smoothstep); and
    ``cross`` m/s across the road (pedestrians and cyclists crossing; they keep their arc length)."""

    amplitude: np.ndarray
    omega: np.ndarray
    phase: np.ndarray
    shift: np.ndarray
    start: np.ndarray
    duration: np.ndarray
    cross: np.ndarray

    def along(self, s_dot: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(distance travelled along the road since t = 0 [M] m, speed along it at ``t`` [M] m/s)."""
        angle = self.omega * t + self.phase
        travelled = s_dot * t - self.amplitude / self.omega * (np.cos(angle) - np.cos(self.phase))
        return travelled, s_dot + self.amplitude * np.sin(angle)

    def lateral(self, d0: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(offset d at ``t`` [M] m, its rate [M] m/s) from lane ``d0``."""
        x = np.clip((t - self.start) / self.duration, 0.0, 1.0)
        d = d0 + self.shift * x * x * (3 - 2 * x) + self.cross * t
        d_dot = self.shift * 6 * x * (1 - x) / self.duration + self.cross
        crossing = self.cross != 0
        d = np.where(crossing, (d + _CROSSING_SPAN) % (2 * _CROSSING_SPAN) - _CROSSING_SPAN, d)
        return d, d_dot


@dataclass(frozen=True)
class _Traffic:
    """Moving objects: label [M], lateral offset d [M] (m), ds/dt [M] (m/s, negative = against
    the ego's direction), arc length ahead of the ego at t = 0 [M] (m), dims [M, 3] (m), and
    their manoeuvres (None: constant speed in their lane)."""

    label: np.ndarray
    d: np.ndarray
    s_dot: np.ndarray
    ahead0: np.ndarray
    dims: np.ndarray
    manoeuvres: _Manoeuvres | None = None

    def at(self, road: _Road, ego_speed: float, t: float) -> _Boxes:
        """World boxes and velocities at time ``t`` (s), wrapped into the traffic window."""
        low, high = _TRAFFIC_WINDOW
        ident = _MOVER_ID + np.arange(len(self.label), dtype=np.int64)
        if self.manoeuvres is None:
            ahead = (self.ahead0 + (self.s_dot - ego_speed) * t - low) % (high - low) + low
            s = ego_speed * t + ahead
            centre = road.to_world(s, self.d, self.dims[:, 2] / 2)
            yaw = road.heading(s) + np.where(self.s_dot < 0, np.pi, 0.0)
            return _Boxes(centre, self.dims, yaw, self.label, road.velocity(s, self.d, self.s_dot), ident)
        travelled, speed = self.manoeuvres.along(self.s_dot, t)
        ahead = (self.ahead0 + travelled - ego_speed * t - low) % (high - low) + low
        s = ego_speed * t + ahead
        d, d_dot = self.manoeuvres.lateral(self.d, t)
        waiting = (self.manoeuvres.cross != 0) & (np.abs(ahead) < 6.0) & (np.abs(d) < 2.5)  # the ego passes
        d = np.where(waiting, np.where(d < 0, -2.5, 2.5), d)
        centre = road.to_world(s, d, self.dims[:, 2] / 2)
        yaw = road.heading(s) + np.arctan2(d_dot, speed * (1.0 - road.curvature_at(s) * d))
        velocity = road.velocity(s, d, speed) + road.to_world_direction(s, 0.0, d_dot)
        return _Boxes(centre, self.dims, yaw, self.label, velocity, ident)


def _draw_lane_and_speed(rng: np.random.Generator, kind: str, on_road: float = 0.0) -> tuple[float, float]:
    """Lateral offset d (m) and ds/dt (m/s) of one moving object; traffic keeps to the right.
    A pedestrian or cyclist moves on the carriageway with chance ``on_road`` (drawn only when > 0)."""
    side = rng.choice([-1.0, 1.0])
    if kind == "car":
        speed = rng.uniform(4, 16) if side < 0 else -rng.uniform(6, 14)
        return side * _LANE + rng.uniform(-0.3, 0.3), speed
    if on_road > 0 and rng.random() < on_road:
        speed = rng.uniform(0.8, 1.8) if kind == "pedestrian" else rng.uniform(3, 7)
        return side * rng.uniform(1.0, 4.0), -side * speed
    if kind == "pedestrian":
        return side * rng.uniform(*_SIDEWALK), rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.8)
    return side * rng.uniform(*_BIKE_LANE), -side * rng.uniform(3, 7)


def _draw_traffic(config: SceneConfig) -> _Traffic:
    rng = _rng(config.seed, _STREAM_TRAFFIC)
    label = np.repeat(np.arange(3), [config.num_cars, config.num_pedestrians, config.num_cyclists])
    lanes = np.array([_draw_lane_and_speed(rng, CLASS_NAMES[c], config.vru_on_road) for c in label]).reshape(-1, 2)
    traffic = _Traffic(label, lanes[:, 0], lanes[:, 1], rng.uniform(10, 60, label.size), _draw_dims(rng, label))
    if config.traffic_accel_max or config.swerves or config.vru_crossing:
        traffic = _draw_manoeuvres(config, traffic)
    return traffic


def _draw_manoeuvres(config: SceneConfig, traffic: _Traffic) -> _Traffic:
    """``traffic`` with manoeuvres drawn from their own stream (the lanes and speeds stay those
    of the plain scene): crossers (``vru_crossing``) walk or ride across the road at 0.8-1.8 /
    2.5-5 m/s from a random offset; the others vary their speed by up to 60 % with a peak
    acceleration of at most ``traffic_accel_max``; with chance ``swerves`` a car or cyclist
    swerves 0.5-1.5 m to either side over 2-4 s, starting in the first 20 s (never into the ego
    lane's middle: the traffic window wraps round the ego)."""
    rng = _rng(config.seed, _STREAM_MANOEUVRE)
    m = len(traffic.label)
    pedestrian, cyclist, car = (traffic.label == k for k in range(3))
    crossing = (pedestrian | cyclist) & (rng.random(m) < config.vru_crossing)
    cross = np.where(
        crossing,
        rng.choice([-1.0, 1.0], m) * np.where(pedestrian, rng.uniform(0.8, 1.8, m), rng.uniform(2.5, 5.0, m)),
        0.0,
    )
    omega = rng.uniform(0.15, 0.5, m)
    amplitude = np.minimum(config.traffic_accel_max / omega, 0.6 * np.abs(traffic.s_dot)) * rng.uniform(0.3, 1.0, m)
    changing = (car | cyclist) & ~crossing & (rng.random(m) < config.swerves)
    swerve = rng.uniform(0.5, 1.5, m) * np.where(
        np.abs(traffic.d) < 2.5, np.sign(traffic.d), rng.choice([-1.0, 1.0], m)
    )
    shift = np.where(changing, swerve, 0.0)
    manoeuvres = _Manoeuvres(
        np.where(crossing, 0.0, amplitude),
        omega,
        rng.uniform(0, 2 * np.pi, m),
        shift,
        rng.uniform(0.0, 20.0, m),
        rng.uniform(2.0, 4.0, m),
        cross,
    )
    d = np.where(crossing, rng.uniform(-_CROSSING_SPAN, _CROSSING_SPAN, m), traffic.d)
    return dataclasses.replace(traffic, d=d, s_dot=np.where(crossing, 0.0, traffic.s_dot), manoeuvres=manoeuvres)


# ----------------------------------------------------------------------------- one scan


@dataclass(frozen=True)
class _Scene:
    """Everything a frame is drawn from; the world caches segments as frames ask for them."""

    config: SceneConfig
    ego: _Ego
    world: _StaticWorld
    traffic: _Traffic


def _sample_static(
    rng: np.random.Generator, config: SceneConfig, reflectors: _Reflectors, pose: np.ndarray
) -> np.ndarray:
    """Indices of the reflectors detected in this scan (radar-facing, in FOV, weighted sample)."""
    xyz = _to_radar(pose, reflectors.xyz)
    candidates = np.flatnonzero(_in_fov(xyz, config) & _faces_radar(reflectors.normal, reflectors.xyz, pose[:3, 3]))
    n = min(int(rng.poisson(config.static_points)), candidates.size)
    if n == 0:
        return candidates[:0]
    weight = _detection_weight(reflectors.rcs[candidates], np.linalg.norm(xyz[candidates], axis=1))
    return rng.choice(candidates, size=n, replace=False, p=weight / weight.sum())


def _sample_moving(
    rng: np.random.Generator, config: SceneConfig, movers: _Boxes, pose: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """About ``n`` points on the radar-facing faces of the movers whose centre is in the FOV:
    (world xyz [n, 3] m, rcs [n] dBsm, mover row [n])."""
    centre = _to_radar(pose, movers.centre)
    visible = _in_fov(centre, config)
    if n == 0 or not visible.any():
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
    l, w, h = movers.dims.T
    rcs_mean = np.array([config.rcs_dbsm[CLASS_NAMES[c]][0] for c in movers.label])
    weight = visible * (l * w + 2 * (l + w) * h) * _detection_weight(rcs_mean, np.linalg.norm(centre, axis=1))
    xyz, rcs, owner = [], [], []
    for i, count in enumerate(rng.multinomial(n, weight / weight.sum())):
        if count == 0:
            continue
        local, normal = _box_surface(rng, movers.dims[i], 4 * count + 16)
        points, normal = _box_points_world(movers, i, local, normal)
        seen = _faces_radar(normal, points, pose[:3, 3]) & _in_fov(_to_radar(pose, points), config)
        points = points[seen][:count]
        xyz.append(points)
        rcs.append(_draw_rcs(rng, config, CLASS_NAMES[movers.label[i]], len(points)))
        owner.append(np.full(len(points), i, dtype=np.int64))
    return np.concatenate(xyz), np.concatenate(rcs), np.concatenate(owner)


def _ghosts(
    rng: np.random.Generator, config: SceneConfig, xyz: np.ndarray, rcs: np.ndarray, v_ego: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Multipath ghosts of the real radar-frame points ``xyz``: (xyz [G, 3] m, noise-free v_r [G]
    m/s, rcs [G] dBsm, source row [G]). Half are mirrored across a vertical plane y = const 1-8 m
    beyond their source, half are double bounces at twice the source's range."""
    n_real = len(xyz)
    n = int(rng.poisson(config.ghost_fraction / (1 - config.ghost_fraction) * n_real)) if n_real else 0
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64)
    source = rng.integers(0, n_real, 4 * n)
    ghost = xyz[source].copy()
    mirror = rng.random(source.size) < 0.5
    plane = ghost[:, 1] + np.where(ghost[:, 1] < 0, -1.0, 1.0) * rng.uniform(1, 8, source.size)
    ghost[mirror, 1] = 2 * plane[mirror] - ghost[mirror, 1]
    ghost[~mirror] *= 2
    keep = np.flatnonzero(_in_fov(ghost, config))[:n]
    ghost = ghost[keep]
    offset = rng.choice([-1.0, 1.0], keep.size) * rng.uniform(*_GHOST_DOPPLER, keep.size)
    return ghost, -_unit(ghost) @ v_ego + offset, rcs[source[keep]] - rng.uniform(3, 10, keep.size), source[keep]


def _radar_frame_boxes(objects: _Boxes, pose: np.ndarray) -> np.ndarray:
    """float64 [M, 7] boxes of ``objects`` in the radar frame of ``pose``: centre, dims, yaw
    relative to the radar's heading (a mounting tilt moves the centre, not the box's axes)."""
    radar_yaw = math.atan2(pose[1, 0], pose[0, 0])
    return np.column_stack(
        [_to_radar(pose, objects.centre), objects.dims, _wrap_angle(objects.yaw - radar_yaw)]
    ).reshape(-1, 7)


def _radar_boxes(
    config: SceneConfig, objects: _Boxes, pose: np.ndarray, object_index: np.ndarray, n_parked: int
) -> tuple[dict, np.ndarray]:
    """RadarScan box fields of the objects in the FOV or with points, and ``object_index``
    renumbered to rows of those boxes."""
    counts = np.bincount(object_index[object_index >= 0], minlength=len(objects))
    boxes = _radar_frame_boxes(objects, pose)
    keep = _in_fov(boxes[:, :3], config) | (counts > 0)
    row = np.append(np.cumsum(keep) - 1, -1)  # object_index -1 picks the trailing -1
    fields = dict(
        boxes=boxes[keep].astype(np.float32).reshape(-1, 7),
        box_labels=objects.label[keep].astype(np.int64),
        box_velocities=(objects.velocity @ pose[:3, :3])[keep].astype(np.float32).reshape(-1, 3),
        box_dynamic=(np.arange(len(objects)) >= n_parked)[keep],
        box_num_points=counts[keep].astype(np.int64),
        box_ids=objects.ident[keep].astype(np.int64),
    )
    return fields, row[object_index]


def _detect(
    rng: np.random.Generator,
    config: SceneConfig,
    reflectors: _Reflectors,
    movers: _Boxes,
    n_parked: int,
    pose: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The true reflectors of one scan: (world xyz [N, 3] m, rcs [N] dBsm, object row [N] in
    parked cars + movers, -1 for none); static points first, then those on movers."""
    picked = _sample_static(rng, config, reflectors, pose)
    n_dynamic = round(picked.size * config.dynamic_fraction / (1 - config.dynamic_fraction))
    moving_xyz, moving_rcs, mover = _sample_moving(rng, config, movers, pose, n_dynamic)
    return (
        np.concatenate([reflectors.xyz[picked], moving_xyz]),
        np.concatenate([reflectors.rcs[picked], moving_rcs]),
        np.concatenate([reflectors.owner[picked], mover + n_parked]),
    )


def _sample_objects(
    rng: np.random.Generator, config: SceneConfig, objects: _Boxes, boxes: np.ndarray, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on every object by the radar equation (``points_model`` "radar"): Poisson(
    :func:`radar_physics.expected_object_points`) a scan, drawn on the radar-facing faces with
    chance proportional to the cosine of incidence (projected area), their RCS the class's
    draw plus :func:`radar_physics.incidence_gain_db`. ``boxes`` are the objects in the radar
    frame. Returns (world xyz [n, 3] m, rcs [n] dBsm, object row [n])."""
    names = [CLASS_NAMES[c] for c in objects.label]
    rcs_mean = np.array([config.rcs_dbsm[n][0] for n in names]).reshape(-1)
    near = np.linalg.norm(boxes[:, :3], axis=1) <= config.max_range + 5.0
    counts = rng.poisson(np.where(near, radar_physics.expected_object_points(boxes, names, rcs_mean), 0.0))
    xyz, rcs, owner = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros(0, dtype=np.int64)]
    for i in np.flatnonzero(counts):
        local, normal = _box_surface(rng, objects.dims[i], 8 * counts[i] + 32)
        points, normal = _box_points_world(objects, i, local, normal)
        radar_xyz, radar_normal = _to_radar(pose, points), normal @ pose[:3, :3]
        cos_in = np.clip(-np.einsum("ij,ij->i", radar_normal, _unit(radar_xyz)), 0.0, 1.0)
        chosen = np.flatnonzero((rng.random(len(points)) < cos_in) & _in_fov(radar_xyz, config))[: counts[i]]
        xyz.append(points[chosen])
        rcs.append(
            _draw_rcs(rng, config, names[i], chosen.size)
            + radar_physics.incidence_gain_db(radar_normal[chosen], radar_xyz[chosen])
        )
        owner.append(np.full(chosen.size, i, dtype=np.int64))
    return np.concatenate(xyz), np.concatenate(rcs), np.concatenate(owner)


def _detect_radar(
    rng: np.random.Generator,
    config: SceneConfig,
    reflectors: _Reflectors,
    objects: _Boxes,
    boxes: np.ndarray,
    pose: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_detect` for ``points_model`` "radar": the static world without parked cars' fixed
    reflectors (weighted sample, as "budget"), then every object by :func:`_sample_objects`."""
    background = reflectors.owner < 0
    world = _Reflectors(
        reflectors.xyz[background],
        reflectors.normal[background],
        reflectors.rcs[background],
        reflectors.owner[background],
    )
    picked = _sample_static(rng, config, world, pose)
    object_xyz, object_rcs, owner = _sample_objects(rng, config, objects, boxes, pose)
    return (
        np.concatenate([world.xyz[picked], object_xyz]),
        np.concatenate([world.rcs[picked], object_rcs]),
        np.concatenate([np.full(picked.size, -1, dtype=np.int64), owner]),
    )


def _measure(
    rng: np.random.Generator,
    config: SceneConfig,
    xyz_world: np.ndarray,
    object_index: np.ndarray,
    dynamic: np.ndarray,
    objects: _Boxes,
    pose: np.ndarray,
    v_ego: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Reported positions (radar frame, with position noise) [N, 3] m and their noise-free v_r
    = r̂·(v_obj - v_ego) [N] m/s, with v_obj the object's velocity for dynamic points, else 0.
    With ``range_noise`` / ``*_noise_deg`` the positions also get spherical noise, and with
    ``micro_doppler`` a walker's or cyclist's limb and wheel points their own speed."""
    xyz = _to_radar(pose, xyz_world) + rng.normal(0, config.position_noise, xyz_world.shape)
    xyz = radar_physics.spherical_noise(
        rng, xyz, config.range_noise, math.radians(config.azimuth_noise_deg), math.radians(config.elevation_noise_deg)
    )
    velocity = np.vstack([objects.velocity @ pose[:3, :3], np.zeros((1, 3))])  # radar frame; row -1: none
    v_obj = np.where(dynamic[:, None], velocity[object_index], 0.0)
    if config.micro_doppler and dynamic.any():
        rows = object_index[dynamic]
        bottom = objects.centre[rows, 2] - objects.dims[rows, 2] / 2
        share = (xyz_world[dynamic, 2] - bottom) / objects.dims[rows, 2]
        names = [CLASS_NAMES[c] for c in objects.label[rows]]
        v_obj[dynamic] *= radar_physics.micro_doppler_factor(rng, names, share, config.micro_doppler)[:, None]
    return xyz, np.einsum("ij,ij->i", _unit(xyz), v_obj - v_ego)


def _synthesize(scene: _Scene, k: int) -> RadarScan:
    """Frame ``k`` of the scene's sequence."""
    config, ego = scene.config, scene.ego
    rng = _rng(config.seed, _STREAM_FRAME, k)
    t = k / config.frame_rate
    pose, v_ego, s_ego = ego.pose(t), ego.velocity(), ego.speed * t
    reflectors, parked = scene.world.visible(s_ego, pose[:3, 3])
    movers = scene.traffic.at(ego.road, ego.speed, t)
    objects = _Boxes.concat([parked, movers])

    if config.points_model == "radar":
        boxes = _radar_frame_boxes(objects, pose)
        xyz_world, rcs, object_index = _detect_radar(rng, config, reflectors, objects, boxes, pose)
    else:
        xyz_world, rcs, object_index = _detect(rng, config, reflectors, movers, len(parked), pose)
    if config.occlusion:
        seen = ~radar_physics.hidden_by_boxes(
            _to_radar(pose, xyz_world), _radar_frame_boxes(objects, pose), object_index
        )
        xyz_world, rcs, object_index = xyz_world[seen], rcs[seen], object_index[seen]
    dynamic = object_index >= len(parked)
    xyz, v_r = _measure(rng, config, xyz_world, object_index, dynamic, objects, pose, v_ego)
    ghost_xyz, ghost_v_r, ghost_rcs, source = _ghosts(rng, config, xyz, rcs, v_ego)
    if config.moving_ghosts:
        ghost_v_r = np.where(dynamic[source], v_r[source], ghost_v_r)
    if config.clutter_points:
        alarm_xyz, alarm_v_r, alarm_rcs = radar_physics.false_alarms(
            rng,
            config.clutter_points,
            config.min_range,
            config.max_range,
            math.radians(config.max_azimuth_deg),
            math.radians(config.max_elevation_deg),
            doppler_span=15.0,
        )
        ghost_xyz, ghost_v_r = np.concatenate([ghost_xyz, alarm_xyz]), np.concatenate([ghost_v_r, alarm_v_r])
        ghost_rcs = np.concatenate([ghost_rcs, alarm_rcs])
    n_real, n_ghost = len(xyz), len(ghost_xyz)
    v_r = np.concatenate([v_r, ghost_v_r]) + rng.normal(0, config.doppler_noise, n_real + n_ghost)
    points = np.column_stack([np.concatenate([xyz, ghost_xyz]), v_r, np.concatenate([rcs, ghost_rcs])])
    ghost = np.arange(n_real + n_ghost) >= n_real
    dynamic = np.r_[dynamic, np.zeros(n_ghost, dtype=bool)]
    object_index = np.r_[object_index, np.full(n_ghost, -1, dtype=np.int64)]

    order = rng.permutation(np.flatnonzero(_in_fov(points[:, :3], config)))
    box_fields, object_index = _radar_boxes(config, objects, pose, object_index[order], len(parked))
    return RadarScan(
        points=points[order].astype(np.float32).reshape(-1, len(COLUMNS)),
        dynamic=dynamic[order],
        ghost=ghost[order],
        object_index=object_index,
        ego_velocity=v_ego,
        yaw_rate=ego.yaw_rate_at(t),
        pose=pose,
        timestamp=t,
        **box_fields,
    )


# ----------------------------------------------------------------------------- public API


def _resolve_config(config: SceneConfig | None, seed: int | None, overrides: dict) -> SceneConfig:
    """``config`` (default SceneConfig()) with ``seed`` and field ``overrides`` applied and validated."""
    base = SceneConfig() if config is None else config
    if not isinstance(base, SceneConfig):
        raise ConfigError(f"config must be a SceneConfig or None, got {type(base).__name__}")
    names = {f.name for f in dataclasses.fields(SceneConfig)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ConfigError(f"unknown SceneConfig field(s) {unknown}; expected some of {sorted(names)}")
    if seed is not None:
        overrides = {**overrides, "seed": seed}
    return dataclasses.replace(base, **overrides)


def generate_sequence(
    n_frames: int, config: SceneConfig | None = None, *, seed: int | None = None, **overrides
) -> list[RadarScan]:
    """``n_frames`` consecutive scans of one scene: same world, traffic and ego trajectory.

    Frame k has timestamp k / frame_rate s. ``seed`` and ``overrides`` (SceneConfig field names)
    replace the fields of ``config``. The same configuration always gives the same scans, and a
    frame does not depend on how many frames are asked for.
    """
    config = _resolve_config(config, seed, overrides)
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise ConfigError(f"n_frames must be a positive integer, got {n_frames!r}")
    ego = _draw_ego(config)
    scene = _Scene(config, ego, _StaticWorld(config, ego.road), _draw_traffic(config))
    return [_synthesize(scene, k) for k in range(int(n_frames))]


def generate_scan(config: SceneConfig | None = None, *, seed: int | None = None, **overrides) -> RadarScan:
    """One scan (frame 0 of the scene's sequence); arguments as in :func:`generate_sequence`."""
    return generate_sequence(1, config, seed=seed, **overrides)[0]


def _write_table(path: str | os.PathLike, table: np.ndarray) -> Path:
    with atomic_path(path) as tmp:
        np.ascontiguousarray(table, dtype="<f4").tofile(tmp)
    return Path(path)


def vod_table(scan: RadarScan) -> np.ndarray:
    """``scan`` as View-of-Delft radar rows, float32 [N, 7] of ``radaredge.data.readers.VOD_COLUMNS`` =
    x, y, z (m), rcs (dBsm), v_r (m/s), v_r_compensated (m/s), time (scan index).

    v_r_compensated = v_r + r̂·v_ego (about 0 on static points); time = 0, the current scan, as
    in VoD single-scan files.
    """
    xyz = scan.points[:, :3].astype(np.float64)
    v_r = scan.column("v_r").astype(np.float64)
    v_r_compensated = v_r + _unit(xyz) @ np.asarray(scan.ego_velocity, dtype=np.float64)
    return np.column_stack([xyz, scan.column("rcs"), v_r, v_r_compensated, np.zeros(len(xyz))]).astype(np.float32)


def vod_accumulated_table(scans: list[RadarScan], fov_deg: float | None = None) -> np.ndarray:
    """View-of-Delft ``radar_5frames``-style rows [N, 7] (the :func:`vod_table` columns) from
    consecutive scans, the newest last: every scan's points moved into the newest scan's radar
    frame (through the poses), ``time`` = the scan's index from the newest one (0 for the newest,
    -1 the one before, ...; View-of-Delft's devkit: "a point from the third most recent scan has
    t = -2", a scan index, not seconds), velocities as each scan measured them. ``fov_deg`` keeps the
    points within that azimuth of
    the x axis (a camera field-of-view crop, as VoD's FOV_POINTS_ONLY); None keeps all."""
    if not scans:
        raise InputError("vod_accumulated_table: no scans given")
    newest = scans[-1]
    to_newest = np.linalg.inv(newest.pose)
    rows = []
    for k, scan in enumerate(scans):
        table = vod_table(scan).astype(np.float64)
        xyz1 = np.column_stack([table[:, :3], np.ones(len(table))])
        table[:, :3] = (xyz1 @ (to_newest @ scan.pose).T)[:, :3]
        table[:, 6] = k - (len(scans) - 1)
        rows.append(table)
    out = np.concatenate(rows)
    if fov_deg is not None:
        out = out[np.abs(np.degrees(np.arctan2(out[:, 1], out[:, 0]))) <= fov_deg]
    return out.astype(np.float32)


def tj4d_table(scan: RadarScan) -> np.ndarray:
    """``scan`` as TJ4DRadSet radar rows, float32 [N, 8] of ``radaredge.data.readers.TJ4D_COLUMNS`` =
    X, Y, Z (m), V_r (m/s), Range (m), Power, Alpha, Beta.

    Our choices where the layout leaves room: Power is the point's RCS in dB; Alpha is the
    azimuth atan2(Y, X) and Beta the elevation atan2(Z, hypot(X, Y)), both in radians.
    """
    xyz = scan.points[:, :3].astype(np.float64)
    x, y, z = xyz.T
    return np.column_stack(
        [
            xyz,
            scan.column("v_r"),
            np.linalg.norm(xyz, axis=1),
            scan.column("rcs"),
            np.arctan2(y, x),
            np.arctan2(z, np.hypot(x, y)),
        ]
    ).astype(np.float32)


def write_vod_bin(path: str | os.PathLike, scan: RadarScan) -> Path:
    """Write ``scan`` as a View-of-Delft radar ``.bin`` (float32 little-endian rows of
    :func:`vod_table`). Returns the path."""
    return _write_table(path, vod_table(scan))


def write_tj4d_bin(path: str | os.PathLike, scan: RadarScan) -> Path:
    """Write ``scan`` as a TJ4DRadSet radar ``.bin`` (float32 little-endian rows of
    :func:`tj4d_table`). Returns the path."""
    return _write_table(path, tj4d_table(scan))
