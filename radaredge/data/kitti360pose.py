"""KITTI360Pose reader (Text2Loc's ``cells/<scene>.pkl`` and ``poses/<scene>.pkl``), safely.

The dataset ships Python pickles of Text2Loc's classes (``datapreparation.kitti360pose.imports``:
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
:func:`radaredge.data.cellmap.pack_cells`, :func:`read_poses` the poses as arrays, and
:func:`radaredge.data.cellmap.load_map` packs them into a map (cellmap imports this module,
never the other way round).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from ..errors import InputError

TEXT2LOC_MODULE = "datapreparation.kitti360pose.imports"


class _Record:
    """Stand-in for a Text2Loc class: pickle's BUILD fills its ``__dict__``."""

    def __setstate__(self, state):
        if isinstance(state, tuple):          # (dict, slots) form
            state = {**(state[0] or {}), **(state[1] or {})}
        if not isinstance(state, dict):
            raise InputError(f"unexpected pickled state of type {type(state).__name__} for {type(self).__name__}")
        self.__dict__.update(state)


_CLASSES = {name: type(name, (_Record,), {}) for name in
            ("Cell", "Object3d", "Pose", "DescriptionPoseCell", "DescriptionBestCell")}


def _numpy_globals() -> dict:
    import copyreg
    out = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype,
           ("copyreg", "_reconstructor"): copyreg._reconstructor, ("builtins", "object"): object}
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        out[(mod, "_reconstruct")] = np._core.multiarray._reconstruct
        out[(mod, "scalar")] = np._core.multiarray.scalar
    for mod in ("numpy.core.numeric", "numpy._core.numeric"):
        out[(mod, "_frombuffer")] = np._core.numeric._frombuffer
    return out


class RestrictedUnpickler(pickle.Unpickler):
    """Resolves only Text2Loc's data classes and numpy's array reconstruction."""

    allowed = {**{(TEXT2LOC_MODULE, n): c for n, c in _CLASSES.items()}, **_numpy_globals()}

    def find_class(self, module, name):
        try:
            return self.allowed[(module, name)]
        except KeyError:
            raise InputError(f"refusing to unpickle {module}.{name}: a KITTI360Pose pickle holds only "
                             f"{TEXT2LOC_MODULE} data classes and numpy arrays") from None


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


def hint_text(description) -> str:
    """Text2Loc's rendering of one hint."""
    return (f"The pose is {description.direction} of a {description.object_color_text} "
            f"{description.object_label}.")


def read_cells(path: str | Path) -> list[dict]:
    """The cells of one ``cells/<scene>.pkl`` as :func:`radaredge.data.cellmap.pack_cells` takes
    them: ``{id, scene, origin [2] (world x, y of the cell's min corner, m), size (m), objects:
    [{xyz [N, 3] normalised to the cell, rgb [N, 3] in [0, 1], label}]}``."""
    cells = read_pickle(path)
    if not isinstance(cells, list):
        raise InputError(f"{path}: expected a list of cells, got {type(cells).__name__}")
    raw = []
    for i, c in enumerate(cells):
        where = f"{path}: cell {i}"
        cid = str(_get(c, "id", where))
        bbox = np.asarray(_get(c, "bbox_w", where), np.float64)
        if bbox.shape != (6,):
            raise InputError(f"{path}: cell {cid}: bbox_w must hold 6 values, got shape {bbox.shape}")
        objs = [{"xyz": _get(o, "xyz", f"{path}: cell {cid}, object {j}"), "rgb": _get(o, "rgb", cid),
                 "label": str(_get(o, "label", cid))} for j, o in enumerate(_get(c, "objects", where))]
        raw.append({"id": cid, "scene": str(_get(c, "scene_name", where)), "origin": bbox[:2],
                    "size": float(_get(c, "cell_size", where)), "objects": objs})
    return raw


def read_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The poses of one ``poses/<scene>.pkl``: (world x, y [Q, 2] float64 m, best-cell id [Q] str,
    description [Q] str: the pose's hints rendered by :func:`hint_text`, joined by spaces)."""
    poses = read_pickle(path)
    if not isinstance(poses, list):
        raise InputError(f"{path}: expected a list of poses, got {type(poses).__name__}")
    pose_w = np.array([np.asarray(_get(p, "pose_w", f"{path}: pose {i}"), np.float64)[:2]
                       for i, p in enumerate(poses)]).reshape(-1, 2)
    pose_cell = np.array([str(_get(p, "cell_id", str(path))) for p in poses], dtype=str)
    pose_text = np.array([" ".join(hint_text(d) for d in _get(p, "descriptions", str(path))) for p in poses],
                         dtype=str)
    return pose_w, pose_cell, pose_text
