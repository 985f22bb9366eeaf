"""MAFF-Net model cards from OpenPCDet configs (TRV-Lab/MAFF-Net ``tools/cfgs/MAFF-Net/*.yaml``).

:func:`load_openpcdet_config` reads a config and its ``_BASE_CONFIG_`` the way OpenPCDet's
``pcdet/config.py`` (``cfg_from_yaml_file`` -> ``merge_new_config``) merges them: at the node that
names a base, the base file's keys are set first (a shallow update, the base's own
``_BASE_CONFIG_`` is not followed), then the node's own keys are merged over them, mappings key by
key and everything else (lists included) replaced whole.

:func:`maffnet_card` turns the merged config into a card and accounts for every key: each leaf is
*mapped* to a card field, *checked* (a value radaredge's formulation fixes: any other value is
refused, naming the key and why), *training-only* (optimiser, augmentation, targets, losses) or
*ignored* with the reason (read by upstream's code but without effect on its test-time output).
A key in none of these is refused: radaredge has no formulation of it. Values that the config
does not hold and the card needs (graph capacities, the random-init prior) are radaredge's
deployment choices, the same as the shipped cards', listed in :data:`DEPLOYMENT_CHOICES`.

Upstream behaviours the conversion reproduces rather than repairs (docs/models/maffnet.md):

- the points' columns are ``x, y, z`` then ``used_feature_list``'s other names, in that order
  (``absolute_coordinates_encoding``); the card's ``features`` are those columns;
- RadarPillarVFE / RadarPillarVFE_TJ select their raw inputs by *position* in a hard-coded list
  of names (``available_features``), in the order of their USE_* flags, not by name in
  ``used_feature_list`` (TRV-Lab/MAFF-Net#4). The card's ``vfe_features`` names the columns the
  VFE really reads, in its input order. Where a position lies past the points' columns (upstream
  fails there: MAFF-Net_TJ4D.yaml's SNR, position 5 of 5 columns) the column is taken by its
  name, and a note says so;
- CQCA_cfa's ``DBSCAN_V`` indexes the batch points ``[batch, x, y, z, ...]``;
- ``USE_DIRECTION_CLASSIFIER: False`` still builds and applies the direction classifier
  (AnchorHeadSingle tests the key for presence), and ``ROI_GRID_POOL.POOL_METHOD`` is never read
  (``build_local_aggregation_module`` always max-pools): both convert as upstream computes, with
  a note.

Keys in otherwise training-only subtrees that upstream builds test-time code from are checked:
each head's ``BOX_CODER_CONFIG`` (its box decoder), POST_PROCESSING's NMS_THRESH type (a float
selects the class-agnostic branch), the clustering map's origin and cells against the pillar grid,
the anchors' stride against BACKBONE_2D's output, and the range-mask data processor.
"""

from __future__ import annotations

import hashlib
import math
import re
import stat
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError
from . import MAX_CARD_BYTES, read_yaml

BASE_KEY = "_BASE_CONFIG_"
CFA_MODULES = {"CQCA_cfa": "dbscan", "GridDensityBEV": "grid_density"}
# upstream column names that radaredge's readers call otherwise
COLUMN_NAMES = {"SNR": "snr"}
# VFE class -> (its ``available_features``, its USE_* flags in the order it selects them)
VFE_KINDS = {
    "RadarPillarVFE": (
        ("x", "y", "z", "rcs", "v_r", "v_r_comp", "time"),
        (("USE_RCS", "rcs"), ("USE_VR", "v_r"), ("USE_VR_COMP", "v_r_comp"), ("USE_TIME", "time")),
    ),
    "RadarPillarVFE_TJ": (
        ("x", "y", "z", "v_r", "range", "SNR", "alpha", "beta"),
        (("USE_SNR", "SNR"), ("USE_VR", "v_r"), ("USE_RANGE", "range"), ("USE_ALPHA", "alpha"), ("USE_BETA", "beta")),
    ),
}
# What the card needs and an OpenPCDet config does not hold: radaredge's choices, as in the shipped cards.
DEPLOYMENT_CHOICES = {
    "seed": 0,  # seeded initialisation when no checkpoint is given
    "init": "kaiming",  # random-init only
    "spa.capacity": 2048,  # pillar slots of the exported attention
    "cfa.dbscan.capacity": 4096,  # scan points clustered per call
    "cfa.not_converged": "error",  # DBSCAN beyond its capacity is refused at run time
    "dense_head.cls_prior": 0.1,  # random-init only; a checkpoint replaces the bias
    "stage_two.keypoints.padded_rois": "upstream",
    "quantization.keep_fp32": ["dense_head"],  # int8 of the anchor head costs trained weights 15-24 AP points
    "quantization.reduce_range": True,
}
STAGE_TWO_KEEP_FP32 = ["roi_head"]  # a two-stage card's keep_fp32 also: int8 of the ROI head costs 0.9 Car AP points
# upstream module constants the card spells out (not config keys)
CAF_CONSTANTS = {"pool_size": 16, "heads": 8, "ffn_ratio": 4, "se_reduction": 16}  # TransformerFusionBlock, SELayer
CAF_BN_EPS = 1.0e-5  # CQCA_caf's fusion conv BatchNorm2d (torch's default)
DBSCAN_MAX_CLUSTER = 100  # CQCA_cfa's hard-coded "clusters above 100 points are noise"
GRID_DEFAULTS = {"MAX_DENSITY": 100, "CC_ITERATIONS": 20}  # the fork README's values
MAP_CHANNELS = 3  # the CFA map's channels: velocity, density, label


# ----------------------------------------------------------------------------- reading and merging


@dataclass(frozen=True)
class ConfigFile:
    """One YAML file of the chain: how the config names it, where it was read, its sha256."""

    named: str
    path: Path
    sha256: str

    def __fspath__(self) -> str:
        """The file as read (a ConfigFile is a path: the list of files read can be checked as paths)."""
        return str(self.path)


def _read(path: Path, where: str | None) -> tuple[dict, str]:
    """A config file's mapping and the sha256 of its bytes. ConfigError naming the file, and
    ``where`` (the config and key that name it, for a base config). The size is checked with
    ``stat`` before a byte is read (a model card's limit, :data:`MAX_CARD_BYTES`)."""
    label = path.name if where is None else f"{where} {path.name}"
    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{label}: not a regular file")
        if st.st_size > MAX_CARD_BYTES:
            raise ConfigError(
                f"{label}: {st.st_size} bytes; an OpenPCDet config is at most {MAX_CARD_BYTES} bytes "
                f"(upstream's are a few KiB)"
            )
        with path.open("rb") as f:
            raw = f.read(MAX_CARD_BYTES + 1)  # a file that grew since stat is still cut off
    except OSError as exc:
        raise ConfigError(f"{label}: cannot read {path} ({exc.strerror or exc})") from None
    if len(raw) > MAX_CARD_BYTES:
        raise ConfigError(f"{label}: more than {MAX_CARD_BYTES} bytes; an OpenPCDet config is at most {MAX_CARD_BYTES}")
    if b"\x00" in raw:
        raise ConfigError(f"{label}: a binary file (it holds NUL bytes), not an OpenPCDet YAML config")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{label}: not a UTF-8 text file, so not an OpenPCDet YAML config") from None
    data = read_yaml(text, label)
    if not isinstance(data, dict):
        got = "nothing (an empty file)" if data is None else f"a YAML {_yaml_kind(data)}"
        raise ConfigError(f"{label}: an OpenPCDet config is a YAML mapping of keys, this file holds {got}")
    return data, hashlib.sha256(raw).hexdigest()


