"""A run's output on disk: Parquet shards of graph outputs and the manifest that makes a run resumable.

Layout of a run directory ``OUT/``::

    run.json                 the manifest (format 2): graph, weights hash, data root, window length,
                             shard size; per drive (its path relative to the data root) its scan
                             format, fingerprint, scan and window counts and its shards; per shard
                             its drive, first window, window count and sha256
    shards/<name>.parquet    name = <drive, readable>-<16 hex digits>-<n>: the digits hash the
                             drive's relative path and fingerprint, so no two drives (``a/b`` and
                             ``a__b``) share a name, and a drive whose scans changed gets new names
    .staging/                a run in progress: its new shards and journal.json (hidden; gone
                             once the run finishes, kept for the next attempt when it fails)

A shard holds consecutive windows of one drive, one row each: ``drive`` (str), ``frame`` (the
window's last frame, int64), ``timestamp`` (s, float64), ``northing`` / ``easting`` (m, float64),
and per graph output ``<name>`` (the array's raw bytes, C order) and ``<name>.shape`` (int64 list);
the schema's metadata holds each output's dtype. Decoding gives back the runtime's arrays bit for
bit.

A run is one transaction (:class:`RunOutput`): it checks the previous manifest against the data as
it is now (drives added, removed, or whose fingerprint changed; shards missing or changed since
they were recorded), writes the shards it computes into ``.staging/`` (each atomically, and noted
in the journal), and only when every shard is finished moves them into ``shards/``, replaces
``run.json`` and deletes the shards no drive uses any more. A run that fails or is killed leaves
the previous ``run.json`` and its shards as they were (none, when there was none); the next
attempt with the same setup takes the staged shards it can verify from the journal.

A format-1 ``run.json`` (older radaredge: no drive fingerprints, shard names ``<drive>-<n>``) is
still read by :func:`read_run`; resuming it recomputes every shard under the new names.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import atomic
from ..errors import ConfigError, InputError

MANIFEST = "run.json"
SHARDS = "shards"
STAGING = ".staging"
JOURNAL = "journal.json"
FORMAT = 2  # run.json's layout; 1: before drive fingerprints (no "format" key)
READABLE_FORMATS = (1, 2)
POSE_COLUMNS = ("drive", "frame", "timestamp", "northing", "easting")
_STEM_CHARS = 64  # of the drive's path in a shard name (file names stay far below 255 bytes)


def shard_stem(drive: str, fingerprint: str) -> str:
    """The name prefix of the shards of ``drive`` (its path relative to the data root) whose scans
    have ``fingerprint``: the path made file-name safe and short, for people, then 16 hex digits
    of the sha256 of the path and the fingerprint, which keep names of different drives apart
    (``a/b`` and ``a__b``; ``A`` and ``a`` on a case-insensitive file system)."""
    readable = re.sub(r"[^A-Za-z0-9._-]+", "_", drive.replace("/", "__"))[:_STEM_CHARS].lstrip(".") or "drive"
    digest = hashlib.sha256(f"{drive}\0{fingerprint}".encode("utf-8", "surrogateescape")).hexdigest()[:16]
    return f"{readable}-{digest}"


@dataclass(frozen=True)
class ShardPlan:
    """One shard to compute: ``count`` consecutive windows of drive ``drive`` (its directory
    ``path``, scans in format ``fmt``) from window ``first`` on."""

    name: str
    drive: str
    path: str
    first: int
    count: int
    fmt: str = ""  # the drive's scan format ("" = the TransLoc4D pointclouds/ layout's own)

    def entry(self, sha256: str) -> dict:
        return {"drive": self.drive, "first": self.first, "count": self.count, "sha256": sha256}

    def matches(self, entry) -> bool:
        """``entry`` (of a manifest or journal) records this shard's windows."""
        return (
            isinstance(entry, dict)
            and isinstance(entry.get("sha256"), str)
            and {k: entry.get(k) for k in ("drive", "first", "count")}
            == {"drive": self.drive, "first": self.first, "count": self.count}
        )


