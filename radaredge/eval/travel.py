"""Which way a window drives, from positions alone: a window's heading, and whether a query
drives against the database windows at its place (a revisit in the opposite direction sees the
same street mirrored, the hardest case for a BEV descriptor).

Positions are (northing, easting) in metres; a heading is atan2(d_easting, d_northing) in
radians (0 north, pi/2 east).
"""

from __future__ import annotations

import numpy as np

MIN_MOVE_M = 0.5  # a window that moves less than this has no heading (the car stands)
AGAINST, WITH, UNKNOWN = 1, 0, -1


def window_headings(window_set, min_move: float = MIN_MOVE_M) -> np.ndarray:
    """float64 [W]: each window's direction of travel from its oldest to its newest scan
    position (rad); NaN where the two lie less than ``min_move`` m apart. ``window_set`` is a
    :class:`radaredge.eval.places.WindowSet`."""
    out = np.full(len(window_set), np.nan)
    for i, (drive, frames) in enumerate(window_set.items):
        pos = window_set.sequences[drive].positions
        step = pos[frames[-1]] - pos[frames[0]]
        if np.hypot(*step) >= min_move:
            out[i] = np.arctan2(step[1], step[0])
    return out


def against_database(query_pos, query_heading, db_pos, db_heading, radius: float) -> np.ndarray:
    """int8 [Q]: AGAINST (1) where a query's heading differs by more than 90 degrees from that
    of the nearest database window, WITH (0) where it does not, UNKNOWN (-1) where either has no
    heading or no database window lies within ``radius`` m. Positions [Q, 2] / [B, 2] m,
    headings [Q] / [B] rad (:func:`window_headings`)."""
    query_pos, db_pos = np.asarray(query_pos, dtype=np.float64), np.asarray(db_pos, dtype=np.float64)
    out = np.full(len(query_pos), UNKNOWN, dtype=np.int8)
    for first in range(0, len(query_pos), 512):
        block = slice(first, first + 512)
        dist = np.linalg.norm(db_pos[None] - query_pos[block, None], axis=2)  # [q, B] m
        nearest = dist.argmin(1)
        near = dist[np.arange(len(nearest)), nearest] <= radius
        turn = np.abs(np.angle(np.exp(1j * (np.asarray(query_heading[block]) - db_heading[nearest]))))
        known = near & np.isfinite(turn)
        out[block][known] = np.where(turn[known] > np.pi / 2, AGAINST, WITH)
    return out
