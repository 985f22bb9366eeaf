"""GNSS latitude/longitude to planar UTM (easting, northing), the positions of recorded drives.

The Transverse Mercator projection on the WGS 84 ellipsoid with the UTM conventions: 6-degree
zones numbered from 180 W, scale 0.9996 on the central meridian, false easting 500 km and, south
of the equator, false northing 10,000 km. The series are Snyder's ("Map Projections: A Working
Manual", USGS Professional Paper 1395, eq. 3-21, 8-9 and 8-10), good to well under a millimetre
within a zone, which is ample for place-recognition radii of metres.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

WGS84_A = 6378137.0  # m, semi-major axis
WGS84_F = 1.0 / 298.257223563  # flattening
UTM_K0 = 0.9996
FALSE_EASTING = 500_000.0
FALSE_NORTHING_SOUTH = 10_000_000.0


def utm_zone(lon_deg: float) -> int:
    """The UTM zone (1..60) of a longitude in degrees (the Norway/Svalbard exceptions are not applied)."""
    return int(math.floor(((lon_deg + 180.0) % 360.0) / 6.0)) + 1


def transverse_mercator(
    lat_deg, lon_deg, lon0_deg: float, a: float = WGS84_A, f: float = WGS84_F, k0: float = UTM_K0
) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) m of latitudes/longitudes (degrees) on the ellipsoid (a, f) about the central
    meridian ``lon0_deg``, scale ``k0``: x east of the central meridian, y north of the equator,
    without false easting or northing."""
    lat = np.radians(np.asarray(lat_deg, np.float64))
    dlon = np.radians(np.asarray(lon_deg, np.float64) - lon0_deg)
    e2 = f * (2.0 - f)
    ep2 = e2 / (1.0 - e2)
    sin, cos, tan = np.sin(lat), np.cos(lat), np.tan(lat)
    n = a / np.sqrt(1.0 - e2 * sin * sin)
    t = tan * tan
    c = ep2 * cos * cos
    big_a = cos * dlon
    e4, e6 = e2 * e2, e2 * e2 * e2
    m = a * (
        (1 - e2 / 4 - 3 * e4 / 64 - 5 * e6 / 256) * lat
        - (3 * e2 / 8 + 3 * e4 / 32 + 45 * e6 / 1024) * np.sin(2 * lat)
        + (15 * e4 / 256 + 45 * e6 / 1024) * np.sin(4 * lat)
        - (35 * e6 / 3072) * np.sin(6 * lat)
    )
    x = k0 * n * (big_a + (1 - t + c) * big_a**3 / 6 + (5 - 18 * t + t * t + 72 * c - 58 * ep2) * big_a**5 / 120)
    y = k0 * (
        m
        + n
        * tan
        * (
            big_a**2 / 2
            + (5 - t + 9 * c + 4 * c * c) * big_a**4 / 24
            + (61 - 58 * t + t * t + 600 * c - 330 * ep2) * big_a**6 / 720
        )
    )
    return x, y


def utm_from_latlon(
    lat_deg, lon_deg, zone: int | None = None, south: bool | None = None
) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """(easting m, northing m, zone, south) of WGS 84 latitudes/longitudes in degrees, all in one
    zone: ``zone`` (default: the zone of the first point) and hemisphere ``south`` (default: that
    of the first point), so that a whole drive shares one planar frame. InputError for a
    non-finite or out-of-range coordinate."""
    lat = np.asarray(lat_deg, np.float64).ravel()
    lon = np.asarray(lon_deg, np.float64).ravel()
    if lat.shape != lon.shape or lat.size == 0:
        raise InputError(
            f"latitudes and longitudes must be two equal, non-empty lists, got {lat.shape} and {lon.shape}"
        )
    bad = ~(np.isfinite(lat) & np.isfinite(lon) & (np.abs(lat) <= 84.0) & (np.abs(lon) <= 180.0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"fix {i}: latitude {lat[i]!r}, longitude {lon[i]!r} deg is not a UTM position "
            f"(finite, |lat| <= 84, |lon| <= 180)"
        )
    zone = utm_zone(float(lon[0])) if zone is None else int(zone)
    south = bool(lat[0] < 0) if south is None else bool(south)
    x, y = transverse_mercator(lat, lon, (zone - 1) * 6.0 - 180.0 + 3.0)
    return x + FALSE_EASTING, y + (FALSE_NORTHING_SOUTH if south else 0.0), zone, south
