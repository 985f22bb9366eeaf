"""Every kind of file an export consists of, in one table (in the spirit of Ultralytics'
``export_formats()``): its name beside the graph, the verb that writes it and the verbs and
runtimes that read it. Nothing else in radaredge spells these names.

An export is a *bundle*: one graph per part of the model. A one-graph model's bundle is the
``.onnx`` itself (the file users see); a multi-graph model's is a directory holding
``<graph>.onnx`` per part and the manifest. :func:`graph_files` resolves both alike, and every
copy of a graph (int8, debug) and its sidecar sit beside it under :func:`copy_path`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Artifact:
    """One kind of export file. ``suffix`` replaces the graph's ``.onnx`` (a copy or the
    sidecar) or, for the manifest, is the file's whole name inside the bundle directory."""

    kind: str
    suffix: str
    written_by: str
    read_by: tuple[str, ...]
    what: str


GRAPH, INT8, DEBUG, SIDECAR, MANIFEST = "graph", "int8", "debug", "sidecar", "manifest"

ARTIFACTS: dict[str, Artifact] = {a.kind: a for a in (
    Artifact(GRAPH, ".onnx", "export",
             ("parity-check", "bench", "eval", "locate", "inspect", "radaredge.runtime", "examples/c"),
             "the fp32 graph: raw points in, result out, the card in its metadata"),
    Artifact(INT8, ".int8.onnx", "export --quantize int8",
             ("parity-check --quantized", "bench --int8", "locate --int8-text", "radaredge.runtime"),
             "the int8 copy of a graph (static QDQ, or dynamic where the model's int8 policy says)"),
    Artifact(DEBUG, ".debug.onnx", "export --debug, parity-check",
             ("parity-check (where a failing output first diverges)",),
             "the graph with its traced intermediates as extra outputs named debug.<intermediate>"),
    Artifact(SIDECAR, ".json", "export",
             ("people and scripts (inputs, outputs, op histogram, versions)",),
             "a JSON summary beside each graph"),
    Artifact(MANIFEST, "bundle.json", "export (a multi-graph model)",
             ("parity-check", "bench", "eval", "locate", "radaredge.runtime"),
             "the parts of a multi-graph bundle with their weight hashes, its shared files and the card"),
)}

COPY_KINDS = (INT8, DEBUG)       # graphs written beside a graph; never a graph's own name


def copy_path(graph: str | Path, kind: str) -> Path:
    """The ``kind`` file (int8, debug or sidecar) of the graph at ``graph`` (an ``.onnx``)."""
    return Path(graph).with_suffix(ARTIFACTS[kind].suffix)


def is_copy(path: str | Path) -> bool:
    """True when ``path`` is named like an int8 or debug copy rather than a graph."""
    return Path(path).name.lower().endswith(tuple(ARTIFACTS[k].suffix for k in COPY_KINDS))


def copy_kind(path: str | Path) -> str | None:
    """The copy kind (int8 or debug) ``path`` is named as, or None for a graph's own name."""
    name = Path(path).name.lower()
    return next((k for k in COPY_KINDS if name.endswith(ARTIFACTS[k].suffix)), None)


def graph_of_copy(path: str | Path) -> Path:
    """The graph an int8 or debug copy was made from (``x.int8.onnx`` -> ``x.onnx``); ``path`` itself
    when it is named as a graph."""
    kind = copy_kind(path)
    if kind is None:
        return Path(path)
    path = Path(path)
    return path.with_name(path.name[: -len(ARTIFACTS[kind].suffix)] + ARTIFACTS[GRAPH].suffix)


def manifest_path(bundle: str | Path) -> Path:
    """The manifest of the bundle directory ``bundle``."""
    return Path(bundle) / ARTIFACTS[MANIFEST].suffix


def graph_files(graphs: list[str] | tuple[str, ...], bundle: str | Path) -> dict[str, Path]:
    """Where each graph (by name) of a bundle lives: a one-graph bundle is the ``.onnx``
    ``bundle`` itself; a multi-graph bundle's graphs are ``bundle/<graph>.onnx``."""
    bundle = Path(bundle)
    if len(graphs) == 1:
        return {graphs[0]: bundle}
    return {g: bundle / f"{g}{ARTIFACTS[GRAPH].suffix}" for g in graphs}


def bundle_files(graphs: list[str] | tuple[str, ...], bundle: str | Path) -> list[Path]:
    """Every path an export of ``graphs`` into ``bundle`` may write: each graph with its sidecar,
    int8 and debug copies, and a multi-graph bundle's directory and manifest."""
    files = [copy for g in graph_files(graphs, bundle).values()
             for copy in (g, *(copy_path(g, k) for k in (SIDECAR, *COPY_KINDS)))]
    return files if len(graphs) == 1 else [Path(bundle), manifest_path(bundle), *files]


def bundle_root(graphs: list[str] | tuple[str, ...], bundle: str | Path) -> Path:
    """The directory the files of a bundle are written into (a one-graph bundle's parent)."""
    return Path(bundle) if len(graphs) > 1 else Path(bundle).parent


def describe(kind: str) -> str:
    """A help-text phrase naming the file of ``kind`` beside a graph (``<graph>`` and the suffix)."""
    a = ARTIFACTS[kind]
    return a.suffix if kind == MANIFEST else f"<graph>{a.suffix}"
