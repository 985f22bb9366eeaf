"""Independent re-writing of the View-of-Delft devkit's KITTI-style evaluation -- for tests only.

What this is
    A slow, loop-based, numpy + standard-library re-statement of how the VoD devkit scores 3-D
    detections (2-D image box AP, BEV AP, 3-D AP and AOS; 11-point and 40-point
    interpolation), kept as an oracle for radaredge's own evaluator.  It was written from the
    devkit's source alone and deliberately shares no code (and was written without reading any
    code) with the ``radaredge`` package; nothing here imports ``radaredge``.

Where it comes from
    github.com/tudelft-iv/view-of-delft-dataset, commit a9df89290f118965b73e5cb4aa5409f42862894b:
    ``vod/evaluation/kitti_official_evaluate.py`` (clean_data, image_box_overlap, d3_box_overlap,
    compute_statistics_jit, get_thresholds, eval_class, get_m_ap, get_m_ap_r40,
    get_official_eval_result), ``vod/evaluation/rotate_iou_cpu.py`` (rotated BEV intersection),
    ``vod/evaluation/evaluation_common.py`` (label parsing) and ``vod/evaluation/evaluate.py``
    (entire-area and driving-corridor passes).  The Truck class (slot 5 'truck', overlaps image
    0.7 / BEV 0.5 / 3-D 0.5) follows TRV-Lab/MAFF-Net's TJ4D copy,
    ``pcdet/datasets/TJ4DRadSet/kitti_object_eval_python/eval.py``.

Deliberate differences from the devkit (none of which changes a result on sane input)
    * Rotated-box geometry runs in float64 plain Python; the devkit casts to float32.
    * Frames are handled one at a time; the devkit's "parts" batching only speeds things up.
    * Only the reported (second, looser) overlap set is evaluated, and only difficulty 0.
    * Where the devkit's jitted code would raise on a zero denominator inside an IoU (degenerate
      zero-size boxes), the value follows numpy float64 division (nan / inf) instead.
    * ``read_label_file`` skips blank lines (the devkit fails on them).
"""

from __future__ import annotations

import math

import numpy as np

# Reported min-overlap per class and metric (the devkit's second overlap set).
CLASSES = {
    "Car": {"image": 0.7, "bev": 0.5, "3d": 0.5},
    "Pedestrian": {"image": 0.5, "bev": 0.25, "3d": 0.25},
    "Cyclist": {"image": 0.5, "bev": 0.25, "3d": 0.25},
    "Truck": {"image": 0.7, "bev": 0.5, "3d": 0.5},
}

# Class slots the cleaning step knows about (lower case; the evaluated class is looked up here).
_CLASS_SLOTS = ["car", "pedestrian", "cyclist", "van", "person_sitting", "truck"]
# Ground-truth classes that are "neighbours" of an evaluated class: never counted, never penalised.
_NEIGHBOUR_OF = {"car": "van", "pedestrian": "person_sitting"}

MIN_BOX_HEIGHT_PX = 40.0
MAX_OCCLUSION = 4
CORRIDOR_HALF_WIDTH_M = 4.0  # camera x must lie in [-4, 4]
CORRIDOR_MAX_DEPTH_M = 25.0  # camera z must not exceed 25
N_RECALL_POINTS = 41

# Per-box flags produced by the cleaning step (same integer codes as the devkit uses).
COUNTED = 0  # belongs to the evaluated class and is scored
NEUTRAL = 1  # may absorb a match but never counts as TP / FP / FN
UNRELATED = -1  # another class: skipped entirely

_NO_MATCH = -10000000  # sentinel "no candidate yet" value

METRIC_IMAGE, METRIC_BEV, METRIC_3D = 0, 1, 2


# --------------------------------------------------------------------------------------------
# label files
# --------------------------------------------------------------------------------------------


