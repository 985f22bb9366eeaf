"""Packaging: the wheel ships the model cards, a base install (no torch) runs `radaredge list`,
`radaredge inspect` and `radaredge.runtime` from any directory, and an install with the `export`
extra exports a shipped card.

Each install is a fresh venv with the built wheel installed non-editable (``--no-deps``). Its
dependencies come from this venv without a registry: a ``.pth`` file points the new venv at a
folder of symlinks to exactly the distributions that the wheel's declared requirements pull in
(the closure of its ``Requires-Dist`` over this venv's installed metadata). So the test also
proves that the declared base dependencies suffice for the runtime and that torch is not among
them, and that the ``export`` extra suffices for an export.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import zipfile
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = sorted(p.stem for p in (ROOT / "models").glob("*.yaml"))
EXPORT_CARD = "tdfanet-edge"  # the quickest shipped card to export (a 2 MB graph)
SITE = Path(sysconfig.get_paths()["purelib"])


def _run(cmd, cwd=None, env=None, timeout=300, check=True) -> subprocess.CompletedProcess:
    res = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    if check:
        assert res.returncode == 0, f"{' '.join(map(str, cmd))} failed ({res.returncode}):\n{res.stdout}\n{res.stderr}"
    return res


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of the sources (a build in the clone would leave build/ there,
    and a stale build/lib could slip removed modules into the wheel)."""
    d = tmp_path_factory.mktemp("wheel")
    src = d / "src"
    for tree in ("radaredge", "models"):
        shutil.copytree(ROOT / tree, src / tree, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    _run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", d / "dist", src]
    )
    wheels = list((d / "dist").glob("radaredge-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def _installed() -> dict[str, md.Distribution]:
    """This venv's distributions by canonical name (the editable radaredge left out)."""
    dists = {}
    for dist in md.distributions(path=[str(SITE)]):
        name = canonicalize_name(dist.metadata["Name"])
        if name != "radaredge":
            dists.setdefault(name, dist)
    return dists


def _wants(req: Requirement, extras: set[str]) -> bool:
    if req.marker is None:
        return True
    return any(req.marker.evaluate({"extra": e}) for e in extras | {""})


def _closure(requires: list[str], extras: set[str]) -> list[md.Distribution]:
    """The installed distributions that ``requires`` (with ``extras`` selected) pull in."""
    installed = _installed()
    chosen: dict[str, set[str]] = {}  # distribution -> the extras asked of it so far
    todo = [(Requirement(r), extras) for r in requires]
    while todo:
        req, wanted = todo.pop()
        name = canonicalize_name(req.name)
        if not _wants(req, wanted) or name == "radaredge":  # radaredge[...]: a self-reference
            continue
        assert name in installed, f"{req} is required but not installed in {SITE}"
        dist = installed[name]
        assert req.specifier.contains(dist.version, prereleases=True), f"{req}: installed {dist.version}"
        if name in chosen and set(req.extras) <= chosen[name]:
            continue
        chosen[name] = chosen.get(name, set()) | set(req.extras)
        todo += [(Requirement(r), chosen[name]) for r in dist.requires or []]
    return [installed[n] for n in chosen]


def _deps_dir(path: Path, dists: list[md.Distribution]) -> Path:
    """A folder of symlinks to the top-level modules and metadata of ``dists`` (from this venv)."""
    path.mkdir()
    for dist in dists:
        tops = {f.parts[0] for f in dist.files or []}
        for top in sorted(tops):
            if top in ("..", "__pycache__") or top.endswith(".pth"):
                continue
            target = SITE / top
            if target.exists() and not (path / top).exists():
                (path / top).symlink_to(target)
    return path


def _venv(root: Path, wheel: Path, deps: Path) -> tuple[Path, dict]:
    """A fresh venv at ``root`` with ``wheel`` installed non-editable and ``deps`` on its path;
    (its python, an environment that runs its scripts first and sees nothing of this venv)."""
    env = {
        k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "RADAREDGE_CARDS")
    }
    env.update(PATH=f"{root / 'bin'}{os.pathsep}{env.get('PATH', '')}", PYTHONNOUSERSITE="1")
    python = root / "bin" / "python"
    if Version(md.version("pip")) >= Version("22.3"):  # pip --python: install into another interpreter
        _run([sys.executable, "-m", "venv", "--without-pip", root], env=env)
        pip = [sys.executable, "-m", "pip", "--python", python]
    else:
        _run([sys.executable, "-m", "venv", root], env=env)
        pip = [python, "-m", "pip"]
    purelib = _run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], env=env).stdout
    Path(purelib.strip(), "radaredge_test_deps.pth").write_text(f"{deps}\n")
    _run(pip + ["install", "--no-deps", "--no-index", "--quiet", wheel], env=env)
    return python, env


