"""A map of cells (submaps) in the fixed-slot layout of the Des4Pos submap encoder, numpy only.

Per cell: ``points`` [T, P, 6] (x, y, z normalised to the cell as in KITTI360Pose / Text2Loc,
r, g, b in [0, 1]), ``num_points`` [T] (the object's original point count), ``object_mask``
[T] (True for a real object; padding slots are zero), ``origin`` [2] (world x, y of the cell's
min corner, m, float64) and ``size`` (cell edge, m). A position inside a cell is
``origin + pos_in_cell * size`` (Text2Loc's convention).

Maps are saved as ``.npz`` without pickles (``allow_pickle=False``) and may carry query poses:
their world position, best cell and description text.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError
from . import kitti360pose

MAX_WORLD_M = 2.0e7  # |world x, y| of cell origins and poses, m (a UTM northing is below 1e7)
MAX_CELL_M = 1.0e4  # a cell's edge, m
MAX_CELL_COORD = 1.0e3  # |normalised x, y, z| of an object's points, in cell sizes
MAX_OBJECT_POINTS = 1.0e9  # an object's original point count


@dataclass
class CellMap:
    ids: np.ndarray  # [C] str, e.g. 2013_05_28_drive_0003_sync_00012 / city_00012
    scenes: np.ndarray  # [C] str
    origins: np.ndarray  # [C, 2] float64 m
    sizes: np.ndarray  # [C] float64 m
    points: np.ndarray  # [C, T, P, 6] float32
    num_points: np.ndarray  # [C, T] float32
    object_mask: np.ndarray  # [C, T] bool
    labels: np.ndarray  # [C, T] str ('' at padding), for display
    dropped_objects: np.ndarray = None  # [C] int: objects beyond the T slots (the smallest are dropped)
    pose_w: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [Q, 2] float64 m
    pose_cell: np.ndarray = field(default_factory=lambda: np.zeros(0, "<U1"))  # [Q] best-cell id
    pose_text: np.ndarray = field(default_factory=lambda: np.zeros(0, "<U1"))  # [Q] description

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def slots(self) -> tuple[int, int]:
        return self.points.shape[1], self.points.shape[2]

    def save(self, path: str | Path) -> Path:
        """Write the map to ``path`` (a .npz) atomically; returns the path."""
        if Path(path).suffix != ".npz":
            raise InputError(f"{path}: a cell map is written to a .npz file")
        with atomic_path(path) as tmp:
            np.savez_compressed(tmp, **{k: np.asarray(v) for k, v in self.__dict__.items()})
        return Path(path)


def load_map(path: str | Path, slots: int | None = None, points: int | None = None) -> CellMap:
    """A map written by :meth:`CellMap.save` (``.npz``) or a KITTI360Pose ``cells/<scene>.pkl``
    (packed into ``slots`` objects of ``points`` points; ``poses/<scene>.pkl`` beside ``cells/``
    is read too when it exists)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(
            f"map {path} does not exist; make one with `radaredge make-city --out {path}` or pass a "
            f"KITTI360Pose cells/<scene>.pkl"
        )
    if path.suffix == ".pkl":
        if slots is None or points is None:
            raise InputError(f"{path}: a KITTI360Pose pickle is packed for a model; pass its slots and points")
        m = pack_cells(kitti360pose.read_cells(path), slots, points, str(path))
        poses = path.parent.parent / "poses" / path.name
        if poses.is_file():
            m.pose_w, m.pose_cell, m.pose_text = kitti360pose.read_poses(poses)
        return m
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (ValueError, OSError) as exc:
        raise InputError(f"{path} is not a radaredge cell map (.npz without pickles): {exc}") from exc
    need = ("ids", "scenes", "origins", "sizes", "points", "num_points", "object_mask", "labels")
    missing = [k for k in need if k not in data]
    if missing:
        raise InputError(f"{path} is not a radaredge cell map: it lacks {missing}")
    m = CellMap(**data)
    validate_map(m, str(path))
    return m


