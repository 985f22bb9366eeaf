"""radaredge.eval.travel: window headings from positions, and queries driving against the database."""

from types import SimpleNamespace

import numpy as np

from radaredge.eval.travel import AGAINST, UNKNOWN, WITH, against_database, window_headings


class _Set(SimpleNamespace):
    def __len__(self):
        return len(self.items)


def _set(tracks, k=3):
    """A WindowSet-like object: one drive per track ([T, 2] positions), every K-frame window."""
    sequences = [SimpleNamespace(positions=np.asarray(t, dtype=np.float64)) for t in tracks]
    items = [(d, np.arange(i, i + k)) for d, t in enumerate(tracks) for i in range(len(t) - k + 1)]
    positions = np.array([sequences[d].positions[f[-1]] for d, f in items])
    return _Set(sequences=sequences, items=items, positions=positions)


def test_headings_follow_the_track_and_standing_has_none():
    north = np.stack([np.arange(6.0), np.zeros(6)], 1)  # northing grows: heading 0
    east = np.stack([np.zeros(6), np.arange(6.0)], 1)  # easting grows: heading pi/2
    still = np.zeros((4, 2))
    h = window_headings(_set([north, east, still]))
    assert np.allclose(h[:4], 0.0) and np.allclose(h[4:8], np.pi / 2) and np.isnan(h[8:]).all()


def test_queries_against_the_database_are_told_apart():
    db = _set([np.stack([np.arange(0.0, 50.0), np.zeros(50)], 1)])  # north along easting 0
    queries = _set(
        [
            np.stack([np.arange(10.0, 20.0), np.full(10, 3.0)], 1),  # the other lane, northward
            np.stack([np.arange(40.0, 30.0, -1.0), np.zeros(10)], 1),  # southward
            np.stack([np.full(5, 20.0), np.zeros(5)], 1),  # standing
            np.stack([np.arange(10.0), np.full(10, 100.0)], 1),
        ]
    )  # no database within 5 m
    way = against_database(queries.positions, window_headings(queries), db.positions, window_headings(db), 5.0)
    drive = np.array([d for d, _ in queries.items])
    assert (way[drive == 0] == WITH).all() and (way[drive == 1] == AGAINST).all()
    assert (way[drive == 2] == UNKNOWN).all() and (way[drive == 3] == UNKNOWN).all()
