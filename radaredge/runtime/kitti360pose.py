"""KITTI360Pose reader (Text2Loc's ``cells/<scene>.pkl`` and ``poses/<scene>.pkl``), safely.

The dataset ships Python pickles of Text2Loc's classes (``datapreparation.kitti360pose.imports``,
or its older path ``datapreparation.kitti360.imports``, which Text2Loc maps onto it:
``Cell``, ``Object3d``, ``Pose``, ``DescriptionPoseCell``, ``DescriptionBestCell``) holding numpy
arrays. Unpickling can execute arbitrary code, so :class:`RestrictedUnpickler` resolves only
those class names (to plain stand-ins that receive the attributes) and the few numpy / copyreg
callables that rebuild arrays; any other global is refused with an InputError that names it.

Layout (Text2Loc): a cell has ``id`` (``<scene>_<idx:05>``), ``scene_name``, ``objects``,
``cell_size`` (m, longest edge) and ``bbox_w`` (world [x0, y0, z0, x1, y1, z1], m); an object
has ``id``, ``instance_id``, ``xyz`` [N, 3] normalised to the cell ([0, 1]), ``rgb`` [N, 3] in
[0, 1] and ``label``. A pose has ``pose_w`` (world, m), ``cell_id`` (its best cell) and
``descriptions``, each rendered as "The pose is {direction} of a {color} {label}.".

This module only reads: :func:`read_cells` gives the cells in the input form of
:func:`radaredge.runtime.cellmap.pack_cells`, :func:`read_poses` the poses as arrays, and
:func:`radaredge.runtime.cellmap.load_map` packs them into a map (cellmap imports this module,
never the other way round).
"""

from __future__ import annotations

import copyreg
import importlib
import pickle
from pathlib import Path

import numpy as np

from ..errors import InputError

TEXT2LOC_MODULE = "datapreparation.kitti360pose.imports"
# Text2Loc maps this older module path onto the one above for data generated before a rename.
TEXT2LOC_OLD_MODULE = "datapreparation.kitti360.imports"


class _Record:
    """Stand-in for a Text2Loc class: pickle's BUILD fills its ``__dict__``."""

    def __setstate__(self, state):
        if isinstance(state, tuple):  # (dict, slots) form
            state = {**(state[0] or {}), **(state[1] or {})}
        if not isinstance(state, dict):
            raise InputError(f"unexpected pickled state of type {type(state).__name__} for {type(self).__name__}")
        self.__dict__.update(state)


_CLASSES = {
    name: type(name, (_Record,), {})
    for name in ("Cell", "Object3d", "Pose", "DescriptionPoseCell", "DescriptionBestCell")
}


def _numpy_globals() -> dict:
    """Array reconstruction by both of numpy's module paths: pickles written under numpy 1 name
    ``numpy.core``, under numpy 2 ``numpy._core``; either resolves to this numpy's functions."""
    core = "numpy._core" if hasattr(np, "_core") else "numpy.core"
    multiarray = importlib.import_module(f"{core}.multiarray")
    numeric = importlib.import_module(f"{core}.numeric")
    out = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("copyreg", "_reconstructor"): copyreg._reconstructor,
        ("builtins", "object"): object,
    }
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        out[(mod, "_reconstruct")] = multiarray._reconstruct
        out[(mod, "scalar")] = multiarray.scalar
    for mod in ("numpy.core.numeric", "numpy._core.numeric"):
        out[(mod, "_frombuffer")] = numeric._frombuffer
    return out


class RestrictedUnpickler(pickle.Unpickler):
    """Resolves only Text2Loc's data classes and numpy's array reconstruction."""

    allowed = {
        **{(module, n): c for module in (TEXT2LOC_MODULE, TEXT2LOC_OLD_MODULE) for n, c in _CLASSES.items()},
        **_numpy_globals(),
    }

    def find_class(self, module, name):
        try:
            return self.allowed[(module, name)]
        except KeyError:
            raise InputError(
                f"refusing to unpickle {module}.{name}: a KITTI360Pose pickle holds only "
                f"{TEXT2LOC_MODULE} data classes and numpy arrays"
            ) from None


def read_pickle(path: str | Path):
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return RestrictedUnpickler(f).load()
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    except FileNotFoundError:
        raise InputError(f"{path} does not exist") from None
    except Exception as exc:
        raise InputError(f"{path} is not a readable KITTI360Pose pickle: {type(exc).__name__}: {exc}") from exc


def _get(obj, attr: str, where: str):
    if not hasattr(obj, attr):
        raise InputError(f"{where}: has no attribute {attr!r} (is this a KITTI360Pose cells/poses pickle?)")
    return getattr(obj, attr)


def _text(obj, attr: str, where: str) -> str:
    """A text field (ids, labels, names): a str, or a number written as one."""
    value = _get(obj, attr, where)
    if not isinstance(value, (str, int, np.integer, np.str_)) or isinstance(value, bool):
        raise InputError(f"{where}: {attr} must be text, got {type(value).__name__}")
    return str(value)


def _list(obj, attr: str, where: str) -> list | tuple:
    """A list field (a cell's objects, a pose's descriptions), at most :data:`MAX_ITEMS` long."""
    value = _get(obj, attr, where)
    if not isinstance(value, (list, tuple)):
        raise InputError(f"{where}: {attr} must be a list, got {type(value).__name__}")
    if len(value) > MAX_ITEMS:
        raise InputError(f"{where}: {attr} has {len(value):,} entries; at most {MAX_ITEMS:,}")
    return value


