"""Whole-pipeline export: raw points in, result out, one self-contained ``.onnx`` + JSON sidecar.

The card, the feature columns, the input signature, the package versions and a hash of the
weights travel inside the ONNX ``metadata_props``, so an embedded app needs nothing else.
"""

from __future__ import annotations

import collections
import hashlib
import json
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import onnx
import torch

from . import __version__
from .cards import ModelCard
from .errors import ConfigError, ExportError
from .onnx_export import DEFAULT_OPSET, export_onnx
from .registry import model_spec
from .runtime import META_PREFIX, RadarModel

DEBUG_PREFIX = "debug."   # debug-export outputs are named debug.<intermediate>


def weights_hash(model: torch.nn.Module) -> str:
    """SHA-256 over the state dict (names, shapes and bytes, in key order)."""
    h = hashlib.sha256()
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def require_same_weights(exported: RadarModel, model: torch.nn.Module, checkpoint=None) -> None:
    """ConfigError unless ``exported`` was exported from exactly ``model``'s weights."""
    if exported.weights_sha256 != weights_hash(model):
        source = f"checkpoint {checkpoint}" if checkpoint else "the seeded initialisation of this card"
        raise ConfigError(f"{exported.path} was exported with other weights than {source}; "
                          f"pass the same --checkpoint/--config as at export")


def save_checkpoint(model: torch.nn.Module, path: str | Path) -> Path:
    """Write the model's state_dict to ``path`` (parent directories created), in the form
    :func:`load_checkpoint` and ``--checkpoint`` read. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), path)
    return path


# Entries of an OpenPCDet ``model_state`` that are bookkeeping, not weights (Detector3DTemplate's step counter).
IGNORED_CHECKPOINT_KEYS = ("global_step",)


@dataclass
class LoadReport:
    """What :func:`load_checkpoint` did: tensors loaded, and the dropped keys by the rule that dropped them."""

    path: str
    loaded: int
    dropped: dict[str, list[str]] = field(default_factory=dict)   # rule -> keys
    ignored: list[str] = field(default_factory=list)

    def summary(self) -> str:
        parts = [f"loaded {self.loaded} tensors from {self.path}"]
        parts += [f"dropped {len(keys)} ({rule})" for rule, keys in self.dropped.items()]
        if self.ignored:
            parts.append(f"ignored {', '.join(self.ignored)}")
        return "; ".join(parts)


def _read_state(path: str | Path) -> dict:
    """The state_dict inside a ``.pth`` (bare, or under OpenPCDet's ``model_state``, ``state_dict`` or
    ``model``), its values tensors; ConfigError naming the file and the problem otherwise."""
    try:
        with warnings.catch_warnings():            # torch warns about pickle protocols before refusing
            warnings.simplefilter("ignore")
            obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ConfigError(f"checkpoint {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"checkpoint {path} is a directory, not a .pth file") from None
    except Exception as exc:
        if not zipfile.is_zipfile(path):
            why = "not a file written by torch.save (truncated, or another format)"
        elif "weights_only" in str(exc) or "Unsupported global" in str(exc):
            why = "a pickle of objects other than tensors and plain containers (radaredge runs no pickled code)"
        else:
            why = f"damaged ({type(exc).__name__})"
        raise ConfigError(f"checkpoint {path} is not a readable torch checkpoint: {why}") from None
    for key in ("model_state", "state_dict", "model"):
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
    if not isinstance(obj, dict):
        raise ConfigError(f"checkpoint {path}: expected a state_dict mapping, got {type(obj).__name__}")
    bad = [f"{k!r} ({type(v).__name__})" for k, v in obj.items() if not isinstance(k, str) or not torch.is_tensor(v)]
    if bad:
        raise ConfigError(f"checkpoint {path}: state_dict entries must be named tensors; not so: {', '.join(bad[:5])}")
    return obj


def load_checkpoint(model: torch.nn.Module, path: str | Path) -> LoadReport:
    """Load a state_dict ``.pth`` into ``model`` and account for every key.

    Keys the model declares as having no effect on its output (``model.checkpoint_drop_rules()``:
    (rule, key prefixes, only zero-size tensors) per rule, e.g. upstream MAFF-Net parameters that
    its test-time path never reads) are dropped by rule; :data:`IGNORED_CHECKPOINT_KEYS` are
    ignored. Any other missing, unexpected or shape-mismatched key is a one-line ConfigError
    naming the keys.
    """
    obj = _read_state(path)
    rules = model.checkpoint_drop_rules() if hasattr(model, "checkpoint_drop_rules") else []
    own = model.state_dict()
    report = LoadReport(str(path), 0)
    state = {}
    for key, value in obj.items():
        rule = next((r for r, prefixes, empty_only in rules if key not in own and key.startswith(tuple(prefixes))
                     and (value.numel() == 0 or not empty_only)), None)
        if rule is not None:
            report.dropped.setdefault(rule, []).append(key)
        elif key in IGNORED_CHECKPOINT_KEYS and key not in own:
            report.ignored.append(key)
        else:
            state[key] = value
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    shapes = sorted(f"{k} (checkpoint {tuple(state[k].shape)}, model {tuple(own[k].shape)})"
                    for k in set(own) & set(state) if tuple(state[k].shape) != tuple(own[k].shape))
    problems = []
    for what, keys in (("missing keys", missing), ("unexpected keys", unexpected), ("wrong shapes", shapes)):
        if keys:
            more = f" and {len(keys) - 12} more" if len(keys) > 12 else ""
            problems.append(f"{what} ({len(keys)}): {', '.join(keys[:12])}{more}")
    if problems:
        raise ConfigError(f"checkpoint {path} does not fit this card's model: {'; '.join(problems)}")
    model.load_state_dict(state)
    report.loaded = len(state)
    return report


def build_model(card: ModelCard, checkpoint: str | Path | None = None) -> torch.nn.Module:
    """The card's model, seeded, with ``checkpoint`` loaded when given."""
    model = model_spec(card).build(card)
    if checkpoint:
        model.checkpoint_report = load_checkpoint(model, checkpoint)
    return model.eval()


