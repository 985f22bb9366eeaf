"""Radar effects of the synthetic scenes that go beyond geometry: line-of-sight occlusion,
points per object from the radar equation, measurement noise in spherical coordinates,
micro-Doppler of walking and pedalling, and false alarms.

Radar frame (x forward, y left, z up, m; velocities m/s). Boxes are float [M, 7] rows
x, y, z (centre), length, width, height, yaw (rad about z from the x axis), as
``RadarScan.boxes``. :mod:`radaredge.data.synthetic` calls these when a ``SceneConfig`` asks for
them; every function here is deterministic given its generator.
"""

from __future__ import annotations

import numpy as np

OCCLUDER_SHRINK = 0.9  # occluders block within 90 % of their extent: radar sees under cars and past edges
OCCLUSION_MARGIN = 0.15  # m: a box this close in front of a point (along the ray) does not hide it
SNR_SLOPE_DB = 3.0  # dB, width of the detection probability's logistic step
REFERENCE_RANGE = 10.0  # m, range at which ``snr_margin_db`` applies

# points per (m^2 of projected area / m of range) at full detection probability, per class:
# a car seen broadside at 10 m gives about 35 points a scan, a pedestrian about 8, a cyclist
# broadside about 12, falling with 1/range (cells per object) and the detection probability.
POINT_DENSITY = {"car": 52.0, "pedestrian": 80.0, "cyclist": 40.0}
SNR_MARGIN_DB = 22.0  # dB of SNR at 10 m above a 0 dBsm reflector's detection threshold

# unit-box face samples for the occlusion share of a label: 4 x 4 points on each of the five
# outer faces (no bottom), with their outward normals
_GRID = np.array([-0.375, -0.125, 0.125, 0.375])


def _face_samples() -> tuple[np.ndarray, np.ndarray]:
    u, v = (a.ravel() for a in np.meshgrid(_GRID, _GRID))
    points, normals = [], []
    for axis in range(3):
        for sign in (1.0, -1.0) if axis < 2 else (1.0,):
            p = np.zeros((u.size, 3))
            others = [k for k in range(3) if k != axis]
            p[:, axis] = 0.5 * sign
            p[:, others[0]], p[:, others[1]] = u, v
            n = np.zeros((u.size, 3))
            n[:, axis] = sign
            points.append(p)
            normals.append(n)
    return np.concatenate(points), np.concatenate(normals)


_FACE_POINTS, _FACE_NORMALS = _face_samples()


def _rotate_z(xyz: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotate [..., 3] vectors by ``yaw`` (broadcast) about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * xyz[..., 0] - s * xyz[..., 1], s * xyz[..., 0] + c * xyz[..., 1], xyz[..., 2]], -1)


def hidden_by_boxes(
    points: np.ndarray,
    boxes: np.ndarray,
    own: np.ndarray | None = None,
    shrink: float = OCCLUDER_SHRINK,
    margin: float = OCCLUSION_MARGIN,
) -> np.ndarray:
    """bool [N]: the straight path from the radar (the origin) to point n passes through a box
    ([M, 7], scaled by ``shrink`` about its centre) more than ``margin`` m before the point, in
    3D (azimuth and elevation). ``own`` [N] is the row of the box each point lies on (-1 for
    none); a point is never hidden by its own box."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    n, m = len(points), len(boxes)
    if n == 0 or m == 0:
        return np.zeros(n, bool)
    yaw = boxes[:, 6]
    target = _rotate_z(points[:, None, :] - boxes[None, :, :3], -yaw[None, :])  # [N, M, 3] box frame
    origin = _rotate_z(-boxes[:, :3], -yaw)  # [M, 3]
    half = 0.5 * shrink * boxes[:, 3:6]  # [M, 3]
    direction = target - origin[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - origin)[None] / direction
        t2 = (half - origin)[None] / direction
    flat = direction == 0
    inside = (np.abs(origin) <= half)[None]
    low = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    high = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    enter, leave = low.max(-1), high.min(-1)
    length = np.maximum(np.linalg.norm(points, axis=1), 1e-6)[:, None]
    hit = (enter <= leave) & (leave > 0) & (enter > 0) & (enter < 1.0 - margin / length)
    if own is not None:
        own = np.asarray(own).reshape(-1)
        rows = np.flatnonzero(own >= 0)
        hit[rows, own[rows]] = False
    return hit.any(1)


def occluded_share(boxes: np.ndarray) -> np.ndarray:
    """Share [M] of each box's radar-facing surface (16 samples a face) that the other boxes hide
    (:func:`hidden_by_boxes`); 0 for a box with no face towards the radar."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    m = len(boxes)
    if m == 0:
        return np.zeros(0)
    local = _FACE_POINTS[None] * boxes[:, None, 3:6]  # [M, K, 3]
    points = _rotate_z(local, boxes[:, 6:7]) + boxes[:, None, :3]
    normals = _rotate_z(np.broadcast_to(_FACE_NORMALS, local.shape), boxes[:, 6:7])
    facing = np.einsum("mkj,mkj->mk", normals, points) < 0
    own = np.repeat(np.arange(m), local.shape[1])
    hidden = hidden_by_boxes(points.reshape(-1, 3), boxes, own).reshape(m, -1)
    seen = facing.sum(1)
    return np.where(seen > 0, (hidden & facing).sum(1) / np.maximum(seen, 1), 0.0)


