"""3D-detection AP of a MAFF-Net export on a labelled set, backend beside backend.

``radaredge eval --model maffnet-vod --onnx G --data ROOT --split val`` reads the split of a
KITTI-layout set (:mod:`radaredge.data.kitti_detection`: View-of-Delft, TJ4DRadSet, or
``radaredge make-benchmark --task detection``), crops each scan to the camera's view when the
card's ``input.crop`` says so (upstream's ``FOV_POINTS_ONLY``), and runs every backend over
every frame, one backend after another:

* ``torch reference``: the card's reference formulation with the weights the graph holds;
* ``onnxruntime``: the graph G;
* ``onnxruntime int8``: G's int8 copy, when one lies beside it;
* ``openvino``: G in OpenVINO's CPU plugin, when OpenVINO is installed.

Detections (radar frame) go into the camera frame as OpenPCDet writes them for the devkits,
and :mod:`radaredge.eval.kitti_ap` scores them with the dataset's protocol: per class 3D AP, BEV
AP and AOS over the entire annotated area and (VoD) the driving corridor, 11 recall positions
as VoD reports them, 40 beside. Each backend's difference from the reference is in AP points.
Beside AP, the box errors of matched detections (:mod:`radaredge.eval.box_errors`) say where
the boxes go wrong: centre, height, size, heading.
"""

from __future__ import annotations

import os
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .. import artifacts, atomic, runtime
from ..cards import ModelCard
from ..data.detection_benchmark import make_detection_benchmark
from ..data.kitti_detection import (
    LAYOUTS,
    DetectionFrame,
    DetectionLayout,
    DetectionSet,
    Labels,
    camera_fov_mask,
    labels_to_radar_boxes,
    radar_boxes_to_labels,
)
from ..data.readers import scan_features
from ..errors import CapacityError, ConfigError, InputError
from ..exporting.graphs import require_same_weights
from ..models.factory import create_model
from ..ops.box_iou import bev_iou_paired
from ..runtime.openvino import openvino_installed
from ..runtime.runners import graph_runner
from .box_errors import MATCH_DISTANCE, BoxErrors, box_error_lines, class_box_errors
from .kitti_ap import AREAS, ClassCurve, ap_table, bootstrap_rows, evaluate_frames, resampled_ap
from .recall_stats import percentile_interval

REFERENCE, ORT, ORT_INT8, OPENVINO = "torch reference", "onnxruntime", "onnxruntime int8", "openvino"
PICTURE_FRAMES = 4  # BEV pictures in the report directory, the frames where backends disagree most
PICTURE_BOXES = 20  # detections drawn (and compared) per backend and frame, highest scores first
AREA_LABELS = {"entire_area": "entire area", "corridor": "corridor"}
AP_RESAMPLES, AP_INTERVAL_METRICS = 1000, ("3d", "bev")  # bootstrap over frames (seed 0) behind each AP interval
MEAN = "mAP"

Detector = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


def layout_for_card(card: ModelCard, name: str | None = None) -> DetectionLayout:
    """The dataset layout named ``name`` (vod, tj4d), or the one whose scan files hold every
    feature of the card (VoD's 7 columns or TJ4D's 8)."""
    if name is not None:
        if name not in LAYOUTS:
            raise ConfigError(f"unknown dataset layout {name!r}; choose one of {sorted(LAYOUTS)}")
        return LAYOUTS[name]
    fits = [n for n, layout in LAYOUTS.items() if set(card.features) <= set(scan_features(layout.scan_format))]
    if not fits:
        raise ConfigError(
            f"{card.name}: its features {card.features} are not all in a VoD or TJ4D scan file; "
            f"no labelled dataset layout reads them"
        )
    return LAYOUTS[fits[0]]


# ----------------------------------------------------------------------------- backends


def _detections(out: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        np.asarray(out["boxes"], np.float64).reshape(-1, 7),
        np.asarray(out["scores"], np.float64).ravel(),
        np.asarray(out["labels"], np.int64).ravel(),
    )


def reference_detector(net) -> Detector:
    def run(points):
        with torch.no_grad():
            out = net.run(torch.from_numpy(points), reference=True)
        return _detections({k: v.numpy() for k, v in out.items() if k in ("boxes", "scores", "labels")})

    return run