def _yaml_kind(value) -> str:
    return {list: "list", str: "string", int: "number", float: "number", bool: "boolean"}.get(
        type(value), type(value).__name__
    )


def _base_path(named: str, config: Path, override: Path | None) -> Path:
    """The file a ``_BASE_CONFIG_`` names: ``override`` (--dataset-config) if given; else the path
    as OpenPCDet opens it (relative to the working directory), then relative to the config's
    folder and each folder above it (upstream's configs name ``tools/cfgs/...`` from the
    repository root). The config's path is resolved first, so a relative one (``cfgs/...`` run
    from ``tools/``) searches the same folders as its absolute path."""
    if override is not None:
        return override
    folder = config.resolve().parent
    candidates = [Path(named)] + [d / named for d in (folder, *folder.parents)]
    for c in candidates:
        if c.is_file():
            return c
    raise ConfigError(
        f"{config.name}: {BASE_KEY} {named!r} not found (looked in the working directory and in "
        f"{folder} and the folders above it); pass it with --dataset-config"
    )


def _merge(node: dict, new: dict, at: str, config: Path, override: Path | None, files: list[ConfigFile]) -> None:
    """OpenPCDet's ``merge_new_config(node, new)``, recording each base file read."""
    if BASE_KEY in new:
        named = new[BASE_KEY]
        if not isinstance(named, str):
            raise ConfigError(f"{config.name}: {at}{BASE_KEY}: expected a file path, got {named!r}")
        path = _base_path(named, config, override)
        base, digest = _read(path, f"{config.name}: {at}{BASE_KEY}")
        if BASE_KEY in base:
            raise ConfigError(
                f"{path.name}: {BASE_KEY}: a base config's own base is not followed by OpenPCDet "
                f"(merge_new_config updates with the base file as it is); merge it by hand"
            )
        files.append(ConfigFile(named, path, digest))
        node.update(base)
    for key, value in new.items():
        if not isinstance(value, dict):
            node[key] = value
            continue
        if key not in node:
            node[key] = {}
        elif not isinstance(node[key], dict):
            raise ConfigError(
                f"{config.name}: {at}{key}: a mapping here, but the base config's {key} is "
                f"{node[key]!r}; OpenPCDet cannot merge the two"
            )
        _merge(node[key], value, f"{at}{key}.", config, override, files)


def load_openpcdet_config(path: str | Path, dataset_config: str | Path | None = None) -> tuple[dict, list[ConfigFile]]:
    """The merged config of ``path`` (its ``_BASE_CONFIG_`` chain as OpenPCDet merges it) and the
    files read, the config first; ``dataset_config`` replaces the file its ``_BASE_CONFIG_`` names."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such OpenPCDet config file")
    data, digest = _read(path, None)
    override = None
    if dataset_config is not None:
        override = Path(dataset_config)
        if not override.is_file():
            raise ConfigError(f"--dataset-config {override}: no such file")
        if _count_bases(data) != 1:
            raise ConfigError(
                f"--dataset-config: {path.name} names {_count_bases(data)} {BASE_KEY} files; "
                f"--dataset-config replaces exactly one"
            )
    files = [ConfigFile(path.name, path, digest)]
    merged: dict = {}
    _merge(merged, data, "", path, override, files)
    return merged, files


def _count_bases(node) -> int:
    if not isinstance(node, dict):
        return 0
    return int(BASE_KEY in node) + sum(_count_bases(v) for v in node.values())


# ----------------------------------------------------------------------------- key accounting


MAPPED, CHECKED, TRAINING, IGNORED = "mapped", "checked", "training-only", "ignored"


@dataclass(frozen=True)
class KeyFate:
    """What the conversion did with one config key: ``fate`` (mapped, checked, training-only or
    ignored) and ``detail`` (the card field, the value radaredge requires, or why)."""

    key: str
    fate: str
    detail: str


def _leaves(node, prefix: str = "") -> list[str]:
    """Every leaf key of a config tree, dotted, list entries of mappings as ``[i]``."""
    if isinstance(node, dict) and node:
        return [leaf for k, v in node.items() for leaf in _leaves(v, f"{prefix}.{k}" if prefix else str(k))]
    if isinstance(node, list) and node and all(isinstance(v, dict) for v in node):
        return [leaf for i, v in enumerate(node) for leaf in _leaves(v, f"{prefix}[{i}]")]
    return [prefix]


class _Ledger:
    """Reads a merged config key by key and records each key's fate."""

    def __init__(self, cfg: dict, where: str):
        self.cfg, self.where = cfg, where
        self.fates: dict[str, KeyFate] = {}
        self.notes: list[str] = []

    def has(self, key: str) -> bool:
        return self._find(key)[0]

    def _find(self, key: str):
        node: Any = self.cfg
        for part in re.findall(r"[^.\[\]]+|\[\d+\]", key):
            if part.startswith("["):
                i = int(part[1:-1])
                if not isinstance(node, list) or i >= len(node):
                    return False, None
                node = node[i]
            elif isinstance(node, dict) and part in node:
                node = node[part]
            else:
                return False, None
        return True, node

    def error(self, key: str, why: str) -> ConfigError:
        return ConfigError(f"{self.where}: {key}: {why}")

    def value(self, key: str, default: Any = ..., kind: type | tuple | None = None) -> Any:
        found, v = self._find(key)
        if not found:
            if default is ...:
                raise self.error(key, "missing; upstream's MAFF-Net reads it")
            return default
        if kind is not None and (not isinstance(v, kind) or isinstance(v, bool) and bool not in _kinds(kind)):
            raise self.error(key, f"expected {_kind_name(kind)}, got {v!r}")
        bad = _non_finite(v, key)
        if bad is not None:
            raise self.error(
                bad[0],
                f"{bad[1]!r} is not a finite number (YAML's .nan / .inf); upstream's computation is undefined with it",
            )
        return v

    def _mark(self, key: str, fate: str, detail: str) -> None:
        found, node = self._find(key)
        if not found:
            return
        for leaf in _leaves(node, key):
            self.fates.setdefault(leaf, KeyFate(leaf, fate, detail))

    def map(self, key: str, card_field: str, default: Any = ..., kind=None) -> Any:
        v = self.value(key, default, kind)
        self._mark(key, MAPPED, card_field)
        return v

    def check(self, key: str, allowed: tuple, why: str, default: Any = ...) -> Any:
        """The key's value, which must be one of ``allowed`` (``why`` says what radaredge computes)."""
        v = self.value(key, default)
        if not any(_same(v, a) for a in allowed):
            want = " or ".join(repr(a) for a in allowed)
            raise self.error(key, f"{v!r} is not supported: radaredge computes {why} ({want})")
        self._mark(key, CHECKED, f"must be {' or '.join(repr(a) for a in allowed)}: {why}")
        return v

    def training(self, key: str, why: str = "training only") -> None:
        self._mark(key, TRAINING, why)

    def ignore(self, key: str, why: str) -> None:
        self._mark(key, IGNORED, why)

    def unaccounted(self) -> list[str]:
        return [leaf for leaf in _leaves(self.cfg) if leaf not in self.fates]