def encode_shard(rows: list[dict], outputs: list[dict[str, np.ndarray]]) -> bytes:
    """A shard's Parquet bytes: ``rows`` (the pose columns of each window) beside its graph
    ``outputs`` (name -> array), one row per window."""
    # optional: pyarrow is the scale extra
    import pyarrow as pa
    import pyarrow.parquet as pq

    names = list(outputs[0]) if outputs else []
    columns = {c: [r[c] for r in rows] for c in POSE_COLUMNS}
    dtypes = {}
    for name in names:
        arrays = [np.ascontiguousarray(o[name]) for o in outputs]
        dtypes[name] = arrays[0].dtype.str
        columns[name] = pa.array([a.tobytes() for a in arrays], pa.binary())
        columns[f"{name}.shape"] = pa.array([list(a.shape) for a in arrays], pa.list_(pa.int64()))
    table = pa.table(columns).replace_schema_metadata({"radaredge.dtypes": json.dumps(dtypes)})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def decode_shard(path: Path) -> tuple[dict[str, np.ndarray], dict[str, list[np.ndarray]]]:
    """(pose columns as arrays, output name -> one array per window) of a shard file;
    InputError naming the file when it is not a readable shard."""
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
        dtypes = json.loads(table.schema.metadata[b"radaredge.dtypes"])
    except Exception as exc:  # pyarrow's errors (ArrowInvalid, OSError, KeyError) name no file
        raise InputError(
            f"{path}: not a readable radaredge shard ({str(exc).splitlines()[0][:160]}); "
            f"delete it and run again to recompute it"
        ) from None
    poses = {c: table.column(c).to_numpy(zero_copy_only=False) for c in POSE_COLUMNS}
    outputs = {}
    for name, dtype in dtypes.items():
        blobs = table.column(name).to_pylist()
        shapes = table.column(f"{name}.shape").to_pylist()
        outputs[name] = [np.frombuffer(b, dtype=np.dtype(dtype)).reshape(s) for b, s in zip(blobs, shapes)]
    return poses, outputs


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def recorded(out: str | Path, key: str):
    """``key`` of the manifest in ``out``, if there is a readable one."""
    try:
        return json.loads((Path(out) / MANIFEST).read_text()).get(key)
    except (OSError, ValueError, AttributeError):
        return None


def _format_of(manifest: dict, path: Path) -> int:
    fmt = manifest.get("format", 1)
    if fmt not in READABLE_FORMATS:
        raise InputError(
            f"{path}: run manifest format {fmt!r}, written by a newer radaredge (this one reads formats "
            f"{', '.join(map(str, READABLE_FORMATS))}); upgrade radaredge or use another --out"
        )
    return fmt


def _repair_hint(out: Path) -> str:
    return (
        f"`radaredge run` with the same arguments (--out {out}; for a map's run/, `radaredge map build` with "
        f"the same arguments) recomputes it"
    )


@dataclass
class RunChanges:
    """How the data and the run directory differed from the previous manifest, and what the run did
    about it: drives ``added``, ``removed`` (their shards dropped) and ``changed`` (their scans or
    gps.csv differ: shards recomputed); shards named in the manifest but ``missing`` (recomputed);
    shards computed by an earlier attempt that failed and ``reused`` from the staging area; and
    whether the previous manifest was an ``older_format`` one (every shard recomputed)."""

    added: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    changed: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    dropped_shards: int = 0
    reused: int = 0
    older_format: bool = False

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def lines(self) -> list[str]:
        """What a person needs to know, one line each; none when nothing changed."""
        out = []
        if self.older_format:
            out.append(
                f"{MANIFEST} was written by an older radaredge (no drive fingerprints): every shard recomputed "
                f"under injective names"
            )
        if self.removed:
            out.append(
                f"{len(self.removed)} drive(s) no longer in the data, their shards dropped: " + _names(self.removed)
            )
        if self.changed:
            out.append(
                f"{len(self.changed)} drive(s) whose scans or gps.csv changed, their shards recomputed: "
                + _names(self.changed)
            )
        if self.added:
            out.append(f"{len(self.added)} drive(s) new in the data, computed: " + _names(self.added))
        if self.missing:
            out.append(
                f"{len(self.missing)} shard(s) named in {MANIFEST} but missing, recomputed: " + _names(self.missing)
            )
        if self.reused:
            out.append(f"{self.reused} shard(s) finished by an earlier attempt that failed, reused")
        return out


def _names(items: list[str], most: int = 5) -> str:
    return ", ".join(items[:most]) + (f" and {len(items) - most} more" if len(items) > most else "")