def validate_map(m: CellMap, where: str = "map", slots: tuple[int, int] | None = None) -> None:
    """InputError naming the cell (and object) that breaks the layout or holds values of the
    wrong kind (names as text, positions and points as finite numbers, the object mask boolean)."""
    kinds = {
        "ids": "U",
        "scenes": "U",
        "labels": "U",
        "origins": "fiu",
        "sizes": "fiu",
        "points": "f",
        "num_points": "fiu",
        "object_mask": "b",
        "pose_w": "fiu",
        "pose_cell": "U",
        "pose_text": "U",
    }
    for name, kind in kinds.items():
        value = getattr(m, name)
        if not isinstance(value, np.ndarray) or value.dtype.kind not in kind:
            got = value.dtype if isinstance(value, np.ndarray) else type(value).__name__
            want = {"U": "text", "fiu": "numbers", "f": "floating-point numbers", "b": "booleans"}[kind]
            raise InputError(f"{where}: {name} must hold {want}, got {got}")
    c = len(m.ids)
    if c == 0 or m.ids.ndim != 1:
        raise InputError(f"{where}: the map holds no cell (ids {m.ids.shape}); a map needs at least one cell")
    if m.scenes.shape != (c,) or m.labels.shape != m.points.shape[:2]:
        raise InputError(f"{where}: scenes must be [{c}] and labels [{c}, objects]")
    if m.points.ndim != 4 or m.points.shape[0] != c or m.points.shape[3] != 6:
        raise InputError(
            f"{where}: points must be [cells, objects, points, 6] (x, y, z, r, g, b), got {m.points.shape}"
        )
    if slots is not None and m.points.shape[1:3] != tuple(slots):
        raise InputError(
            f"{where}: cells have {m.points.shape[1]} object slots of {m.points.shape[2]} points; the "
            f"model takes {slots[0]} slots of {slots[1]} points (re-make the map for this card)"
        )
    if m.object_mask.shape != m.points.shape[:2] or m.num_points.shape != m.points.shape[:2]:
        raise InputError(f"{where}: object_mask and num_points must be [{c}, {m.points.shape[1]}]")
    if m.origins.shape != (c, 2) or m.sizes.shape != (c,):
        raise InputError(f"{where}: origins must be [{c}, 2] and sizes [{c}] (m)")
    if not np.isfinite(m.origins).all():
        ci = int(np.flatnonzero(~np.isfinite(m.origins).all(1))[0])
        raise InputError(f"{where}: cell {m.ids[ci]} has a non-finite origin {m.origins[ci].tolist()}")
    far = np.flatnonzero(np.abs(m.origins).max(1) > MAX_WORLD_M)
    if len(far):
        raise InputError(
            f"{where}: cell {m.ids[far[0]]} has its origin at {m.origins[far[0]].tolist()}; world "
            f"positions are metres within {MAX_WORLD_M:g} (UTM or a local frame)"
        )
    if not (np.isfinite(m.sizes).all() and (m.sizes > 0).all() and (m.sizes <= MAX_CELL_M).all()):
        ci = int(np.flatnonzero(~(np.isfinite(m.sizes) & (m.sizes > 0) & (m.sizes <= MAX_CELL_M)))[0])
        raise InputError(
            f"{where}: cell {m.ids[ci]} has size {m.sizes[ci]!r}; cell sizes are positive distances in "
            f"metres up to {MAX_CELL_M:g} (KITTI360Pose cells are 30 m)"
        )
    empty = np.flatnonzero(~m.object_mask.any(1))
    if len(empty):
        raise InputError(
            f"{where}: cell {m.ids[empty[0]]} has no object ({len(empty)} empty cell(s)); drop empty cells"
        )
    bad = ~np.isfinite(m.points).all((2, 3)) & m.object_mask
    if bad.any():
        ci, oi = np.argwhere(bad)[0]
        raise InputError(f"{where}: cell {m.ids[ci]}, object {oi} ({m.labels[ci, oi]}) has non-finite points")
    xyz, rgb = np.abs(m.points[..., :3]).max((2, 3)), m.points[..., 3:]
    far = (xyz > MAX_CELL_COORD) & m.object_mask
    if far.any():
        ci, oi = np.argwhere(far)[0]
        raise InputError(
            f"{where}: cell {m.ids[ci]}, object {oi} ({m.labels[ci, oi]}) has a point at "
            f"{xyz[ci, oi]:g} cell sizes from the cell; x, y, z are normalised to the cell (0 to 1 inside "
            f"it), at most {MAX_CELL_COORD:g} away"
        )
    off = ((rgb < 0) | (rgb > 1)).any((2, 3)) & m.object_mask
    if off.any():
        ci, oi = np.argwhere(off)[0]
        raise InputError(
            f"{where}: cell {m.ids[ci]}, object {oi} ({m.labels[ci, oi]}) has colours outside [0, 1] "
            f"(from {float(rgb[ci, oi].min()):g} to {float(rgb[ci, oi].max()):g}); r, g, b are in [0, 1]"
        )
    low = ((m.num_points < 1) | ~np.isfinite(m.num_points) | (m.num_points > MAX_OBJECT_POINTS)) & m.object_mask
    if low.any():
        ci, oi = np.argwhere(low)[0]
        raise InputError(
            f"{where}: cell {m.ids[ci]}, object {oi} has a point count of {m.num_points[ci, oi]}; "
            f"a real object has 1 to {MAX_OBJECT_POINTS:,} points"
        )
    q = len(m.pose_w)
    if m.pose_w.size == m.pose_cell.size == m.pose_text.size == 0:
        return
    if (
        m.pose_w.shape != (q, 2)
        or m.pose_cell.shape != (q,)
        or m.pose_text.shape != (q,)
        or not np.isfinite(m.pose_w).all()
    ):
        raise InputError(
            f"{where}: described poses need pose_w [Q, 2] finite m, pose_cell [Q] and pose_text [Q]; got "
            f"{m.pose_w.shape}, {m.pose_cell.shape}, {m.pose_text.shape}"
        )
    far = np.flatnonzero(np.abs(m.pose_w).max(1) > MAX_WORLD_M)
    if len(far):
        raise InputError(
            f"{where}: described pose {int(far[0])} lies at {m.pose_w[far[0]].tolist()}; world positions "
            f"are metres within {MAX_WORLD_M:g}"
        )