def graph_detector(exported, runner=None) -> Detector:
    """Detections of an exported graph (a :class:`radaredge.runtime.RadarModel`) in onnxruntime,
    or through ``runner`` (feeds -> outputs, e.g. OpenVINO) with the same input checks. The
    detector's ``model`` is the graph (its ``flag_tally`` counts the input flags of onnxruntime's runs)."""

    def run(points):
        if runner is None:
            return _detections(exported.run([points]))
        feeds = exported.feeds([points])
        out = runner(feeds)
        exported.apply_checks(out, feeds)
        return _detections(out)

    run.model = exported
    return run


def detectors(
    card: ModelCard, onnx_path, checkpoint=None, reference: bool = True, openvino: bool | None = None
) -> dict[str, Detector]:
    """Backend name -> detector for the export at ``onnx_path``: the torch reference (unless
    ``reference`` is False), onnxruntime, its int8 copy when present, OpenVINO when installed
    (``openvino`` None) or asked for (True). ``onnx_path`` may name the int8 copy itself; then
    the fp32 graph beside it is scored too when it exists."""
    given = Path(onnx_path)
    fp32 = artifacts.graph_of_copy(given)
    int8 = given if fp32 != given else artifacts.copy_path(given, artifacts.INT8)
    graphs = {name: runtime.load(p) for name, p in ((ORT, fp32), (ORT_INT8, int8)) if p.is_file()}
    if not graphs:
        raise InputError(f"{given}: no such graph")
    for g in graphs.values():
        g.say_flags = False  # evaluate_detection says the input flags' totals once
    for name, g in graphs.items():
        if g.card.name != card.name or g.features != card.features:
            raise ConfigError(
                f"{g.path} is an export of card {g.card.name!r} ({g.features}), not {card.name!r} "
                f"({card.features}); pass the --model/--config it was exported with"
            )
    first = next(iter(graphs.values()))
    if len(graphs) == 2 and graphs[ORT_INT8].weights_sha256 != graphs[ORT].weights_sha256:
        raise ConfigError(
            f"{int8} was quantised from other weights than {fp32}; re-write it with "
            f"`radaredge export --model {card.name} --quantize int8`"
        )
    out: dict[str, Detector] = {}
    if reference:
        net = create_model(card, checkpoint)
        require_same_weights(first, net, checkpoint)
        out[REFERENCE] = reference_detector(net)
    out.update({name: graph_detector(g) for name, g in graphs.items()})
    if openvino is None:
        openvino = openvino_installed()
    if openvino and ORT in graphs:
        out[OPENVINO] = graph_detector(graphs[ORT], graph_runner(fp32, "openvino"))
    return out


# ----------------------------------------------------------------------------- the set


def flag_notes(card: ModelCard, backends: dict[str, Detector]) -> list[str]:
    """The input flags of the first graph backend's runs over the set, as sentences to say once:
    frames with points dropped by a pillar's cap (``pillars.max_points_per_pillar``, input_flags
    bit 8) and the share of points outside ``pillars.point_cloud_range`` (bit 4)."""
    tally = next(
        (
            d.model.flag_tally
            for d in backends.values()
            if getattr(d, "model", None) is not None and d.model.flag_tally.runs
        ),
        None,
    )
    if tally is None:
        return []
    notes = [tally.capacity_note(card, "frame")] if tally.capacity else []
    if tally.outside:
        notes.append(tally.range_note(card, "frame"))
    return notes


def card_points(frame: DetectionFrame, card: ModelCard) -> np.ndarray:
    """The frame's points as the card's graph takes them: cropped to the camera's view when the
    card's ``input.crop`` is ``camera_fov``."""
    if card.get("input.crop", "none") != "camera_fov":
        return frame.points
    xyz = frame.points[:, [card.features.index(c) for c in ("x", "y", "z")]]
    return frame.points[camera_fov_mask(xyz, frame.calib, frame.image_size)]


def as_labels(detections, frame: DetectionFrame, classes: list[str]) -> Labels:
    """A backend's detections of ``frame`` as camera-frame KITTI labels (labels are 1-based
    indices into the card's ``classes``)."""
    boxes, scores, labels = detections
    if len(labels) and (labels.min() < 1 or labels.max() > len(classes)):
        raise InputError(
            f"frame {frame.frame_id}: class index {int(labels.max())} outside the card's classes {classes}"
        )
    names = np.array([classes[i - 1] for i in labels], dtype=object)
    return radar_boxes_to_labels(boxes, scores, names, frame.calib, frame.image_size)