class _PipelineWrapper(torch.nn.Module):
    """Positional-input wrapper of the export formulation; ``debug`` also returns the traced
    intermediates named in ``spec.trace_order(card)`` (for divergence reports)."""

    def __init__(self, model, spec, card, debug: bool):
        super().__init__()
        self.model, self.spec, self.names, self.debug = model, spec, spec.input_names(card), debug
        self.trace_names = spec.trace_order(card)

    def forward(self, *inputs):
        trace: dict | None = {} if self.debug else None
        out = self.spec.run_export(self.model, dict(zip(self.names, inputs)), trace)
        extra = tuple(trace[n] for n in self.trace_names) if self.debug else ()
        return tuple(out[n] for n in self.spec.output_names) + extra


@dataclass
class ExportResult:
    path: Path
    sidecar: Path
    size_bytes: int
    op_histogram: dict[str, int]
    metadata: dict[str, str] = field(default_factory=dict)


def metadata_for(card: ModelCard, model: torch.nn.Module, spec, opset: int) -> dict[str, str]:
    """The ``metadata_props`` written into the graph."""
    import onnxruntime
    return {
        META_PREFIX + "model": card.name,
        META_PREFIX + "card": card.to_yaml(),
        META_PREFIX + "features": json.dumps(card.features),
        META_PREFIX + "inputs": json.dumps({
            "names": spec.input_names(card),
            "dynamic_axes": {k: {str(a): s for a, s in v.items()} for k, v in spec.dynamic_axes(card).items()},
        }),
        META_PREFIX + "outputs": json.dumps(spec.output_names),
        META_PREFIX + "weights_sha256": weights_hash(model),
        META_PREFIX + "versions": json.dumps({"radaredge": __version__, "torch": torch.__version__,
                                              "onnx": onnx.__version__, "onnxruntime": onnxruntime.__version__,
                                              "opset": opset}),
    }


