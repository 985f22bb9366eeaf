"""Model cards: YAML files that hold every range, size, channel and threshold.

A card is the single source of truth for a model: code reads its sections through
:meth:`ModelCard.section`, and the exported ONNX carries the card in its metadata.

The shipped cards live in the top-level ``models/<name>.yaml`` and travel in the wheel as the
package data ``radaredge/model_cards/``, so a non-editable install has them too.
:func:`load_card` takes a shipped card's name or the path of any card file;
``$RADAREDGE_CARDS`` points the by-name lookup at another directory.
"""

from __future__ import annotations

import difflib
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Type, TypeVar

import yaml

from ..config import Range, check_numbers, config_from_dict, positive
from ..errors import ConfigError
from ..registry import card_sections

T = TypeVar("T")
REQUIRED = ("name", "description", "model", "features")
CARD_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,127}")
# Top-level numbers every model reads: (range, integral). Sections are checked by their dataclasses.
TOP_LEVEL_NUMBERS = {
    "frames": (Range(1, 64), True),  # scans per window
    "frame_rate": (positive(1000.0), False),  # Hz, the recording's nominal rate
    "seed": (Range(0, 2**32 - 1), True),  # weight initialisation seed
    "max_points_per_frame": (Range(1, 2**24), True),  # runtime capacity per scan
}

# The values a sensor can return in each named point column (units as in radaredge.data.readers):
# a point with a value outside its column's range is left out by the graph (input_flags bit
# ``implausible``) or refused by the runtime (the card's ``implausible: refuse``). A card's
# ``plausible`` section overrides these per column; a column named neither here nor there is an
# error. x, y, z are bounded by each model's point_cloud_range, which drops what lies outside.
PLAUSIBLE_DEFAULTS = {
    "v_r": (-100.0, 100.0),  # m/s: radial velocity; automotive radars measure well within it
    "v_r_comp": (-100.0, 100.0),  # m/s: ego-motion compensated radial velocity
    "rcs": (-100.0, 100.0),  # dBsm (or the power/intensity stand-in, see readers)
    "snr": (-100.0, 200.0),  # dB
    "power": (-100.0, 200.0),  # dB
    "range": (0.0, 1000.0),  # m
    "alpha": (-360.0, 360.0),  # azimuth angle (degrees or radians)
    "beta": (-360.0, 360.0),  # elevation angle (degrees or radians)
    "time": (-10.0, 10.0),  # VoD radar_5frames: the point's scan index, 0 the current, -1 the one before
    "r": (0.0, 1.0),
    "g": (0.0, 1.0),
    "b": (0.0, 1.0),  # colour of a map object's points (Des4Pos)
}
COORDINATES = ("x", "y", "z")
IMPLAUSIBLE_POLICIES = ("drop", "refuse")
MAX_PLAUSIBLE = 3.0e38  # inside float32: the graphs compare in float32

# a window's points are ranked by a float32 CumSum (RANSAC order; TensorRT takes no integer
# CumSum), exact up to 2**24; the graph adds at most a few padding rows
MAX_WINDOW_POINTS = 2**24 - 64
# The BEV maps of one window (frames x x cells x y cells x pillars.out_channels float32) a card may
# ask for. Exporting or running a model keeps many maps of this size at once: measured peak
# tensor memory of a forward pass, 24-31 times the window's BEV bytes for TDFANet and 16 times for
# MAFF-Net, so this bound keeps an export within about 4 GB (a 0.016 m tdfanet-tiny grid,
# 4 M cells of 8 channels, 3 frames, needed 8 GB and is refused when the card is read).
MAX_WINDOW_BEV_BYTES = 128 * 2**20


# Top-level card fields every model takes; each family declares its own sections
# (radaredge.registry.ModelFamily): any other field of a card of that model is refused, so a
# misspelt section is an error rather than a section left silently at its defaults.
COMMON_FIELDS = (
    "name",
    "description",
    "model",
    "features",
    "seed",
    "frames",
    "frame_rate",
    "max_points_per_frame",
    "classes",
    "plausible",
    "implausible",
    "quantization",
    "source",
)


SHIPPED_CARDS = "model_cards"  # the wheel's package of the shipped cards: radaredge/model_cards/*.yaml


def cards_dir() -> Path:
    """Directory searched by card name: $RADAREDGE_CARDS, else the shipped cards: the installed
    package's ``radaredge/model_cards/`` (the wheel maps the top-level ``models/`` there), or
    the top-level ``models/`` of a source checkout (an editable install)."""
    env = os.environ.get("RADAREDGE_CARDS")
    if env:
        return Path(env)
    package = Path(__file__).resolve().parent.parent
    installed = package / SHIPPED_CARDS
    return installed if installed.is_dir() else package.parent / "models"