def _class_pair(detections, frame: DetectionFrame, classes: list[str], cls: str):
    """(boxes [D, 7], scores [D], ground truth [G, 7]) of class ``cls`` in ``frame``, radar frame."""
    boxes, scores, labels = detections
    mine = labels == classes.index(cls) + 1
    gt = frame.labels.select(np.asarray(frame.labels.name) == cls)
    return boxes[mine], scores[mine], labels_to_radar_boxes(gt, frame.calib)


def unmatched_boxes(a, b, top: int = PICTURE_BOXES) -> int:
    """Boxes of two detection sets ((boxes [D, 7], scores [D], labels [D]), the ``top`` highest
    scores of each) that find no box of the same class with BEV IoU >= 0.5 in the other, greedily
    by score: 0 when the two detectors agree on every box."""

    def top_boxes(d):
        order = np.argsort(-d[1], kind="stable")[:top]
        return d[0][order], d[2][order]

    (ba, la), (bb, lb) = top_boxes(a), top_boxes(b)
    if not len(ba) or not len(bb):
        return len(ba) + len(bb)
    n, m = len(ba), len(bb)
    iou = bev_iou_paired(torch.from_numpy(ba).repeat_interleave(m, 0), torch.from_numpy(bb).repeat(n, 1))
    iou = iou.numpy().reshape(n, m) * (la[:, None] == lb[None, :])
    used, matched = np.zeros(m, bool), 0
    for i in range(n):
        j = np.flatnonzero(~used & (iou[i] >= 0.5))
        if len(j):
            used[j[np.argmax(iou[i, j])]] = True
            matched += 1
    return n + m - 2 * matched


# ----------------------------------------------------------------------------- the report