def _non_finite(value, key: str):
    """(dotted key, value) of the first NaN or infinite number in ``value``, or None."""
    if isinstance(value, float) and not math.isfinite(value):
        return key, value
    if isinstance(value, dict):
        items = ((f"{key}.{k}", v) for k, v in value.items())
    elif isinstance(value, list):
        items = ((f"{key}[{i}]", v) for i, v in enumerate(value))
    else:
        return None
    for sub, v in items:
        bad = _non_finite(v, sub)
        if bad is not None:
            return bad
    return None


def _kinds(kind) -> tuple:
    return kind if isinstance(kind, tuple) else (kind,)


def _kind_name(kind) -> str:
    names = {
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "a list",
        dict: "a mapping",
        bool: "true/false",
    }
    return " or ".join(names.get(k, k.__name__) for k in _kinds(kind))


def _same(a, b) -> bool:
    return type(a) is type(b) and a == b if isinstance(b, bool) or isinstance(a, bool) else a == b


NUMBER = (int, float)


# ----------------------------------------------------------------------------- the conversion


@dataclass
class Conversion:
    """A converted card (``card``, the mapping to write), every config key's fate, and notes on
    what upstream does that a reader of the config would not expect."""

    card: dict
    keys: list[KeyFate] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        out = {f: 0 for f in (MAPPED, CHECKED, TRAINING, IGNORED)}
        for k in self.keys:
            out[k.fate] += 1
        return out


def maffnet_card(
    cfg: dict, files: list[ConfigFile], *, name: str | None = None, stage_two: bool = True, cfa: str | None = None
) -> Conversion:
    """The radaredge card of a merged MAFF-Net OpenPCDet config (see the module docstring).

    ``stage_two`` False writes a stage-one card (the PFE, point head and ROI head are not run);
    ``cfa`` ``"dbscan"`` or ``"grid_density"`` picks the clustering map, default the one the
    config's IMAGE_BACKBONE names (CQCA_cfa: upstream's DBSCAN; GridDensityBEV: the fthbng77
    fork's). ConfigError naming the key for anything radaredge cannot reproduce."""
    where = files[0].named
    led = _Ledger(cfg, where)
    led.check("MODEL.NAME", ("MAFF_Net",), "TRV-Lab's MAFF_Net detector")
    classes = led.map("CLASS_NAMES", "classes", kind=list)
    if not classes or not all(isinstance(c, str) and c for c in classes):
        raise led.error("CLASS_NAMES", f"expected a list of class names, got {classes!r}")

    columns = _point_columns(led)
    vfe_cols, out_channels = _vfe(led, columns)
    features = [COLUMN_NAMES.get(c, c) for c in columns]
    vfe_features = [COLUMN_NAMES.get(c, c) for c in vfe_cols]

    card: dict = {
        "name": name or _default_name(where, stage_two),
        "description": (
            f"MAFF-Net {'two-stage' if stage_two else 'stage one'} converted from the OpenPCDet config {where}"
        ),
        "model": "maffnet",
        "seed": DEPLOYMENT_CHOICES["seed"],
        "init": DEPLOYMENT_CHOICES["init"],
        "features": features,
    }
    if vfe_features != features:
        card["vfe_features"] = vfe_features
    card["classes"] = list(classes)
    card["input"] = _input(led)
    pillars, ny, nx = _pillars(led, out_channels)
    card["pillars"] = pillars
    scatter = led.check(
        "MODEL.MAP_TO_BEV.NAME",
        ("PointPillarScatter_spa", "PointPillarScatter"),
        "the pillar scatter, with or without MAFF-Net's sparse pillar attention",
    )
    spa = scatter == "PointPillarScatter_spa" and led.map("MODEL.MAP_TO_BEV.IS_SPA", "spa.enabled", kind=bool)
    led.check(
        "MODEL.MAP_TO_BEV.NUM_BEV_FEATURES", (out_channels,), "the pillar map with the VFE's NUM_FILTERS channels"
    )
    if spa and out_channels != 64:
        raise led.error("MODEL.VFE.NUM_FILTERS", f"[{out_channels}]: upstream's SPA is hard-coded to 64 channels")
    card["spa"] = {"enabled": bool(spa), "capacity": DEPLOYMENT_CHOICES["spa.capacity"]}
    _voxel_cap(led, spa, ny * nx)
    card["cfa"] = _cfa(led, cfa, columns, features, pillars)
    card["caf"] = _caf(led, out_channels)
    card["backbone_2d"] = _backbone(led)
    card["dense_head"] = _dense_head(led)
    _check_head_grid(led, card["backbone_2d"], card["dense_head"]["anchors"], ny, nx)
    nms = _post_processing(led)
    card["post_processing"] = nms
    if stage_two:
        card["stage_two"] = _stage_two(led, dict(nms))
    else:
        for module in ("PFE", "POINT_HEAD", "ROI_HEAD"):
            led.ignore(f"MODEL.{module}", "stage two, not run by a stage-one card (--stage-one)")
    keep = (STAGE_TWO_KEEP_FP32 if stage_two else []) + DEPLOYMENT_CHOICES["quantization.keep_fp32"]
    card["quantization"] = {"keep_fp32": list(keep), "reduce_range": DEPLOYMENT_CHOICES["quantization.reduce_range"]}
    _training_and_data_keys(led)
    for f in files[1:]:
        for key in _base_keys(cfg):
            led.ignore(key, f"names the base config merged here ({f.named})")
    unknown = led.unaccounted()
    if unknown:
        raise ConfigError(
            f"{where}: {', '.join(unknown)}: not a MAFF-Net config key radaredge knows; it has no "
            f"formulation of {'them' if len(unknown) > 1 else 'it'}, so a card cannot reproduce "
            f"{'them' if len(unknown) > 1 else 'it'} (remove {'them' if len(unknown) > 1 else 'it'}, "
            "or see docs/models/maffnet.md for the keys it maps)"
        )
    card["source"] = _source(files, stage_two, cfa)
    order = [k for k in _leaves(cfg)]
    keys = sorted(led.fates.values(), key=lambda f: order.index(f.key))
    return Conversion(card=card, keys=keys, notes=led.notes)


def _default_name(config_name: str, stage_two: bool) -> str:
    stem = re.sub(r"[^a-z0-9]+", "-", Path(config_name).stem.lower()).strip("-") or "maffnet"
    return stem if stage_two else f"{stem}-stage-one"


def _base_keys(node, prefix: str = "") -> list[str]:
    if not isinstance(node, dict):
        return []
    here = [f"{prefix}{BASE_KEY}"] if BASE_KEY in node else []
    return here + [k for key, v in node.items() for k in _base_keys(v, f"{prefix}{key}.")]


def _source(files: list[ConfigFile], stage_two: bool, cfa: str | None) -> dict:
    """Where the card came from: each config file as the chain names it with its sha256, and the
    options of the conversion."""
    src: dict = {"format": "openpcdet", "config": files[0].named, "sha256": files[0].sha256}
    if len(files) > 1:
        src["base_configs"] = [{"named": f.named, "sha256": f.sha256} for f in files[1:]]
    options = ([] if stage_two else ["--stage-one"]) + ([f"--cfa {cfa}"] if cfa else [])
    if options:
        src["options"] = options
    return src


