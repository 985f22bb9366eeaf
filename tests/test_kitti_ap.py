"""radaredge's VoD / KITTI detection AP against an independent re-writing of the VoD devkit's
evaluation (tests/references/vod_devkit_eval.py, which shares no code with radaredge), on random
detections against random ground truth: rotated boxes, occlusion, DontCare, neighbour classes,
empty predictions, empty ground truth, single-object frames; both areas, every metric."""

from __future__ import annotations

import numpy as np
import pytest
from references import vod_devkit_eval as devkit

from radaredge.data.kitti_detection import TJ4D, VOD, Labels
from radaredge.eval.kitti_ap import ap_table, bootstrap_rows, evaluate_frames, recall_thresholds, resampled_ap

SIZES = {
    "Car": (4.2, 1.6, 1.8),
    "Van": (5.0, 2.0, 2.0),
    "Truck": (8.0, 3.0, 2.5),
    "Pedestrian": (0.7, 1.7, 0.6),
    "Person_sitting": (0.8, 1.2, 0.6),
    "Cyclist": (1.8, 1.7, 0.6),
    "bicycle": (1.7, 1.1, 0.5),
}
GT_NAMES = [
    "Car",
    "Car",
    "Car",
    "Pedestrian",
    "Pedestrian",
    "Cyclist",
    "Cyclist",
    "Van",
    "Person_sitting",
    "Truck",
    "bicycle",
    "DontCare",
]
DT_NAMES = ["Car", "Pedestrian", "Cyclist", "Truck"]


def _objects(rng, names) -> dict:
    """Annotation arrays (the devkits' dict) of objects ``names``, placed and sized at random."""
    m = len(names)
    dims = np.array([SIZES.get(n, (-1.0, -1.0, -1.0)) for n in names]).reshape(m, 3)  # (l, h, w)
    dims = np.where(dims > 0, dims * rng.uniform(0.8, 1.2, (m, 3)), dims)
    loc = np.column_stack([rng.uniform(-12, 12, m), rng.uniform(1.0, 2.0, m), rng.uniform(2, 45, m)])
    dc = np.array([n == "DontCare" for n in names], bool)
    loc[dc] = -1000.0
    top = rng.uniform(300, 700, m)
    height = rng.choice([rng.uniform(15, 40), rng.uniform(40.5, 300)], m) if m else np.zeros(0)
    left = rng.uniform(0, 1800, m)
    bbox = np.column_stack([left, top, left + rng.uniform(20, 300, m), top + height])
    return {
        "name": np.array(names, dtype=object),
        "truncated": np.zeros(m),
        "occluded": rng.choice([0, 1, 2, 2, 5], m).astype(np.int64),
        "alpha": rng.uniform(-np.pi, np.pi, m),
        "bbox": bbox.reshape(m, 4),
        "dimensions": dims,
        "location": loc.reshape(m, 3),
        "rotation_y": rng.uniform(-np.pi, np.pi, m),
        "score": np.zeros(m),
    }


def _detections(rng, gt: dict) -> dict:
    """Noisy copies of some labels (class sometimes wrong; some labels twice, as an NMS leaves
    near-duplicates, one of them with a short 2D box) plus false positives, random scores."""
    keep = [i for i in range(len(gt["name"])) if gt["name"][i] != "DontCare" and rng.random() < 0.7]
    keep += [i for i in keep if rng.random() < 0.4]
    n_fp = int(rng.integers(0, 5))
    fp = _objects(rng, list(rng.choice(DT_NAMES, n_fp)))
    names = [
        gt["name"][i] if gt["name"][i] in DT_NAMES and rng.random() < 0.85 else str(rng.choice(DT_NAMES)) for i in keep
    ]
    det = {k: np.concatenate([np.asarray(gt[k])[keep], fp[k]]) if len(keep) else fp[k] for k in gt}
    det["name"] = np.array(names + list(fp["name"]), dtype=object)
    m, k = len(det["name"]), len(keep)
    det["location"] = det["location"] + np.concatenate([rng.normal(0, 0.3, (k, 3)), np.zeros((m - k, 3))])
    det["dimensions"] = np.abs(det["dimensions"]) * np.concatenate(
        [rng.uniform(0.85, 1.15, (k, 3)), np.ones((m - k, 3))]
    )
    det["rotation_y"] = det["rotation_y"] + np.concatenate([rng.normal(0, 0.2, k), np.zeros(m - k)])
    det["alpha"] = det["alpha"] + rng.normal(0, 0.3, m)
    det["bbox"] = det["bbox"] + rng.normal(0, 8, (m, 4))
    short = rng.random(m) < 0.25
    det["bbox"][short, 3] = det["bbox"][short, 1] + rng.uniform(10, 39, short.sum())
    det["score"] = rng.random(m)
    det["occluded"] = np.zeros(m, np.int64)
    return det


