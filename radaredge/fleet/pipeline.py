"""``radaredge run``: one exported graph over every window of every drive under a root, on Ray Data.

The pipeline: the driver plans shards (consecutive windows of one drive, :class:`ShardPlan`),
fingerprints each drive's scans (:func:`drive_fingerprint`) and checks the previous run against
the data as it is now (:class:`RunOutput`: shards of removed drives are dropped, of changed drives
recomputed, missing ones recomputed, unchanged ones kept when their sha256 is as recorded); Ray
Data maps the rest over an actor pool of torch-free runtime sessions (:class:`ShardWorker`, each
loading the graph once, on ``threads`` threads, and reading its drives' scans itself), and streams
each finished shard's Parquet bytes back to the driver, which stages it; when every shard is
finished the driver puts the run in place at once, so a run that fails leaves the previous one as
it was. Ray runs embedded (a local instance sized to the CPUs this process may use) unless
``ray_address`` (or ``RAY_ADDRESS``) names a cluster; threads and workers beyond the CPUs there are
cut down with a warning (a Ray actor that asks for more CPUs than a node has never starts).
:func:`run_sequential` computes the same shards in one process without Ray: the yardstick the
Ray output equals bit for bit, and the plain loop whose throughput Ray's overhead is measured
against.

A window is what ``radaredge eval`` feeds the graph: K consecutive scans of a drive (K = the
graph's frame count; 1 for a single-scan detector), their timestamps relative to the oldest,
and the pose of its last frame.
"""

from __future__ import annotations

import hashlib
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .. import runtime
from ..data.readers import infer_format
from ..data.run_shards import RunChanges, RunOutput, ShardPlan, encode_shard, recorded, shard_stem
from ..data.sequences import drive_directories, is_drive, load_sequence, name_the_scan, windows
from ..errors import ConfigError, InputError, RadarEdgeError
from ..runtime.backends import check_backend

DEFAULT_SHARD_WINDOWS = 256


def find_drives(data: str | Path) -> list[tuple[str, Path]]:
    """Every drive at or below ``data`` (a folder with ``scans/`` or ``pointclouds/``; nothing
    below a drive is searched), as (its path relative to ``data``, or the drive's name when
    ``data`` is one, and its path), sorted. InputError when there is none."""
    data = Path(data)
    if not data.is_dir() or is_drive(data):
        return [(d.name, d) for d in drive_directories(data)]
    found = []
    for here, dirs, _ in os.walk(data):
        here_path = Path(here)
        for name in sorted(dirs):
            if is_drive(here_path / name):
                found.append(((here_path / name).relative_to(data).as_posix(), here_path / name))
        dirs[:] = sorted(d for d in dirs if not is_drive(here_path / d))
    if not found:
        drive_directories(data)  # its error: no drives found, and what a drive is
    return sorted(found)


def drive_format(drive: Path, given: str | None = None) -> str:
    """The scan format of ``drive``: ``given``, else inferred from its ``scans/`` files (.npy:
    transloc; .bin: vod or tj4d by size and content); "" for the TransLoc4D ``pointclouds/`` layout."""
    if given:
        return given
    scans = drive / "scans"
    if not scans.is_dir():
        return ""
    files = [p for p in scans.iterdir() if p.is_file()]
    return infer_format(files) if files else "transloc"


def drive_fingerprint(seq, directory: Path) -> str:
    """A sha256 that changes when the drive's data does: its scan format, gps.csv's bytes, and each
    scan file's name, size and modification time (the test make and rsync use: reading every scan
    to hash it would double a run's reads)."""
    h = hashlib.sha256(f"{seq.fmt}\n".encode())
    h.update((Path(directory) / "gps.csv").read_bytes())
    for p in seq.scan_paths:
        st = os.stat(p)
        h.update(f"\n{Path(p).name}\0{st.st_size}\0{st.st_mtime_ns}".encode("utf-8", "surrogateescape"))
    return h.hexdigest()