@dataclass
class ModelCard:
    """A parsed model card. ``data`` is the whole YAML mapping."""

    data: dict[str, Any]
    path: Path | None = None

    @property
    def name(self) -> str:
        return self.data["name"]

    @property
    def model(self) -> str:
        return self.data["model"]

    @property
    def description(self) -> str:
        return self.data["description"]

    @property
    def features(self) -> list[str]:
        return list(self.data["features"])

    def get(self, dotted: str, default: Any = None) -> Any:
        """Value at ``a.b.c`` or ``default``."""
        node: Any = self.data
        for part in dotted.split("."):
            if not isinstance(node, dict) or part not in node:
                return default
            node = node[part]
        return node

    def section(self, dotted: str, cls: Type[T]) -> T:
        """The section at ``dotted`` as dataclass ``cls`` (defaults fill missing fields)."""
        raw = self.get(dotted, {})
        if not isinstance(raw, dict):
            raise ConfigError(f"{self.where}: {dotted} must be a mapping, got {type(raw).__name__}")
        return config_from_dict(cls, raw, f"{self.where}: {dotted}")

    @property
    def where(self) -> str:
        return str(self.path.name) if self.path else self.data.get("name", "<card>")

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.data, sort_keys=False)


def _check_window_bev(data: dict, where: str) -> None:
    """ConfigError when a window's BEV maps (``frames`` x the ``pillars`` grid x ``out_channels``
    float32) exceed :data:`MAX_WINDOW_BEV_BYTES`. A malformed pillars section is left to its own
    checks, which name the field."""
    pillars = data.get("pillars")
    try:
        lo, hi, size = pillars["point_cloud_range"][:3], pillars["point_cloud_range"][3:6], pillars["voxel_size"]
        nx, ny = [max(1, round((float(b) - float(a)) / float(v))) for a, b, v in zip(lo, hi, size)][:2]
        frames, channels = int(data.get("frames", 1)), int(pillars.get("out_channels", 64))
    except (TypeError, KeyError, ValueError, ZeroDivisionError, OverflowError, IndexError):
        return
    cells = (nx, ny)
    window = frames * nx * ny * channels * 4
    if window > MAX_WINDOW_BEV_BYTES:
        raise ConfigError(
            f"{where}: pillars: {frames} frame(s) of a {cells[0]} x {cells[1]} grid of {channels} "
            f"channels are {window / 2**20:.0f} MiB BEV maps per window; at most "
            f"{MAX_WINDOW_BEV_BYTES // 2**20} MiB (an export holds 16-31 times that): a coarser "
            f"pillars.voxel_size, a smaller point_cloud_range, fewer out_channels or frames"
        )


