"""Place-recognition training data: every K-frame window of the drives under one directory,
split by drive, and the tuples the lazy quadruplet loss trains on.

Layout. ``root`` holds drives at any depth (at most four levels): a drive is a directory with
``scans/`` (or TransLoc4D's ``pointclouds/``) and ``gps.csv`` (:mod:`radaredge.data.sequences`),
the layout ``radaredge eval`` reads, or a ROS bag with radar scans and GNSS fixes
(:mod:`radaredge.data.bag_drives`, NTU4DRadLM's topics by default; all bags in the UTM zone
of the first). ``radaredge make-benchmark`` towns qualify as they are (``town/database/drive-00``,
``town/queries/drive-01`` ...); towns of different seeds lie 10 km apart, so several can share
one root. All drives share one planar (northing, easting) frame.

Places. A window's place is the position of its last scan. As in the paper (section IV-B),
windows within ``positive_radius`` (5 m) of a query are its true positives and windows beyond
``negative_radius`` (10 m) its true negatives; between the two a window is neither. Positives
are taken from *other drives* only: a drive's own neighbouring windows share scans with the
query, and retrieval always meets another drive's database. Negatives come from any drive.

Windows. Every K consecutive scans of a drive make a window, except where two consecutive scans
lie more than ``MAX_WINDOW_GAP_S`` (1 s) apart: frames are missing there, or a folder joins
several recordings, as TransLoc4D's merged gps.csv files do.

Split. Validation is by drive: by default the last drive (by name) of every directory that
holds two or more drives; validation windows are queries against the training windows as the
database, scored by Recall@N. A training drive none of whose windows has a positive, or a
validation drive none of whose windows has a training window within 5 m, is an error naming
the drive: it shares no place with the others.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..data.bag_drives import BagSource, is_bag, load_bag_sequence
from ..data.sequences import RadarSequence, is_drive, load_sequence, windows
from ..errors import InputError
from ..eval.places import WindowSet

MAX_DEPTH = 4
MAX_WINDOW_GAP_S = 1.0  # s: a window whose consecutive scans lie further apart is skipped


def find_drives(root: str | os.PathLike) -> list[Path]:
    """Every drive directory (``scans/`` or ``pointclouds/`` inside) under ``root``, ``root`` itself included, at
    most :data:`MAX_DEPTH` levels down, sorted by path. InputError when there is none."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root} is not a directory; expected drives (scans/ + gps.csv) under it")
    found, level = [], [root]
    for _ in range(MAX_DEPTH + 1):
        nxt = []
        for d in level:
            if is_drive(d) or is_bag(d):
                found.append(d)
            elif d.is_dir():
                nxt += sorted(p for p in d.iterdir() if (p.is_dir() or is_bag(p)) and not p.name.startswith("."))
        level = nxt
    if not found:
        raise InputError(
            f"{root}: no drives found; a drive is a directory with scans/ (one scan file per frame) "
            f"or TransLoc4D's pointclouds/, and gps.csv (timestamp, northing, easting), e.g. from "
            f"`radaredge make-benchmark`"
        )
    return sorted(found)


def default_validation(drives: Sequence[Path]) -> list[Path]:
    """The last drive (by name) of every parent directory holding two or more drives."""
    by_parent: dict[Path, list[Path]] = {}
    for d in drives:
        by_parent.setdefault(d.parent, []).append(d)
    return [sorted(ds)[-1] for ds in by_parent.values() if len(ds) >= 2]


@dataclass
class PlaceWindows(WindowSet):
    """The K-frame windows of a set of training drives under ``path``: besides a
    :class:`~radaredge.eval.places.WindowSet`'s fields, ``names`` the drive names, ``drive`` [W]
    the drive row of each window and ``validation`` [W] bool (window of a validation drive)."""

    names: list[str]
    drive: np.ndarray
    validation: np.ndarray

    def distances(self, i: int, among: np.ndarray | None = None) -> np.ndarray:
        """Planar distance (m) from window ``i``'s place to every window (or to ``among``)."""
        pos = self.positions if among is None else self.positions[among]
        return np.linalg.norm(pos - self.positions[i], axis=1)