def plan_run(
    data: str | Path, k: int, shard_windows: int = DEFAULT_SHARD_WINDOWS, fmt: str | None = None
) -> tuple[list[ShardPlan], dict[str, dict]]:
    """The shards of every drive under ``data`` (:func:`find_drives`): its K-frame windows in
    order, ``shard_windows`` a shard, named by :func:`radaredge.data.run_shards.shard_stem` (the
    drive's relative path and fingerprint); and each drive's record for the manifest (label ->
    fmt, fingerprint, scans, windows). ``fmt`` is the scan format of every drive (default:
    inferred per drive, :func:`drive_format`). InputError naming a drive without scans or with
    fewer scans than K, or whose gps.csv or scans cannot be read."""
    plans, drives = [], {}
    for label, d in find_drives(data):
        drive_fmt = drive_format(d, fmt)
        seq = load_sequence(d, drive_fmt or None)
        if len(seq) == 0:
            raise InputError(f"{d}: the drive has no scans")
        n = len(windows(seq, k))
        if n == 0:
            raise InputError(f"{d}: {len(seq)} scans, fewer than the graph's window of {k}")
        try:
            fingerprint = drive_fingerprint(seq, d)
        except OSError as exc:
            raise InputError(f"{exc.filename or d}: cannot be read ({exc.strerror or exc})") from None
        stem = shard_stem(label, fingerprint)
        drives[label] = {"fmt": drive_fmt, "fingerprint": fingerprint, "scans": len(seq), "windows": n}
        for i, first in enumerate(range(0, n, shard_windows)):
            plans.append(
                ShardPlan(f"{stem}-{i:05d}", label, str(d.resolve()), first, min(shard_windows, n - first), drive_fmt)
            )
    seen: dict[str, str] = {}
    for p in plans:  # 64 bits of sha256 apart: never expected to fire
        if seen.setdefault(p.name.lower(), p.drive) != p.drive:
            raise InputError(
                f"drives {seen[p.name.lower()]!r} and {p.drive!r} under {data} hash to one shard name "
                f"{p.name}; rename one of them"
            )
    return plans, drives


def plan_shards(
    data: str | Path, k: int, shard_windows: int = DEFAULT_SHARD_WINDOWS, fmt: str | None = None
) -> list[ShardPlan]:
    """The shards of :func:`plan_run`."""
    return plan_run(data, k, shard_windows, fmt)[0]


def available_cpus() -> int:
    """The CPUs this process may run on: its affinity mask where the OS has one (a container or
    ``taskset`` limit), else the machine's count."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _positive(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{name} must be a positive integer, got {value!r}")
    return value


def bound_threads(threads: int, cpus: int, where: str = "available to this process") -> int:
    """``threads`` (checked to be a positive integer), cut down to ``cpus`` with a warning: more
    threads than CPUs only contend, and a Ray actor asking for more CPUs than a node has never
    starts (the run would wait for it for ever)."""
    threads = _positive(threads, "threads")
    if threads > cpus:
        warnings.warn(f"--threads {threads}: more than the {cpus} CPU(s) {where}; using --threads {cpus}", stacklevel=2)
        return cpus
    return threads


class ShardWorker:
    """One loaded graph that computes whole shards: what a Ray actor holds, and what the
    sequential run uses directly."""

    bound: tuple = ()  # (graph, threads, backend) of a subclass made for Ray (:func:`_ray_results`)

    def __init__(self, graph: str | None = None, threads: int = 1, backend: str = "onnxruntime"):
        if graph is None:
            graph, threads, backend = self.bound
        self.model = runtime.load(graph, threads=threads, backend=backend)
        self._drives: dict[str, object] = {}

    def outputs(self, plan: ShardPlan) -> tuple[list[dict], list[dict[str, np.ndarray]]]:
        """(pose rows, graph outputs) of every window of ``plan``."""
        seq = self._drives.get(plan.path)
        if seq is None:
            seq = self._drives[plan.path] = load_sequence(plan.path, plan.fmt or None)
        k = self.model.frames
        rows, outs = [], []
        for w in range(plan.first, plan.first + plan.count):
            frames = np.arange(w, w + k)
            t = seq.timestamps[frames]
            try:
                outs.append(self.model.run([seq.scan(int(f), self.model.features) for f in frames], t - t[0]))
            except InputError as exc:
                raise InputError(name_the_scan(seq, frames, str(exc))) from None
            last = int(frames[-1])
            rows.append(
                {
                    "drive": plan.drive,
                    "frame": last,
                    "timestamp": float(seq.timestamps[last]),
                    "northing": float(seq.positions[last, 0]),
                    "easting": float(seq.positions[last, 1]),
                }
            )
        return rows, outs

    def __call__(self, row: dict) -> dict:
        """Ray Data's row function: a planned shard in, its Parquet bytes (or the error) out."""
        plan = ShardPlan(
            **{
                k: (int(row[k]) if k in ("first", "count") else str(row[k]))
                for k in ("name", "drive", "path", "first", "count", "fmt")
            }
        )
        try:
            return {"name": plan.name, "parquet": encode_shard(*self.outputs(plan)), "error": ""}
        except RadarEdgeError as exc:
            return {"name": plan.name, "parquet": b"", "error": str(exc)}
        except OSError as exc:  # a scan file that vanished or cannot be read on this node
            return {"name": plan.name, "parquet": b"", "error": f"{exc.filename or plan.path}: {exc.strerror or exc}"}


