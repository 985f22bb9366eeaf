"""The exported-graph wrapper: :class:`RadarModel` (load, check input, run, apply the graph's
declared checks), :class:`FrameFeeds` (raw frames -> the graph's feeds) and :func:`inspect_export`.

Loading a graph checks it before anything runs on it: its radaredge metadata against the graph's
own inputs and outputs (:func:`check_signature`), its contents against the content hash recorded
at export (:mod:`.integrity`) and its embedded card against the graph (:func:`card_findings`).
:func:`load` refuses a graph that fails one (InputError naming the file); :func:`inspect_export`
reports what it found instead.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import onnxruntime as ort

from ..cards import ModelCard, card_from_yaml, implausible_policy, plausible_ranges
from ..config import checked_arguments
from ..errors import CapacityError, ConfigError, InputError
from . import backends, integrity
from .bundle import bundle_graphs, part_findings
from .flags import CAPACITY, INPUT_ERRORS, OUT_OF_RANGE, describe
from .flags import OUTPUT as FLAGS_OUTPUT
from .metadata import GraphMetadata
from .session import make_session, run_session

DEFAULT_MAX_POINTS = 65_536  # points per frame a card takes unless it says max_points_per_frame


def max_points_per_frame(card: ModelCard) -> int:
    """The card's ``max_points_per_frame`` (default :data:`DEFAULT_MAX_POINTS`; the card parser
    checks its range)."""
    return int(card.get("max_points_per_frame", DEFAULT_MAX_POINTS))


# Frame times more than this factor apart from the card's frame period (1 / frame_rate), either
# way, are refused: a dropped frame or two stays well inside it, while stamps in milliseconds,
# microseconds or nanoseconds are 1e3, 1e6, 1e9 times too far apart.
PERIOD_FACTOR = 10.0
_TIME_UNITS = ((1e9, "nanoseconds"), (1e6, "microseconds"), (1e3, "milliseconds"))


class FrameFeeds:
    """A point-cloud graph's inputs: checks raw frames against the card's columns and builds the
    graph's feeds. Used by :class:`RadarModel` and by int8 calibration on recordings, so both
    feed a graph the same way. ``refuse`` maps the columns whose values are checked against a
    plausible (low, high) before the graph runs (a card with ``implausible: refuse``)."""

    def __init__(
        self,
        name: str,
        features: list[str],
        frame_inputs: list[str],
        timestamps_input: str | None,
        frame_rate: float = 10.0,
        where: str = "",
        max_points: int = DEFAULT_MAX_POINTS,
        refuse: dict[str, tuple[float, float]] | None = None,
    ):
        self.name, self.features, self.frame_inputs = name, list(features), list(frame_inputs)
        self.timestamps_input, self.frame_rate, self.where = timestamps_input, float(frame_rate), where or name
        self.frames = len(self.frame_inputs)
        self.max_points = max_points
        self.refuse = dict(refuse or {})

    @classmethod
    def of_card(
        cls, card: ModelCard, frame_inputs: list[str], timestamps_input: str | None, where: str = ""
    ) -> "FrameFeeds":
        """The feeds of a graph of ``card`` taking ``frame_inputs`` (and ``timestamps_input``)."""
        refuse = plausible_ranges(card) if implausible_policy(card) == "refuse" else None
        return cls(
            card.name,
            card.features,
            frame_inputs,
            timestamps_input,
            float(card.get("frame_rate", 10.0)),
            where,
            max_points_per_frame(card),
            refuse,
        )

    def _check_plausible(self, k: int, a: np.ndarray) -> None:
        for col, name in enumerate(self.features):
            if name not in self.refuse:
                continue
            lo, hi = self.refuse[name]
            bad = np.flatnonzero((a[:, col] < lo) | (a[:, col] > hi))
            if bad.size:
                raise InputError(
                    f"frame {k}: point {int(bad[0])}, column '{name}': {float(a[bad[0], col])!r} is "
                    f"outside its plausible range [{lo:g}, {hi:g}] ({bad.size} point(s) affected; "
                    f"the card's plausible, implausible: refuse)"
                )

    def _check_period(self, ts: np.ndarray) -> None:
        """InputError when consecutive frame times are not within PERIOD_FACTOR of the card's
        frame period, naming the unit the stamps look like."""
        period = 1.0 / self.frame_rate
        gaps = np.diff(ts)
        bad = np.flatnonzero((gaps > period * PERIOD_FACTOR) | (gaps < period / PERIOD_FACTOR))
        if not bad.size:
            return
        gap = float(gaps[bad[0]])
        unit = next(
            (u for f, u in _TIME_UNITS if period * f / PERIOD_FACTOR <= gap <= period * f * PERIOD_FACTOR), None
        )
        hint = f"; they look like {unit}: pass seconds" if unit else ""
        raise InputError(
            f"timestamps: frames {int(bad[0])} and {int(bad[0]) + 1} are {gap:g} s apart; {self.name} "
            f"records at {self.frame_rate:g} Hz (a frame every {period:g} s), and frame times more than "
            f"{PERIOD_FACTOR:g}x off that are refused{hint}"
        )

    def validate(self, frames: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Check frame count, shapes, dtype and finiteness against the card; return float32 copies."""
        if not self.frames:
            raise InputError(f"{self.where} takes no point-cloud frames: run it with its session")
        if isinstance(frames, np.ndarray):
            frames = [frames] if self.frames == 1 else list(frames)
        if len(frames) != self.frames:
            raise InputError(f"{self.name} takes {self.frames} frame(s) (oldest first), got {len(frames)}")
        cols = len(self.features)
        out = []
        for k, f in enumerate(frames):
            try:
                a = np.asarray(f)
            except (ValueError, TypeError) as exc:
                raise InputError(f"frame {k}: not an array of points ({str(exc).splitlines()[0][:120]})") from None
            if a.dtype.kind not in "fiu":
                raise InputError(f"frame {k}: expected a numeric array of points, got dtype {a.dtype}")
            if a.ndim != 2 or a.shape[1] != cols:
                raise InputError(f"frame {k}: expected shape [N, {cols}] with columns {self.features}, got {a.shape}")
            if len(a) > self.max_points:
                raise CapacityError(
                    f"frame {k}: {len(a)} points; {self.name} takes at most max_points_per_frame = "
                    f"{self.max_points} a frame (memory grows with every point): crop or "
                    f"subsample the scan, or raise the card's max_points_per_frame"
                )
            a = np.ascontiguousarray(a, np.float32)
            bad = ~np.isfinite(a)
            if bad.any():
                row, col = np.argwhere(bad)[0]
                raise InputError(
                    f"frame {k}: non-finite value {a[row, col]} at point {row}, column "
                    f"'{self.features[col]}' ({int(bad.any(1).sum())} point(s) affected)"
                )
            if self.refuse:
                self._check_plausible(k, a)
            out.append(a)
        return out

    def feeds(self, frames: Sequence[np.ndarray], timestamps: Sequence[float] | None = None) -> dict[str, np.ndarray]:
        """The graph's input feeds for one window: the validated frames (:meth:`validate`) and,
        when the graph takes them, the frame times [K] (s, oldest first, strictly increasing;
        default: the card's frame rate). Times may be absolute (ROS or Unix epoch, time since
        boot): they are checked and made relative to the oldest frame in float64, and only the
        relative times go to the graph as float32, so their differences keep sub-millisecond
        precision whatever the epoch."""
        frames = self.validate(frames)
        feeds = dict(zip(self.frame_inputs, frames))
        if self.timestamps_input is not None:
            if timestamps is None:
                ts = np.arange(self.frames, dtype=np.float64) / self.frame_rate
            else:
                try:
                    ts = np.asarray(timestamps, np.float64)
                except (TypeError, ValueError):
                    ts = None
                if ts is None or ts.shape != (self.frames,) or not np.isfinite(ts).all():
                    raise InputError(f"timestamps: expected {self.frames} finite values in seconds, got {timestamps!r}")
                if (np.diff(ts) <= 0).any():
                    raise InputError(f"timestamps must increase strictly (oldest frame first), got {ts.tolist()}")
                self._check_period(ts)
            feeds[self.timestamps_input] = (ts - ts[0]).astype(np.float32)
        return feeds


