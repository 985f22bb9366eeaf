"""A seeded synthetic city for text-to-point-cloud localisation: objects, cells, poses, hints.

Objects (buildings, boxes, poles, traffic signs, vegetation, fences, trash bins: KITTI360Pose
classes) stand on a flat ground in a square world; each is a set of coloured surface points
(xyz in m, rgb in [0, 1]).
Cells are ``size`` x ``size`` m squares on a ``stride`` grid (Des4Pos / Text2Loc: 30 m, 10 m);
each holds the parts of the objects inside it (at least ``min_points`` points), with xyz
normalised to the cell as in KITTI360Pose. Query poses are random ground positions; each is
described by hints on the nearest objects of its best cell (the cell whose centre is nearest),
in Text2Loc's template: "The pose is {direction} of a {colour} {label}." with direction north
(+y), south, east (+x), west, or "on-top" when the pose lies on the object's footprint.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cards.des4pos import CellConfig, TextConfig
from ..errors import ConfigError
from ..runtime.cellmap import CellMap, pack_cells

COLOURS = {
    "red": (0.80, 0.12, 0.10),
    "gray": (0.50, 0.50, 0.50),
    "green": (0.15, 0.60, 0.20),
    "white": (0.92, 0.92, 0.90),
    "black": (0.08, 0.08, 0.08),
    "blue": (0.12, 0.25, 0.75),
    "beige": (0.80, 0.72, 0.55),
    "yellow": (0.90, 0.80, 0.10),
}
# label -> (footprint x, y range m, height range m, points per m^2 of surface, shape, colours). The
# labels are KITTI360Pose's (Text2Pos's classes), so a model's object classes cover them.
CLASSES = {
    "building": ((8, 16), (8, 16), (6, 15), 3.0, "box", ("gray", "beige", "white", "red")),
    "box": ((1.0, 1.6), (0.8, 1.2), (1.0, 1.4), 60.0, "box", ("red", "blue", "black", "white", "gray")),
    "pole": ((0.2, 0.3), (0.2, 0.3), (4, 8), 120.0, "cylinder", ("gray", "black")),
    "traffic sign": ((0.6, 0.9), (0.1, 0.2), (2.2, 2.8), 120.0, "box", ("blue", "red", "yellow")),
    "vegetation": ((3, 6), (3, 6), (4, 8), 8.0, "ellipsoid", ("green",)),
    "fence": ((6, 14), (0.1, 0.2), (1.0, 1.8), 12.0, "box", ("gray", "white", "beige")),
    "trash bin": ((0.6, 0.8), (0.6, 0.8), (0.9, 1.2), 150.0, "box", ("green", "black", "gray")),
}


def colour_name(rgb) -> str:
    """Nearest named colour (L2 in RGB), as Text2Loc names an object's mean colour."""
    names = list(COLOURS)
    d = np.linalg.norm(np.array([COLOURS[n] for n in names]) - np.asarray(rgb), axis=1)
    return names[int(np.argmin(d))]


def _surface(rng, shape: str, ext: np.ndarray, n: int) -> np.ndarray:
    """``n`` points on the surface of a box / cylinder / ellipsoid of extent ``ext`` at the origin."""
    if shape == "box":
        p = rng.uniform(-0.5, 0.5, (n, 3)) * ext
        face = rng.integers(0, 5, n)  # 4 walls + roof (no floor)
        axis = np.array([0, 0, 1, 1, 2])[face]
        sign = np.array([-0.5, 0.5, -0.5, 0.5, 0.5])[face]
        p[np.arange(n), axis] = sign * ext[axis]
    elif shape == "cylinder":
        a = rng.uniform(0, 2 * np.pi, n)
        p = np.stack([np.cos(a) * ext[0] / 2, np.sin(a) * ext[1] / 2, rng.uniform(-0.5, 0.5, n) * ext[2]], 1)
    else:
        v = rng.normal(size=(n, 3))
        p = v / np.linalg.norm(v, axis=1, keepdims=True) * ext / 2
    p[:, 2] += ext[2] / 2  # stand on z = 0
    return p