def _point_columns(led: _Ledger) -> list[str]:
    """The points' columns after OpenPCDet's ``absolute_coordinates_encoding``: x, y, z (the
    source's first three columns), then ``used_feature_list``'s other names in their order."""
    enc = "DATA_CONFIG.POINT_FEATURE_ENCODING"
    led.check(f"{enc}.encoding_type", ("absolute_coordinates_encoding",), "absolute-coordinate point features")
    used = led.map(f"{enc}.used_feature_list", "features", kind=list)
    src = led.map(f"{enc}.src_feature_list", "features (the file's columns the encoder picks from)", kind=list)
    if list(src[:3]) != ["x", "y", "z"]:
        raise led.error(f"{enc}.src_feature_list", f"must start with x, y, z (OpenPCDet asserts it), got {src}")
    for c in used:
        if c not in src:
            raise led.error(f"{enc}.used_feature_list", f"{c!r} is not in src_feature_list {src}")
    columns = ["x", "y", "z"] + [c for c in used if c not in ("x", "y", "z")]
    if len(set(columns)) != len(columns):
        raise led.error(f"{enc}.used_feature_list", f"names a column twice: {used}")
    return columns


def _vfe(led: _Ledger, columns: list[str]) -> tuple[list[str], int]:
    """The columns the VFE reads, in its input order, and its output channels (see the module
    docstring on upstream's positional selection)."""
    kind = led.check("MODEL.VFE.NAME", tuple(VFE_KINDS), "MAFF-Net's radar pillar VFE")
    available, flags = VFE_KINDS[kind]
    for key, value, what in (
        ("USE_NORM", True, "the PFN layer with BatchNorm"),
        ("USE_ABSLOTE_XYZ", True, "the VFE on absolute x, y, z"),  # upstream's spelling
        ("WITH_DISTANCE", False, "the VFE without the point distance"),
        ("USE_ELEVATION", True, "the VFE with z"),
    ):
        led.check(f"MODEL.VFE.{key}", (value,), what)
    wanted = ["x", "y", "z"]
    for flag, feature in flags:
        if led.map(f"MODEL.VFE.{flag}", "vfe_features", kind=bool):
            wanted.append(feature)
    filters = led.map("MODEL.VFE.NUM_FILTERS", "pillars.out_channels", kind=list)
    if len(filters) != 1 or not isinstance(filters[0], int) or isinstance(filters[0], bool):
        raise led.error(
            "MODEL.VFE.NUM_FILTERS", f"radaredge's VFE has one PFN layer; expected [channels], got {filters}"
        )
    read = []
    for feature in wanted:
        pos = available.index(feature)
        if pos < len(columns):
            col = columns[pos]
            if col != feature:
                led.notes.append(
                    f"MODEL.VFE: {kind} reads its {feature} input from column {pos} of the points, "
                    f"which used_feature_list makes {col} (it selects by position in {list(available)}, "
                    f"TRV-Lab/MAFF-Net#4); the card feeds {col} there, as upstream does"
                )
        elif feature in columns:
            col = feature
            led.notes.append(
                f"MODEL.VFE: {kind} would read its {feature} input from column {pos}, past the "
                f"{len(columns)} columns of used_feature_list {columns} (upstream fails there); the "
                f"card takes the column named {feature}"
            )
        else:
            raise led.error(
                "MODEL.VFE",
                f"{kind} reads {feature} (USE_ flag set) from column {pos}, and the points "
                f"have neither that column nor one named {feature}: {columns}",
            )
        read.append(col)
    if len(set(read)) != len(read):
        raise led.error("MODEL.VFE", f"{kind} would read a column twice: {read} from the points {columns}")
    return read, filters[0]


def _input(led: _Ledger) -> dict:
    """``input``: scans accumulated (VoD's ``radar_<n>frames`` data folder) and the camera crop."""
    path = led.map("DATA_CONFIG.DATA_PATH", "input.scans_accumulated (a radar_<n>frames folder)", default="", kind=str)
    m = re.search(r"radar_(\d+)frames/*$", path)
    crop = led.map("DATA_CONFIG.FOV_POINTS_ONLY", "input.crop", default=False, kind=bool)
    return {"scans_accumulated": int(m.group(1)) if m else 1, "crop": "camera_fov" if crop else "none"}


PROCESSORS = ("mask_points_and_boxes_outside_range", "shuffle_points", "transform_points_to_voxels")


def _processor(led: _Ledger, name: str) -> str | None:
    """The DATA_PROCESSOR entry's key prefix for processor ``name`` (None if absent); ConfigError
    for a processor radaredge has no formulation of."""
    steps = led.value("DATA_CONFIG.DATA_PROCESSOR", [], kind=list)
    for i, s in enumerate(steps):
        if not isinstance(s, dict) or s.get("NAME") not in PROCESSORS:
            raise led.error(
                f"DATA_CONFIG.DATA_PROCESSOR[{i}]",
                f"{s.get('NAME') if isinstance(s, dict) else s!r}: "
                f"radaredge has no formulation of this processor (it knows {', '.join(PROCESSORS)})",
            )
    hits = [i for i, s in enumerate(steps) if isinstance(s, dict) and s.get("NAME") == name]
    if len(hits) > 1:
        raise led.error("DATA_CONFIG.DATA_PROCESSOR", f"{name} appears {len(hits)} times")
    return f"DATA_CONFIG.DATA_PROCESSOR[{hits[0]}]" if hits else None


def _pillars(led: _Ledger, out_channels: int) -> tuple[dict, int, int]:
    """``pillars`` (metres) and the grid's (ny, nx)."""
    rng = led.map("DATA_CONFIG.POINT_CLOUD_RANGE", "pillars.point_cloud_range", kind=list)
    vox = _processor(led, "transform_points_to_voxels")
    if vox is None:
        raise led.error("DATA_CONFIG.DATA_PROCESSOR", "no transform_points_to_voxels step; MAFF-Net is pillar based")
    led.check(f"{vox}.NAME", ("transform_points_to_voxels",), "pillars")
    size = led.map(f"{vox}.VOXEL_SIZE", "pillars.voxel_size", kind=list)
    per = led.map(f"{vox}.MAX_POINTS_PER_VOXEL", "pillars.max_points_per_pillar", kind=int)
    for key, v, n in (("DATA_CONFIG.POINT_CLOUD_RANGE", rng, 6), (f"{vox}.VOXEL_SIZE", size, 3)):
        if len(v) != n or not all(isinstance(x, NUMBER) and not isinstance(x, bool) for x in v):
            raise led.error(key, f"expected {n} numbers, got {v}")
    if not all(s > 0 for s in size):
        raise led.error(f"{vox}.VOXEL_SIZE", f"entries must be > 0, got {size}")
    for i, axis in enumerate("xyz"):
        if not rng[i] < rng[i + 3]:
            raise led.error(
                "DATA_CONFIG.POINT_CLOUD_RANGE",
                f"{rng}: [x_min, y_min, z_min, x_max, y_max, z_max] needs {axis}_min < {axis}_max",
            )
    nx, ny = (round((rng[i + 3] - rng[i]) / size[i]) for i in (0, 1))
    if nx < 1 or ny < 1:
        raise led.error(f"{vox}.VOXEL_SIZE", f"{size}: larger than the range {rng}, the pillar grid has no cell")
    pillars = {
        "point_cloud_range": [float(x) for x in rng],
        "voxel_size": [float(x) for x in size],
        "max_points_per_pillar": per,
        "out_channels": out_channels,
    }
    return pillars, ny, nx