@dataclass
class RunReport:
    """What :func:`run_graph` did: shards and windows planned, computed now and found finished,
    the workers, the seconds and windows per second of the computed part (from a running Ray:
    actor start and graph loading included, starting Ray itself not)."""

    out: str
    shards: int
    windows: int
    computed_shards: int
    computed_windows: int
    workers: int
    seconds: float
    engine: str
    changes: dict = field(default_factory=dict)  # RunChanges.to_dict(): what differed from the previous run

    @property
    def windows_per_second(self) -> float:
        return self.computed_windows / self.seconds if self.seconds > 0 else 0.0

    def to_dict(self) -> dict:
        return {**self.__dict__, "windows_per_second": self.windows_per_second}

    def lines(self) -> list[str]:
        reused = self.shards - self.computed_shards
        return [
            f"{self.out}: {self.windows} windows in {self.shards} shards ({reused} already finished)",
            f"computed {self.computed_windows} windows in {self.seconds:.1f} s on {self.workers} "
            f"{self.engine} worker(s): {self.windows_per_second:.1f} windows/s",
            *RunChanges(**self.changes).lines(),
        ]


def _setup(graph: Path, data: Path, shard_windows: int) -> tuple[dict, int]:
    model = runtime.load(graph, threads=1)
    return {
        "graph_weights_sha256": model.weights_sha256,
        "model": model.card.name,
        "data": str(data.resolve()),
        "window_frames": model.frames,
        "shard_windows": shard_windows,
    }, model.frames


def _prepare(graph, data, out, shard_windows, fmt=None) -> tuple[list[ShardPlan], RunOutput]:
    graph, data, out = Path(graph), Path(data), Path(out)
    if shard_windows is None:  # a resumed run keeps its shards; a new one takes the default
        shard_windows = recorded(out, "shard_windows") or DEFAULT_SHARD_WINDOWS
    if isinstance(shard_windows, bool) or not isinstance(shard_windows, int) or shard_windows < 1:
        raise ConfigError(f"shard_windows must be a positive integer, got {shard_windows!r}")
    setup, k = _setup(graph, data, shard_windows)
    plans, drives = plan_run(data, k, shard_windows, fmt)
    return plans, RunOutput(out, setup, plans, drives)


def _report(out, plans, output: RunOutput, workers: int, seconds: float, engine: str) -> RunReport:
    pending = output.pending
    return RunReport(
        str(out),
        len(plans),
        sum(p.count for p in plans),
        len(pending),
        sum(p.count for p in pending),
        workers,
        seconds,
        engine,
        output.changes.to_dict(),
    )