def export_model(card: ModelCard, output: str | Path, checkpoint: str | Path | None = None,
                 opset: int = DEFAULT_OPSET, debug: bool = False, model: torch.nn.Module | None = None,
                 spec=None, extra_metadata: dict | None = None) -> ExportResult:
    """Export the card's whole pipeline to ``output`` and write ``output`` with suffix .json.

    ``debug`` adds the intermediate tensors of ``spec.trace_order(card)`` as extra graph outputs.
    ``spec`` (default: the card's) and ``extra_metadata`` serve the parts of a bundle
    (:func:`export_bundle`).
    """
    spec = spec or model_spec(card)
    model = model if model is not None else build_model(card, checkpoint)
    names = spec.input_names(card)
    _, example = spec.make_cases(card, 1, 0)[0]
    args = tuple(torch.from_numpy(example[n]) for n in names)
    module = _PipelineWrapper(model, spec, card, debug)
    out_names = spec.output_names + ([DEBUG_PREFIX + n for n in spec.trace_order(card)] if debug else [])
    path = Path(output)
    export_onnx(module, args, path, names, out_names, spec.dynamic_axes(card), opset=opset)
    proto = onnx.load(str(path))
    meta = {**metadata_for(card, model, spec, opset), **(extra_metadata or {})}
    del proto.metadata_props[:]
    for k, v in meta.items():
        proto.metadata_props.add(key=k, value=v)
    proto.doc_string = f"radaredge export of {card.name}: {card.description}"
    try:
        onnx.checker.check_model(proto, full_check=True)
    except onnx.checker.ValidationError as exc:
        raise ExportError(f"onnx.checker rejected the exported graph: {exc}") from exc
    onnx.save(proto, str(path))
    hist = dict(sorted(collections.Counter(n.op_type for n in proto.graph.node).items(), key=lambda kv: -kv[1]))
    custom = sorted({n.domain for n in proto.graph.node if n.domain not in ("", "ai.onnx")})
    if custom:
        raise ExportError(f"exported graph uses custom op domains {custom}; radaredge graphs must not")
    sidecar = path.with_suffix(".json")
    result = ExportResult(path, sidecar, path.stat().st_size, hist, meta)
    sidecar.write_text(json.dumps({
        "model": card.name, "onnx": path.name, "size_bytes": result.size_bytes, "opset": opset,
        "debug_outputs": list(spec.trace_order(card)) if debug else [],
        "inputs": [{"name": i.name, "shape": _shape(i)} for i in proto.graph.input],
        "outputs": [{"name": o.name, "shape": _shape(o)} for o in proto.graph.output],
        "op_histogram": hist, "weights_sha256": meta[META_PREFIX + "weights_sha256"],
        "versions": json.loads(meta[META_PREFIX + "versions"]),
    }, indent=2))
    return result


def _shape(value_info) -> list:
    dims = value_info.type.tensor_type.shape.dim
    return [d.dim_param or d.dim_value for d in dims]


@dataclass
class BundleResult:
    directory: Path
    manifest: Path
    parts: dict[str, ExportResult]


def export_bundle(card: ModelCard, out_dir: str | Path, model: torch.nn.Module, opset: int = DEFAULT_OPSET,
                  progress=None) -> BundleResult:
    """Export every part of a multi-graph card (a BundleSpec) to ``out_dir/<part>.onnx`` + sidecar,
    copy the bundle's extra files (e.g. tokenizer.json) and write ``out_dir/bundle.json``.

    Each graph carries its part name and the hash of its own weights and of the whole bundle.
    """
    import shutil
    spec = model_spec(card)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bundle_hash = weights_hash(model)
    parts = {}
    items = list(spec.parts.items())
    for name, pspec in (progress(items) if progress else items):
        parts[name] = export_model(card, out_dir / f"{name}.onnx", opset=opset, model=spec.part_module(model, name),
                                   spec=pspec, extra_metadata={META_PREFIX + "part": name,
                                                               META_PREFIX + "bundle_weights_sha256": bundle_hash})
    files = {}
    for fname, src in spec.files(card).items():
        shutil.copyfile(src, out_dir / fname)
        files[fname] = str(fname)
    manifest = out_dir / "bundle.json"
    manifest.write_text(json.dumps({
        "model": card.name, "family": card.model, "opset": opset, "weights_sha256": bundle_hash,
        "parts": {n: {"onnx": r.path.name, "sidecar": r.sidecar.name, "size_bytes": r.size_bytes,
                      "weights_sha256": r.metadata[META_PREFIX + "weights_sha256"]} for n, r in parts.items()},
        "files": files, "card": card.data,
    }, indent=2))
    return BundleResult(out_dir, manifest, parts)
