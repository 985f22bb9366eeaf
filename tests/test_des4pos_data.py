"""KITTI360Pose pickles are read safely; Text2Loc's top-k localisation recall on hand-made cases."""

import os
import pickle
import subprocess
import sys
import types

import numpy as np
import pytest

from radaredge.errors import InputError
from radaredge.eval.places import localization_recall
from radaredge.runtime.cellmap import load_map
from radaredge.runtime.kitti360pose import read_cells, read_pickle, read_poses

MODULE = "datapreparation.kitti360pose.imports"


@pytest.fixture
def text2loc_classes(monkeypatch):
    """Classes named and placed like Text2Loc's, so pickle writes the dataset's global names."""
    mod = types.ModuleType(MODULE)
    for name in ("Cell", "Object3d", "Pose", "DescriptionBestCell"):
        cls = type(name, (), {"__module__": MODULE})
        setattr(mod, name, cls)
    for parent in ("datapreparation", "datapreparation.kitti360pose"):
        monkeypatch.setitem(sys.modules, parent, types.ModuleType(parent))
    monkeypatch.setitem(sys.modules, MODULE, mod)
    return mod


def _obj(mod, i, label, n, rng):
    o = mod.Object3d()
    o.id, o.instance_id, o.label = i, 100 + i, label
    o.xyz, o.rgb = rng.random((n, 3)), rng.random((n, 3))
    return o


def test_reads_text2loc_cells_and_poses(tmp_path, text2loc_classes):
    mod, rng = text2loc_classes, np.random.default_rng(0)
    cells = []
    for k in range(2):
        c = mod.Cell()
        c.id, c.scene_name, c.cell_size = (
            f"2013_05_28_drive_0003_sync_{k:05d}"[-10:],
            "2013_05_28_drive_0003_sync",
            30.0,
        )
        c.bbox_w = np.array([100.0 + 10 * k, 200.0, 0.0, 130.0 + 10 * k, 230.0, 30.0])
        c.objects = [_obj(mod, j, lab, n, rng) for j, (lab, n) in enumerate([("pole", 40), ("building", 900)])]
        cells.append(c)
    d = mod.DescriptionBestCell()
    d.direction, d.object_color_text, d.object_label = "north", "gray", "pole"
    pose = mod.Pose()
    pose.pose_w, pose.cell_id, pose.descriptions = np.array([112.0, 215.0, 1.0]), cells[0].id, [d, d]
    (tmp_path / "cells").mkdir()
    (tmp_path / "poses").mkdir()
    for sub, obj in (("cells", cells), ("poses", [pose])):
        with open(tmp_path / sub / "scene.pkl", "wb") as f:
            pickle.dump(obj, f, protocol=4)
    m = load_map(tmp_path / "cells" / "scene.pkl", slots=4, points=16)
    assert m.points.shape == (2, 4, 16, 6) and m.object_mask.sum(1).tolist() == [2, 2]
    assert m.num_points[0, :2].tolist() == [40, 900] and m.labels[0, :2].tolist() == ["pole", "building"]
    assert m.origins.tolist() == [[100.0, 200.0], [110.0, 200.0]] and m.sizes.tolist() == [30.0, 30.0]
    assert m.pose_w.tolist() == [[112.0, 215.0]] and m.pose_cell.tolist() == [cells[0].id]
    assert m.pose_text[0] == "The pose is north of a gray pole. The pose is north of a gray pole."
    src = cells[0].objects[0]
    assert np.isin(m.points[0, 0, :, :3], src.xyz.astype(np.float32)).all()  # sampled from the object's points


def test_refuses_code_in_a_pickle(tmp_path):
    class Evil:
        def __reduce__(self):
            return os.system, ("echo pwned",)

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps([Evil()]))
    with pytest.raises(InputError, match=r"refusing to unpickle (posix|os|nt)\.system"):
        read_pickle(path)


def test_pickle_of_the_wrong_thing_is_a_clear_error(tmp_path):
    path = tmp_path / "cells.pkl"
    path.write_bytes(pickle.dumps({"not": "cells"}))
    with pytest.raises(InputError, match="expected a list of cells, got dict"):
        read_cells(path)
    with pytest.raises(InputError, match="expected a list of poses, got dict"):
        read_poses(path)
    path.write_bytes(pickle.dumps([np.zeros(3)]))
    with pytest.raises(InputError, match="cell 0: has no attribute 'id'"):
        read_cells(path)
    with pytest.raises(InputError, match="pose 0: has no attribute 'pose_w'"):
        read_poses(path)


def test_the_reader_does_not_import_the_map_module():
    """One-way dependency: cellmap.load_map packs what kitti360pose reads, never the reverse."""
    code = "import sys, radaredge.runtime.kitti360pose; print('radaredge.runtime.cellmap' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.split() == ["False"], res.stderr


# ----------------------------------------------------------------------------- recall protocol


def test_localization_recall_hand_made():
    pose = np.array([[0.0, 0.0], [100.0, 100.0], [0.0, 0.0]])
    pred = np.array(
        [
            [[4.0, 3.0], [50.0, 0.0], [0.0, 0.0]],  # top-1 exactly 5 m away: boundary counts
            [[100.0, 112.0], [108.0, 100.0], [103.0, 100.0]],  # 12 m, then 8 m, then 3 m
            [[0.0, 20.0], [16.0, 0.0], [0.0, 1.0]],  # 1 m only at rank 3, but in another scene
        ]
    )
    same = np.array([[True, True, True], [True, True, True], [True, True, False]])
    r = localization_recall(pred, pose, ks=(1, 2, 3), thresholds=(5, 10, 15), same_scene=same)
    assert r[1] == {5.0: 1 / 3, 10.0: 1 / 3, 15.0: 2 / 3}
    assert r[2] == {5.0: 1 / 3, 10.0: 2 / 3, 15.0: 2 / 3}
    assert r[3] == {5.0: 2 / 3, 10.0: 2 / 3, 15.0: 2 / 3}
    with pytest.raises(InputError, match="top-5 recall needs 5 predictions per query; 3 were given"):
        localization_recall(pred, pose, ks=(1, 5), same_scene=same)
    no_scene = localization_recall(pred, pose, ks=(3,), thresholds=(5,))
    assert no_scene[3][5.0] == 1.0


def test_localization_recall_rejects_bad_input():
    with pytest.raises(InputError, match=r"predictions \[Q, K, 2\]"):
        localization_recall(np.zeros((2, 3)), np.zeros((2, 2)))
    with pytest.raises(InputError, match="same_scene must be"):
        localization_recall(np.zeros((2, 3, 2)), np.zeros((2, 2)), same_scene=np.ones((2, 2), bool))