@dataclass
class DetectionEvalReport:
    """Result of :func:`evaluate_detection`; ``ap[backend][area][class][metric]`` in % (11 recall
    positions; ``*_r40`` 40), ``fps[backend]`` frames per second of the whole frame loop."""

    model: str
    onnx: str
    checkpoint: str | None
    data: str
    split: str
    layout: str
    classes: list[str]
    frames: list[DetectionFrame]
    points: list[np.ndarray]
    detections: dict[str, list]
    ap: dict[str, dict]
    curves: dict[str, dict]
    fps: dict[str, float]
    min_iou: dict[str, float]
    areas: tuple[str, ...]
    disagreement: list[tuple[str, int]] = field(default_factory=list)
    box_errors: dict[str, dict[str, BoxErrors]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)  # what was read or dropped unasked, said once as warnings
    # 95 % bootstrap intervals over frames (:func:`ap_intervals`): [backend][area][class or "mAP"][metric]
    intervals: dict = field(default_factory=dict)
    delta_intervals: dict = field(default_factory=dict)  # paired, against the baseline; other backends only

    @property
    def baseline(self) -> str:
        """The backend the others are compared with: the reference, else the first graph."""
        return REFERENCE if REFERENCE in self.ap else next(iter(self.ap))

    def mean_ap(self, backend: str, area: str, metric: str = "3d") -> float:
        rows = self.ap[backend][area]
        return float(np.mean([rows[c][metric] for c in self.classes]))

    def delta(self, backend: str, area: str, cls: str, metric: str = "3d") -> float:
        return self.ap[backend][area][cls][metric] - self.ap[self.baseline][area][cls][metric]

    def to_dict(self) -> dict:
        """The JSON report: setup, protocol, per backend AP per area/class/metric and mAP, the
        difference from the reference, frames per second, and the frames where backends disagree most."""
        backends = list(self.ap)
        return {
            "model": self.model,
            "onnx": self.onnx,
            "checkpoint": self.checkpoint,
            "data": self.data,
            "split": self.split,
            "dataset": self.layout,
            "frames": len(self.frames),
            "classes": self.classes,
            "protocol": {
                "min_iou_3d_bev": self.min_iou,
                "areas": list(self.areas),
                "ap": "11 recall positions (VoD's reported figure); *_r40: 40 positions",
                "interval": f"95 % percentile bootstrap over frames ({AP_RESAMPLES} resamples, seed 0), the "
                f"devkit's AP recomputed on each; differences paired (same resamples)",
                "corridor": "camera x in [-4, 4] m, z <= 25 m",
                "min_box_height_px": 40,
            },
            "backends": backends,
            "reference": self.baseline,
            "ap": self.ap,
            "map": {
                b: {a: {m: self.mean_ap(b, a, m) for m in ("3d", "bev", "aos")} for a in self.areas} for b in backends
            },
            "delta_ap_points": {
                b: {
                    a: {c: {m: self.delta(b, a, c, m) for m in ("3d", "bev", "aos")} for c in self.classes}
                    for a in self.areas
                }
                for b in backends
                if b != self.baseline
            },
            "ap_interval": self.intervals,
            "delta_ap_interval": self.delta_intervals,
            "frames_per_second": self.fps,
            "most_disagreeing_frames": [{"frame": f, "unmatched_boxes": n} for f, n in self.disagreement],
            "notes": list(self.notes),
            "box_errors": {
                "matching": f"nuScenes' true-positive matching: centres within {MATCH_DISTANCE:g} m in "
                f"bird's-eye view, detections in descending score; radar frame, metres, "
                f"dz = detection minus ground truth",
                **{b: {c: e.to_dict() for c, e in per.items()} for b, per in self.box_errors.items()},
            },
        }

    def lines(self) -> list[str]:
        """Text: one table per metric (3D, BEV): class x area rows, a column per backend with AP
        and its difference from the reference."""
        backends = list(self.ap)
        others = [b for b in backends if b != self.baseline]
        n_gt = {a: {c: self.ap[self.baseline][a][c]["num_gt"] for c in self.classes} for a in self.areas}
        lines = [
            f"eval {self.model} on {self.data} ({self.layout}, split {self.split}): {len(self.frames)} frames; "
            f"AP in % at 11 recall positions (VoD's protocol); min IoU "
            + ", ".join(f"{c} {v:g}" for c, v in self.min_iou.items())
        ]
        if self.intervals:
            lines.append(
                f"[95 % interval: percentile bootstrap over frames, {AP_RESAMPLES} resamples; diff: paired, "
                f"against {self.baseline}]"
            )

        def cell(backend: str, area: str, cls: str, metric: str, value: float) -> str:
            iv = self.intervals.get(backend, {}).get(area, {}).get(cls, {}).get(metric)
            return f"{value:>26.2f}" if iv is None else f"{f'{value:6.2f} [{iv[0]:6.2f}, {iv[1]:6.2f}]':>26}"

        def diff(backend: str, area: str, cls: str, metric: str, value: float) -> str:
            iv = self.delta_intervals.get(backend, {}).get(area, {}).get(cls, {}).get(metric)
            return f"{value:>+24.2f}" if iv is None else f"{f'{value:+6.2f} [{iv[0]:+6.2f}, {iv[1]:+6.2f}]':>24}"

        for metric, title in (("3d", "3D AP"), ("bev", "BEV AP")):
            head = f"{title:<12}{'area':<13}{'objects':>8}" + f"{self.baseline:>26}"
            head += "".join(f"{b:>26}{'diff':>24}" for b in others)
            lines += ["", head]
            for area in self.areas:
                for cls in [*self.classes, MEAN]:
                    if cls == MEAN:
                        value = {b: self.mean_ap(b, area, metric) for b in backends}
                        row = f"{MEAN:<12}{AREA_LABELS[area]:<13}{sum(n_gt[area].values()):>8}"
                    else:
                        value = {b: self.ap[b][area][cls][metric] for b in backends}
                        row = f"{cls:<12}{AREA_LABELS[area]:<13}{n_gt[area][cls]:>8}"
                    row += cell(self.baseline, area, cls, metric, value[self.baseline])
                    row += "".join(
                        cell(b, area, cls, metric, value[b])
                        + diff(b, area, cls, metric, value[b] - value[self.baseline])
                        for b in others
                    )
                    lines.append(row)
        if self.box_errors:
            lines += [
                "",
                *box_error_lines(self.box_errors),
                f"(matched: detections within {MATCH_DISTANCE:g} m of a labelled box's centre, "
                f"nuScenes' rule; dz = detection minus ground truth)",
            ]
        lines += ["", "frames per second: " + ", ".join(f"{b} {v:.1f}" for b, v in self.fps.items())]
        return lines

    def write_json(self, path: str | os.PathLike) -> Path:
        return atomic.write_json(path, self.to_dict())

    def write_directory(self, directory: str | os.PathLike) -> list[Path]:
        """``directory``/report.json, pr-<class>.png (3D precision-recall of every backend, both
        areas) and bev-<frame>.png of the frames where backends disagree most (points, ground
        truth, each backend's top detections). The plots need matplotlib (the eval extra)."""
        directory = Path(directory)
        with atomic.Staging(directory) as stage:
            written = [self.write_json(stage.path(directory / "report.json"))]
            written += [self._pr_plot(stage.path(directory / f"pr-{cls}.png"), cls) for cls in self.classes]
            written += [
                self._bev_plot(stage.path(directory / f"bev-{fid}.png"), fid)
                for fid, _ in self.disagreement[:PICTURE_FRAMES]
            ]
            stage.commit()
        return [directory / p.name for p in written]

    def _figure(self, size):
        # optional: matplotlib (eval extra) draws the report's pictures only when they are asked for
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=size, layout="constrained")
        FigureCanvasAgg(fig)
        return fig

    def _pr_plot(self, path: Path, cls: str) -> Path:
        fig = self._figure((5.5 * len(self.areas), 4.5))
        for ax, area in zip(np.atleast_1d(fig.subplots(1, len(self.areas))), self.areas):
            for backend, style in zip(self.ap, ("-", "--", ":", "-.")):
                curve: ClassCurve = self.curves[backend][area][cls]["3d"]
                ax.plot(
                    curve.recall[: curve.filled],
                    curve.precision[: curve.filled],
                    style,
                    marker=".",
                    ms=3,
                    label=f"{backend} (AP {curve.ap11:.1f})",
                )
            ax.set(
                xlabel="recall",
                ylabel="precision",
                xlim=(0, 1.01),
                ylim=(0, 1.01),
                title=f"{cls}, {AREA_LABELS[area]}, 3D IoU > {self.min_iou[cls]:g}",
            )
            ax.grid(alpha=0.3)
            ax.legend(loc="lower left", fontsize="small")
        with atomic.atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=90, format="png")
        return path

    def _bev_plot(self, path: Path, fid: str) -> Path:
        from matplotlib.patches import Polygon

        i = [f.frame_id for f in self.frames].index(fid)
        frame, pts = self.frames[i], self.points[i]
        fig = self._figure((7, 7))
        ax = fig.subplots()
        ax.scatter(pts[:, 1], pts[:, 0], s=2, color="0.55", label="radar points")

        def draw(boxes, colour, style, label):
            for k, b in enumerate(boxes):
                c, s = np.cos(b[6]), np.sin(b[6])
                corners = [
                    (b[0] + c * u - s * v, b[1] + s * u + c * v)
                    for u, v in (
                        (b[3] / 2, b[4] / 2),
                        (-b[3] / 2, b[4] / 2),
                        (-b[3] / 2, -b[4] / 2),
                        (b[3] / 2, -b[4] / 2),
                    )
                ]
                ax.add_patch(
                    Polygon(
                        [(y, x) for x, y in corners],
                        fill=False,
                        ec=colour,
                        ls=style,
                        lw=1.4,
                        label=label if k == 0 else None,
                    )
                )

        draw(
            labels_to_radar_boxes(
                frame.labels.select(np.array([n != "DontCare" for n in frame.labels.name], bool)), frame.calib
            ),
            "tab:green",
            "-",
            "ground truth",
        )
        for (backend, dets), colour, style in zip(
            self.detections.items(), ("tab:blue", "tab:red", "tab:orange", "tab:purple"), ("-", "--", ":", "-.")
        ):
            boxes, scores, _ = dets[i]
            draw(boxes[np.argsort(-scores, kind="stable")[:PICTURE_BOXES]], colour, style, backend)
        ax.set(xlabel="y (m, left)", ylabel="x (m, forward)", aspect="equal", title=f"frame {fid}")
        ax.invert_xaxis()
        ax.legend(loc="upper right", fontsize="small")
        with atomic.atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=90, format="png")
        return path