def _seed(key: str) -> int:
    return zlib.crc32(key.encode())


def sample_object(xyz: np.ndarray, rgb: np.ndarray, n: int, key: str) -> np.ndarray:
    """``n`` points [n, 6] of one object, drawn with a generator seeded by ``key`` (cell and object
    id): without replacement when the object has at least ``n`` points, else all of them plus
    repeats (PyG FixedPoints)."""
    m = len(xyz)
    rng = np.random.default_rng(_seed(key))
    if m >= n:
        idx = np.sort(rng.choice(m, n, replace=False))
    else:
        idx = np.concatenate([np.arange(m), rng.choice(m, n - m, replace=True)])
    return np.concatenate([xyz[idx], rgb[idx]], 1).astype(np.float32)


MAX_PACKED_BYTES = 4 * 2**30  # one map's packed object points (float32)


def pack_cells(cells: list[dict], slots: int, points: int, where: str = "map") -> CellMap:
    """Pack cells ``{id, scene, origin, size, objects: [{xyz [N,3], rgb [N,3], label}]}`` into
    slots. Objects beyond ``slots`` are dropped, smallest first (their count is kept in
    ``dropped_objects``). InputError names the cell and object with malformed points."""
    c = len(cells)
    need = c * slots * points * 6 * 4
    if need > MAX_PACKED_BYTES:
        raise InputError(
            f"{where}: {c} cells of {slots} objects x {points} points pack into {need / 2**30:.1f} GiB; "
            f"at most {MAX_PACKED_BYTES / 2**30:g} GiB per map (split the map)"
        )
    out = CellMap(
        ids=np.array([x["id"] for x in cells], dtype=str),
        scenes=np.array([x["scene"] for x in cells], dtype=str),
        origins=np.zeros((c, 2)),
        sizes=np.zeros(c),
        points=np.zeros((c, slots, points, 6), np.float32),
        num_points=np.zeros((c, slots), np.float32),
        object_mask=np.zeros((c, slots), bool),
        labels=np.full((c, slots), "", dtype="<U24"),
        dropped_objects=np.zeros(c, np.int64),
    )
    for i, cell in enumerate(cells):
        out.origins[i] = cell["origin"]
        out.sizes[i] = cell["size"]
        objs = []
        for j, o in enumerate(cell["objects"]):
            xyz, rgb = np.asarray(o["xyz"], np.float64), np.asarray(o["rgb"], np.float64)
            if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape or len(xyz) == 0:
                raise InputError(
                    f"{where}: cell {cell['id']}, object {j} ({o.get('label')}): expected xyz and rgb "
                    f"[N, 3] with N >= 1, got {xyz.shape} and {rgb.shape}"
                )
            if not (np.isfinite(xyz).all() and np.isfinite(rgb).all()):
                raise InputError(f"{where}: cell {cell['id']}, object {j} ({o.get('label')}) has non-finite points")
            objs.append((j, xyz, rgb, o.get("label", "")))
        if not objs:
            raise InputError(f"{where}: cell {cell['id']} has no object")
        if len(objs) > slots:
            keep = sorted(sorted(range(len(objs)), key=lambda k: -len(objs[k][1]))[:slots])
            out.dropped_objects[i] = len(objs) - slots
            objs = [objs[k] for k in keep]
        for s, (j, xyz, rgb, label) in enumerate(objs):
            out.points[i, s] = sample_object(xyz, rgb, points, f"{cell['id']}/{j}")
            out.num_points[i, s] = len(xyz)
            out.object_mask[i, s] = True
            out.labels[i, s] = label
    return out