def _load_drives(
    drives: list[Path], fmt: str | None, features: Sequence[str] | None, bag: BagSource | None
) -> list[RadarSequence]:
    """Each drive's sequence; bags are read whole (``features`` columns), all in one UTM zone."""
    out, zone = [], None
    for d in drives:
        if is_bag(d):
            if features is None:
                raise InputError(f"{d}: a ROS bag drive is read at load; pass the card's features")
            seq = load_bag_sequence(d, features, bag or BagSource(), zone)
            zone = seq.utm_zone
        else:
            seq = load_sequence(d, fmt)
        out.append(seq)
    return out


def load_place_windows(
    root: str | os.PathLike,
    k: int,
    validation: Sequence[str] | None = None,
    fmt: str | None = None,
    positive_radius: float = 5.0,
    features: Sequence[str] | None = None,
    bag: BagSource | None = None,
) -> PlaceWindows:
    """The windows of every drive under ``root`` (see the module docstring), with the drives
    named in ``validation`` (paths relative to ``root``; None: :func:`default_validation`; an
    empty list: none) held out. Scan files are read on demand; ROS bags (``bag`` says where
    their scans and fixes are) are read at load, in the columns ``features``. InputError naming
    the drive for a drive that cannot be read, has fewer than ``k`` scans, or shares no place
    (``positive_radius`` m) with the others."""
    root = Path(root)
    drives = find_drives(root)
    names = [d.relative_to(root).as_posix() or "." for d in drives]
    if validation is None:
        held = {d.relative_to(root).as_posix() for d in default_validation(drives)}
    else:
        held = set(validation)
        unknown = sorted(held - set(names))
        if unknown:
            raise InputError(f"validation drive(s) {unknown} are not drives under {root}; drives: {names}")
    sequences = _load_drives(drives, fmt, features, bag)
    short = [f"{n} ({len(s)} scans)" for n, s in zip(names, sequences) if len(s) < k]
    if short:
        raise InputError(f"{root}: drive(s) {', '.join(short)} hold fewer scans than the K = {k} frames of one window")
    items, positions, drive = [], [], []
    for row, seq in enumerate(sequences):
        for frames in windows(seq, k):
            if np.diff(seq.timestamps[frames]).max(initial=0.0) > MAX_WINDOW_GAP_S:
                continue  # frames missing, or two recordings merged into one folder
            items.append((row, frames))
            positions.append(seq.positions[frames[-1]])
            drive.append(row)
        if row not in drive:
            raise InputError(
                f"{drives[row]}: no {k} consecutive scans lie within {MAX_WINDOW_GAP_S:g} s of each "
                f"other (gps.csv timestamps); no window can be formed"
            )
    out = PlaceWindows(
        root,
        k,
        sequences,
        items,
        np.asarray(positions, np.float64),
        names,
        np.asarray(drive),
        np.array([names[r] in held for r in drive]),
    )
    _check_overlap(out, positive_radius)
    return out


def _check_overlap(data: PlaceWindows, radius: float) -> None:
    """Every training drive has a window with a positive in another training drive, and every
    validation drive a window with a training window within ``radius`` m; InputError naming
    the first drive that has none."""
    train = ~data.validation
    if len(set(data.drive[train])) < 2:
        raise InputError(
            f"{data.path}: training needs two or more training drives of the same places; "
            f"found {sorted({data.names[r] for r in data.drive[train]})} "
            f"(validation: {sorted({data.names[r] for r in data.drive[data.validation]})})"
        )
    for row, name in enumerate(data.names):
        mine = np.flatnonzero(data.drive == row)
        others = np.flatnonzero(train & (data.drive != row))
        near = np.array([(data.distances(i, others) <= radius).any() for i in mine])
        if not near.any():
            role = "validation" if data.validation[mine[0]] else "training"
            raise InputError(
                f"{data.path / name}: none of this {role} drive's {len(mine)} windows lies within "
                f"{radius:g} m of a window of another training drive (too few positives: it shares "
                f"no place with the others; check its gps.csv)"
            )


OTHER_NEGATIVES = ("random", "hardest")


@dataclass
class Tuple:
    """One training tuple of window indices: the query, its positives, negatives and the other
    negative neg* (a true negative of the query and of every negative)."""

    query: int
    positives: list[int]
    negatives: list[int]
    other_negative: int