def ap_intervals(
    curves: dict, classes: list[str], areas: tuple[str, ...], baseline: str, samples: int = AP_RESAMPLES, seed: int = 0
) -> tuple[dict, dict]:
    """95 % percentile-bootstrap intervals over frames (``samples`` resamples drawn with
    ``seed``) of every backend's 11-point AP (%) in ``curves`` [backend][area][class][metric] for
    the metrics of :data:`AP_INTERVAL_METRICS`, per class and for the mean over ``classes``
    ("mAP"); and of each other backend's difference from ``baseline``, paired (the same resamples).
    Returns ([backend][area][class][metric] -> (low, high), the same for the differences)."""
    frames = len(curves[baseline][areas[0]][classes[0]][AP_INTERVAL_METRICS[0]].frames)
    rows = bootstrap_rows(frames, samples, seed)
    draws = {
        b: {
            a: {c: {m: resampled_ap(per_class[c][m].frames, rows)[0] for m in AP_INTERVAL_METRICS} for c in classes}
            for a, per_class in per_area.items()
            if a in areas
        }
        for b, per_area in curves.items()
    }
    for per_area in draws.values():
        for per_class in per_area.values():
            per_class[MEAN] = {m: np.mean([per_class[c][m] for c in classes], 0) for m in AP_INTERVAL_METRICS}

    def intervals(pick) -> dict:
        return {
            a: {c: {m: percentile_interval(pick(a, c, m)) for m in AP_INTERVAL_METRICS} for c in [*classes, MEAN]}
            for a in areas
        }

    return (
        {b: intervals(lambda a, c, m, b=b: draws[b][a][c][m]) for b in draws},
        {
            b: intervals(lambda a, c, m, b=b: draws[b][a][c][m] - draws[baseline][a][c][m])
            for b in draws
            if b != baseline
        },
    )