def _voxel_cap(led: _Ledger, spa: bool, cells: int) -> None:
    """MAX_NUMBER_OF_VOXELS at test time must not drop pillars the graph keeps: at least
    spa.capacity (scans with more pillars are refused) or, without SPA, every grid cell."""
    vox = _processor(led, "transform_points_to_voxels")
    key = f"{vox}.MAX_NUMBER_OF_VOXELS"
    caps = led.value(key, kind=(dict, int))
    test = caps.get("test") if isinstance(caps, dict) else caps
    if isinstance(caps, dict):
        led.training(f"{key}.train")
        key = f"{key}.test"
    need = DEPLOYMENT_CHOICES["spa.capacity"] if spa else cells
    if not isinstance(test, int) or test < need:
        raise led.error(
            key,
            f"{test!r} pillars at test time would drop pillars the graph keeps; radaredge needs at "
            f"least {need} ({'spa.capacity' if spa else 'every grid cell'})",
        )
    led.ignore(key, f"test-time pillar cap {test} >= {need}: never reached by a scan the graph accepts")


def _cfa(led: _Ledger, cfa: str | None, columns: list[str], features: list[str], pillars: dict) -> dict:
    """``cfa``: upstream CQCA_cfa's DBSCAN map or the fork's GridDensityBEV, per ``cfa``; its
    origin and cells must be the pillar grid's (:func:`_check_map_on_grid`)."""
    ib = "MODEL.IMAGE_BACKBONE"
    module = led.check(f"{ib}.NAME", tuple(CFA_MODULES), "CQCA_cfa's DBSCAN map or the fork's GridDensityBEV")
    method = cfa or CFA_MODULES[module]
    v = led.value(f"{ib}.DBSCAN_V", kind=int)
    if not 1 <= v <= len(columns):
        raise led.error(
            f"{ib}.DBSCAN_V",
            f"{v} is not a point column: it indexes the batch points [batch, {', '.join(columns)}] (1..{len(columns)})",
        )
    led.map(f"{ib}.DBSCAN_V", "cfa.velocity_feature")
    out: dict = {"velocity_feature": features[v - 1]}
    rows = led.map(f"{ib}.DBSCAN_MAP_W", "cfa map rows (y cells)", kind=int)
    cols = led.map(f"{ib}.DBSCAN_MAP_H", "cfa map columns (x cells)", kind=int)
    res = led.map(f"{ib}.RESOLUTION", "cfa resolution", kind=NUMBER)
    y_off = led.map(f"{ib}.DBSCAN_Y", "cfa y offset", kind=NUMBER)
    eps = led.map(f"{ib}.DBSCAN_EPS", "cfa eps", kind=NUMBER)
    samples = led.map(f"{ib}.DBSCAN_SAMPLE", "cfa minimum density / samples", kind=int)
    led.check(f"{ib}.DBSCAN_FEATURE", (MAP_CHANNELS,), "a 3-channel clustering map", default=MAP_CHANNELS)
    _check_map_on_grid(led, float(res), float(y_off), pillars)
    for key in ("POINTX", "POINTY"):
        led.ignore(f"{ib}.{key}", "read by CQCA_cfa's constructor, never used")
    if method == "dbscan":
        for k in GRID_DEFAULTS:
            led.ignore(f"{ib}.{k}", "GridDensityBEV only; --cfa dbscan runs CQCA_cfa's DBSCAN")
        out.update(method="dbscan", not_converged=DEPLOYMENT_CHOICES["cfa.not_converged"])
        out["dbscan"] = {
            "eps": float(eps),
            "min_samples": samples,
            "max_cluster_size": DBSCAN_MAX_CLUSTER,
            "capacity": DEPLOYMENT_CHOICES["cfa.dbscan.capacity"],
            "map_rows": rows,
            "map_cols": cols,
            "resolution": float(res),
            "y_offset": float(y_off),
        }
    else:
        grid_keys = {
            k: led.map(f"{ib}.{k}", f"cfa.grid.{k.lower()}", default=d, kind=int) for k, d in GRID_DEFAULTS.items()
        }
        if module == "CQCA_cfa":
            led.notes.append(
                f"{ib}: CQCA_cfa's settings run as the fthbng77 fork's GridDensityBEV (--cfa "
                f"grid_density), with the fork's MAX_DENSITY {grid_keys['MAX_DENSITY']} and "
                f"CC_ITERATIONS {grid_keys['CC_ITERATIONS']}"
            )
        out["grid"] = {
            "map_h": rows,
            "map_w": cols,
            "resolution": float(res),
            "x_min": 0.0,
            "y_min": -float(y_off),
            "eps": float(eps),
            "min_density": samples,
            "max_density": grid_keys["MAX_DENSITY"],
            "cc_mode": "maxpool",
            "cc_iterations": grid_keys["CC_ITERATIONS"],
        }
    return out


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-6)


def _check_map_on_grid(led: _Ledger, res: float, y_off: float, pillars: dict) -> None:
    """The clustering map must lie on the pillar grid: CQCA_caf fuses the two maps cell by cell.

    CQCA_cfa bins a point into column ``int(x / RESOLUTION) - 1`` and row
    ``int((y + DBSCAN_Y) / RESOLUTION) - 1``: its map starts at x = 0 (no key moves it) and
    y = -DBSCAN_Y, in cells of RESOLUTION metres. The pillar grid starts at POINT_CLOUD_RANGE's
    (x_min, y_min), in VOXEL_SIZE cells. Another origin or cell size would fuse each pillar with
    another place's clustering cell and put points of the range outside the map (upstream's
    indexing then wraps or fails); radaredge refuses it (the cell counts are checked when the
    model is built)."""
    ib = "MODEL.IMAGE_BACKBONE"
    (x_min, y_min), (vx, vy) = pillars["point_cloud_range"][:2], pillars["voxel_size"][:2]
    vox = "VOXEL_SIZE of DATA_CONFIG.DATA_PROCESSOR's transform_points_to_voxels"
    if not (_close(res, vx) and _close(res, vy)):
        raise led.error(
            f"{ib}.RESOLUTION",
            f"{res:g} m cells, but the pillar grid's are {vx:g} x {vy:g} m ({vox}); "
            "the clustering map is fused with the pillar map cell by cell, so RESOLUTION must equal "
            "the voxel size in x and y",
        )
    if not _close(x_min, 0.0):
        raise led.error(
            "DATA_CONFIG.POINT_CLOUD_RANGE",
            f"x_min {x_min:g}: CQCA_cfa's clustering map starts at "
            "x = 0 (it bins x / RESOLUTION, no key offsets it), so the pillar grid it is fused with "
            "must start there too",
        )
    if not _close(-y_off, y_min):
        raise led.error(
            f"{ib}.DBSCAN_Y",
            f"{y_off:g} starts the clustering map at y = {-y_off:g} m, but the pillar "
            f"grid starts at POINT_CLOUD_RANGE y_min {y_min:g} m; the two maps are fused cell by cell, "
            f"so DBSCAN_Y must be {-y_min:g}",
        )


def _caf(led: _Ledger, pillar_channels: int) -> dict:
    """``caf``: CQCA_caf's channels (its attention constants are the module's, not config keys)."""
    fu = "MODEL.FUSER"
    led.check(f"{fu}.NAME", ("CQCA_caf",), "CQCA_caf's cross-attention fusion")
    led.check(f"{fu}.IN_CHANNEL_CROSS", (64,), "the fusion of the CFA's 64-channel map")
    led.check(f"{fu}.IN_CHANNEL", (pillar_channels + 64,), "the fusion conv over the pillar map and the SE output")
    out = led.map(f"{fu}.OUT_CHANNEL", "caf.out_channels", kind=int)
    if out != pillar_channels:
        raise led.error(
            f"{fu}.OUT_CHANNEL",
            f"{out}: upstream builds BACKBONE_2D on NUM_BEV_FEATURES "
            f"({pillar_channels}) channels, so the fused map must be as wide",
        )
    return {**CAF_CONSTANTS, "out_channels": out, "bn_eps": CAF_BN_EPS}


