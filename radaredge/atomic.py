"""Atomic outputs: every file radaredge writes appears complete or not at all.

A file is written under a temporary name in its own directory (same file system) and renamed
onto its final name only when it is complete (``os.replace`` is atomic on POSIX and Windows).
A command that fails or is interrupted (Ctrl-C; SIGTERM, which the CLI turns into the same
orderly exit) leaves the previous file as it was and
removes its temporary. Outputs made of several files (an export: graph, sidecar, int8 and debug
copies; a Des4Pos bundle) are written into a staging directory and moved into place together,
with SIGINT and SIGTERM held back during the moves, so no interruption leaves a mix of old and
new files. A process killed outright (SIGKILL, power loss) may leave a hidden temporary behind,
never a partial file under a final name.

Standard library only (no numpy, no torch): the runtime and the CLI use it too.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import math
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import Iterator

_HELD = (signal.SIGINT, signal.SIGTERM)
# Temporaries not yet renamed or removed: an interrupt that lands between a temporary's creation
# and the block that would remove it (a bytecode boundary away) still removes it at exit.
_LIVE: set[Path] = set()


@atexit.register
def _remove_leftovers() -> None:
    for path in list(_LIVE):
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


@contextlib.contextmanager
def signals_held(notice: str | None = None) -> Iterator[None]:
    """Hold SIGINT and SIGTERM back for the duration (main thread only; elsewhere a no-op): a
    signal that arrives meanwhile is recorded, and delivered to the handler in force before the
    block when the block ends (Ctrl-C raises KeyboardInterrupt there). ``notice``, when given,
    is printed on stderr at the first held signal (a long block: say what the process finishes
    first).

    The signals are caught by a recording handler rather than masked: a mask covers only the
    calling thread, and a signal the kernel hands to another thread (torch's and onnxruntime's
    workers) still raises KeyboardInterrupt in the main thread at its next bytecode."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []

    def record(signum, frame):
        if notice and not arrived:
            with contextlib.suppress(OSError):
                os.write(2, f"{notice}\n".encode())
        arrived.append(signum)

    old = {}
    try:
        for sig in _HELD:
            if signal.getsignal(sig) is not None:  # None: a handler set outside Python, left alone
                old[sig] = signal.signal(sig, record)
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(arrived):
            if old[sig] is not signal.SIG_IGN:
                signal.raise_signal(sig)


def exit_on_sigterm() -> None:
    """Make SIGTERM end the process as Ctrl-C does (main thread only): SystemExit(143) unwinds
    the stack, so every temporary and staging directory is removed on the way out. Without it
    SIGTERM kills the process where it stands."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminated)


def _terminated(signum, frame):
    raise SystemExit(128 + signum)


_UMASK = os.umask(0)
os.umask(_UMASK)


def _temporary_name(path: Path) -> Path:
    """A new hidden file beside ``path`` that keeps its suffix (``np.savez`` appends ``.npz`` to
    a name without it), with the permissions an ordinary new file gets; registered for removal
    at exit until it is renamed or removed."""
    with signals_held():
        fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".partial{path.suffix}", dir=path.parent)
        _LIVE.add(Path(name))
    os.close(fd)
    os.chmod(name, 0o666 & ~_UMASK)
    return Path(name)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write the whole file to; renamed onto ``path`` when
    the block ends normally, removed when it raises (KeyboardInterrupt included). The parent
    directory is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_name(path)
    try:
        yield tmp
        with signals_held():
            os.replace(tmp, path)
            _LIVE.discard(tmp)
    finally:
        tmp.unlink(missing_ok=True)
        _LIVE.discard(tmp)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def finite(obj):
    """``obj`` with every non-finite float as None: JSON has no NaN or Infinity (Python's json
    writes them, and strict readers refuse the document)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


def dumps(obj, indent: int = 2) -> str:
    """One strict JSON document (non-finite numbers as null)."""
    return json.dumps(finite(obj), indent=indent, allow_nan=False, default=str)


def write_json(path: str | os.PathLike, obj, indent: int = 2) -> Path:
    """Write ``obj`` as strict JSON (:func:`dumps`) to ``path`` atomically; returns the path."""
    return write_text(path, dumps(obj, indent))


class Staging:
    """A hidden staging directory inside ``dest`` (a directory, created if missing) whose files
    :meth:`commit` moves into ``dest`` under the same names, all with signals held back.
    As a context manager: the staging directory is removed when the block ends, committed or not,
    and so is ``dest`` when this created it and nothing was committed."""

    def __init__(self, dest: str | os.PathLike):
        self.dest = Path(dest)
        self.created = not self.dest.exists()
        self.dest.mkdir(parents=True, exist_ok=True)
        self.committed = False
        with signals_held():
            self.dir = Path(tempfile.mkdtemp(prefix=".radaredge-", suffix=".staging", dir=self.dest))
            _LIVE.add(self.dir)

    def path(self, final: str | os.PathLike) -> Path:
        """Where to write the file that will become ``final`` (a path inside ``dest``)."""
        return self.dir / Path(final).name

    def commit(self) -> list[Path]:
        """Move every staged file into ``dest``; the final paths, in name order."""
        moved = []
        with signals_held():
            for f in sorted(self.dir.iterdir()):
                target = self.dest / f.name
                os.replace(f, target)
                moved.append(target)
            self.committed = True
        return moved

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
        _LIVE.discard(self.dir)
        if self.created and not self.committed:
            with contextlib.suppress(OSError):
                self.dest.rmdir()

    def __enter__(self) -> "Staging":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
