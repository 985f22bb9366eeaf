"""A recorded drive from a ROS bag: radar scans from a point-cloud topic, positions from GNSS fixes.

NTU4DRadLM records each drive as ROS 1 bags holding the Oculii radar's clouds on
``/radar_enhanced_pcl`` (``sensor_msgs/PointCloud``: x, y, z from the points, the Doppler velocity
and the power as channels) and the u-blox receiver's fixes on ``/ublox/fix``
(``sensor_msgs/NavSatFix``); its ground-truth trajectory lives in a local odometry frame of each
sequence, so only the fixes put several drives into one frame. :func:`load_bag_sequence` reads:

- the scans of ``radar_topic`` with :func:`radaredge.data.readers.iter_rosbag` (columns found by
  name, or by ``field_map``: e.g. ``{"v_r": 0, "rcs": 2}`` for NTU4DRadLM's channel indices),
  the radial velocity multiplied by ``doppler_sign`` (-1 for a sensor whose Doppler is positive
  when approaching; radaredge's ``v_r`` is positive moving away);
- the fixes of ``gps_topic`` with a fix (``status.status`` >= 0) and finite coordinates,
  projected to UTM (:mod:`radaredge.data.geodesy`, the zone of the bag's first fix);
- each scan's position, interpolated linearly in time between the fixes around its header
  stamp; scans before the first or after the last fix are left out.

A drive is then a :class:`radaredge.data.sequences.RadarSequence` held in memory.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import InputError
from .geodesy import utm_from_latlon
from .readers import bag_topic, iter_rosbag
from .sequences import RadarSequence

BAG_SUFFIXES = (".bag", ".mcap", ".db3")
NAVSATFIX = "sensor_msgs/msg/NavSatFix"


@dataclass(frozen=True)
class BagSource:
    """Where a bag holds its radar scans and GNSS fixes (defaults: NTU4DRadLM's topics)."""

    radar_topic: str = "/radar_enhanced_pcl"
    gps_topic: str = "/ublox/fix"
    field_map: Mapping[str, str | int] = field(default_factory=dict)
    doppler_sign: float = 1.0

    def __post_init__(self):
        if self.doppler_sign not in (1.0, -1.0):
            raise InputError(f"doppler_sign must be 1 or -1, got {self.doppler_sign!r}")


def is_bag(path: str | os.PathLike) -> bool:
    """``path`` is a ROS bag: a ``.bag``/``.mcap``/``.db3`` file or a rosbag2 directory (metadata.yaml)."""
    path = Path(path)
    return (path.is_file() and path.suffix in BAG_SUFFIXES) or (path.is_dir() and (path / "metadata.yaml").is_file())


def read_fixes(path: str | os.PathLike, topic: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(header stamps s, latitudes deg, longitudes deg) of the valid fixes (status >= 0, finite)
    on ``topic`` (``sensor_msgs/NavSatFix``) of a ROS 1 or ROS 2 bag, in recording order."""
    path = Path(path)
    stamps, lat, lon = [], [], []
    with bag_topic(path, topic, [NAVSATFIX], "GNSS ") as (reader, connections):
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            if msg.status.status < 0 or not (np.isfinite(msg.latitude) and np.isfinite(msg.longitude)):
                continue
            stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
            lat.append(msg.latitude)
            lon.append(msg.longitude)
    return np.asarray(stamps, np.float64), np.asarray(lat, np.float64), np.asarray(lon, np.float64)


def load_bag_sequence(
    path: str | os.PathLike, features: Sequence[str], source: BagSource = BagSource(), zone: int | None = None
) -> RadarSequence:
    """The drive recorded in the bag at ``path`` (module docstring), its scans in the columns
    ``features``, its positions (northing, easting) in UTM ``zone`` (default: the first fix's).
    InputError naming the bag for a missing topic, no valid fix, or no scan within the fixes' time span."""
    path = Path(path)
    features = list(features)
    t_fix, lat, lon = read_fixes(path, source.gps_topic)
    if len(t_fix) < 2:
        raise InputError(
            f"{path}: {len(t_fix)} valid GNSS fix(es) on {source.gps_topic!r}; positions need at least "
            f"2 (a fix with status >= 0 and finite latitude and longitude)"
        )
    order = np.argsort(t_fix, kind="stable")
    t_fix, lat, lon = t_fix[order], lat[order], lon[order]
    easting, northing, zone, _ = utm_from_latlon(lat, lon, zone)
    scans, stamps = [], []
    for stamp, points in iter_rosbag(path, source.radar_topic, features, source.field_map):
        if t_fix[0] <= stamp <= t_fix[-1]:
            if "v_r" in features and source.doppler_sign != 1.0:
                points[:, features.index("v_r")] *= source.doppler_sign
            scans.append(points)
            stamps.append(stamp)
    if not scans:
        raise InputError(
            f"{path}: no scan on {source.radar_topic!r} lies within the GNSS fixes' time span "
            f"{t_fix[0]:.3f}-{t_fix[-1]:.3f} s"
        )
    stamps = np.asarray(stamps, np.float64)
    order = np.argsort(stamps, kind="stable")
    keep = order[np.r_[True, np.diff(stamps[order]) > 0]]  # one scan per stamp, in time order
    positions = np.stack([np.interp(stamps[keep], t_fix, northing), np.interp(stamps[keep], t_fix, easting)], 1)
    return RadarSequence(
        path.name,
        [path] * len(keep),
        stamps[keep],
        positions,
        "rosbag",
        [scans[i] for i in keep],
        tuple(features),
        zone,
    )