def _backbone(led: _Ledger) -> dict:
    b = "MODEL.BACKBONE_2D"
    led.check(f"{b}.NAME", ("BaseBEVBackbone",), "OpenPCDet's BaseBEVBackbone")
    return {
        k.lower(): led.map(f"{b}.{k}", f"backbone_2d.{k.lower()}", kind=list)
        for k in ("LAYER_NUMS", "LAYER_STRIDES", "NUM_FILTERS", "UPSAMPLE_STRIDES", "NUM_UPSAMPLE_FILTERS")
    }


def _dense_head(led: _Ledger) -> dict:
    h = "MODEL.DENSE_HEAD"
    led.check(f"{h}.NAME", ("AnchorHeadSingle",), "OpenPCDet's AnchorHeadSingle")
    led.check(f"{h}.CLASS_AGNOSTIC", (False,), "a class logit per class and anchor")
    # AnchorHeadSingle builds (and AnchorHeadTemplate applies) the direction classifier whenever
    # the key is present: ``model_cfg.get('USE_DIRECTION_CLASSIFIER', None) is not None``
    if (
        led.check(
            f"{h}.USE_DIRECTION_CLASSIFIER",
            (True, False),
            "the heading with its direction bin, which upstream builds whenever the key is present",
        )
        is False
    ):
        led.notes.append(
            f"{h}.USE_DIRECTION_CLASSIFIER: False still builds and applies upstream's direction "
            "classifier (AnchorHeadSingle tests the key for presence, not truth); the card does too"
        )
    out = {
        "dir_offset": float(led.map(f"{h}.DIR_OFFSET", "dense_head.dir_offset", kind=NUMBER)),
        "dir_limit_offset": float(led.map(f"{h}.DIR_LIMIT_OFFSET", "dense_head.dir_limit_offset", kind=NUMBER)),
        "num_dir_bins": led.map(f"{h}.NUM_DIR_BINS", "dense_head.num_dir_bins", kind=int),
        "cls_prior": DEPLOYMENT_CHOICES["dense_head.cls_prior"],
    }
    ta = f"{h}.TARGET_ASSIGNER_CONFIG"
    led.check(f"{ta}.BOX_CODER", ("ResidualCoder",), "OpenPCDet's ResidualCoder box decoding")
    _box_coder_config(led, f"{ta}.BOX_CODER_CONFIG", "the anchor head's boxes")
    led.training(ta, "anchor target assignment (training only)")
    led.training(f"{h}.LOSS_CONFIG", "loss (training only)")
    entries = led.value(f"{h}.ANCHOR_GENERATOR_CONFIG", kind=list)
    anchors = []
    for i, e in enumerate(entries):
        key = f"{h}.ANCHOR_GENERATOR_CONFIG[{i}]"
        if not isinstance(e, dict):
            raise led.error(key, f"expected a mapping of one class's anchors, got {e!r}")
        anchors.append(_anchor_class(led, key, f"dense_head.anchors[{i}]"))
        for k in ("matched_threshold", "unmatched_threshold"):
            led.training(f"{key}.{k}", "anchor target assignment (training only)")
    out["anchors"] = anchors
    return out


def _numbers(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, NUMBER) and not isinstance(x, bool) for x in v)


def _anchor_class(led: _Ledger, key: str, card_field: str) -> dict:
    """One ANCHOR_GENERATOR_CONFIG entry as upstream's AnchorGenerator reads it: a class's
    anchors at each location are its sizes x rotations x bottom heights, so an empty list would
    leave the class without anchors (no box of it could ever be output)."""
    name = led.map(f"{key}.class_name", f"{card_field}.class_name", kind=str)
    sizes = led.map(f"{key}.anchor_sizes", f"{card_field}.anchor_sizes", kind=list)
    if not sizes or not all(_numbers(sz) and len(sz) == 3 and all(x > 0 for x in sz) for sz in sizes):
        raise led.error(
            f"{key}.anchor_sizes",
            f"expected a non-empty list of [dx, dy, dz] sizes > 0, got {sizes} "
            "(with none, the class has no anchor and no box of it is ever output)",
        )
    rots = led.map(f"{key}.anchor_rotations", f"{card_field}.anchor_rotations", kind=list)
    if not _numbers(rots):
        raise led.error(
            f"{key}.anchor_rotations",
            f"expected a non-empty list of headings in radians, got {rots} "
            "(with none, the class has no anchor and no box of it is ever output)",
        )
    heights = led.map(f"{key}.anchor_bottom_heights", f"{card_field}.anchor_bottom_heights", kind=list)
    if not _numbers(heights) or len(heights) != 1:
        raise led.error(
            f"{key}.anchor_bottom_heights",
            f"expected one bottom height, got {heights}: radaredge's anchor head has one anchor height per class",
        )
    align = led.map(f"{key}.align_center", f"{card_field}.align_center", default=False, kind=bool)
    stride = led.map(f"{key}.feature_map_stride", f"{card_field}.feature_map_stride", kind=int)
    if stride < 1:
        raise led.error(f"{key}.feature_map_stride", f"expected a stride >= 1, got {stride}")
    return {
        "class_name": name,
        "anchor_sizes": sizes,
        "anchor_rotations": rots,
        "anchor_bottom_heights": heights,
        "align_center": align,
        "feature_map_stride": stride,
    }


def _box_coder_config(led: _Ledger, key: str, what: str) -> None:
    """A ResidualCoder's BOX_CODER_CONFIG (its keyword arguments). Upstream builds the decoder of
    ``what`` from it at test time: ``encode_angle_by_sincos: True`` makes the code 8 values
    (cos and sin residuals of the heading, decoded with atan2) and ``code_size`` changes the
    regression layer's width. radaredge decodes 7 values with one heading residual, so only
    the values that keep that are accepted; any other key is refused by name."""
    if not led.has(key):
        return
    known = ("encode_angle_by_sincos", "code_size")
    for k in led.value(key, kind=dict):
        if k not in known:
            raise led.error(
                f"{key}.{k}",
                f"not a ResidualCoder setting radaredge reproduces; it decodes {what} "
                "with the 7-value code (encode_angle_by_sincos: False, code_size: 7)",
            )
    sincos = led.value(f"{key}.encode_angle_by_sincos", False, kind=bool)
    if sincos:
        raise led.error(
            f"{key}.encode_angle_by_sincos",
            f"True makes upstream decode {what} from 8 values (the "
            "heading as cos and sin residuals, joined by atan2); radaredge decodes the 7-value "
            "ResidualCoder code (one heading residual): encode_angle_by_sincos False only",
        )
    size = led.value(f"{key}.code_size", 7, kind=int)
    if size != 7:
        raise led.error(
            f"{key}.code_size",
            f"{size}: radaredge decodes {what} from the 7-value ResidualCoder "
            "code (x, y, z, dx, dy, dz, heading): code_size 7 only",
        )
    why = f"{what} decoded from the 7-value ResidualCoder code"
    led.check(f"{key}.encode_angle_by_sincos", (False,), why, default=False)
    led.check(f"{key}.code_size", (7,), why, default=7)