def evaluate_detection(
    card: ModelCard,
    onnx_path,
    data,
    split: str = "val",
    checkpoint=None,
    reference: bool = True,
    dataset: str | None = None,
    openvino: bool | None = None,
    progress: Callable[[str], Callable] | None = None,
) -> DetectionEvalReport:
    """AP of every backend (:func:`detectors`) over the ``split`` of the labelled set at ``data``
    (module docstring). ``progress(desc)`` wraps each backend's frame loop (a progress bar)."""
    layout = layout_for_card(card, dataset)
    classes = [c.name for c in layout.eval_classes if c.name in card.get("classes")]
    if not classes:
        raise ConfigError(
            f"{card.name} detects {card.get('classes')}, none of the classes {layout.name} evaluates "
            f"({[c.name for c in layout.eval_classes]})"
        )
    eval_classes = tuple(layout.eval_class(c) for c in classes)
    the_set = DetectionSet(
        data, split, layout, int(card.get("input.scans_accumulated", 1)), card.get("input.image_size")
    )
    backends = detectors(card, onnx_path, checkpoint, reference, openvino)
    frames = [the_set.frame(i, card.features) for i in range(len(the_set))]
    points = [card_points(f, card) for f in frames]
    wrap = progress or (lambda desc: iter)
    detections, fps = {}, {}
    for name, detect in backends.items():
        found = []
        start = time.perf_counter()
        for i in wrap(f"frames [{name}]")(range(len(frames))):
            try:
                found.append(detect(points[i]))
            except (InputError, CapacityError) as exc:
                raise InputError(f"{the_set.training / 'velodyne' / (frames[i].frame_id + '.bin')}: {exc}") from None
        fps[name] = len(frames) / max(time.perf_counter() - start, 1e-9)
        detections[name] = found
    notes = the_set.notes + flag_notes(card, backends)
    for note in notes[len(the_set.notes) :]:
        warnings.warn(note, UserWarning, stacklevel=2)
    areas = AREAS if layout.corridor else ("entire_area",)
    gts = [f.labels for f in frames]
    curves = {
        name: evaluate_frames(
            gts,
            [as_labels(d, f, card.get("classes")) for d, f in zip(dets, frames)],
            eval_classes,
            areas,
            AP_INTERVAL_METRICS,
        )
        for name, dets in detections.items()
    }
    ap = {name: ap_table(c) for name, c in curves.items()}
    report = DetectionEvalReport(
        card.name,
        str(onnx_path),
        str(checkpoint) if checkpoint else None,
        str(the_set.root),
        split,
        layout.name,
        classes,
        frames,
        points,
        detections,
        ap,
        curves,
        fps,
        {c.name: c.min_iou for c in eval_classes},
        areas,
    )
    report.notes = notes
    report.intervals, report.delta_intervals = ap_intervals(curves, classes, areas, report.baseline)
    report.box_errors = {
        name: {
            cls: class_box_errors([_class_pair(d, f, card.get("classes"), cls) for d, f in zip(dets, frames)])
            for cls in classes
        }
        for name, dets in detections.items()
    }
    base = detections[report.baseline]
    score = [
        max(
            (unmatched_boxes(base[i], dets[i]) for name, dets in detections.items() if name != report.baseline),
            default=0,
        )
        for i in range(len(frames))
    ]
    order = sorted(range(len(frames)), key=lambda i: -score[i])
    report.disagreement = [(frames[i].frame_id, int(score[i])) for i in order[: max(PICTURE_FRAMES, 10)]]
    return report