def _requires(wheel: Path) -> list[str]:
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        text = z.read(meta).decode()
    return [line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("Requires-Dist:")]


def test_wheel_ships_every_card(wheel):
    assert SHIPPED and EXPORT_CARD in SHIPPED
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    assert {f"radaredge/model_cards/{c}.yaml" for c in SHIPPED} <= names
    assert "radaredge/cards/__init__.py" in names


def test_wheel_ships_every_package(wheel):
    """pyproject.toml lists the packages by hand (the cards' package is mapped from models/):
    every package of the source tree must be in the wheel."""
    packages = {str(p.parent.relative_to(ROOT)) for p in (ROOT / "radaredge").rglob("__init__.py")}
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    assert {f"{p}/__init__.py" for p in packages} <= names, sorted(f"{p}/__init__.py" for p in packages)


def test_base_install_runs_without_torch(wheel, tiny_export, tmp_path):
    base = [r for r in _requires(wheel) if Requirement(r).marker is None]
    assert sorted(canonicalize_name(Requirement(r).name) for r in base) == ["click", "numpy", "onnxruntime", "pyyaml"]
    deps = _deps_dir(tmp_path / "deps", _closure(base, set()))
    python, env = _venv(tmp_path / "venv", wheel, deps)
    work = tmp_path / "work"  # not the clone: only the installed package can be found
    work.mkdir()
    onnx_path = shutil.copy(tiny_export[2], work / "tiny.onnx")

    res = _run([python, "-c", "import torch"], cwd=work, env=env, check=False)
    assert res.returncode != 0 and "No module named 'torch'" in res.stderr, res.stderr
    where = _run([python, "-c", "import radaredge; print(radaredge.__file__)"], cwd=work, env=env).stdout
    assert Path(where.strip()).is_relative_to(tmp_path / "venv"), where

    listed = _run(["radaredge", "list"], cwd=work, env=env).stdout
    for name in SHIPPED:
        assert any(line.split()[0] == name for line in listed.splitlines() if line.strip()), listed

    inspected = _run(["radaredge", "inspect", "tiny.onnx"], cwd=work, env=env).stdout
    assert "tdfanet-tiny" in inspected, inspected

    script = textwrap.dedent(f"""
        import sys
        import numpy as np
        from radaredge import runtime
        m = runtime.load({str(onnx_path)!r})
        rng = np.random.default_rng(0)
        lo, hi = np.array([0.0, -16.0, -3.0, -5.0, -10.0]), np.array([32.0, 16.0, 10.0, 5.0, 30.0])
        frames = [(lo + (hi - lo) * rng.random((n, 5))).astype(np.float32) for n in (40, 50, 60)]
        out = m.run(frames)
        assert "torch" not in sys.modules
        print(m.card.name, *sorted(out))
        print(out)
    """)
    out = _run([python, "-c", script], cwd=work, env=env).stdout
    first = out.splitlines()[0].split()
    assert first[0] == "tdfanet-tiny" and "descriptor_normalized" in first[1:], out


def test_export_extra_exports_a_shipped_card(wheel, tmp_path):
    requires = _requires(wheel)
    deps = _deps_dir(tmp_path / "deps", _closure(requires, {"export"}))
    python, env = _venv(tmp_path / "venv", wheel, deps)
    work = tmp_path / "work"
    work.mkdir()

    where = _run(
        [python, "-c", "import radaredge, radaredge.cards as c; print(radaredge.__file__); print(c.cards_dir())"],
        cwd=work,
        env=env,
    ).stdout.split()
    assert all(Path(w).is_relative_to(tmp_path / "venv") for w in where), where

    _run(["radaredge", "export", "--model", EXPORT_CARD, "--output", "out.onnx"], cwd=work, env=env, timeout=240)
    assert (work / "out.onnx").stat().st_size > 100_000
    assert EXPORT_CARD in _run(["radaredge", "inspect", "out.onnx"], cwd=work, env=env).stdout