def make_objects(rng: np.random.Generator, world: float, count: int) -> list[dict]:
    objs = []
    names = list(CLASSES)
    weights = np.array([0.18, 0.22, 0.14, 0.12, 0.16, 0.08, 0.10])
    for i in range(count):
        label = names[rng.choice(len(names), p=weights)]
        (x0, x1), (y0, y1), (z0, z1), dens, shape, cols = CLASSES[label]
        ext = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1), rng.uniform(z0, z1)])
        if rng.random() < 0.5:
            ext[[0, 1]] = ext[[1, 0]]  # turned by 90 degrees
        area = 2 * (ext[0] + ext[1]) * ext[2] + ext[0] * ext[1]
        n = int(np.clip(area * dens, 40, 4000))
        centre = np.array([rng.uniform(0, world), rng.uniform(0, world)])
        xyz = _surface(rng, shape, ext, n) + np.array([centre[0], centre[1], 0.0])
        col = cols[rng.integers(len(cols))]
        rgb = np.clip(np.array(COLOURS[col]) + rng.normal(0, 0.04, (n, 3)), 0, 1)
        objs.append(
            {
                "id": i,
                "label": label,
                "centre": centre,
                "extent": ext,
                "xyz": xyz,
                "rgb": rgb,
                "colour": colour_name(rgb.mean(0)),
            }
        )
    return objs


def direction(pose: np.ndarray, obj: dict) -> str:
    """Text2Loc's hint direction of ``pose`` relative to ``obj`` (world x east, y north)."""
    off = pose - obj["centre"]
    if (np.abs(off) <= obj["extent"][:2] / 2).all():
        return "on-top"
    if abs(off[1]) >= abs(off[0]):
        return "north" if off[1] > 0 else "south"
    return "east" if off[0] > 0 else "west"


MAX_MAP_BYTES = 2 * 2**30  # a map's packed points (cells x slots x points x 6 float32)
MAX_CELL_OBJECT_PAIRS = 5 * 10**7  # cells x objects membership tests (a minute of work)