def parse_card(data: Any, path: Path | None = None) -> ModelCard:
    """Validate the top level of a card mapping."""
    where = path.name if path else "<card>"
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: a model card must be a YAML mapping")
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise ConfigError(f"{where}: missing required field(s) {missing}")
    feats = data["features"]
    if not isinstance(feats, list) or not feats or not all(isinstance(f, str) for f in feats):
        raise ConfigError(f"{where}: features must be a non-empty list of column names, e.g. [x, y, z, v_r, rcs]")
    if feats[:3] != ["x", "y", "z"]:
        raise ConfigError(f"{where}: features must start with x, y, z (radar frame, metres); got {feats[:3]}")
    if len(set(feats)) != len(feats):
        raise ConfigError(f"{where}: features: duplicate column names in {feats}")
    for key in ("name", "description", "model"):
        if not isinstance(data[key], str) or not data[key]:
            raise ConfigError(f"{where}: {key} must be a non-empty string, got {data[key]!r}")
    if not CARD_NAME.fullmatch(data["name"]) or ".." in data["name"]:
        raise ConfigError(
            f"{where}: name {data['name']!r}: a card name becomes file names (export/<name>.onnx, "
            f"runs/<name>/), so it is letters, digits and . _ + - only, starting with a letter or "
            f"digit, without '..' (e.g. maffnet-vod-edge)"
        )
    for key, (rng, integral) in TOP_LEVEL_NUMBERS.items():
        if key in data:
            if isinstance(data[key], (list, tuple, dict)):
                raise ConfigError(
                    f"{where}: {key}: expected {'an integer' if integral else 'a number'} in {rng}, got {data[key]!r}"
                )
            check_numbers(data[key], rng, integral, f"{where}: {key}")
    window_points = int(data.get("frames", 1)) * int(data.get("max_points_per_frame", 65536))
    if window_points > MAX_WINDOW_POINTS:
        raise ConfigError(
            f"{where}: frames x max_points_per_frame is {window_points:,}; at most "
            f"{MAX_WINDOW_POINTS:,} points per window (the graphs count points in float32, "
            f"exact to 2**24)"
        )
    _check_window_bev(data, where)
    classes = data.get("classes", [])
    if not isinstance(classes, list) or not all(isinstance(c, str) and CARD_NAME.fullmatch(c) for c in classes):
        raise ConfigError(
            f"{where}: classes must be a list of class names (letters, digits and . _ + -, as the "
            f"labels spell them: they name report files too), got {classes!r}"
        )
    sections = card_sections(data["model"])
    known = COMMON_FIELDS + (sections or ())
    unknown = [k for k in data if k not in known]
    if unknown and sections is not None:
        hints = [
            f"{k!r} (did you mean {close[0]!r}?)" if (close := difflib.get_close_matches(str(k), known, 1)) else repr(k)
            for k in unknown
        ]
        raise ConfigError(
            f"{where}: unknown top-level field(s) {', '.join(hints)}; a {data['model']} card takes {', '.join(known)}"
        )
    source = data.get("source", {})
    if not isinstance(source, dict) or not all(isinstance(k, str) for k in source):
        raise ConfigError(
            f"{where}: source must be a mapping (where the card came from, e.g. the OpenPCDet config "
            f"and its sha256), got {source!r}"
        )
    card = ModelCard(data=data, path=path)
    _given_ranges(card)
    implausible_policy(card)
    return card


def _given_ranges(card: ModelCard) -> dict[str, tuple[float, float]]:
    """The card's ``plausible`` section, checked: feature column -> (low, high)."""
    where = card.where
    given = card.data.get("plausible", {})
    if not isinstance(given, dict):
        raise ConfigError(f"{where}: plausible must map feature columns to [low, high], got {given!r}")
    unknown = sorted(set(given) - set(card.features) - set(COORDINATES))
    if unknown or any(k in COORDINATES for k in given):
        bad = unknown or [k for k in given if k in COORDINATES]
        raise ConfigError(
            f"{where}: plausible: {bad} are not bounded here; name non-coordinate feature columns "
            f"of {card.features} (x, y, z are bounded by the point_cloud_range)"
        )
    out = {}
    for name, pair in given.items():
        if not (isinstance(pair, list) and len(pair) == 2):
            raise ConfigError(f"{where}: plausible.{name}: expected [low, high], got {pair!r}")
        check_numbers(pair, Range(-MAX_PLAUSIBLE, MAX_PLAUSIBLE), False, f"{where}: plausible.{name}")
        if not pair[0] < pair[1]:
            raise ConfigError(f"{where}: plausible.{name}: low {pair[0]!r} must be below high {pair[1]!r}")
        out[name] = (float(pair[0]), float(pair[1]))
    return out


def plausible_ranges(card: ModelCard) -> dict[str, tuple[float, float]]:
    """Each non-coordinate feature column's plausible (low, high), in card order: the card's
    ``plausible`` entry, else :data:`PLAUSIBLE_DEFAULTS`; ConfigError naming the column when it
    has neither (asked by the models that take point frames, and by the runtime)."""
    given = _given_ranges(card)
    out = {}
    for name in card.features:
        if name in COORDINATES:
            continue
        if name in given:
            out[name] = given[name]
        elif name in PLAUSIBLE_DEFAULTS:
            out[name] = PLAUSIBLE_DEFAULTS[name]
        else:
            raise ConfigError(
                f"{card.where}: features: column {name!r} has no plausible range; add "
                f"plausible: {{{name}: [low, high]}} (the values your sensor returns in it)"
            )
    return out


def implausible_policy(card: ModelCard) -> str:
    """The card's ``implausible``: ``drop`` (default: the graph leaves such points out and sets
    the ``implausible`` input flag) or ``refuse`` (the runtime refuses the frame)."""
    policy = card.data.get("implausible", "drop")
    if policy not in IMPLAUSIBLE_POLICIES:
        raise ConfigError(f"{card.where}: implausible must be one of {list(IMPLAUSIBLE_POLICIES)}, got {policy!r}")
    return policy