# ----------------------------------------------------------------------------- int8 judged by AP

INT8_AP_BUDGET = 1.0  # AP points per class an int8 graph may lose against its fp32 graph
INT8_AP_DRIVES, INT8_AP_FRAMES = 3, 12  # the labelled synthetic set, every split of it: 36 frames
INT8_AP_SPLIT = "all"  # the split int8_ap_loss writes: every frame of the set (a model never trained on it)


@dataclass
class Int8ApReport:
    """AP per class (3D, entire area) of an fp32 graph and its int8 copy on a labelled synthetic
    set; true when int8 loses at most :data:`INT8_AP_BUDGET` points in every class."""

    fp32: dict[str, float]
    int8: dict[str, float]
    frames: int
    budget: float = INT8_AP_BUDGET

    def loss(self, cls: str) -> float:
        return self.fp32[cls] - self.int8[cls]

    @property
    def passed(self) -> bool:
        return all(self.loss(c) <= self.budget for c in self.fp32)

    def __bool__(self) -> bool:
        return self.passed

    def to_dict(self) -> dict:
        return {
            "metric": "3D AP, entire area, 11 recall positions (%)",
            "frames": self.frames,
            "budget_ap_points": self.budget,
            "fp32": self.fp32,
            "int8": self.int8,
            "loss": {c: self.loss(c) for c in self.fp32},
            "passed": self.passed,
        }

    def lines(self) -> list[str]:
        out = [
            f"int8 by AP: 3D AP (entire area) on {self.frames} labelled synthetic frames, budget "
            f"{self.budget:g} point lost per class"
        ]
        out += [
            f"  {c:<12} fp32 {self.fp32[c]:6.2f}  int8 {self.int8[c]:6.2f}  lost {self.loss(c):+6.2f}"
            f"  {'ok' if self.loss(c) <= self.budget else 'FAIL'}"
            for c in self.fp32
        ]
        if max(self.fp32.values(), default=0.0) < 10.0:
            out.append(
                "  note: the fp32 graph scores below 10 AP here (seeded or unfitted weights), so this says "
                "little; judge int8 by AP on trained weights and your own labelled split (`radaredge eval`)"
            )
        return out


def int8_ap_loss(card: ModelCard, onnx_path, checkpoint=None) -> Int8ApReport:
    """3D AP per class of the fp32 graph at ``onnx_path`` (or the graph of an int8 copy named
    there) and of its int8 copy, on every frame of a labelled synthetic set in the card's dataset
    layout (:func:`radaredge.data.detection_benchmark.make_detection_benchmark`, version 1, seed 7:
    none of its drives is one a model trained on the default set has seen). All three splits count: a
    1-point budget on a dozen frames is decided by one or two boxes."""
    fp32 = artifacts.graph_of_copy(onnx_path)
    for path, what in ((fp32, "fp32 graph"), (artifacts.copy_path(fp32, artifacts.INT8), "int8 copy")):
        if not path.is_file():
            raise InputError(
                f"{path} does not exist: AP lost to int8 compares the {what} with the other one; "
                f"write both with `radaredge export --model {card.name} --quantize int8`"
            )
    layout = layout_for_card(card)
    with tempfile.TemporaryDirectory(prefix="radaredge-int8-ap-") as tmp:
        root = Path(tmp) / "set"
        make_detection_benchmark(root, INT8_AP_DRIVES, INT8_AP_FRAMES, seed=7, dataset=layout.name, version=1)
        for image_sets in root.glob("**/ImageSets"):
            ids = "".join((image_sets / f"{split}.txt").read_text() for split in ("train", "val", "test"))
            (image_sets / f"{INT8_AP_SPLIT}.txt").write_text(ids)
        with warnings.catch_warnings():  # the notes of a synthetic set compared with itself say nothing
            warnings.simplefilter("ignore", UserWarning)
            report = evaluate_detection(card, fp32, root, INT8_AP_SPLIT, checkpoint, reference=False, openvino=False)
    area = "entire_area"
    return Int8ApReport(
        {c: report.ap[ORT][area][c]["3d"] for c in report.classes},
        {c: report.ap[ORT_INT8][area][c]["3d"] for c in report.classes},
        len(report.frames),
    )
