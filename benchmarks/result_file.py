"""How every benchmark writes its result JSON (:func:`save_result`: ``results/<kind>-<date>.json``,
dated): strict JSON, written atomically, with no path of
the machine that ran it. A path inside the repository is written relative to it; any other
absolute path (a work directory, a data set, a checkpoint elsewhere) keeps only its last two
parts below the machine's root folder, after ``…/``, since the machine's directories mean nothing to
a reader. What identifies a
checkpoint or a graph is its sha256 (:func:`sha256_of`), which the scripts record beside it.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import re
from pathlib import Path

from radaredge import atomic

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
# An absolute path under one of the roots a machine keeps work in (not "m/s", not a URL, not a
# path this module already shortened to "…/scratch/set").
MACHINE_PATH = re.compile(
    r"(?<![\w.~/…-])/(?:tmp|work|root|home|mnt|var|opt|scratch|Users|private)/"
    r"[^\s\"'`,;()\[\]{}<>|]*"
)


def portable_path(text: str) -> str:
    """``text`` with every absolute machine path in it made portable (module docstring). A path
    inside the repository is recognised wherever the checkout lives, not only under the roots of
    :data:`MACHINE_PATH`."""
    text = re.sub(rf"(?<![\w.~/-]){re.escape(str(ROOT))}/", "", text)

    def shown(match: re.Match) -> str:
        path = Path(match.group(0).rstrip("."))
        tail = match.group(0)[len(str(path)) :]
        try:
            return str(path.relative_to(ROOT)) + tail
        except ValueError:
            return "…/" + "/".join(path.parts[2:][-2:]) + tail  # never the machine's root folder

    return MACHINE_PATH.sub(shown, text)


def portable(obj):
    """``obj`` (a JSON document) with :func:`portable_path` applied to every string and key."""
    if isinstance(obj, str):
        return portable_path(obj)
    if isinstance(obj, dict):
        return {portable_path(str(k)): portable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [portable(v) for v in obj]
    if isinstance(obj, Path):
        return portable_path(str(obj))
    return obj


def sha256_of(path: str | Path | None) -> str | None:
    """The sha256 of the file at ``path`` (None when there is none)."""
    if path is None or not Path(path).is_file():
        return None
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_result(path: str | Path, doc: dict) -> Path:
    """Write ``doc`` to ``path`` as strict, portable JSON (atomically) and say so."""
    path = Path(path)
    atomic.write_text(path, atomic.dumps(portable(doc)) + "\n")
    print(f"wrote {path}")
    return path


def utc_stamp() -> str:
    """Now, as the results' ``date`` field writes it: ``YYYY-MM-DD HH:MM UTC``."""
    return dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def result_path(kind: str, date: str, folder: str | Path = RESULTS, keep_same_day: bool = False) -> Path:
    """``<folder>/<kind>-<YYYY-MM-DD>.json`` for a result dated ``date`` (``YYYY-MM-DD ...``); with
    ``keep_same_day``, ``-HHMM`` is added when a result of that kind and day is there already, so
    each run keeps its file (benchmarks/render.py shows the newest)."""
    path = Path(folder) / f"{kind}-{date[:10]}.json"
    if keep_same_day and path.exists():
        path = path.with_name(f"{kind}-{date[:10]}-{date[11:16].replace(':', '')}.json")
    return path


def save_result(kind: str, doc: dict, folder: str | Path = RESULTS, keep_same_day: bool = False) -> Path:
    """Writes ``doc`` (dated now in UTC unless it has a ``date``) as the result of ``kind`` at
    :func:`result_path`: how every benchmark ends."""
    doc = {"date": utc_stamp(), **doc} if "date" not in doc else doc
    Path(folder).mkdir(parents=True, exist_ok=True)
    return write_result(result_path(kind, doc["date"], folder, keep_same_day), doc)