def run_sequential(
    graph: str | Path,
    data: str | Path,
    out: str | Path,
    *,
    threads: int = 1,
    backend: str = "onnxruntime",
    shard_windows: int | None = None,
    fmt: str | None = None,
    progress: Callable | None = None,
) -> RunReport:
    """:func:`run_graph`'s shards computed in this process, one after the other (no Ray)."""
    threads = bound_threads(threads, available_cpus())
    plans, output = _prepare(graph, data, out, shard_windows, fmt)
    start = time.perf_counter()
    if output.pending:
        worker = ShardWorker(str(graph), threads, backend)
        for plan in output.pending:
            output.record(plan, encode_shard(*worker.outputs(plan)))
            if progress:
                progress(plan.count)
    output.commit()
    return _report(out, plans, output, 1, time.perf_counter() - start, "sequential")


def start_ray(address: str | None = None):
    """The ray module, connected: to the cluster at ``address`` (or ``RAY_ADDRESS``), else to an
    embedded local instance with the CPUs this process may use (:func:`available_cpus`; reused
    when one is running)."""
    # optional: ray is the scale extra
    import logging

    # Ray Data keeps the actor class in Ray's object store, and Ray's C++ core reports that as an
    # "E" line on stderr; only its fatal errors go there (the variable still takes the user's value)
    os.environ.setdefault("RAY_BACKEND_LOG_LEVEL", "fatal")
    import ray

    if ray.is_initialized():
        return ray
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        _reachable(address)
    try:
        if address:
            ray.init(address=address, logging_level=logging.ERROR, log_to_driver=False)
        else:
            ray.init(
                num_cpus=available_cpus(), include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False
            )
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise ConfigError(
            f"--ray-address {address}: cannot connect to a Ray cluster there ({str(exc).splitlines()[0][:160]})"
            if address
            else f"cannot start an embedded Ray instance ({str(exc).splitlines()[0][:160]})"
        ) from None
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    ctx.print_on_execution_start = False
    _quiet_ray_loggers()
    return ray


def _quiet_ray_loggers() -> None:
    """Ray and Ray Data configure their own loggers (at init and when Ray Data loads): only their
    errors reach stderr, where radaredge's own lines and its progress bar are."""
    import logging

    for name in [n for n in logging.root.manager.loggerDict if n == "ray" or n.startswith("ray.")]:
        logging.getLogger(name).setLevel(logging.ERROR)


def _reachable(address: str, timeout: float = 5.0) -> None:
    """ConfigError unless ``address`` (``host:port`` or ``ray://host:port``; ``auto`` is left to
    Ray) accepts a TCP connection within ``timeout`` s: Ray itself retries an unreachable address
    for minutes."""
    import socket

    hostport = address.split("://", 1)[-1]
    if address == "auto" or ":" not in hostport:
        return
    host, _, port = hostport.rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            pass
    except (OSError, ValueError) as exc:
        raise ConfigError(
            f"--ray-address {address}: cannot connect to a Ray cluster there ({getattr(exc, 'strerror', None) or exc})"
        ) from None


def _ray_results(ray, graph: str, pending: list[ShardPlan], workers: int, threads: int, backend: str) -> Iterator[dict]:
    items = [
        {"name": p.name, "drive": p.drive, "path": p.path, "first": p.first, "count": p.count, "fmt": p.fmt}
        for p in pending
    ]
    ds = ray.data.from_items(items, override_num_blocks=len(items))
    # the settings travel in the class, not as constructor arguments in Ray's object store (whose
    # loss would stop a restarted actor from being built)
    bound = type("BoundShardWorker", (ShardWorker,), {"bound": (graph, threads, backend)})
    ds = ds.map(bound, compute=ray.data.ActorPoolStrategy(size=workers), num_cpus=threads)
    _quiet_ray_loggers()
    yield from ds.iter_rows()