def _usable(card: ModelCard, frame: np.ndarray) -> np.ndarray:
    """[N] bool: the frame's points a graph keeps before its range: finite, and (the card's
    ``implausible: drop``) every column within its plausible range."""
    keep = np.isfinite(frame).all(1)
    try:
        ranges = plausible_ranges(card) if implausible_policy(card) == "drop" else {}
    except ConfigError:
        ranges = {}
    for col, name in enumerate(card.features):
        if name in ranges and col < frame.shape[1]:
            lo, hi = ranges[name]
            with np.errstate(invalid="ignore"):
                keep &= (frame[:, col] >= lo) & (frame[:, col] <= hi)
    return keep


def input_counts(card: ModelCard, frames: Sequence[np.ndarray]) -> dict[str, int]:
    """Point counts of one run's frames [N_k, F] (columns ``card.features``), the values an output
    check's message may name beside the graph's outputs (:meth:`RadarModel.apply_checks`):

    - ``points``: the points fed;
    - ``points_in_range``: those a pillar graph's stages see as the scan (finite, plausible, x and
      y within ``pillars.point_cloud_range``, bounds included, z not tested: OpenPCDet's
      ``mask_points_by_range``, the points MAFF-Net's DBSCAN clusters);
    - ``points_outside``: finite points outside ``pillars.point_cloud_range`` in x, y or z, the
      points the pillar grid drops (``input_flags`` bit 4).

    Without ``pillars.point_cloud_range`` (or x, y, z columns) only ``points``."""
    arrays = [np.asarray(f, np.float32).reshape(-1, len(card.features)) for f in frames]
    out = {"points": int(sum(len(a) for a in arrays))}
    r = card.get("pillars.point_cloud_range")
    if r is None or not all(c in card.features for c in ("x", "y", "z")):
        return out
    lo, hi = np.asarray(r[:3], np.float32), np.asarray(r[3:], np.float32)  # float32, as the graph compares
    xyz_cols = [card.features.index(c) for c in ("x", "y", "z")]
    in_range = outside = 0
    for a in arrays:
        xyz = a[:, xyz_cols]
        usable = _usable(card, a)
        with np.errstate(invalid="ignore"):
            xy = ((xyz[:, :2] >= lo[:2]) & (xyz[:, :2] <= hi[:2])).all(1)
            grid = ((xyz >= lo) & (xyz < hi)).all(1)
        in_range += int((usable & xy).sum())
        outside += int((np.isfinite(xyz).all(1) & ~grid).sum())
    out.update(points_in_range=in_range, points_outside=outside)
    return out


