"""Every kind of file an export consists of, in one table (in the spirit of Ultralytics'
``export_formats()``): its name beside the graph, the verb that writes it and the verbs and
runtimes that read it. Nothing else in radaredge spells these names.

An export is a *bundle* of named graphs (:class:`Bundle`), one per part of the model, and every
verb handles one graph or many through it alike. A bundle of one keeps the layout users see: the
``.onnx`` itself; a bundle of several is a directory holding ``<graph>.onnx`` per part and the
manifest. Every copy of a graph (int8, debug) and its sidecar sit beside it under
:func:`copy_path`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .errors import ConfigError


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

ARTIFACTS: dict[str, Artifact] = {
    a.kind: a
    for a in (
        Artifact(
            GRAPH,
            ".onnx",
            "export",
            ("parity-check", "bench", "eval", "locate", "inspect", "radaredge.runtime", "examples/c"),
            "the fp32 graph: raw points in, result out, the card in its metadata",
        ),
        Artifact(
            INT8,
            ".int8.onnx",
            "export --quantize int8",
            ("parity-check --quantized", "bench --int8", "locate --int8-text", "radaredge.runtime"),
            "the int8 copy of a graph (static QDQ, or dynamic where the model's int8 policy says)",
        ),
        Artifact(
            DEBUG,
            ".debug.onnx",
            "export --debug, parity-check",
            ("parity-check (where a failing output first diverges)",),
            "the graph with its traced intermediates as extra outputs named debug.<intermediate>",
        ),
        Artifact(
            SIDECAR,
            ".json",
            "export",
            ("people and scripts (inputs, outputs, op histogram, versions)",),
            "a JSON summary beside each graph",
        ),
        Artifact(
            MANIFEST,
            "bundle.json",
            "export (a multi-graph model)",
            ("parity-check", "bench", "eval", "locate", "radaredge.runtime"),
            "the parts of a multi-graph bundle with their weight hashes, its shared files and the card",
        ),
    )
}

COPY_KINDS = (INT8, DEBUG)  # graphs written beside a graph; never a graph's own name


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


def part_path(bundle: str | Path, graph: str) -> Path:
    """The ``.onnx`` of the part ``graph`` inside the bundle directory ``bundle``."""
    return Path(bundle) / f"{graph}{ARTIFACTS[GRAPH].suffix}"


@dataclass(frozen=True)
class Bundle:
    """The export of a model's named ``graphs`` at ``path``: the ``.onnx`` for one graph, the
    directory for several (module docstring). The one place that knows the two layouts."""

    path: Path
    graphs: tuple[str, ...]

    @classmethod
    def default(cls, card_name: str, graphs) -> "Bundle":
        """``export/<card>.onnx``, or the directory ``export/<card>/`` for several graphs."""
        graphs = tuple(graphs)
        suffix = "" if len(graphs) > 1 else ARTIFACTS[GRAPH].suffix
        return cls(Path("export") / f"{card_name}{suffix}", graphs)

    @classmethod
    def for_output(cls, card_name: str, graphs, output: str | Path | None) -> "Bundle":
        """Where ``export --output`` writes, checked before any work: one graph's ``.onnx`` (an
        existing directory, or a path ending in a slash, receives ``<card>.onnx``; another suffix,
        or a name ending like the int8 or debug copies, is refused); several graphs' directory (an
        existing file, or a name ending in .onnx, is refused). None: :meth:`default`."""
        graphs = tuple(graphs)
        if output is None:
            return cls.default(card_name, graphs)
        text, path, onnx = str(output), Path(output), ARTIFACTS[GRAPH].suffix
        as_dir = text.endswith(("/", os.sep)) or path.is_dir()
        if len(graphs) > 1:
            if path.exists() and not path.is_dir():
                raise ConfigError(
                    f"--output {text}: a file; {card_name} exports {len(graphs)} graphs into a "
                    f"directory (e.g. export/{card_name}/)"
                )
            if not as_dir and path.suffix.lower() == onnx:
                raise ConfigError(
                    f"--output {text}: {card_name} exports {len(graphs)} graphs into a directory, "
                    f"not one {onnx} (e.g. export/{card_name}/)"
                )
            return cls(path, graphs)
        if as_dir:
            return cls(path / f"{card_name}{onnx}", graphs)
        if path.suffix.lower() != onnx:
            raise ConfigError(
                f"--output {text}: a graph is written to a file ending in {onnx} (its "
                f"{ARTIFACTS[SIDECAR].suffix} sidecar goes beside it), e.g. export/{card_name}{onnx}"
            )
        if is_copy(path):
            copies = " or ".join(ARTIFACTS[k].suffix for k in COPY_KINDS)
            raise ConfigError(
                f"--output {text}: names ending in {copies} are the int8 and debug copies export "
                f"writes beside a graph; name the fp32 graph, e.g. export/{card_name}{onnx}"
            )
        return cls(path, graphs)

    @property
    def multi(self) -> bool:
        return len(self.graphs) > 1

    @property
    def root(self) -> Path:
        """The directory the bundle's files are written into (a one-graph bundle's parent)."""
        return self.path if self.multi else self.path.parent

    @property
    def manifest(self) -> Path | None:
        """The manifest of a bundle of several graphs; None for one."""
        return manifest_path(self.path) if self.multi else None

    def moved(self, root: str | Path) -> "Bundle":
        """The same bundle with its files under ``root`` instead of :attr:`root` (a staging directory)."""
        return Bundle(Path(root) if self.multi else Path(root) / self.path.name, self.graphs)

    def graph_files(self) -> dict[str, Path]:
        """graph name -> its ``.onnx``."""
        if not self.multi:
            return {self.graphs[0]: self.path}
        return {g: part_path(self.path, g) for g in self.graphs}

    def files(self) -> list[Path]:
        """Every path an export of this bundle may write: each graph with its sidecar, int8 and
        debug copies, and a multi-graph bundle's directory and manifest."""
        files = [
            copy
            for g in self.graph_files().values()
            for copy in (g, *(copy_path(g, k) for k in (SIDECAR, *COPY_KINDS)))
        ]
        return [self.path, self.manifest, *files] if self.multi else files


def describe(kind: str) -> str:
    """A help-text phrase naming the file of ``kind`` beside a graph (``<graph>`` and the suffix)."""
    a = ARTIFACTS[kind]
    return a.suffix if kind == MANIFEST else f"<graph>{a.suffix}"