def run_graph(
    graph: str | Path,
    data: str | Path,
    out: str | Path,
    *,
    workers: int | None = None,
    threads: int = 1,
    backend: str = "onnxruntime",
    ray_address: str | None = None,
    shard_windows: int | None = None,
    fmt: str | None = None,
    progress: Callable | None = None,
) -> RunReport:
    """Run the exported single-graph model ``graph`` over every window of every drive under
    ``data`` on Ray Data and write Parquet shards of its outputs, with each window's drive,
    frame, timestamp and pose, to ``out`` (layout in :mod:`radaredge.data.run_shards`).

    ``workers`` actors (default: as many as the cluster's CPUs hold at ``threads`` each), each a
    runtime session on ``threads`` threads with ``backend``; more threads than a node's CPUs, or
    more workers than the CPUs hold, are cut down with a warning. ``shard_windows`` windows a shard
    (default :data:`DEFAULT_SHARD_WINDOWS`, or what the run in ``out`` used). The run is checked
    against the previous one in ``out`` and the data as it is now: shards of unchanged drives whose
    files have their recorded sha256 are kept, the rest (new or changed drives, missing shards, an
    interrupted run's) computed, removed drives' shards dropped (``RunReport.changes`` says which).
    Shards are staged until all are finished: a run that fails leaves ``out`` as it was.
    ``fmt`` is the scan format of every drive (default: inferred per drive). ``progress`` is
    called with each finished shard's window count."""
    check_backend(backend)
    _positive(threads, "threads")
    if workers is not None:
        _positive(workers, "workers")
    plans, output = _prepare(graph, data, out, shard_windows, fmt)
    start = time.perf_counter()
    used = 0
    with warnings.catch_warnings():
        # Ray Data's own deprecation notices about its settings are not the user's to act on
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"ray(\.|$)")
        if output.pending:
            used, start = _run_on_ray(graph, output, workers, threads, backend, ray_address, progress)
    output.commit()
    return _report(out, plans, output, used, time.perf_counter() - start, "ray")


def ray_node_cpus(ray) -> list[int]:
    """The CPUs of each live node of the running Ray instance (one entry when embedded)."""
    try:
        nodes = [int(n.get("Resources", {}).get("CPU", 0)) for n in ray.nodes() if n.get("Alive", True)]
    except Exception:  # an older or remote client without the node table
        nodes = []
    return [c for c in nodes if c > 0] or [max(1, int(ray.cluster_resources().get("CPU", 1)))]


def bound_workers(workers: int | None, threads: int, node_cpus: list[int]) -> int:
    """The actor count: ``workers`` (default: all that fit), cut down with a warning to the actors
    of ``threads`` CPUs each that the nodes' CPUs hold (an actor pool larger than that waits for
    ever for actors that cannot start)."""
    fit = max(1, sum(c // threads for c in node_cpus))
    if workers is None:
        return fit
    _positive(workers, "workers")
    if workers > fit:
        warnings.warn(
            f"--workers {workers}: more than the {fit} worker(s) of --threads {threads} that the "
            f"{sum(node_cpus)} CPU(s) {'of the Ray cluster' if len(node_cpus) > 1 else 'Ray has here'} "
            f"hold; using --workers {fit}",
            stacklevel=2,
        )
        return fit
    return workers


def _run_on_ray(
    graph, output: RunOutput, workers, threads: int, backend: str, ray_address, progress
) -> tuple[int, float]:
    """Compute the pending shards on Ray and stage each: (the workers used, when Ray was up)."""
    ray = start_ray(ray_address)
    start = time.perf_counter()  # the timing starts at a running Ray (its start is once per process)
    nodes = ray_node_cpus(ray)
    threads = bound_threads(threads, max(nodes), "a Ray node has" if len(nodes) > 1 else "Ray has here")
    used = min(bound_workers(workers, threads, nodes), len(output.pending))
    by_name = {p.name: p for p in output.pending}
    for result in _ray_results(ray, str(Path(graph).resolve()), output.pending, used, threads, backend):
        if result["error"]:
            raise InputError(result["error"])
        plan = by_name[result["name"]]
        output.record(plan, bytes(result["parquet"]))
        if progress:
            progress(plan.count)
    return used, start
