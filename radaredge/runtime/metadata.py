"""The ``radaredge.*`` entries of an exported graph's ``metadata_props``: the one contract between
the exporter, which writes them, and the runtime, which reads them.

Standard library only (no numpy, no torch). Every key is named here; nothing else spells one.

The keys and their values:

- ``radaredge.model``: card name
- ``radaredge.card``: the whole card, YAML
- ``radaredge.features``: JSON list: the point columns, in order (x, y, z first)
- ``radaredge.inputs``: JSON: ``names`` (graph order), ``dynamic_axes``, ``frames`` (the inputs that
  take one point cloud each, oldest first), ``timestamps`` (the input taking per-frame times in s,
  or null)
- ``radaredge.outputs``: JSON list: output names, graph order
- ``radaredge.checks``: JSON list of :class:`OutputCheck`: flag outputs the runtime turns into an
  error or a warning
- ``radaredge.weights_sha256``: hash of the weights this graph computes with
- ``radaredge.versions``: JSON: radaredge, torch, onnx, onnxruntime, opset at export
- ``radaredge.part``: graph name inside a multi-graph model (absent for one-graph models)
- ``radaredge.bundle_weights_sha256``: hash of the whole multi-graph model's weights
- ``radaredge.quantization``: JSON: how an int8 copy was made (absent in fp32 graphs)
- ``radaredge.input_flags``: JSON: bit (as a string) -> meaning, for a graph with an ``input_flags``
  output (:mod:`radaredge.ops.input_flags`)
- ``radaredge.input_errors``: the ``input_flags`` bits (an integer mask) that mean the input was
  wrong: the caller refuses the frame
- ``radaredge.content_sha256``: hash of the graph file's own contents: every node and initializer
  and every other ``radaredge.*`` entry (:mod:`radaredge.runtime.integrity` defines it); the runtime
  recomputes it on load
"""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any, Mapping

from ..errors import CapacityError, InputError

PREFIX = "radaredge."
MODEL = PREFIX + "model"
CARD = PREFIX + "card"
FEATURES = PREFIX + "features"
INPUTS = PREFIX + "inputs"
OUTPUTS = PREFIX + "outputs"
CHECKS = PREFIX + "checks"
WEIGHTS_SHA256 = PREFIX + "weights_sha256"
VERSIONS = PREFIX + "versions"
PART = PREFIX + "part"
BUNDLE_WEIGHTS_SHA256 = PREFIX + "bundle_weights_sha256"
QUANTIZATION = PREFIX + "quantization"
INPUT_FLAGS = PREFIX + "input_flags"
INPUT_ERRORS = PREFIX + "input_errors"
CONTENT_SHA256 = PREFIX + "content_sha256"


