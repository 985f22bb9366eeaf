"""Reading an export bundle (:mod:`radaredge.artifacts`): its manifest, read and checked in one
place, and the graph files it lists; a one-graph export is a bundle of one.

A manifest records each part's content hash (``parts.<graph>.content_sha256``,
:mod:`.integrity`); reading it checks every part file against it, so a part replaced by another
graph, or edited, is named. Manifests written before content hashes lack it and are read as
before."""

from __future__ import annotations

import json
import re
from pathlib import Path

from .. import artifacts
from ..errors import InputError
from .integrity import content_hash

_SHA256 = re.compile(r"[0-9a-f]{64}")


def read_manifest(path: Path, check_parts: bool = True) -> dict:
    """A bundle's manifest (:mod:`radaredge.artifacts`), checked: ``weights_sha256`` a string and
    ``parts`` mapping each graph to an ``onnx`` file name inside the bundle (and, when recorded,
    its ``content_sha256``); InputError naming the file and the entry otherwise. With
    ``check_parts``, also InputError when a part's file does not have the contents the manifest
    recorded (:func:`part_findings`)."""
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(
            f"{path}: not a readable bundle manifest ({type(exc).__name__}: {str(exc)[:120]}); re-export the bundle"
        ) from None
    parts = manifest.get("parts") if isinstance(manifest, dict) else None
    if not isinstance(parts, dict) or not isinstance(manifest.get("weights_sha256"), str):
        raise InputError(
            f"{path}: a bundle manifest holds 'weights_sha256' (a string) and 'parts' (graph name -> "
            f"file); re-export the bundle"
        )
    for name, info in parts.items():
        onnx_name, expected = info.get("onnx") if isinstance(info, dict) else None, artifacts.part_path(".", name)
        if onnx_name != expected.name or expected.parent != Path("."):
            raise InputError(
                f"{path}: parts.{name}.onnx must be {expected.name} (the part's graph inside the "
                f"bundle), got {onnx_name!r}"
            )
        recorded = info.get("content_sha256")
        if recorded is not None and not (isinstance(recorded, str) and _SHA256.fullmatch(recorded)):
            raise InputError(
                f"{path}: parts.{name}.content_sha256 must be a sha256 (64 hex digits), got "
                f"{recorded!r}; re-export the bundle"
            )
    if check_parts:
        for message in _part_mismatches(path.parent, parts).values():
            raise InputError(f"{path}: {message}")
    return manifest


def _part_mismatches(directory: Path, parts: dict) -> dict[str, str]:
    found = {}
    for name, info in parts.items():
        recorded, file = info.get("content_sha256"), artifacts.part_path(directory, name)
        if recorded is None or not file.is_file():  # an older manifest; a missing file is named by its loader
            continue
        computed = content_hash(file).computed
        if computed != recorded:
            found[name] = (
                f"parts.{name}: the contents of {info['onnx']} hash to {computed}, not the {recorded} "
                f"recorded at export: the file was replaced or edited after export; re-export the bundle"
            )
    return found


def part_findings(path: str | Path) -> dict[str, str]:
    """For a bundle directory, part name -> why its graph file's contents are not the ones the
    manifest recorded at export (parts without a recorded hash are left out); {} for a graph file."""
    path = Path(path)
    if not path.is_dir():
        return {}
    manifest = artifacts.manifest_path(path)
    return _part_mismatches(path, read_manifest(manifest, check_parts=False)["parts"]) if manifest.is_file() else {}


def bundle_graphs(path: str | Path, check_parts: bool = True) -> dict[str | None, Path]:
    """part name -> graph file of the export at ``path``: a graph file is a bundle of one (its
    part None); a directory is read through its manifest (:func:`read_manifest`, which checks the
    parts' contents unless ``check_parts`` is false). InputError for a directory without one."""
    path = Path(path)
    if not path.is_dir():
        return {None: path}
    manifest = artifacts.manifest_path(path)
    if not manifest.is_file():
        raise InputError(
            f"{path} is a directory without {manifest.name}; pass an .onnx or a multi-graph export directory"
        )
    return {name: artifacts.part_path(path, name) for name in read_manifest(manifest, check_parts)["parts"]}