class TupleMiner:
    """Draws training tuples from :class:`PlaceWindows` (training windows only). The queries are
    the training windows that have a positive and enough true negatives for a tuple.

    Positives: ``positives`` windows of other drives within ``positive_radius`` m, drawn at
    random (with repetition when fewer exist). Negatives: ``negatives`` windows beyond
    ``negative_radius`` m; ``hard`` of them the nearest to the query in descriptor space among
    up to ``hard_pool`` random true negatives (descriptors from :meth:`set_descriptors`; without
    them all are random), the rest random. neg*: a window beyond ``negative_radius`` m of the
    query and of every negative (any true negative of the query when there is none), drawn at
    random (``other_negative="random"``) or, with descriptors, the nearest to the query in
    descriptor space among up to ``hard_pool`` of them (``"hardest"``).
    """

    def __init__(
        self,
        data: PlaceWindows,
        positives: int,
        negatives: int,
        hard: int,
        positive_radius: float = 5.0,
        negative_radius: float = 10.0,
        hard_pool: int = 4000,
        other_negative: str = "random",
    ):
        if other_negative not in OTHER_NEGATIVES:
            raise ValueError(f"other_negative must be one of {list(OTHER_NEGATIVES)}, got {other_negative!r}")
        self.other = other_negative
        self.data, self.p, self.n, self.hard = data, positives, negatives, min(hard, negatives)
        self.pos_r, self.neg_r, self.pool = positive_radius, negative_radius, hard_pool
        self.train = np.flatnonzero(~data.validation)
        self.descriptors: np.ndarray | None = None
        # a query needs a positive and negatives + 1 true negatives (the negatives and neg*)
        self.queries = np.array(
            [i for i in self.train if len(self._positives(i)) and len(self._negatives(i)) > self.n], dtype=np.int64
        )
        if not len(self.queries):
            raise InputError(
                f"{data.path}: no training window has both a window of another training drive within "
                f"{positive_radius:g} m and {self.n + 1} training windows beyond {negative_radius:g} m; "
                f"the drives share no place, or cover too little ground for the negatives"
            )

    def _positives(self, i: int) -> np.ndarray:
        d = self.data
        cand = self.train[d.drive[self.train] != d.drive[i]]
        return cand[d.distances(i, cand) <= self.pos_r]

    def _negatives(self, i: int) -> np.ndarray:
        return self.train[self.data.distances(i, self.train) > self.neg_r]

    def set_descriptors(self, descriptors: np.ndarray | None) -> None:
        """Descriptors [W, D] of every window (validation rows unused) for hard negatives; None: random negatives."""
        self.descriptors = descriptors

    def tuple_for(self, q: int, rng: np.random.Generator) -> Tuple:
        pos = self._positives(q)
        neg_all = self._negatives(q)
        if not len(pos) or len(neg_all) < self.n + 1:
            raise InputError(
                f"window {q} of {self.data.names[self.data.drive[q]]}: {len(pos)} positives within "
                f"{self.pos_r:g} m and {len(neg_all)} negatives beyond {self.neg_r:g} m; a tuple needs "
                f"1 and {self.n + 1}"
            )
        positives = list(rng.choice(pos, self.p, replace=len(pos) < self.p))
        chosen: list[int] = []
        if self.hard and self.descriptors is not None:
            cand = rng.choice(neg_all, min(len(neg_all), self.pool), replace=False)
            dist = np.linalg.norm(self.descriptors[cand] - self.descriptors[q], axis=1)
            chosen = list(cand[np.argsort(dist, kind="stable")[: self.hard]])
        rest = np.setdiff1d(neg_all, chosen)
        chosen += list(rng.choice(rest, self.n - len(chosen), replace=False))
        far = neg_all[
            np.all(
                np.linalg.norm(self.data.positions[neg_all][:, None] - self.data.positions[chosen][None], axis=2)
                > self.neg_r,
                axis=1,
            )
        ]
        far = far if len(far) else np.setdiff1d(neg_all, chosen)
        if self.other == "hardest" and self.descriptors is not None:
            cand = rng.choice(far, min(len(far), self.pool), replace=False)
            star = int(cand[np.argmin(np.linalg.norm(self.descriptors[cand] - self.descriptors[q], axis=1))])
        else:
            star = int(rng.choice(far))
        return Tuple(int(q), [int(i) for i in positives], [int(i) for i in chosen], star)
