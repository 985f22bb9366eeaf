"""Progress bars on stderr for the command line (tqdm, when installed: it comes with the export
extra; a runtime-only install draws none), and the bar that draws nothing, which the library's
long loops take by default. Torch-free."""

from __future__ import annotations

import sys
from typing import Any, Callable

Progress = Callable[[str, int], Any]  # (description, total) -> a tqdm-like bar (update, set_postfix, close)


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, **kwargs) -> None:
        pass

    def close(self) -> None:
        pass


def no_progress(desc: str, total: int) -> _NoBar:
    """A bar that draws nothing."""
    return _NoBar()


def _tqdm():
    """tqdm's class, or None when it is not installed (an optional extra, imported on first use)."""
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm


def iterate(desc: str) -> Callable:
    """``wrap(iterable)`` drawing a bar on stderr when it is a terminal; the iterable as is without tqdm."""
    tqdm = _tqdm()
    if tqdm is None:
        return lambda it: it
    return lambda it: tqdm(it, desc=desc, leave=False, file=sys.stderr, disable=not sys.stderr.isatty())


def bar(desc: str, total: int | None):
    """A bar on stderr when it is a terminal (update, set_postfix, close); :func:`no_progress` without tqdm."""
    tqdm = _tqdm()
    if tqdm is None:
        return no_progress(desc, total)
    return tqdm(total=total, desc=desc, leave=False, file=sys.stderr, disable=not sys.stderr.isatty())
