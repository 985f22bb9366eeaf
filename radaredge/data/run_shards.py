"""A run's output on disk: Parquet shards of graph outputs and the manifest that makes a run resumable.

Layout of a run directory ``OUT/``::

    run.json                 the manifest: graph, weights hash, data root, window length, shard size,
                             and per finished shard its drive, first window, window count and sha256
    shards/<drive>-<n>.parquet

A shard holds consecutive windows of one drive, one row each: ``drive`` (str), ``frame`` (the
window's last frame, int64), ``timestamp`` (s, float64), ``northing`` / ``easting`` (m, float64),
and per graph output ``<name>`` (the array's raw bytes, C order) and ``<name>.shape`` (int64 list);
the schema's metadata holds each output's dtype. Decoding gives back the runtime's arrays bit for
bit. Shards are written atomically and entered in the manifest after they are complete, so a run
that is killed leaves only whole shards, each checked against its recorded sha256 on resume.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import atomic
from ..errors import ConfigError, InputError

MANIFEST = "run.json"
SHARDS = "shards"
POSE_COLUMNS = ("drive", "frame", "timestamp", "northing", "easting")


@dataclass(frozen=True)
class ShardPlan:
    """One shard to compute: ``count`` consecutive windows of drive ``drive`` (its directory
    ``path``, scans in format ``fmt``) from window ``first`` on."""

    name: str
    drive: str
    path: str
    first: int
    count: int
    fmt: str = ""           # the drive's scan format ("" = the TransLoc4D pointclouds/ layout's own)

    def entry(self, sha256: str) -> dict:
        return {"drive": self.drive, "first": self.first, "count": self.count, "sha256": sha256}


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
    except Exception as exc:     # pyarrow's errors (ArrowInvalid, OSError, KeyError) name no file
        raise InputError(f"{path}: not a readable radaredge shard ({str(exc).splitlines()[0][:160]}); "
                         f"delete it and run again to recompute it") from None
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


class Manifest:
    """``OUT/run.json``: what the run computes (``setup``) and the shards finished so far."""

    def __init__(self, out: Path, setup: dict):
        self.out, self.setup = Path(out), setup
        self.path = self.out / MANIFEST
        self.shards: dict[str, dict] = {}
        if self.path.exists():
            try:
                old = json.loads(self.path.read_text())
                same = {k: old.get(k) for k in setup}
            except (OSError, ValueError, AttributeError):
                raise InputError(f"{self.path}: not a radaredge run manifest; use another --out") from None
            if same != setup:
                diff = [k for k in setup if same[k] != setup[k]]
                raise ConfigError(f"{out} holds a run of other inputs ({'; '.join(f'{k} {same[k]!r} there, {setup[k]!r} now' for k in diff)}); "
                                  f"use another --out")
            self.shards = dict(old.get("shards", {}))

    @staticmethod
    def recorded(out: Path, key: str):
        """``key`` of the manifest in ``out``, if there is a readable one."""
        try:
            return json.loads((Path(out) / MANIFEST).read_text()).get(key)
        except (OSError, ValueError, AttributeError):
            return None

    def finished(self, plan: ShardPlan) -> bool:
        """True when ``plan``'s shard is recorded with the same windows and its file still has the
        recorded sha256; InputError when the file differs (truncated, edited) from what was recorded."""
        entry = self.shards.get(plan.name)
        if entry is None or {k: entry.get(k) for k in ("drive", "first", "count")} != \
                {"drive": plan.drive, "first": plan.first, "count": plan.count}:
            return False
        path = self.shard_path(plan.name)
        if not path.is_file():
            return False
        if file_sha256(path) != entry.get("sha256"):
            raise InputError(f"{path}: its sha256 differs from the one {self.path} recorded when it was written "
                             f"(truncated or changed since); delete it and run again to recompute it")
        return True

    def shard_path(self, name: str) -> Path:
        return self.out / SHARDS / f"{name}.parquet"

    def record(self, plan: ShardPlan, data: bytes) -> None:
        """Write a finished shard atomically, then enter it (with its sha256) in the manifest."""
        path = self.shard_path(plan.name)
        with atomic.atomic_path(path) as tmp:
            tmp.write_bytes(data)
        self.shards[plan.name] = plan.entry(hashlib.sha256(data).hexdigest())
        self.write()

    def write(self) -> None:
        atomic.write_json(self.path, {**self.setup, "shards": self.shards})


def read_run(out: str | Path) -> tuple[dict, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """A finished run: (its manifest, pose columns [W] and output name -> stacked outputs [W, ...])
    over every shard in drive and window order; outputs whose shapes vary (detections) come back
    as object arrays of per-window arrays."""
    out = Path(out)
    try:
        manifest = json.loads((out / MANIFEST).read_text())
    except (OSError, ValueError):
        raise InputError(f"{out}: no readable {MANIFEST}; expected the --out directory of `radaredge run`") from None
    names = sorted(manifest.get("shards", {}), key=lambda n: (manifest["shards"][n]["drive"],
                                                              manifest["shards"][n]["first"]))
    if not names:
        raise InputError(f"{out}: the run has no finished shards")
    poses, outputs = {c: [] for c in POSE_COLUMNS}, {}
    for name in names:
        path = out / SHARDS / f"{name}.parquet"
        if not path.is_file() or file_sha256(path) != manifest["shards"][name]["sha256"]:
            raise InputError(f"{path}: missing, or its sha256 differs from {out / MANIFEST}; run again to recompute it")
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