def make_city(
    slots: int,
    points: int,
    seed: int = 0,
    world: float = 90.0,
    size: float = 30.0,
    stride: float = 10.0,
    objects: int = 70,
    poses: int = 40,
    min_hints: int = 2,
    max_hints: int = 6,
    min_points: int = 8,
) -> CellMap:
    """The synthetic city as a :class:`CellMap` in the model's slot layout, with query poses.
    ConfigError for a city that cannot hold a cell (no objects, a world smaller than a cell)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {seed!r}")
    if not np.isfinite(world) or objects < 1 or poses < 0 or not size <= world or stride <= 0:
        raise ConfigError(
            f"a synthetic city needs objects >= 1, poses >= 0, a world edge >= the cell size "
            f"({size:g} m) and a positive stride; got objects={objects}, poses={poses}, "
            f"world={world:g} m, stride={stride:g} m"
        )
    cells_max = int((world - size) // stride + 1) ** 2
    if cells_max * objects > MAX_CELL_OBJECT_PAIRS or cells_max * slots * points * 24 > MAX_MAP_BYTES:
        raise ConfigError(
            f"a {world:g} m city of {objects} objects makes up to {cells_max} cells of {size:g} m every "
            f"{stride:g} m: {cells_max * slots * points * 24 / 2**30:.1f} GiB of packed points and "
            f"{cells_max * objects:.3g} cell-object tests; at most {MAX_MAP_BYTES / 2**30:g} GiB and "
            f"{MAX_CELL_OBJECT_PAIRS:.0e} (a smaller --world or fewer --objects)"
        )
    rng = np.random.default_rng(seed)
    objs = make_objects(rng, world, objects)
    starts = np.arange(0.0, world - size + 1e-9, stride)
    cells, members = [], []
    for oy in starts:
        for ox in starts:
            lo = np.array([ox, oy])
            inside = []
            for o in objs:
                keep = ((o["xyz"][:, :2] >= lo) & (o["xyz"][:, :2] < lo + size)).all(1)
                if keep.sum() >= min_points:
                    xyz = o["xyz"][keep] - np.array([ox, oy, 0.0])
                    inside.append((o, {"xyz": xyz / size, "rgb": o["rgb"][keep], "label": o["label"]}))
            if not inside:
                continue
            inside.sort(key=lambda t: -len(t[1]["xyz"]))  # the largest objects take the slots first
            cells.append(
                {
                    "id": f"city_{len(cells):05d}",
                    "scene": f"city-{seed}",
                    "origin": lo,
                    "size": size,
                    "objects": [t[1] for t in inside],
                }
            )
            members.append([t[0] for t in inside][:slots])
    m = pack_cells(cells, slots, points, f"synthetic city (seed {seed})")
    centres = m.origins + m.sizes[:, None] / 2
    pose_w, pose_cell, pose_text = [], [], []
    while len(pose_w) < poses:
        p = rng.uniform(0, world, 2)
        best = int(np.argmin(np.linalg.norm(centres - p, axis=1)))
        near = sorted(members[best], key=lambda o: np.linalg.norm(o["centre"] - p))
        k = min(len(near), int(rng.integers(min_hints, max_hints + 1)))
        if k < min_hints:
            continue
        hints = [f"The pose is {direction(p, o)} of a {o['colour']} {o['label']}." for o in near[:k]]
        pose_w.append(p)
        pose_cell.append(m.ids[best])
        pose_text.append(" ".join(hints))
    m.pose_w, m.pose_cell, m.pose_text = (
        np.array(pose_w),
        np.array(pose_cell, dtype=str),
        np.array(pose_text, dtype=str),
    )
    return m


def make_city_for_card(card, seed: int = 0, world: float = 90.0, objects: int = 70, poses: int = 40) -> CellMap:
    """:func:`make_city` in the layout of a Des4Pos ``card``: its object slots, points per object,
    cell size and stride (m), and descriptions of at most its ``text.max_hints`` hints."""
    if card.model != "des4pos":
        raise ConfigError(f"{card.name} is a {card.model} card; a synthetic city is Des4Pos's map (--model des4pos)")
    c, t = card.section("cell", CellConfig), card.section("text", TextConfig)
    return make_city(
        c.max_objects,
        c.points_per_object,
        seed=seed,
        world=world,
        size=c.size,
        stride=c.stride,
        objects=objects,
        poses=poses,
        max_hints=min(6, t.max_hints),
    )


def check_city_output(out, cities: int) -> None:
    """ConfigError unless ``out`` can take what ``make-city`` writes, checked before any work: one
    city is a ``.npz`` file (not an existing directory), several go into a directory (not an
    existing file)."""

    as_dir = str(out).endswith(("/", "\\"))
    out = Path(out)
    if cities == 1:
        if out.is_dir() or as_dir:
            raise ConfigError(
                f"--out {out}: a directory; one city is one .npz file (e.g. --out {out / 'city.npz'}), "
                f"several (--cities N) go into a directory"
            )
        if out.suffix != ".npz":
            raise ConfigError(f"--out {out}: a city map is a .npz file; name it {out.name}.npz")
    elif out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: an existing file; {cities} cities are written into a directory")


# The described poses one make-city call writes over all its cities: describing a pose costs about
# 0.2 ms (100,000 poses of one city: 19 s on 2 cores), so this bounds a call to a few minutes.
MAX_DESCRIBED_POSES = 1_000_000


def check_city_work(cities: int, poses: int) -> None:
    """ConfigError when ``cities`` x ``poses`` exceeds :data:`MAX_DESCRIBED_POSES`, before any work."""
    if cities * poses > MAX_DESCRIBED_POSES:
        raise ConfigError(
            f"--cities {cities} x --poses {poses} is {cities * poses:,} described poses; at most "
            f"{MAX_DESCRIBED_POSES:,} per call (about 0.2 ms each): write them in several calls with "
            f"other --seed values"
        )


def write_cities(
    out_dir, card, cities: int, seed: int = 0, world: float = 90.0, objects: int = 70, poses: int = 40
) -> list[tuple[str, CellMap]]:
    """``cities`` synthetic cities of seeds ``seed``, ``seed + 1``, ... in the layout of ``card``
    (:func:`make_city_for_card`), written as ``out_dir/city-<seed>.npz``: one scene each, the
    training data of ``radaredge train --model des4pos`` (the last by name validates). Returns
    (path, map) pairs."""

    if isinstance(cities, bool) or not isinstance(cities, int) or cities < 1:
        raise ConfigError(f"--cities must be an integer >= 1, got {cities!r}")
    out = []
    for s in range(seed, seed + cities):
        m = make_city_for_card(card, seed=s, world=world, objects=objects, poses=poses)
        path = Path(out_dir) / f"city-{s:04d}.npz"
        m.save(path)
        out.append((str(path), m))
    return out