# What one pickle may make radaredge build: pickle's memo lets a few kilobytes name one list
# from many places, so nested lists of shared lists describe billions of numbers; they are
# counted, shared parts as often as they occur, before any array is built.
MAX_ARRAY_VALUES = 10**7  # numbers in one field (an object's points: a few thousand x 3)
MAX_ITEMS = 10**6  # cells, objects of a cell, poses, descriptions of a pose
MAX_FILE_VALUES = 10**8  # numbers in one file's objects (a KITTI360Pose scene holds a few million)


def _count_values(value, limit: int, where: str, attr: str) -> None:
    """InputError when the nested lists/tuples of ``value`` hold more than ``limit`` leaves."""
    stack, count = [value], 0
    while stack:
        v = stack.pop()
        if isinstance(v, (list, tuple)):
            count += len(v) if not v or not isinstance(v[0], (list, tuple)) else 0
            if count > limit:
                break
            stack.extend(x for x in v if isinstance(x, (list, tuple)))
        elif isinstance(v, np.ndarray):
            count += v.size
        if count > limit:
            break
    if count > limit:
        raise InputError(
            f"{where}: {attr} unpacks into more than {limit:,} values (nested references to shared "
            f"lists); a KITTI360Pose field holds an object's points at most"
        )


def _array(obj, attr: str, where: str, shape: tuple) -> np.ndarray:
    """A finite float64 array field whose shape matches ``shape`` (None: any length)."""
    value = _get(obj, attr, where)
    if isinstance(value, (list, tuple)):
        _count_values(value, MAX_ARRAY_VALUES, where, attr)
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise InputError(
            f"{where}: {attr} must be numbers of shape {_shape_text(shape)}, got {type(value).__name__}"
        ) from None
    if (
        arr.ndim != len(shape)
        or any(s is not None and a != s for a, s in zip(arr.shape, shape))
        or not np.isfinite(arr).all()
    ):
        raise InputError(
            f"{where}: {attr} must be finite numbers of shape {_shape_text(shape)}, got shape "
            f"{arr.shape}" + ("" if np.isfinite(arr).all() else " with NaN/Inf")
        )
    return arr


def _shape_text(shape: tuple) -> str:
    return "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"


def hint_text(description) -> str:
    """Text2Loc's rendering of one hint."""
    return f"The pose is {description.direction} of a {description.object_color_text} {description.object_label}."


def read_cells(path: str | Path) -> list[dict]:
    """The cells of one ``cells/<scene>.pkl`` as :func:`radaredge.runtime.cellmap.pack_cells` takes
    them: ``{id, scene, origin [2] (world x, y of the cell's min corner, m), size (m), objects:
    [{xyz [N, 3] normalised to the cell, rgb [N, 3] in [0, 1], label}]}``."""
    cells = read_pickle(path)
    if not isinstance(cells, list):
        raise InputError(f"{path}: expected a list of cells, got {type(cells).__name__}")
    if len(cells) > MAX_ITEMS:
        raise InputError(f"{path}: {len(cells):,} cells; at most {MAX_ITEMS:,}")
    raw, total = [], 0
    for i, c in enumerate(cells):
        where = f"{path}: cell {i}"
        cid = _text(c, "id", where)
        where = f"{path}: cell {cid}"
        bbox = _array(c, "bbox_w", where, (6,))
        size = _array(c, "cell_size", where, ())
        if size <= 0:
            raise InputError(f"{where}: cell_size must be > 0 m, got {float(size)!r}")
        objs = []
        for j, o in enumerate(_list(c, "objects", where)):
            at = f"{where}, object {j}"
            xyz = _array(o, "xyz", at, (None, 3))
            total += 2 * xyz.size
            if total > MAX_FILE_VALUES:
                raise InputError(
                    f"{at}: the file's objects hold more than {MAX_FILE_VALUES:,} numbers (nested "
                    f"references to shared objects?); a KITTI360Pose scene holds a few million"
                )
            objs.append({"xyz": xyz, "rgb": _array(o, "rgb", at, (len(xyz), 3)), "label": _text(o, "label", at)})
        raw.append(
            {
                "id": cid,
                "scene": _text(c, "scene_name", where),
                "origin": bbox[:2],
                "size": float(size),
                "objects": objs,
            }
        )
    return raw


def read_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The poses of one ``poses/<scene>.pkl``: (world x, y [Q, 2] float64 m, best-cell id [Q] str,
    description [Q] str: the pose's hints rendered by :func:`hint_text`, joined by spaces)."""
    poses = read_pickle(path)
    if not isinstance(poses, list):
        raise InputError(f"{path}: expected a list of poses, got {type(poses).__name__}")
    if len(poses) > MAX_ITEMS:
        raise InputError(f"{path}: {len(poses):,} poses; at most {MAX_ITEMS:,}")
    pose_w, pose_cell, pose_text = [], [], []
    for i, p in enumerate(poses):
        where = f"{path}: pose {i}"
        pose_w.append(_array(p, "pose_w", where, (None,))[:2])
        if len(pose_w[-1]) != 2:
            raise InputError(f"{where}: pose_w must hold x, y (and z) in m, got {len(pose_w[-1])} value(s)")
        pose_cell.append(_text(p, "cell_id", where))
        hints = []
        for j, d in enumerate(_list(p, "descriptions", where)):
            at = f"{where}, description {j}"
            for attr in ("direction", "object_color_text", "object_label"):
                _text(d, attr, at)
            hints.append(hint_text(d))
        pose_text.append(" ".join(hints))
    return (np.array(pose_w, np.float64).reshape(-1, 2), np.array(pose_cell, dtype=str), np.array(pose_text, dtype=str))
