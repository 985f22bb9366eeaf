"""Reading an export bundle (:mod:`radaredge.artifacts`): its manifest, read and checked in one
place, and the graph files it lists; a one-graph export is a bundle of one."""

from __future__ import annotations

import json
from pathlib import Path

from .. import artifacts
from ..errors import InputError


def read_manifest(path: Path) -> dict:
    """A bundle's manifest (:mod:`radaredge.artifacts`), checked: ``weights_sha256`` a string and ``parts`` mapping each graph to an
    ``onnx`` file name inside the bundle; InputError naming the file and the entry otherwise."""
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not a readable bundle manifest ({type(exc).__name__}: {str(exc)[:120]}); "
                         f"re-export the bundle") from None
    parts = manifest.get("parts") if isinstance(manifest, dict) else None
    if not isinstance(parts, dict) or not isinstance(manifest.get("weights_sha256"), str):
        raise InputError(f"{path}: a bundle manifest holds 'weights_sha256' (a string) and 'parts' (graph name -> "
                         f"file); re-export the bundle")
    for name, info in parts.items():
        onnx_name = info.get("onnx") if isinstance(info, dict) else None
        if not isinstance(onnx_name, str) or Path(onnx_name).name != onnx_name or not onnx_name.endswith(".onnx"):
            raise InputError(f"{path}: parts.{name}.onnx must name an .onnx file inside the bundle, got {onnx_name!r}")
    return manifest


def bundle_graphs(path: str | Path) -> dict[str | None, Path]:
    """part name -> graph file of the export at ``path``: a graph file is a bundle of one (its
    part None); a directory is read through its manifest. InputError for a directory without one."""
    path = Path(path)
    if not path.is_dir():
        return {None: path}
    manifest = artifacts.manifest_path(path)
    if not manifest.is_file():
        raise InputError(f"{path} is a directory without {manifest.name}; pass an .onnx or a multi-graph export "
                         f"directory")
    return {name: path / info["onnx"] for name, info in read_manifest(manifest)["parts"].items()}