@dataclass
class FlagTally:
    """What a graph's ``input_flags`` said over the runs of one :class:`RadarModel`: ``runs``;
    runs with bit 8 (``capacity``: more points in a pillar than ``pillars.max_points_per_pillar``,
    the rest dropped) and with bit 4 (``out_of_range``); the points fed and those of them outside
    ``pillars.point_cloud_range``."""

    runs: int = 0
    capacity: int = 0
    out_of_range: int = 0
    points: int = 0
    outside: int = 0

    def capacity_note(self, card: ModelCard, what: str = "run") -> str:
        """The totals of bit 8 as one sentence (``what`` names a run: frame, window)."""
        return (
            f"input_flags bit 8 (capacity) in {self.capacity} of {_count(self.runs, what)}: a pillar held more "
            f"points than the card's pillars.max_points_per_pillar = {card.get('pillars.max_points_per_pillar')} "
            f"keeps, and the points beyond were dropped"
        )

    def range_note(self, card: ModelCard, what: str = "run") -> str:
        """The share of points outside the range as one sentence."""
        return (
            f"{self.outside} of {self.points} points fed ({self.outside / max(self.points, 1):.1%}; input_flags "
            f"bit 4 in {self.out_of_range} of {_count(self.runs, what)}) lie outside the card's "
            f"pillars.point_cloud_range {card.get('pillars.point_cloud_range')} and were dropped"
        )


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "s")