def projected_area(boxes: np.ndarray) -> np.ndarray:
    """Area (m^2) [M] of the boxes' vertical faces as seen from the radar: |cos a| w h + |sin a| l h
    with a the line of sight's azimuth relative to the box's heading."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    aspect = np.arctan2(boxes[:, 1], boxes[:, 0]) - boxes[:, 6]
    return (np.abs(np.cos(aspect)) * boxes[:, 4] + np.abs(np.sin(aspect)) * boxes[:, 3]) * boxes[:, 5]


def detection_probability(rcs_dbsm: np.ndarray, r: np.ndarray, margin_db: float = SNR_MARGIN_DB) -> np.ndarray:
    """Chance that a reflector of ``rcs_dbsm`` at range ``r`` m crosses the detection threshold: a
    logistic step in the SNR, which falls 40 dB a decade of range (the radar equation)."""
    snr = np.asarray(rcs_dbsm) + margin_db - 40.0 * np.log10(np.maximum(np.asarray(r), 1.0) / REFERENCE_RANGE)
    return 1.0 / (1.0 + np.exp(-snr / SNR_SLOPE_DB))


def expected_object_points(boxes: np.ndarray, class_names: list[str], rcs_mean: np.ndarray) -> np.ndarray:
    """Mean points a scan [M] on each object: the class's point density x projected area /
    range (resolution cells fall with range) x detection probability of its mean RCS."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    r = np.maximum(np.linalg.norm(boxes[:, :3], axis=1), 3.0)
    density = np.array([POINT_DENSITY[c] for c in class_names])
    return density * projected_area(boxes) / r * detection_probability(rcs_mean, r)


def incidence_gain_db(normals: np.ndarray, points: np.ndarray, specular_db: float = 6.0) -> np.ndarray:
    """RCS gain (dB) [N] of a face point from its incidence angle: ``specular_db`` head-on, falling
    as cos^4 to -3 dB at grazing incidence (flat panels reflect mostly back along their normal)."""
    cos_in = np.clip(
        -np.einsum("ij,ij->i", normals, points) / np.maximum(np.linalg.norm(points, axis=1), 1e-9), 0.0, 1.0
    )
    return (specular_db + 3.0) * cos_in**4 - 3.0


def spherical_noise(
    rng: np.random.Generator, xyz: np.ndarray, range_sigma: float, azimuth_sigma: float, elevation_sigma: float
) -> np.ndarray:
    """``xyz`` [N, 3] (m) with Gaussian noise on range (m), azimuth and elevation (rad): a radar
    measures angles, and a 4D radar's elevation far less precisely than its azimuth."""
    xyz = np.asarray(xyz, np.float64)
    if len(xyz) == 0 or not (range_sigma or azimuth_sigma or elevation_sigma):
        return xyz
    r = np.linalg.norm(xyz, axis=1)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0]) + rng.normal(0, azimuth_sigma, len(xyz))
    elevation = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])) + rng.normal(0, elevation_sigma, len(xyz))
    r = np.maximum(r + rng.normal(0, range_sigma, len(xyz)), 0.0)
    return np.column_stack(
        [r * np.cos(elevation) * np.cos(azimuth), r * np.cos(elevation) * np.sin(azimuth), r * np.sin(elevation)]
    )


def micro_doppler_factor(
    rng: np.random.Generator, class_names: list[str], height_share: np.ndarray, strength: float
) -> np.ndarray:
    """Factor [N] on an object point's velocity along the object's heading: a walker's legs
    (lower half) swing between standing still and twice the body's speed, a cyclist's wheel rims
    (lowest 40 %) between 0 and 2x (cos of the rim angle) and the pedalling legs above them by
    +-30 %; a car's points and a walker's torso move with the body (1). ``strength`` scales the
    spread (0: none, 1: as described)."""
    n = len(height_share)
    factor = np.ones(n)
    if n == 0 or strength == 0:
        return factor
    names = np.asarray(class_names, dtype=object)
    legs = (names == "pedestrian") & (height_share < 0.5)
    wheels = (names == "cyclist") & (height_share < 0.4)
    pedals = (names == "cyclist") & (height_share >= 0.4) & (height_share < 0.7)
    spread = np.zeros(n)
    spread[legs] = rng.uniform(-1.0, 1.0, legs.sum())
    spread[wheels] = np.cos(rng.uniform(0.0, 2 * np.pi, wheels.sum()))
    spread[pedals] = rng.uniform(-0.3, 0.3, pedals.sum())
    return factor + strength * spread


def false_alarms(
    rng: np.random.Generator,
    mean: float,
    min_range: float,
    max_range: float,
    max_azimuth: float,
    max_elevation: float,
    doppler_span: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poisson(``mean``) CFAR false alarms, uniform over the field of view's area (range drawn
    with density rising linearly in r), azimuth and elevation (rad): (xyz [F, 3] m, v_r [F] m/s
    uniform in +-``doppler_span``, rcs [F] dBsm near the noise floor)."""
    count = int(rng.poisson(mean)) if mean > 0 else 0
    r = np.sqrt(rng.uniform(min_range**2, max_range**2, count))
    azimuth = rng.uniform(-max_azimuth, max_azimuth, count)
    elevation = rng.uniform(-max_elevation, max_elevation, count)
    xyz = np.column_stack(
        [r * np.cos(elevation) * np.cos(azimuth), r * np.cos(elevation) * np.sin(azimuth), r * np.sin(elevation)]
    )
    return xyz, rng.uniform(-doppler_span, doppler_span, count), rng.normal(-15.0, 4.0, count)