class RunOutput:
    """The run directory ``out`` brought up to date as one transaction.

    ``setup`` is what the run computes (graph weights hash, data root, window length, shard
    size); ``plans`` every shard of the data as it is now and ``drives`` each drive's record (label
    -> fmt, fingerprint, scans, windows). Constructing it reads the previous manifest (ConfigError
    when it holds a run of another setup; InputError when it is unreadable, or a shard it keeps no
    longer has its recorded sha256) and the staging journal, and sets :attr:`pending` (the shards
    to compute) and :attr:`changes`. :meth:`record` stages a computed shard; :meth:`commit` puts
    the run in place. Nothing under a final name changes before :meth:`commit`."""

    def __init__(self, out: str | Path, setup: dict, plans: list[ShardPlan], drives: dict[str, dict]):
        self.out, self.setup, self.plans, self.drives = Path(out), setup, plans, drives
        self.path = self.out / MANIFEST
        self.staging = self.out / STAGING
        self.finished: dict[str, dict] = {}  # name -> entry: kept from the previous run
        self.staged: dict[str, dict] = {}  # name -> entry: in the staging area
        self.changes = RunChanges()
        previous = self._previous()
        journal = self._journal()
        prev_shards = (previous.get("shards") or {}) if previous else {}
        prev_drives = None  # format 1 recorded no drives
        if previous and _format_of(previous, self.path) >= 2:
            prev_drives = {k: v for k, v in (previous.get("drives") or {}).items() if isinstance(v, dict)}
        self.pending: list[ShardPlan] = []
        for plan in plans:
            entry = prev_shards.get(plan.name)
            if plan.matches(entry):
                path = self.shard_path(plan.name)
                if path.is_file():
                    if file_sha256(path) != entry["sha256"]:
                        raise InputError(
                            f"{path}: its sha256 differs from the one {self.path} recorded when it was "
                            f"written (truncated or changed since); delete it and run again to "
                            f"recompute it"
                        )
                    self.finished[plan.name] = plan.entry(entry["sha256"])
                    continue
                self.changes.missing.append(plan.name)
            elif prev_drives is not None and plan.name in prev_drives.get(plan.drive, {}).get("shards", ()):
                self.changes.missing.append(plan.name)  # the drive lists it, its entry is gone
            if self._staged_ok(plan, journal.get(plan.name)):
                self.staged[plan.name] = plan.entry(journal[plan.name]["sha256"])
                self.changes.reused += 1
                continue
            self.pending.append(plan)
        if previous is not None:
            before = (
                set(prev_drives)
                if prev_drives is not None
                else {
                    e["drive"] for e in prev_shards.values() if isinstance(e, dict) and isinstance(e.get("drive"), str)
                }
            )
            now = set(drives)
            self.changes.added = sorted(now - before)
            self.changes.removed = sorted(before - now)
            if prev_drives is not None:
                self.changes.changed = sorted(
                    d
                    for d in now & before
                    if prev_drives[d].get("fingerprint") != drives[d]["fingerprint"]
                    or prev_drives[d].get("fmt") != drives[d]["fmt"]
                )
            self.changes.older_format = prev_drives is None and bool(prev_shards)
            names = {p.name for p in plans}
            self.changes.dropped_shards = sum(1 for n in prev_shards if n not in names)

    def _previous(self) -> dict | None:
        """The previous manifest, if any, checked to be of this setup."""
        if not self.path.exists():
            return None
        try:
            old = json.loads(self.path.read_text())
            if not isinstance(old, dict) or not isinstance(old.get("shards", {}), dict):
                raise ValueError
            same = {k: old.get(k) for k in self.setup}
        except (OSError, ValueError):
            raise InputError(f"{self.path}: not a radaredge run manifest; use another --out") from None
        _format_of(old, self.path)
        if same != self.setup:
            diff = [k for k in self.setup if same[k] != self.setup[k]]
            raise ConfigError(
                f"{self.out} holds a run of other inputs "
                f"({'; '.join(f'{k} {same[k]!r} there, {self.setup[k]!r} now' for k in diff)}); "
                f"use another --out"
            )
        return old

    def _journal(self) -> dict:
        """The staged shards' entries of an earlier attempt with this setup; a staging area of
        another setup (or unreadable) is removed."""
        path = self.staging / JOURNAL
        if not self.staging.exists():
            return {}
        try:
            journal = json.loads(path.read_text())
            if journal.get("setup") == self.setup and isinstance(journal.get("shards"), dict):
                return journal["shards"]
        except (OSError, ValueError, AttributeError):
            pass
        shutil.rmtree(self.staging, ignore_errors=True)
        return {}

    def _staged_ok(self, plan: ShardPlan, entry) -> bool:
        """``entry`` of the journal records ``plan``'s windows, and its file (in the staging area, or
        already moved into shards/ by a commit that was cut short) has the recorded sha256."""
        if not plan.matches(entry):
            return False
        return any(
            p.is_file() and file_sha256(p) == entry["sha256"]
            for p in (self.staged_path(plan.name), self.shard_path(plan.name))
        )

    def shard_path(self, name: str) -> Path:
        return self.out / SHARDS / f"{name}.parquet"

    def staged_path(self, name: str) -> Path:
        return self.staging / f"{name}.parquet"

    def record(self, plan: ShardPlan, data: bytes) -> None:
        """Stage a computed shard (atomically) and note it, with its sha256, in the journal."""
        with atomic.atomic_path(self.staged_path(plan.name)) as tmp:
            tmp.write_bytes(data)
        self.staged[plan.name] = plan.entry(hashlib.sha256(data).hexdigest())
        atomic.write_json(self.staging / JOURNAL, {"setup": self.setup, "shards": self.staged})

    def manifest(self) -> dict:
        """The manifest of the finished run: every planned shard, in plan order."""
        entries = {**self.finished, **self.staged}
        missing = [p.name for p in self.plans if p.name not in entries]
        if missing:
            raise RuntimeError(f"commit before shards {missing[:3]} were computed")
        drives = {label: {**info, "shards": []} for label, info in self.drives.items()}
        for p in self.plans:
            drives[p.drive]["shards"].append(p.name)
        return {
            "format": FORMAT,
            **self.setup,
            "drives": drives,
            "shards": {p.name: entries[p.name] for p in self.plans},
        }

    def commit(self) -> dict:
        """Move the staged shards into shards/, replace run.json, delete the shard files it no longer
        names and the staging area (SIGINT and SIGTERM held back meanwhile); the manifest written."""
        manifest = self.manifest()
        with atomic.signals_held():
            for name in self.staged:
                src = self.staged_path(name)
                if src.is_file():
                    self.shard_path(name).parent.mkdir(parents=True, exist_ok=True)
                    os.replace(src, self.shard_path(name))
            atomic.write_json(self.path, manifest)
            shards = self.out / SHARDS
            if shards.is_dir():
                for f in shards.glob("*.parquet"):
                    if f.stem not in manifest["shards"]:
                        f.unlink(missing_ok=True)
            shutil.rmtree(self.staging, ignore_errors=True)
        return manifest