def _case(seed: int) -> tuple[list[dict], list[dict]]:
    rng = np.random.default_rng(seed)
    gts, dts = [], []
    for f in range(int(rng.integers(1, 5))):
        kind = rng.integers(0, 10)
        n = 0 if kind == 0 else 1 if kind == 1 else int(rng.integers(2, 12))
        names = ["DontCare"] * int(rng.integers(1, 3)) if kind == 2 else list(rng.choice(GT_NAMES, n))
        gt = _objects(rng, names)
        dt = _detections(rng, gt)
        if kind == 3 or (seed % 17 == 0):
            dt = {k: v[:0] for k, v in dt.items()}  # empty predictions
        gts.append(gt)
        dts.append(dt)
    return gts, dts


def _labels(a: dict) -> Labels:
    return Labels(*(np.asarray(a[f]) for f in Labels.__dataclass_fields__))


@pytest.mark.parametrize("layout", [VOD, TJ4D], ids=["vod", "tj4d"])
def test_ap_equals_the_independent_devkit_reference(layout):
    """120 random cases per layout: every class, area and metric (3D, BEV, 2D box, AOS; 11 and 40
    recall positions) within 1e-4 AP points of the devkit re-written from its source."""
    classes = [c.name for c in layout.eval_classes]
    areas = ("entire_area", "corridor") if layout.corridor else ("entire_area",)
    counted = 0
    for seed in range(120):
        gts, dts = _case(seed + (1000 if layout is TJ4D else 0))
        ours = ap_table(
            evaluate_frames([_labels(g) for g in gts], [_labels(d) for d in dts], layout.eval_classes, areas)
        )
        for area in areas:
            ref = devkit.evaluate(gts, dts, classes, corridor=area == "corridor")
            for cls in classes:
                for metric in ("3d", "bev", "bbox", "aos", "3d_r40", "bev_r40", "bbox_r40", "aos_r40"):
                    a, b = ours[area][cls][metric], ref[cls][metric]
                    assert (np.isnan(a) and np.isnan(b)) or abs(a - b) <= 1e-4, (seed, area, cls, metric, a, b)
                counted += ref[cls]["3d"] > 0
    assert counted > 60  # the cases are not all trivially zero


def test_perfect_and_empty_detections():
    rng = np.random.default_rng(5)
    gts = [_objects(rng, ["Car"] * 4 + ["Pedestrian"] * 3 + ["Cyclist"] * 3) for _ in range(20)]
    for g in gts:
        g["rotation_y"] = np.zeros(len(g["name"]))
        g["bbox"][:, 3] = g["bbox"][:, 1] + 100  # all tall enough
        g["occluded"][:] = 0
    dts = [{**g, "score": rng.uniform(0.5, 1.0, len(g["name"]))} for g in gts]
    perfect = ap_table(evaluate_frames([_labels(g) for g in gts], [_labels(d) for d in dts], VOD.eval_classes))
    assert all(perfect["entire_area"][c]["3d"] == pytest.approx(100.0) for c in ("Car", "Pedestrian", "Cyclist"))
    empty = [{k: v[:0] for k, v in d.items()} for d in dts]
    none = ap_table(evaluate_frames([_labels(g) for g in gts], [_labels(d) for d in empty], VOD.eval_classes))
    assert all(none[a][c]["3d"] == 0.0 for a in none for c in none[a])
    no_gt = ap_table(
        evaluate_frames(
            [_labels({k: v[:0] for k, v in g.items()}) for g in gts], [_labels(d) for d in dts], VOD.eval_classes
        )
    )
    assert all(no_gt[a][c]["3d"] == 0.0 and no_gt[a][c]["num_gt"] == 0 for a in no_gt for c in no_gt[a])