def load_card(name_or_path: str | Path) -> ModelCard:
    """Load a shipped card by name (``tdfanet`` -> models/tdfanet.yaml, or the file of that name
    in $RADAREDGE_CARDS) or any card by path (anything ending in .yaml/.yml)."""
    p = Path(name_or_path)
    if p.suffix not in (".yaml", ".yml"):
        p = cards_dir() / f"{name_or_path}.yaml"
    if p.is_dir():
        raise ConfigError(f"{p} is a directory, not a model card (a YAML file)")
    if not p.is_file():
        raise ConfigError(
            f"no model card {str(name_or_path)!r}: {p} does not exist; "
            f"available: {', '.join(available_cards()) or 'none'}"
        )
    size = p.stat().st_size  # bounded before anything is read: a sparse 4 GB "card" costs nothing here
    if size > MAX_CARD_BYTES:
        raise ConfigError(
            f"{p.name}: {size} bytes; a model card is at most {MAX_CARD_BYTES} bytes (the shipped cards are a few KiB)"
        )
    try:
        with open(p, "rb") as f:
            raw = f.read(MAX_CARD_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the model card ({exc.strerror or type(exc).__name__})") from None
    if len(raw) > MAX_CARD_BYTES:  # it grew after its stat
        raise ConfigError(f"{p.name}: more than {MAX_CARD_BYTES} bytes; a model card is at most {MAX_CARD_BYTES} bytes")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{p.name}: not a text file (a model card is UTF-8 YAML)") from None
    return parse_card(read_yaml(text, p.name), p)


def resolve_card(card: "ModelCard | str | Path") -> ModelCard:
    """``card`` itself, or the card loaded by name or path (:func:`load_card`)."""
    return card if isinstance(card, ModelCard) else load_card(card)


MAX_CARD_BYTES = 256 * 1024  # the largest shipped card is a few KiB


MAX_CARD_DEPTH = 16  # nesting levels; the shipped cards use 5
MAX_INT_DIGITS = 19  # a card's integers are counts and sizes: 64-bit at most


class _NoAliasLoader(yaml.SafeLoader):
    """PyYAML's safe loader, strict: no anchors and aliases (cards never need them, and a few
    nested aliases expand to gigabytes: a "billion laughs" card inside an .onnx's metadata), no
    key given twice in one mapping (YAML's last one would win silently, a repeated section
    included), at most :data:`MAX_CARD_DEPTH` levels of nesting and integers of at most
    :data:`MAX_INT_DIGITS` digits."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, "anchors and aliases are not allowed in a model card", event.start_mark
            )
        self._depth = getattr(self, "_depth", 0) + 1
        try:
            if self._depth > MAX_CARD_DEPTH:
                raise yaml.composer.ComposerError(
                    None, None, f"nested deeper than {MAX_CARD_DEPTH} levels", self.peek_event().start_mark
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"key {key!r} given twice in one mapping (first at line {seen[key] + 1}); "
                    "a card names each field once",
                    key_node.start_mark,
                )
            if isinstance(key, (str, int, float, bool)):
                seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)

    def construct_yaml_int(self, node):
        digits = sum(c.isdigit() for c in str(node.value))
        if digits > MAX_INT_DIGITS:
            raise yaml.constructor.ConstructorError(
                None,
                None,
                f"an integer of {digits} digits; a card's integers have at most {MAX_INT_DIGITS}",
                node.start_mark,
            )
        return super().construct_yaml_int(node)


_NoAliasLoader.add_constructor("tag:yaml.org,2002:int", _NoAliasLoader.construct_yaml_int)


def read_yaml(text: str, where: str):
    """The YAML document ``text`` (safe types only, no aliases, at most :data:`MAX_CARD_BYTES`);
    ConfigError naming ``where`` otherwise."""
    if len(text) > MAX_CARD_BYTES:
        raise ConfigError(f"{where}: {len(text)} characters; a model card is at most {MAX_CARD_BYTES}")
    try:
        return yaml.load(text, Loader=_NoAliasLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{where}: invalid YAML: {' '.join(str(exc).split())}") from None


def card_from_yaml(text: str, where: str = "<card>") -> ModelCard:
    """Parse a card from YAML text (used when the card travels inside ONNX metadata); ``where``
    names its origin in errors."""
    return parse_card(read_yaml(text, where))


def available_cards() -> list[str]:
    """Names of the cards loadable by name (those in :func:`cards_dir`), sorted."""
    d = cards_dir()
    return sorted(p.stem for p in d.glob("*.yaml")) if d.is_dir() else []