def _check_head_grid(led: _Ledger, backbone: dict, anchors: list[dict], ny: int, nx: int) -> None:
    """The anchors must tile the map the head convolves: upstream's AnchorGenerator makes
    (pillar grid // feature_map_stride) anchor locations and AnchorHeadSingle predicts one set per
    cell of BaseBEVBackbone's output; the backbone concatenates its blocks' upsampled maps, so
    they must have one size. A mismatch fails upstream's reshape, and would leave the card's
    anchors beside the wrong cells."""
    b = "MODEL.BACKBONE_2D"
    strides, ups = backbone["layer_strides"], backbone["upsample_strides"]
    if not (
        len(strides) == len(ups) >= 1
        and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in strides)
        and all(isinstance(u, NUMBER) and not isinstance(u, bool) and u > 0 for u in ups)
    ):
        return  # the model refuses these with the card's own message
    sizes, hw = [], (ny, nx)
    for s, u in zip(strides, ups):
        hw = tuple(-(-n // s) for n in hw)  # 3x3 conv, padding 1, stride s
        up = Fraction(u).limit_denominator(1000)
        if up >= 1 and up.denominator != 1 or up < 1 and up.numerator != 1:
            return  # a transposed conv of a fractional stride: the model refuses it
        sizes.append(tuple(n * int(up) for n in hw) if up >= 1 else tuple(n // round(1 / up) for n in hw))
    if len(set(sizes)) != 1:
        raise led.error(
            f"{b}.UPSAMPLE_STRIDES",
            f"{ups}: the blocks' upsampled maps are {sizes} cells (rows x "
            "columns); BaseBEVBackbone concatenates them, so they must have one size",
        )
    head = sizes[0]
    for i, a in enumerate(anchors):
        grid = (ny // a["feature_map_stride"], nx // a["feature_map_stride"])
        if grid != head:
            raise led.error(
                f"MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[{i}].feature_map_stride",
                f"{a['feature_map_stride']} gives {grid[0]} x {grid[1]} anchor locations on the "
                f"{ny} x {nx} pillar grid, but the head predicts on BACKBONE_2D's {head[0]} x {head[1]} "
                "map; they must match",
            )


def _nms(led: _Ledger, key: str, card_field: str, final: bool = False) -> dict:
    """An NMS_CONFIG's class-agnostic rotated NMS as the card's (iou_thresh, pre_max, post_max).

    ``final``: POST_PROCESSING's, where MAFF-Net's ``Detector3DTemplate.post_processing`` runs
    one class-agnostic NMS only when NMS_THRESH is a float (``isinstance(..., float)``); any other
    value takes its per-class branch (thresholds NMS_THRESH.CAR / PED / CYC by label), which
    radaredge has no formulation of, and which an integer makes fail."""
    led.check(f"{key}.MULTI_CLASSES_NMS", (False,), "class-agnostic NMS")
    led.check(f"{key}.NMS_TYPE", ("nms_gpu",), "rotated BEV NMS (OpenPCDet's nms_gpu)")
    thresh = led.value(f"{key}.NMS_THRESH")
    if final and isinstance(thresh, dict):
        raise led.error(
            f"{key}.NMS_THRESH",
            f"{thresh}: per-class NMS thresholds (upstream's CAR/PED/CYC branch) "
            "are not supported: radaredge computes one class-agnostic NMS with a single threshold",
        )
    if final and isinstance(thresh, int) and not isinstance(thresh, bool):
        raise led.error(
            f"{key}.NMS_THRESH",
            f"{thresh} is an integer: upstream's post_processing runs its "
            f"class-agnostic NMS only for a float and fails on an integer; write it as {float(thresh)}",
        )
    return {
        "iou_thresh": float(led.map(f"{key}.NMS_THRESH", f"{card_field}.iou_thresh", kind=NUMBER)),
        "pre_max": led.map(f"{key}.NMS_PRE_MAXSIZE", f"{card_field}.pre_max", kind=int),
        "post_max": led.map(f"{key}.NMS_POST_MAXSIZE", f"{card_field}.post_max", kind=int),
    }


def _post_processing(led: _Ledger) -> dict:
    p = "MODEL.POST_PROCESSING"
    out = {"score_thresh": float(led.map(f"{p}.SCORE_THRESH", "post_processing.score_thresh", kind=NUMBER))}
    out.update(_nms(led, f"{p}.NMS_CONFIG", "post_processing", final=True))
    led.check(f"{p}.OUTPUT_RAW_SCORE", (False,), "sigmoid scores", default=False)
    led.ignore(f"{p}.RECALL_THRESH_LIST", "evaluation only (upstream's recall statistics)")
    led.ignore(f"{p}.EVAL_METRIC", "evaluation only (radaredge eval scores with the dataset's devkit protocol)")
    return out


def _stage_two(led: _Ledger, nms: dict) -> dict:
    """``stage_two``: proposals, CDA keypoints, VSA, point head, ROI head, final NMS."""
    pfe, ph, rh = "MODEL.PFE", "MODEL.POINT_HEAD", "MODEL.ROI_HEAD"
    led.check(f"{pfe}.NAME", ("VoxelSetAbstraction_cda",), "the CDA keypoints and VSA")
    led.check(f"{pfe}.POINT_SOURCE", ("cluster_points",), "keypoints from the CFA's cluster points")
    led.check(f"{pfe}.SAMPLE_METHOD", ("CDA",), "cylindrical denoising-assisted sampling")
    led.check(f"{pfe}.FEATURES_SOURCE", (["bev", "cluster_points"],), "VSA over the fused BEV map and the scan points")
    sa = f"{pfe}.SA_LAYER.cluster_points"
    layers = led.value(f"{pfe}.SA_LAYER", kind=dict)
    if set(layers) != {"cluster_points"}:
        raise led.error(f"{pfe}.SA_LAYER", f"radaredge's VSA has the cluster_points layer only, got {sorted(layers)}")
    cda = f"{pfe}.CDAM_SAMPLING"
    keypoints = {
        "num_keypoints": led.map(f"{pfe}.NUM_KEYPOINTS", "stage_two.keypoints.num_keypoints", kind=int),
        "sample_radius_r": float(led.map(f"{cda}.SAMPLE_RADIUS_R", "stage_two.keypoints.sample_radius_r", kind=NUMBER)),
        "sample_radius_h": float(led.map(f"{cda}.SAMPLE_RADIUS_H", "stage_two.keypoints.sample_radius_h", kind=NUMBER)),
        "num_sectors": led.map(f"{cda}.NUM_SECTORS", "stage_two.keypoints.num_sectors", kind=int),
        "padded_rois": DEPLOYMENT_CHOICES["stage_two.keypoints.padded_rois"],
    }
    vsa = {
        "bev_stride": 1,  # the fused map the BEV source reads has stride 1
        "num_output_features": led.map(f"{pfe}.NUM_OUTPUT_FEATURES", "stage_two.vsa.num_output_features", kind=int),
        "sa_clusterpoints": _sa(led, sa, "stage_two.vsa.sa_clusterpoints"),
    }
    led.check(f"{ph}.NAME", ("PointHeadSimple",), "OpenPCDet's PointHeadSimple")
    led.check(f"{ph}.CLASS_AGNOSTIC", (True,), "a class-agnostic point head")
    led.check(f"{ph}.USE_POINT_FEATURES_BEFORE_FUSION", (True,), "the point head on the features before fusion")
    point_head = {"cls_fc": led.map(f"{ph}.CLS_FC", "stage_two.point_head.cls_fc", kind=list)}
    led.training(f"{ph}.TARGET_CONFIG", "point targets (training only)")
    led.training(f"{ph}.LOSS_CONFIG", "loss (training only)")
    led.check(f"{rh}.NAME", ("PVRCNNHead",), "OpenPCDet's PVRCNNHead")
    led.check(f"{rh}.CLASS_AGNOSTIC", (True,), "a class-agnostic ROI head (labels from the proposals)")
    grid = f"{rh}.ROI_GRID_POOL"
    # build_local_aggregation_module: StackSAModuleMSG(..., pool_method='max_pool'), POOL_METHOD never read
    pool = led.value(f"{grid}.POOL_METHOD", "max_pool")
    led.ignore(f"{grid}.POOL_METHOD", "never read: upstream's build_local_aggregation_module always max-pools")
    if pool != "max_pool":
        led.notes.append(
            f"{grid}.POOL_METHOD: {pool!r} is never read; upstream's build_local_aggregation_module "
            "builds its StackSAModuleMSG with max_pool, and so does the card"
        )
    roi_head = {
        "shared_fc": led.map(f"{rh}.SHARED_FC", "stage_two.roi_head.shared_fc", kind=list),
        "cls_fc": led.map(f"{rh}.CLS_FC", "stage_two.roi_head.cls_fc", kind=list),
        "reg_fc": led.map(f"{rh}.REG_FC", "stage_two.roi_head.reg_fc", kind=list),
        "dropout": float(led.map(f"{rh}.DP_RATIO", "stage_two.roi_head.dropout (identity at test time)", kind=NUMBER)),
        "grid_size": led.map(f"{grid}.GRID_SIZE", "stage_two.roi_head.grid_size", kind=int),
        "roi_grid_pool": _sa(led, grid, "stage_two.roi_head.roi_grid_pool"),
    }
    led.check(f"{rh}.TARGET_CONFIG.BOX_CODER", ("ResidualCoder",), "OpenPCDet's ResidualCoder decoding of the rois")
    # RoIHeadTemplate builds its test-time box decoder from TARGET_CONFIG.BOX_CODER(_CONFIG)
    _box_coder_config(led, f"{rh}.TARGET_CONFIG.BOX_CODER_CONFIG", "the ROI head's refined boxes")
    led.training(f"{rh}.TARGET_CONFIG", "proposal targets (training only)")
    led.training(f"{rh}.LOSS_CONFIG", "loss (training only)")
    led.training(f"{rh}.NMS_CONFIG.TRAIN", "proposals while training")
    proposals = _nms(led, f"{rh}.NMS_CONFIG.TEST", "stage_two.proposals")
    return {
        "proposals": {
            "pre_max": proposals["pre_max"],
            "iou_thresh": proposals["iou_thresh"],
            "post_max": proposals["post_max"],
        },
        "keypoints": keypoints,
        "vsa": vsa,
        "point_head": point_head,
        "roi_head": roi_head,
        "post_processing": nms,
    }


def _sa(led: _Ledger, key: str, card_field: str) -> dict:
    led.check(
        f"{key}.NAME",
        ("StackSAModuleMSG",),
        "multi-scale set abstraction (StackSAModuleMSG, upstream's default)",
        default="StackSAModuleMSG",
    )
    return {
        "radii": led.map(f"{key}.POOL_RADIUS", f"{card_field}.radii", kind=list),
        "nsample": led.map(f"{key}.NSAMPLE", f"{card_field}.nsample", kind=list),
        "mlps": led.map(f"{key}.MLPS", f"{card_field}.mlps", kind=list),
    }


def _training_and_data_keys(led: _Ledger) -> None:
    """Keys about training, the dataset's files and evaluation: none changes the test-time function."""
    led.training("OPTIMIZATION", "optimiser and schedule (training only)")
    led.training("DATA_CONFIG.DATA_AUGMENTOR", "augmentation (training only)")
    led.ignore("DATA_CONFIG.DATASET", "the dataset class (radaredge reads VoD / TJ4D layouts itself)")
    led.ignore("DATA_CONFIG.DATA_SPLIT", "dataset splits (radaredge eval --split)")
    led.ignore("DATA_CONFIG.INFO_PATH", "OpenPCDet's info files")
    items = led.value("DATA_CONFIG.GET_ITEM_LIST", ["points"], kind=list)
    if "points" not in items:
        raise led.error("DATA_CONFIG.GET_ITEM_LIST", f"{items}: MAFF-Net reads points")
    led.ignore("DATA_CONFIG.GET_ITEM_LIST", "the dataset's items (points)")
    mask = _processor(led, "mask_points_and_boxes_outside_range")
    if mask is None:
        # upstream's batch_dict['points'] (the CFA's clustering, the CDA keypoints, the VSA) are the
        # points after the data processor; radaredge's graph always takes them cropped to the range
        raise led.error(
            "DATA_CONFIG.DATA_PROCESSOR",
            "no mask_points_and_boxes_outside_range step: upstream would "
            "cluster and sample the points outside POINT_CLOUD_RANGE too, and radaredge's graph always "
            "crops them to the range (add the step, as upstream's configs have it)",
        )
    led.check(f"{mask}.NAME", ("mask_points_and_boxes_outside_range",), "the range mask")
    led.training(f"{mask}.REMOVE_OUTSIDE_BOXES", "ground-truth boxes (training only)")
    led.training(f"{mask}.min_num_corners", "ground-truth boxes (training only)")
    shuffle = _processor(led, "shuffle_points")
    if shuffle:
        led.check(f"{shuffle}.NAME", ("shuffle_points",), "the points in the order given")
        enabled = led.value(f"{shuffle}.SHUFFLE_ENABLED", kind=(dict, bool))
        test = enabled.get("test", False) if isinstance(enabled, dict) else enabled
        if test is not False:
            raise led.error(
                f"{shuffle}.SHUFFLE_ENABLED.test",
                "shuffled test points: radaredge's graph keeps the "
                "points in the order given (upstream's FPS and ball queries depend on it)",
            )
        led.training(f"{shuffle}.SHUFFLE_ENABLED", "point shuffling while training (off at test time)")


def render_card(conversion: Conversion) -> str:
    """The card as YAML, after a header that says where it came from and what radaredge chose."""
    src = conversion.card["source"]
    chain = " + ".join([src["config"]] + [b["named"] for b in src.get("base_configs", [])])
    lines = [
        f"# Written by `radaredge card from-openpcdet` from {chain} (sha256 of each in `source`).",
        "# Every key of the merged config is mapped to a field below, checked against what radaredge computes,",
        "# training-only or ignored with its reason: `radaredge card from-openpcdet ... --json` lists each.",
        "# Not config keys, radaredge's deployment choices as in the shipped cards: "
        + ", ".join(DEPLOYMENT_CHOICES)
        + ".",
    ]
    lines += [f"# note: {n}" for n in conversion.notes]
    body = yaml.safe_dump(conversion.card, sort_keys=False, default_flow_style=None, width=110)
    return "\n".join(lines) + "\n" + body


def describe_source(source: dict) -> str:
    """One line for ``radaredge inspect``: the config files a card was converted from, with the
    first 12 hex digits of each file's sha256."""
    if source.get("format") != "openpcdet":
        return ", ".join(f"{k} {v}" for k, v in source.items())
    parts = [f"{source.get('config')} (sha256 {str(source.get('sha256', ''))[:12]})"]
    parts += [f"{b.get('named')} (sha256 {str(b.get('sha256', ''))[:12]})" for b in source.get("base_configs", [])]
    opts = " ".join(source.get("options", []))
    return "OpenPCDet config " + " + ".join(parts) + (f", {opts}" if opts else "")