def read_label_file(path) -> dict:
    """Parse one KITTI label text file into the devkit's annotation dict.

    Columns: name, truncated, occluded, alpha, bbox(4), h, w, l, x, y, z, rotation_y[, score].
    Dimensions are reordered to (l, h, w).  A score column is read only when the *first* row
    has 16 fields; otherwise scores are zeros.
    """
    with open(path, "r") as handle:
        rows = [line.strip().split(" ") for line in handle.readlines() if line.strip()]
    anno = {
        "name": np.array([r[0] for r in rows]),
        "truncated": np.array([float(r[1]) for r in rows]),
        "occluded": np.array([int(r[2]) for r in rows]),
        "alpha": np.array([float(r[3]) for r in rows]),
        "bbox": np.array([[float(v) for v in r[4:8]] for r in rows]).reshape(-1, 4),
    }
    hwl = np.array([[float(v) for v in r[8:11]] for r in rows]).reshape(-1, 3)
    anno["dimensions"] = hwl[:, [2, 0, 1]]
    anno["location"] = np.array([[float(v) for v in r[11:14]] for r in rows]).reshape(-1, 3)
    anno["rotation_y"] = np.array([float(r[14]) for r in rows]).reshape(-1)
    if rows and len(rows[0]) == 16:
        anno["score"] = np.array([float(r[15]) for r in rows])
    else:
        anno["score"] = np.zeros([len(anno["bbox"])])
    return anno


def _frame(anno: dict) -> dict:
    """Plain-Python view of one annotation dict (lists of floats; names as str)."""
    names = [str(n) for n in np.asarray(anno["name"]).reshape(-1).tolist()]
    count = len(names)

    def column(key, width=None):
        if key not in anno:
            values = np.zeros(count if width is None else (count, width))
        else:
            values = np.asarray(anno[key], dtype=np.float64)
        values = values.reshape(-1) if width is None else values.reshape(-1, width)
        return values.tolist()

    return {
        "name": names,
        "occluded": column("occluded"),
        "alpha": column("alpha"),
        "bbox": column("bbox", 4),
        "dimensions": column("dimensions", 3),  # (l, h, w)
        "location": column("location", 3),  # camera frame, bottom centre
        "rotation_y": column("rotation_y"),
        "score": column("score"),
    }


# --------------------------------------------------------------------------------------------
# which boxes take part (devkit: clean_data, difficulty 0)
# --------------------------------------------------------------------------------------------


def _outside_corridor(location) -> bool:
    x, _, z = location
    return x < -CORRIDOR_HALF_WIDTH_M or x > CORRIDOR_HALF_WIDTH_M or z > CORRIDOR_MAX_DEPTH_M


def _flag_boxes(gt: dict, dt: dict, wanted: str, corridor: bool):
    """Flags for each gt / detection of one frame, the number of scored gts, DontCare boxes."""
    neighbour = _NEIGHBOUR_OF.get(wanted)
    gt_flags = []
    dontcare = []
    n_counted = 0
    for k, name in enumerate(gt["name"]):
        left, top, right, bottom = gt["bbox"][k]
        lowered = name.lower()
        if lowered == wanted:
            kind = "same"
        elif neighbour is not None and lowered == neighbour:
            kind = "neighbour"
        else:
            kind = "other"
        # gt boxes are dropped when too occluded or at most 40 px tall (signed height)
        dropped = gt["occluded"][k] > MAX_OCCLUSION or (bottom - top) <= MIN_BOX_HEIGHT_PX
        if corridor and _outside_corridor(gt["location"][k]):
            dropped = True
        if kind == "same" and not dropped:
            gt_flags.append(COUNTED)
            n_counted += 1
        elif kind == "neighbour" or kind == "same":
            gt_flags.append(NEUTRAL)
        else:
            gt_flags.append(UNRELATED)
        if name == "DontCare":  # exact spelling, case sensitive
            dontcare.append(list(gt["bbox"][k]))

    dt_flags = []
    for k, name in enumerate(dt["name"]):
        _, top, _, bottom = dt["bbox"][k]
        # order matters: a short box is NEUTRAL whatever its class, before the corridor test
        if abs(bottom - top) < MIN_BOX_HEIGHT_PX:
            dt_flags.append(NEUTRAL)
        elif corridor and _outside_corridor(dt["location"][k]):
            dt_flags.append(NEUTRAL)
        elif name.lower() == wanted:
            dt_flags.append(COUNTED)
        else:
            dt_flags.append(UNRELATED)
    return n_counted, gt_flags, dt_flags, dontcare