def read_run(out: str | Path) -> tuple[dict, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """A finished run: (its manifest, pose columns [W] and output name -> stacked outputs [W, ...])
    over every shard in drive and window order; outputs whose shapes vary (detections) come back
    as object arrays of per-window arrays. InputError naming the shard when one the manifest names
    is missing or no longer has its recorded sha256."""
    out = Path(out)
    try:
        manifest = json.loads((out / MANIFEST).read_text())
        if not isinstance(manifest, dict) or not isinstance(manifest.get("shards", {}), dict):
            raise ValueError
    except (OSError, ValueError):
        raise InputError(f"{out}: no readable {MANIFEST}; expected the --out directory of `radaredge run`") from None
    _format_of(manifest, out / MANIFEST)
    names = sorted(
        manifest.get("shards", {}), key=lambda n: (manifest["shards"][n]["drive"], manifest["shards"][n]["first"])
    )
    if not names:
        raise InputError(f"{out}: the run has no finished shards")
    poses, outputs = {c: [] for c in POSE_COLUMNS}, {}
    for name in names:
        path = out / SHARDS / f"{name}.parquet"
        if not path.is_file():
            raise InputError(
                f"{path}: shard {name} of drive {manifest['shards'][name]['drive']}, named in "
                f"{out / MANIFEST}, is missing; {_repair_hint(out)}"
            )
        if file_sha256(path) != manifest["shards"][name]["sha256"]:
            raise InputError(
                f"{path}: its sha256 differs from the one {out / MANIFEST} recorded (truncated or changed "
                f"since); delete it, then {_repair_hint(out)}"
            )
        p, o = decode_shard(path)
        for c in POSE_COLUMNS:
            poses[c].append(p[c])
        for k, v in o.items():
            outputs.setdefault(k, []).extend(v)
    stacked = {}
    for k, v in outputs.items():
        if len({a.shape for a in v}) == 1:
            stacked[k] = np.stack(v)
        else:
            stacked[k] = np.empty(len(v), dtype=object)
            stacked[k][:] = v
    return manifest, {c: np.concatenate(v) for c, v in poses.items()}, stacked