@dataclass(frozen=True)
class OutputCheck:
    """A flag output the runtime acts on after every run.

    When output ``output`` (a scalar bool) equals ``fails_when``, ``message`` is raised as a
    :class:`radaredge.errors.CapacityError` (``severity`` ``error``) or issued as a
    ``RuntimeWarning`` (``warn``). ``{name}`` in the message is replaced by the scalar value of
    output ``name`` of that run (e.g. the pillar count of the scan that overflowed).
    """

    output: str
    fails_when: bool
    severity: str
    message: str

    def __post_init__(self):
        if self.severity not in ("error", "warn"):
            raise ValueError(f"OutputCheck {self.output}: severity must be 'error' or 'warn', got {self.severity!r}")

    def apply(self, outputs: Mapping[str, Any]) -> None:
        """Raise or warn when this run's flag says so; nothing when the output is absent."""
        if self.output not in outputs or bool(outputs[self.output]) != self.fails_when:
            return
        values = {k: _scalar(v) for k, v in outputs.items()}
        msg = self.message.format_map(_Missing(values))
        if self.severity == "error":
            raise CapacityError(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


def _scalar(value):
    try:
        return value.item() if getattr(value, "size", 2) == 1 else value
    except (AttributeError, ValueError):
        return value


class _Missing(dict):
    def __missing__(self, key):
        return "{" + key + "}"


@dataclass
class GraphMetadata:
    """The parsed ``radaredge.*`` entries of one graph."""

    model: str
    card_yaml: str
    features: list[str]
    input_names: list[str]
    dynamic_axes: dict[str, dict[str, str]]
    frame_inputs: list[str]
    timestamps_input: str | None
    output_names: list[str]
    weights_sha256: str
    versions: dict = field(default_factory=dict)
    checks: list[OutputCheck] = field(default_factory=list)
    part: str | None = None
    bundle_weights_sha256: str | None = None
    quantization: dict | None = None
    input_flags: dict[str, str] | None = None
    input_errors: int | None = None
    content_sha256: str | None = None  # written by the exporter once the graph is final (absent before)

    def to_props(self) -> dict[str, str]:
        """``metadata_props`` entries, key -> string value."""
        props = {
            MODEL: self.model,
            CARD: self.card_yaml,
            FEATURES: json.dumps(self.features),
            INPUTS: json.dumps(
                {
                    "names": self.input_names,
                    "dynamic_axes": self.dynamic_axes,
                    "frames": self.frame_inputs,
                    "timestamps": self.timestamps_input,
                }
            ),
            OUTPUTS: json.dumps(self.output_names),
            CHECKS: json.dumps([asdict(c) for c in self.checks]),
            WEIGHTS_SHA256: self.weights_sha256,
            VERSIONS: json.dumps(self.versions),
        }
        if self.part is not None:
            props[PART] = self.part
        if self.bundle_weights_sha256 is not None:
            props[BUNDLE_WEIGHTS_SHA256] = self.bundle_weights_sha256
        if self.quantization is not None:
            props[QUANTIZATION] = json.dumps(self.quantization)
        if self.input_flags is not None:
            props[INPUT_FLAGS] = json.dumps(self.input_flags)
        if self.input_errors is not None:
            props[INPUT_ERRORS] = str(self.input_errors)
        if self.content_sha256 is not None:
            props[CONTENT_SHA256] = self.content_sha256
        return props

    @classmethod
    def from_props(cls, props: Mapping[str, str], where: str) -> "GraphMetadata":
        """Parse a graph's ``metadata_props``; InputError naming ``where`` and the key when the
        graph is not a radaredge export or was written by an incompatible radaredge."""
        if CARD not in props:
            raise InputError(f"{where} is not a radaredge export: its metadata has no {CARD} entry")
        missing = [k for k in (MODEL, FEATURES, INPUTS, OUTPUTS, WEIGHTS_SHA256) if k not in props]
        if missing:
            raise InputError(f"{where}: its metadata lacks {', '.join(missing)}; re-export it with this radaredge")
        try:
            inputs = json.loads(props[INPUTS])
            meta = cls(
                model=props[MODEL],
                card_yaml=props[CARD],
                features=list(json.loads(props[FEATURES])),
                input_names=list(inputs["names"]),
                dynamic_axes=dict(inputs.get("dynamic_axes", {})),
                frame_inputs=list(inputs["frames"]),
                timestamps_input=inputs.get("timestamps"),
                output_names=list(json.loads(props[OUTPUTS])),
                weights_sha256=props[WEIGHTS_SHA256],
                versions=json.loads(props.get(VERSIONS, "{}")),
                checks=[OutputCheck(**c) for c in json.loads(props.get(CHECKS, "[]"))],
                part=props.get(PART),
                bundle_weights_sha256=props.get(BUNDLE_WEIGHTS_SHA256),
                quantization=json.loads(props[QUANTIZATION]) if QUANTIZATION in props else None,
                input_flags=json.loads(props[INPUT_FLAGS]) if INPUT_FLAGS in props else None,
                input_errors=int(props[INPUT_ERRORS]) if INPUT_ERRORS in props else None,
                content_sha256=props.get(CONTENT_SHA256),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(
                f"{where}: unreadable radaredge metadata ({type(exc).__name__}: {exc}); "
                f"re-export it with this radaredge"
            ) from None
        return meta