def test_recall_thresholds_thin_to_41_positions():
    scores = np.linspace(1.0, 0.01, 100)
    t = recall_thresholds(scores, 100)
    assert len(t) == 41 and t[0] == 1.0 and t[-1] == pytest.approx(0.01)


def test_recall_thresholds_equal_the_devkit_walk():
    """The kept scores equal the devkit's score-by-score walk (the reference), ties, few ground
    truth (every score kept) and many (thinned) alike."""
    rng = np.random.default_rng(3)
    for trial in range(300):
        n = int(rng.integers(0, 120))
        scores = rng.choice(rng.random(max(n // 3, 1)), n) if trial % 3 == 0 else rng.random(n)
        num_gt = n + int(rng.integers(1, 200)) if trial % 2 else max(n, 1)
        ours = recall_thresholds(scores, num_gt)
        assert ours.tolist() == devkit._recall_thresholds(scores, num_gt), (trial, n, num_gt)


def _many_frames(seed: int, n: int) -> tuple[list[dict], list[dict]]:
    gts, dts = [], []
    for k in range(n):
        g, d = _case(seed * 100 + k)
        gts += g
        dts += d
    return gts, dts


def test_a_resample_scores_as_the_devkit_on_its_frames():
    """The bootstrap's AP of a resample is the devkit's AP (the independent reference) on the
    resampled frames, duplicates included; the identity resample gives the set's own AP."""
    gts, dts = _many_frames(5, 12)
    curves = evaluate_frames(
        [_labels(g) for g in gts], [_labels(d) for d in dts], VOD.eval_classes, tables=("3d", "bev")
    )
    rows = np.vstack([np.arange(len(gts)), bootstrap_rows(len(gts), 6, seed=1)])
    checked = 0
    for area in ("entire_area", "corridor"):
        for cls in ("Car", "Pedestrian", "Cyclist"):
            for metric in ("3d", "bev"):
                curve = curves[area][cls][metric]
                ap11, ap40 = resampled_ap(curve.frames, rows)
                assert ap11[0] == pytest.approx(curve.ap11, abs=1e-9) and ap40[0] == pytest.approx(curve.ap40, abs=1e-9)
                for r, row in enumerate(rows[1:], 1):
                    ref = devkit.evaluate(
                        [gts[i] for i in row],
                        [dts[i] for i in row],
                        ["Car", "Pedestrian", "Cyclist"],
                        corridor=area == "corridor",
                    )[cls]
                    assert ap11[r] == pytest.approx(ref[metric], abs=1e-4), (area, cls, metric, r)
                    assert ap40[r] == pytest.approx(ref[metric + "_r40"], abs=1e-4), (area, cls, metric, r)
                    checked += ref[metric] > 0
    assert checked > 20


def test_paired_intervals_of_a_detector_against_itself_and_a_worse_one():
    """The same detections twice: equal intervals and a paired difference of exactly 0; the
    detections with every second true box dropped: a paired difference whose interval lies below 0."""
    from radaredge.eval.detection import ap_intervals

    rng = np.random.default_rng(11)
    gts = [_objects(rng, ["Car"] * 6) for _ in range(30)]
    for g in gts:
        g["bbox"][:, 3] = g["bbox"][:, 1] + 100
        g["occluded"][:] = 0
    dts = [{**g, "score": rng.uniform(0.5, 1.0, len(g["name"]))} for g in gts]
    worse = [{k: v[::2] for k, v in d.items()} for d in dts]
    classes = (VOD.eval_class("Car"),)
    curves = {
        name: evaluate_frames(
            [_labels(g) for g in gts], [_labels(d) for d in ds], classes, ("entire_area",), ("3d", "bev")
        )
        for name, ds in (("a", dts), ("b", dts), ("worse", worse))
    }
    intervals, deltas = ap_intervals(curves, ["Car"], ("entire_area",), "a", samples=200)
    assert intervals["a"] == intervals["b"] and deltas["b"]["entire_area"]["Car"]["3d"] == (0.0, 0.0)
    low, high = deltas["worse"]["entire_area"]["mAP"]["3d"]
    assert high < 0.0 and intervals["worse"]["entire_area"]["Car"]["3d"][1] < 100.0