class RadarModel:
    """An exported radaredge pipeline: ``.card`` (from the ONNX metadata) and ``.run(frames)``.

    ``strict`` (the default) refuses a graph whose contents do not match the content hash
    recorded at export, or whose embedded card disagrees with the graph (InputError naming the
    file), and warns about a graph exported before content hashes; with ``strict=False`` (what
    ``inspect`` uses) the findings are kept in ``.content`` and ``.card_findings`` instead.
    Metadata that does not describe the graph (:func:`check_signature`) is refused either way."""

    def __init__(
        self,
        session: ort.InferenceSession,
        path: Path,
        backend: str = "onnxruntime",
        threads: int = 2,
        strict: bool = True,
    ):
        self.session = session
        self.path = path
        self.metadata = session.get_modelmeta().custom_metadata_map
        self.info = GraphMetadata.from_props(self.metadata, str(path))
        self.card: ModelCard = card_from_yaml(self.info.card_yaml, f"{path}: the card in its metadata")
        self.features: list[str] = self.info.features
        self.input_names = [i.name for i in session.get_inputs()]
        self.output_names = [o.name for o in session.get_outputs()]
        self.weights_sha256: str = self.info.weights_sha256
        check_signature(session, self.info, self.card, path)
        # the contents as they are now (cached per file identity), and the card against the graph
        self.content: integrity.ContentHash = integrity.check_content(path) if strict else integrity.content_hash(path)
        self.content_sha256: str = self.content.computed
        self.card_findings: list[str] = card_findings(session, self.info, self.card)
        if strict and self.card_findings:
            raise InputError(f"{path}: {CARD_DISAGREES}: {'; '.join(self.card_findings)}; re-export it")
        self.inputs = FrameFeeds.of_card(
            self.card,
            self.info.frame_inputs,
            self.info.timestamps_input,
            f"{path} ({self.info.part or self.card.name}, inputs {self.input_names})",
        )
        self.errors = INPUT_ERRORS if self.info.input_errors is None else self.info.input_errors
        self.frames = self.inputs.frames
        self.frame_rate = self.inputs.frame_rate
        self.threads = threads
        self.backend = backends.check_backend(backend)  # "auto" becomes the chosen one at the first run
        if backend == "auto" and not backends.auto_available():
            self.backend = "onnxruntime"  # nothing to choose from without OpenVINO
        elif backend == "auto":
            self.backend = backends.cached_choice(self.weights_sha256, threads) or "auto"
        self._runner = self._runner_of(self.backend) if self.backend != "auto" else None
        # input_flags bits 8 and 4 of every run; said once per loaded graph unless a caller (eval)
        # sets say_flags False and says the totals itself
        self.flag_tally = FlagTally()
        self.say_flags = True
        self._said: set[int] = set()

    def _runner_of(self, backend: str):
        if backend == "openvino":
            return backends.openvino_runner(self.path, self.threads)
        return lambda feeds: run_session(self.session, feeds)

    def _execute(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The graph's outputs on ``feeds`` in the chosen runtime; with ``auto``, the first call
        times both runtimes on these feeds and keeps the faster (:mod:`.backends`)."""
        if self._runner is None:
            runners = {name: self._runner_of(name) for name in ("onnxruntime", "openvino")}
            self.backend = backends.choose(self.weights_sha256, self.threads, runners, feeds)
            self._runner = runners[self.backend]
        return self._runner(feeds)

    def validate(self, frames: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Check frame count, shapes, dtype and finiteness against the card (:class:`FrameFeeds`)."""
        return self.inputs.validate(frames)

    def feeds(self, frames: Sequence[np.ndarray], timestamps: Sequence[float] | None = None) -> dict[str, np.ndarray]:
        """The graph's input feeds for one window (:meth:`FrameFeeds.feeds`)."""
        return self.inputs.feeds(frames, timestamps)

    def apply_checks(self, out: Mapping[str, np.ndarray], feeds: Mapping[str, np.ndarray]) -> None:
        """The graph's declared output checks (capacity flags) on one run's outputs: CapacityError
        or a warning; their messages may name the run's outputs and :func:`input_counts` of its
        frames (``{points_in_range}``: the scan points MAFF-Net's DBSCAN counts)."""
        if not self.info.checks:
            return
        frames = [feeds[n] for n in self.info.frame_inputs if n in feeds]
        values = {**input_counts(self.card, frames), **out}
        for check in self.info.checks:  # declared by the model at export (capacity flags)
            check.apply(values)

    def tally_flags(self, out: Mapping[str, np.ndarray], feeds: Mapping[str, np.ndarray]) -> None:
        """Count this run's informational ``input_flags`` bits in :attr:`flag_tally`; with
        :attr:`say_flags`, say each bit the first time it is set on this graph, naming the card
        field that decides it (``pillars.max_points_per_pillar``, ``pillars.point_cloud_range``)."""
        if FLAGS_OUTPUT not in out or self.card.get("pillars.point_cloud_range") is None:
            return
        flags = np.bitwise_or.reduce(np.asarray(out[FLAGS_OUTPUT], np.int64).ravel(), initial=0)
        counts = input_counts(self.card, [feeds[n] for n in self.info.frame_inputs if n in feeds])
        t = self.flag_tally
        t.runs += 1
        t.capacity += bool(flags & CAPACITY)
        t.out_of_range += bool(flags & OUT_OF_RANGE)
        t.points += counts["points"]
        t.outside += counts.get("points_outside", 0)
        if not self.say_flags:
            return
        once = f" (first in run {t.runs} of this graph; said once, RadarModel.flag_tally counts every run)"
        if flags & CAPACITY and CAPACITY not in self._said:
            self._said.add(CAPACITY)
            warnings.warn(
                f"{self.path}: input_flags bit 8 (capacity) is set: a pillar held more points than the "
                f"card's pillars.max_points_per_pillar = {self.card.get('pillars.max_points_per_pillar')} "
                f"keeps, and the points beyond were dropped{once}",
                UserWarning,
                stacklevel=3,
            )
        if flags & OUT_OF_RANGE and OUT_OF_RANGE not in self._said:
            self._said.add(OUT_OF_RANGE)
            n, k = counts["points"], counts.get("points_outside", 0)
            warnings.warn(
                f"{self.path}: input_flags bit 4 (out_of_range) is set: {k} of the {n} points fed "
                f"({k / max(n, 1):.1%}) lie outside the card's pillars.point_cloud_range "
                f"{self.card.get('pillars.point_cloud_range')} and were dropped{once}",
                UserWarning,
                stacklevel=3,
            )

    def run(self, frames: Sequence[np.ndarray], timestamps: Sequence[float] | None = None) -> dict[str, np.ndarray]:
        """Run the pipeline. ``timestamps`` (s, oldest first) default to the card's frame rate."""
        feeds = self.feeds(frames, timestamps)
        out = self._execute(feeds)
        self.apply_checks(out, feeds)
        refused = np.asarray(out.get(FLAGS_OUTPUT, 0)) & self.errors
        if refused.any():  # the checks above let no such input through; the graph agrees
            k = int(np.flatnonzero(refused.ravel())[0])
            raise InputError(
                f"{self.path}: frame {k}: the graph flagged its input: {'; '.join(describe(refused.ravel()[k]))}"
            )
        self.tally_flags(out, feeds)
        return out


_ONNX_FLOAT = "tensor(float)"


def check_signature(session: ort.InferenceSession, info: GraphMetadata, card: ModelCard, path) -> None:
    """InputError unless the graph's own inputs and outputs are the ones its radaredge metadata
    declares: the same names in the same order, float32 point frames [N, F] with F the card's
    feature count, timestamps [K] float32 (a graph whose metadata was edited, or metadata copied
    onto another graph, would otherwise fail inside onnxruntime or run on misread columns)."""
    where = f"{path}: its radaredge metadata does not describe this graph"
    inputs = {i.name: i for i in session.get_inputs()}
    outputs = [o.name for o in session.get_outputs()]
    if list(inputs) != list(info.input_names):
        raise InputError(
            f"{where}: the graph's inputs are {list(inputs)}, the metadata declares {info.input_names}; "
            f"re-export it with radaredge"
        )
    if outputs != list(info.output_names):
        raise InputError(
            f"{where}: the graph's outputs are {outputs}, the metadata declares {info.output_names}; "
            f"re-export it with radaredge"
        )
    if list(info.features) != card.features:
        raise InputError(
            f"{where}: the metadata's feature columns {info.features} differ from its card's {card.features}"
        )
    undeclared = [n for n in [*info.frame_inputs, info.timestamps_input] if n is not None and n not in inputs]
    if undeclared:
        raise InputError(f"{where}: frame or timestamp input(s) {undeclared} are not inputs of the graph")
    for name in info.frame_inputs:
        i = inputs[name]
        width = i.shape[1] if len(i.shape) == 2 else None
        if i.type != _ONNX_FLOAT or len(i.shape) != 2 or (isinstance(width, int) and width != len(card.features)):
            raise InputError(
                f"{where}: input {name!r} is {i.type} {i.shape}; a point frame is float [N, "
                f"{len(card.features)}] (columns {card.features})"
            )
    if info.timestamps_input is not None:
        i = inputs[info.timestamps_input]
        if i.type != _ONNX_FLOAT or len(i.shape) != 1:
            raise InputError(
                f"{where}: input {info.timestamps_input!r} is {i.type} {i.shape}; timestamps are "
                f"float [{len(info.frame_inputs)}]"
            )


CARD_DISAGREES = "its embedded card disagrees with the graph"


def card_findings(session: ort.InferenceSession, info: GraphMetadata, card: ModelCard) -> list[str]:
    """Where the card embedded in a graph's metadata disagrees with the graph itself, one phrase
    each (none when they agree). What a card fixes that the graph's signature shows:

    - its name is the metadata's ``radaredge.model``;
    - ``frames`` (when the card states it) is the number of point-frame inputs, and a static
      timestamps length is that number too;
    - every point frame takes any number of points (up to the card's ``max_points_per_frame``,
      checked before the graph runs), so its point axis is dynamic.

    The feature columns (the card's, the metadata's and each frame input's width) and the output
    names (metadata against graph) are :func:`check_signature`'s. The output names a card implies
    follow from the model family's code (torch side): ``radaredge eval`` and ``map build`` check
    them (:func:`radaredge.eval.places.check_export`)."""
    found = []
    inputs = {i.name: i for i in session.get_inputs()}
    if info.model != card.name:
        found.append(f"its metadata names model {info.model!r}, its card {card.name!r}")
    frames = [n for n in info.frame_inputs if n in inputs]
    stated = card.data.get("frames")
    if frames and stated is not None and stated != len(frames):
        found.append(
            f"the card says frames: {stated}, the graph takes {len(frames)} point frame(s) ({', '.join(frames)})"
        )
    for name in frames:
        shape = inputs[name].shape
        if len(shape) == 2 and isinstance(shape[0], int):
            found.append(
                f"input {name!r} takes exactly {shape[0]} points, the card any number up to "
                f"max_points_per_frame = {max_points_per_frame(card)}"
            )
    ts = info.timestamps_input
    if (
        ts in inputs
        and len(inputs[ts].shape) == 1
        and isinstance(inputs[ts].shape[0], int)
        and inputs[ts].shape[0] != len(frames)
    ):
        found.append(f"input {ts!r} takes {inputs[ts].shape[0]} frame times for {len(frames)} point frame(s)")
    return found


@checked_arguments
def load(path: str | Path, threads: int = 2, backend: str = "onnxruntime") -> RadarModel:
    """Load an exported radaredge ``.onnx`` for inference on ``threads`` CPU threads in
    ``backend``: ``onnxruntime``, ``openvino`` (the openvino extra) or ``auto`` (the faster of
    the two on this machine, timed on the first input and remembered: :mod:`.backends`). The
    input checks and the outputs' names are the same whichever runs it.

    The graph is checked first (:class:`RadarModel`, strict): InputError when its contents do
    not match the content hash recorded at export (``<path>: its contents do not match the hash
    recorded at export: ...``) or its embedded card disagrees with it; a RuntimeWarning when it
    was exported before content hashes were recorded."""
    path = Path(path)
    backends.check_backend(backend)
    return RadarModel(make_session(path, threads=threads), path, backend, threads)


@checked_arguments
def inspect_export(path: str | Path, targets: tuple[str, ...] = ()) -> dict:
    """What an export holds: for a graph file, or each graph of a multi-graph export directory
    (its manifest lists them), the card name, graph name, feature columns, frame inputs,
    inputs and outputs with their shapes, runtime checks, input flag bits, weights hash,
    versions and the card's ``source`` when it has one; with ``targets``, what each deployment
    target does not support (:mod:`radaredge.targets`, which needs the onnx package).

    And whether each graph is what was exported: ``content_sha256`` (the hash recorded at export,
    None before radaredge recorded one), ``integrity`` (``verified``, ``not recorded`` or
    ``MISMATCH`` with both hashes) and ``findings``: the contents not matching the recorded hash,
    the embedded card disagreeing with the graph (:func:`card_findings`), a bundle part whose
    contents are not the ones its manifest recorded. The top-level ``findings`` lists them all
    (``<file>: <finding>``) and ``ok`` is true when there are none; ``radaredge inspect`` exits 1
    when it is false. Metadata that cannot be read, or does not describe its graph, is an
    InputError as for :func:`load`."""
    path = Path(path)
    files = bundle_graphs(path, check_parts=False)
    replaced = part_findings(path)
    graphs, problems = [], []
    for part, f in files.items():
        m = RadarModel(make_session(f), f, strict=False)
        findings = []
        if m.content.status == "mismatch":
            findings.append(integrity.finding(m.content))
        findings += [f"{CARD_DISAGREES}: {x}" for x in m.card_findings]
        if part in replaced:
            findings.append(replaced[part])
        graphs.append(
            {
                "model": m.card.name,
                "graph": m.info.part or m.card.name,
                "onnx": str(f),
                "features": m.features,
                "frames": m.info.frame_inputs,
                "inputs": {i.name: i.shape for i in m.session.get_inputs()},
                "outputs": {o.name: o.shape for o in m.session.get_outputs()},
                "checks": [c.output for c in m.info.checks],
                "input_flags": m.info.input_flags,
                "quantization": m.info.quantization,
                "weights_sha256": m.weights_sha256,
                "versions": m.info.versions,
                "content_sha256": m.content.recorded,
                "integrity": integrity.describe(m.content),
                "findings": findings,
            }
        )
        problems += [f"{f}: {x}" for x in findings]
        if m.card.data.get("source"):  # where the card came from (an OpenPCDet config and its sha256)
            graphs[-1]["source"] = m.card.data["source"]
        if targets:
            # optional: the target checks need the onnx package, which a runtime-only install lacks
            from ..targets import check_graph

            graphs[-1]["targets"] = {t: [x.to_dict() for x in found] for t, found in check_graph(f, targets).items()}
    return {"path": str(path), "ok": not problems, "findings": problems, "graphs": graphs}