# --------------------------------------------------------------------------------------------
# overlaps
# --------------------------------------------------------------------------------------------


def _ratio(num, den) -> float:
    """num / den with numpy float64 semantics (nan / inf instead of an exception)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.float64(num) / np.float64(den))


def _image_overlap(a, b, criterion=-1) -> float:
    """Overlap of two (left, top, right, bottom) boxes: IoU (-1) or intersection / area(a) (0)."""
    iw = min(a[2], b[2]) - max(a[0], b[0])
    if not iw > 0:
        return 0.0
    ih = min(a[3], b[3]) - max(a[1], b[1])
    if not ih > 0:
        return 0.0
    area_a = (a[2] - a[0]) * (a[3] - a[1])
    if criterion == -1:
        area_b = (b[2] - b[0]) * (b[3] - b[1])
        return _ratio(iw * ih, area_a + area_b - iw * ih)
    if criterion == 0:
        return _ratio(iw * ih, area_a)
    raise ValueError("criterion must be -1 or 0")


def _footprint(cx, cy, size_x, size_y, angle):
    """Four corners of a rotated rectangle, in the devkit's order and rotation sense.

    Local corners are (-x,-y), (-x,+y), (+x,+y), (+x,-y) with half sizes; each is mapped by
    (u, v) -> (cos*u + sin*v + cx, -sin*u + cos*v + cy).
    """
    c = math.cos(angle)
    s = math.sin(angle)
    hx = size_x / 2
    hy = size_y / 2
    local = [(-hx, -hy), (-hx, hy), (hx, hy), (hx, -hy)]
    return [(c * u + s * v + cx, -s * u + c * v + cy) for (u, v) in local]


def _inside(point, quad) -> bool:
    """Point inside (or on) the parallelogram spanned at quad[0] by edges to quad[1] and quad[3]."""
    ox, oy = quad[0]
    e1 = (quad[1][0] - ox, quad[1][1] - oy)
    e2 = (quad[3][0] - ox, quad[3][1] - oy)
    rel = (point[0] - ox, point[1] - oy)
    along1 = e1[0] * rel[0] + e1[1] * rel[1]
    along2 = e2[0] * rel[0] + e2[1] * rel[1]
    return (
        e1[0] * e1[0] + e1[1] * e1[1] >= along1
        and along1 >= 0
        and e2[0] * e2[0] + e2[1] * e2[1] >= along2
        and along2 >= 0
    )


def _crossing(p, q, r, s):
    """Proper crossing point of segments p-q and r-s, or None (strict side tests)."""
    # p and q must fall on different sides of line r-s (strict), then r and s of line p-q
    side_p = (s[1] - p[1]) * (r[0] - p[0]) > (r[1] - p[1]) * (s[0] - p[0])
    side_q = (s[1] - q[1]) * (r[0] - q[0]) > (r[1] - q[1]) * (s[0] - q[0])
    if side_p == side_q:
        return None
    dqp = (q[0] - p[0], q[1] - p[1])
    side_r = (r[1] - p[1]) * dqp[0] > dqp[1] * (r[0] - p[0])
    side_s = (s[1] - p[1]) * dqp[0] > dqp[1] * (s[0] - p[0])
    if side_r == side_s:
        return None
    dsr = (s[0] - r[0], s[1] - r[1])
    cross_pq = p[0] * q[1] - q[0] * p[1]
    cross_rs = r[0] * s[1] - s[0] * r[1]
    denom = dqp[1] * dsr[0] - dqp[0] * dsr[1]
    if denom == 0:
        return None
    return ((cross_pq * dsr[0] - dqp[0] * cross_rs) / denom, (cross_pq * dsr[1] - dqp[1] * cross_rs) / denom)


def _sorted_around_centre(points):
    """Order points of a convex polygon by a pseudo-angle around their mean (stable)."""
    if not points:
        return []
    mx = sum(p[0] for p in points) / len(points)
    my = sum(p[1] for p in points) / len(points)

    def pseudo_angle(p):
        dx, dy = p[0] - mx, p[1] - my
        norm = math.sqrt(dx * dx + dy * dy)
        if norm != 0:
            dx, dy = dx / norm, dy / norm
        return -2 - dx if dy < 0 else dx

    return sorted(points, key=pseudo_angle)


def _fan_area(points) -> float:
    """Area of an ordered convex polygon as a fan of |triangles| from its first vertex."""
    total = 0.0
    a = points[0] if points else None
    for k in range(1, len(points) - 1):
        b, c = points[k], points[k + 1]
        total += abs(((a[0] - c[0]) * (b[1] - c[1]) - (a[1] - c[1]) * (b[0] - c[0])) / 2.0)
    return total


def _bev_intersection(first, second) -> float:
    """Intersection area of two rotated rectangles given as (cx, cy, size_x, size_y, angle)."""
    qa = _footprint(*first)
    qb = _footprint(*second)
    vertices = []
    for k in range(4):
        if _inside(qa[k], qb):
            vertices.append(qa[k])
        if _inside(qb[k], qa):
            vertices.append(qb[k])
    for i in range(4):
        for j in range(4):
            hit = _crossing(qa[i], qa[(i + 1) % 4], qb[j], qb[(j + 1) % 4])
            if hit is not None:
                vertices.append(hit)
    return _fan_area(_sorted_around_centre(vertices))


def _bev_box(frame, k):
    x, _, z = frame["location"][k]
    length, _, width = frame["dimensions"][k]
    return (x, z, length, width, frame["rotation_y"][k])


def _overlap_table(gt: dict, dt: dict, metric: int):
    """table[j][i] = overlap of detection j with ground truth i (the devkit's index order)."""
    n_gt, n_dt = len(gt["name"]), len(dt["name"])
    table = [[0.0] * n_gt for _ in range(n_dt)]
    for i in range(n_gt):
        for j in range(n_dt):
            if metric == METRIC_IMAGE:
                table[j][i] = _image_overlap(dt["bbox"][j], gt["bbox"][i], -1)
                continue
            # rotated footprints: the ground truth is the first box, the detection the second
            g_box, d_box = _bev_box(gt, i), _bev_box(dt, j)
            shared = _bev_intersection(g_box, d_box)
            if metric == METRIC_BEV:
                union = g_box[2] * g_box[3] + d_box[2] * d_box[3] - shared
                table[j][i] = _ratio(shared, union)
            elif metric == METRIC_3D:
                if not shared > 0:
                    table[j][i] = shared
                    continue
                # camera y points down: a box occupies [y - h, y]
                d_y, d_h = dt["location"][j][1], dt["dimensions"][j][1]
                g_y, g_h = gt["location"][i][1], gt["dimensions"][i][1]
                tall = min(d_y, g_y) - max(d_y - d_h, g_y - g_h)
                if tall > 0:
                    d_l, d_hh, d_w = dt["dimensions"][j]
                    g_l, g_hh, g_w = gt["dimensions"][i]
                    common = tall * shared
                    vol_d = d_l * d_hh * d_w
                    vol_g = g_l * g_hh * g_w
                    table[j][i] = _ratio(common, vol_d + vol_g - common)
                else:
                    table[j][i] = 0.0
            else:
                raise ValueError("unknown metric")
    return table


# --------------------------------------------------------------------------------------------
# matching one frame (devkit: compute_statistics_jit)
# --------------------------------------------------------------------------------------------


def _match_frame(
    table, gt, dt, gt_flags, dt_flags, dontcare, metric, min_overlap, score_floor=0.0, count_fp=False, with_aos=False
):
    """Greedy gt-by-gt matching of one frame.

    count_fp=False: each gt takes the highest-scoring free detection above min_overlap (any
    non-UNRELATED flag); returns the TP scores, used to pick recall thresholds.
    count_fp=True: detections scoring below score_floor are out; each gt prefers the COUNTED
    detection with the largest overlap, falling back to the first NEUTRAL one.
    Returns (tp, fp, fn, similarity, tp_scores); similarity is -1 when tp == fp == 0 in AOS mode.
    """
    scores = dt["score"]
    n_dt = len(dt_flags)
    taken = [False] * n_dt
    too_low = [count_fp and scores[j] < score_floor for j in range(n_dt)]
    tp = fp = fn = 0
    tp_scores = []
    angle_errors = []

    for i, g_flag in enumerate(gt_flags):
        if g_flag == UNRELATED:
            continue
        chosen = -1
        chosen_value = _NO_MATCH  # score (threshold mode) or 1 (fp mode) once something found
        best_overlap = 0.0
        chosen_is_neutral = False
        for j in range(n_dt):
            if dt_flags[j] == UNRELATED or taken[j] or too_low[j]:
                continue
            overlap = table[j][i]
            if not overlap > min_overlap:
                continue
            if not count_fp:
                if scores[j] > chosen_value:
                    chosen, chosen_value = j, scores[j]
            elif dt_flags[j] == COUNTED and (overlap > best_overlap or chosen_is_neutral):
                chosen, chosen_value, best_overlap = j, 1, overlap
                chosen_is_neutral = False
            elif dt_flags[j] == NEUTRAL and chosen_value == _NO_MATCH:
                chosen, chosen_value = j, 1
                chosen_is_neutral = True

        found = chosen_value != _NO_MATCH
        if not found:
            if g_flag == COUNTED:
                fn += 1
        elif g_flag == NEUTRAL or dt_flags[chosen] == NEUTRAL:
            taken[chosen] = True  # absorbed: neither TP nor FP
        else:
            tp += 1
            tp_scores.append(scores[chosen])
            if with_aos:
                angle_errors.append(gt["alpha"][i] - dt["alpha"][chosen])
            taken[chosen] = True

    similarity = 0
    if count_fp:
        for j in range(n_dt):
            if not (taken[j] or dt_flags[j] != COUNTED or too_low[j]):
                fp += 1
        if metric == METRIC_IMAGE:
            # unmatched scored detections mostly inside a DontCare area are forgiven
            forgiven = 0
            for box in dontcare:
                for j in range(n_dt):
                    if taken[j] or dt_flags[j] != COUNTED or too_low[j]:
                        continue
                    if _image_overlap(dt["bbox"][j], box, 0) > min_overlap:
                        taken[j] = True
                        forgiven += 1
            fp -= forgiven
        if with_aos:
            if tp > 0 or fp > 0:
                similarity = 0.0
                for err in angle_errors:
                    similarity += (1.0 + math.cos(err)) / 2.0
            else:
                similarity = -1
    return tp, fp, fn, similarity, tp_scores


def _recall_thresholds(tp_scores, n_counted, n_points=N_RECALL_POINTS):
    """Pick score thresholds so that recall steps by ~1/(n_points-1) (devkit: get_thresholds)."""
    ordered = np.sort(np.asarray(tp_scores, dtype=np.float64))[::-1].tolist()
    picked = []
    reached = 0
    last = len(ordered) - 1
    for k, score in enumerate(ordered):
        here = (k + 1) / n_counted
        ahead = (k + 2) / n_counted if k < last else here
        if k < last and (ahead - reached) < (reached - here):
            continue
        picked.append(score)
        reached += 1 / (n_points - 1.0)
    return picked


# --------------------------------------------------------------------------------------------
# curves and AP
# --------------------------------------------------------------------------------------------


def class_curves(gt_frames, dt_frames, tables, wanted, corridor, metric, min_overlap, with_aos=False):
    """Precision / recall / orientation-similarity arrays (41 each) for one class and metric."""
    flagged = [_flag_boxes(g, d, wanted, corridor) for g, d in zip(gt_frames, dt_frames)]
    n_counted = sum(f[0] for f in flagged)

    collected = []
    for g, d, table, (_, g_flags, d_flags, dc) in zip(gt_frames, dt_frames, tables, flagged):
        collected += _match_frame(table, g, d, g_flags, d_flags, dc, metric, min_overlap)[4]
    thresholds = _recall_thresholds(collected, n_counted)

    tally = np.zeros([len(thresholds), 4])  # tp, fp, fn, similarity
    for g, d, table, (_, g_flags, d_flags, dc) in zip(gt_frames, dt_frames, tables, flagged):
        for t, floor in enumerate(thresholds):
            tp, fp, fn, sim, _ = _match_frame(
                table,
                g,
                d,
                g_flags,
                d_flags,
                dc,
                metric,
                min_overlap,
                score_floor=floor,
                count_fp=True,
                with_aos=with_aos,
            )
            tally[t, 0] += tp
            tally[t, 1] += fp
            tally[t, 2] += fn
            if sim != -1:
                tally[t, 3] += sim

    precision = np.zeros(N_RECALL_POINTS)
    recall = np.zeros(N_RECALL_POINTS)
    orientation = np.zeros(N_RECALL_POINTS)
    with np.errstate(divide="ignore", invalid="ignore"):
        for t in range(len(thresholds)):
            recall[t] = tally[t, 0] / (tally[t, 0] + tally[t, 2])
            precision[t] = tally[t, 0] / (tally[t, 0] + tally[t, 1])
            if with_aos:
                orientation[t] = tally[t, 3] / (tally[t, 0] + tally[t, 1])
        # running maximum from the right (the tail of unfilled zeros is part of the window;
        # nan propagates, as np.max does)
        for t in range(len(thresholds)):
            precision[t] = np.max(precision[t:])
            recall[t] = np.max(recall[t:])
            if with_aos:
                orientation[t] = np.max(orientation[t:])
    return {"precision": precision, "recall": recall, "orientation": orientation, "thresholds": np.array(thresholds)}


def ap_11(curve) -> float:
    """11-point interpolated AP in percent: samples 0, 4, ..., 40 of the 41-point curve."""
    total = 0
    for k in range(0, len(curve), 4):
        total = total + curve[k]
    return float(total / 11 * 100)


def ap_40(curve) -> float:
    """40-point interpolated AP in percent: samples 1..40 (sample 0 is skipped)."""
    total = 0
    for k in range(1, len(curve)):
        total = total + curve[k]
    return float(total / 40 * 100)


def evaluate(gt_annos, dt_annos, classes, corridor) -> dict:
    """AP / AOS per class in percent, as the devkit's get_official_eval_result reports them.

    gt_annos[i] and dt_annos[i] describe the same frame.  corridor=True applies the devkit's
    driving-corridor (custom_method 3) cleaning.  Returns
    {class: {"bbox", "bev", "3d", "aos", "bbox_r40", "bev_r40", "3d_r40", "aos_r40"}}.
    """
    if len(gt_annos) != len(dt_annos):
        raise ValueError("gt_annos and dt_annos must have one entry per frame each")
    gt_frames = [_frame(a) for a in gt_annos]
    dt_frames = [_frame(a) for a in dt_annos]
    tables = {
        m: [_overlap_table(g, d, m) for g, d in zip(gt_frames, dt_frames)]
        for m in (METRIC_IMAGE, METRIC_BEV, METRIC_3D)
    }

    results = {}
    for name in classes:
        wanted = name.lower()
        if wanted not in _CLASS_SLOTS:
            raise KeyError("class %r is not evaluated by the devkit" % name)
        overlaps = CLASSES[name]
        image = class_curves(
            gt_frames, dt_frames, tables[METRIC_IMAGE], wanted, corridor, METRIC_IMAGE, overlaps["image"], with_aos=True
        )
        bev = class_curves(gt_frames, dt_frames, tables[METRIC_BEV], wanted, corridor, METRIC_BEV, overlaps["bev"])
        box3d = class_curves(gt_frames, dt_frames, tables[METRIC_3D], wanted, corridor, METRIC_3D, overlaps["3d"])
        results[name] = {
            "3d": ap_11(box3d["precision"]),
            "bev": ap_11(bev["precision"]),
            "aos": ap_11(image["orientation"]),
            "bbox": ap_11(image["precision"]),
            "3d_r40": ap_40(box3d["precision"]),
            "bev_r40": ap_40(bev["precision"]),
            "aos_r40": ap_40(image["orientation"]),
            "bbox_r40": ap_40(image["precision"]),
        }
    return results
