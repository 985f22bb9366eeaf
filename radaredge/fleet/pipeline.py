"""``radaredge run``: one exported graph over every window of every drive under a root, on Ray Data.

The pipeline: the driver plans shards (consecutive windows of one drive, :class:`ShardPlan`)
and skips those a previous run finished (:class:`Manifest`, checked by sha256); Ray Data maps
the rest over an actor pool of torch-free runtime sessions (:class:`ShardWorker`, each loading
the graph once, on ``threads`` threads, and reading its drives' scans itself), and streams each
finished shard's Parquet bytes back to the driver, which writes it atomically and enters it in
the manifest. Ray runs embedded (a local instance sized to the machine) unless ``ray_address``
(or ``RAY_ADDRESS``) names a cluster. :func:`run_sequential` computes the same shards in one
process without Ray: the yardstick the Ray output equals bit for bit, and the plain loop whose
throughput Ray's overhead is measured against.

A window is what ``radaredge eval`` feeds the graph: K consecutive scans of a drive (K = the
graph's frame count; 1 for a single-scan detector), their timestamps relative to the oldest,
and the pose of its last frame.
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .. import runtime
from ..data.readers import infer_format
from ..data.sequences import drive_directories, is_drive, load_sequence, name_the_scan, windows
from ..errors import ConfigError, InputError, RadarEdgeError
from ..runtime.backends import check_backend
from ..data.run_shards import Manifest, ShardPlan, encode_shard

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
        drive_directories(data)              # its error: no drives found, and what a drive is
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


def plan_shards(data: str | Path, k: int, shard_windows: int = DEFAULT_SHARD_WINDOWS,
                fmt: str | None = None) -> list[ShardPlan]:
    """The shards of every drive under ``data`` (:func:`find_drives`): its K-frame windows in
    order, ``shard_windows`` a shard; ``fmt`` the scan format of every drive (default: inferred
    per drive, :func:`drive_format`). InputError naming a drive without scans or with fewer scans
    than K."""
    plans = []
    for label, d in find_drives(data):
        drive_fmt = drive_format(d, fmt)
        seq = load_sequence(d, drive_fmt or None)
        if len(seq) == 0:
            raise InputError(f"{d}: the drive has no scans")
        n = len(windows(seq, k))
        if n == 0:
            raise InputError(f"{d}: {len(seq)} scans, fewer than the graph's window of {k}")
        stem = label.replace("/", "__")
        for i, first in enumerate(range(0, n, shard_windows)):
            plans.append(ShardPlan(f"{stem}-{i:05d}", label, str(d.resolve()), first, min(shard_windows, n - first),
                                   drive_fmt))
    return plans


class ShardWorker:
    """One loaded graph that computes whole shards: what a Ray actor holds, and what the
    sequential run uses directly."""

    bound: tuple = ()       # (graph, threads, backend) of a subclass made for Ray (:func:`_ray_results`)

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
            rows.append({"drive": plan.drive, "frame": last, "timestamp": float(seq.timestamps[last]),
                         "northing": float(seq.positions[last, 0]), "easting": float(seq.positions[last, 1])})
        return rows, outs

    def __call__(self, row: dict) -> dict:
        """Ray Data's row function: a planned shard in, its Parquet bytes (or the error) out."""
        plan = ShardPlan(**{k: (int(row[k]) if k in ("first", "count") else str(row[k]))
                            for k in ("name", "drive", "path", "first", "count", "fmt")})
        try:
            return {"name": plan.name, "parquet": encode_shard(*self.outputs(plan)), "error": ""}
        except RadarEdgeError as exc:
            return {"name": plan.name, "parquet": b"", "error": str(exc)}
        except OSError as exc:         # a scan file that vanished or cannot be read on this node
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

    @property
    def windows_per_second(self) -> float:
        return self.computed_windows / self.seconds if self.seconds > 0 else 0.0

    def to_dict(self) -> dict:
        return {**self.__dict__, "windows_per_second": self.windows_per_second}

    def lines(self) -> list[str]:
        reused = self.shards - self.computed_shards
        return [f"{self.out}: {self.windows} windows in {self.shards} shards ({reused} already finished)",
                f"computed {self.computed_windows} windows in {self.seconds:.1f} s on {self.workers} "
                f"{self.engine} worker(s): {self.windows_per_second:.1f} windows/s"]


def _setup(graph: Path, data: Path, shard_windows: int) -> tuple[dict, int]:
    model = runtime.load(graph, threads=1)
    return {"graph_weights_sha256": model.weights_sha256, "model": model.card.name, "data": str(data.resolve()),
            "window_frames": model.frames, "shard_windows": shard_windows}, model.frames


def _prepare(graph, data, out, shard_windows, fmt=None):
    graph, data, out = Path(graph), Path(data), Path(out)
    if shard_windows is None:                 # a resumed run keeps its shards; a new one takes the default
        shard_windows = Manifest.recorded(out, "shard_windows") or DEFAULT_SHARD_WINDOWS
    if isinstance(shard_windows, bool) or not isinstance(shard_windows, int) or shard_windows < 1:
        raise ConfigError(f"shard_windows must be a positive integer, got {shard_windows!r}")
    setup, k = _setup(graph, data, shard_windows)
    plans = plan_shards(data, k, shard_windows, fmt)
    manifest = Manifest(out, setup)
    pending = [p for p in plans if not manifest.finished(p)]
    return plans, manifest, pending


def run_sequential(graph: str | Path, data: str | Path, out: str | Path, *, threads: int = 1,
                   backend: str = "onnxruntime", shard_windows: int | None = None, fmt: str | None = None,
                   progress: Callable | None = None) -> RunReport:
    """:func:`run_graph`'s shards computed in this process, one after the other (no Ray)."""
    plans, manifest, pending = _prepare(graph, data, out, shard_windows, fmt)
    start = time.perf_counter()
    if pending:
        worker = ShardWorker(str(graph), threads, backend)
        for plan in pending:
            manifest.record(plan, encode_shard(*worker.outputs(plan)))
            if progress:
                progress(plan.count)
    manifest.write()
    return RunReport(str(out), len(plans), sum(p.count for p in plans), len(pending), sum(p.count for p in pending),
                     1, time.perf_counter() - start, "sequential")


def start_ray(address: str | None = None):
    """The ray module, connected: to the cluster at ``address`` (or ``RAY_ADDRESS``), else to an
    embedded local instance with this machine's CPUs (reused when one is running)."""
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
            ray.init(num_cpus=os.cpu_count() or 1, include_dashboard=False, logging_level=logging.ERROR,
                     log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise ConfigError(f"--ray-address {address}: cannot connect to a Ray cluster there "
                          f"({str(exc).splitlines()[0][:160]})" if address else
                          f"cannot start an embedded Ray instance ({str(exc).splitlines()[0][:160]})") from None
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
        raise ConfigError(f"--ray-address {address}: cannot connect to a Ray cluster there "
                          f"({getattr(exc, 'strerror', None) or exc})") from None


def _ray_results(ray, graph: str, pending: list[ShardPlan], workers: int, threads: int,
                 backend: str) -> Iterator[dict]:
    items = [{"name": p.name, "drive": p.drive, "path": p.path, "first": p.first, "count": p.count, "fmt": p.fmt}
             for p in pending]
    ds = ray.data.from_items(items, override_num_blocks=len(items))
    # the settings travel in the class, not as constructor arguments in Ray's object store (whose
    # loss would stop a restarted actor from being built)
    bound = type("BoundShardWorker", (ShardWorker,), {"bound": (graph, threads, backend)})
    ds = ds.map(bound, compute=ray.data.ActorPoolStrategy(size=workers), num_cpus=threads)
    _quiet_ray_loggers()
    yield from ds.iter_rows()


def run_graph(graph: str | Path, data: str | Path, out: str | Path, *, workers: int | None = None,
              threads: int = 1, backend: str = "onnxruntime", ray_address: str | None = None,
              shard_windows: int | None = None, fmt: str | None = None,
              progress: Callable | None = None) -> RunReport:
    """Run the exported single-graph model ``graph`` over every window of every drive under
    ``data`` on Ray Data and write Parquet shards of its outputs, with each window's drive,
    frame, timestamp and pose, to ``out`` (layout in :mod:`radaredge.data.run_shards`).

    ``workers`` actors (default: the cluster's CPUs / ``threads``), each a runtime session on
    ``threads`` threads with ``backend``; ``shard_windows`` windows a shard (default
    :data:`DEFAULT_SHARD_WINDOWS`, or what the run in ``out`` used). A run interrupted or with a
    worker killed resumes: the shards already finished (their sha256 as recorded) are kept, the
    rest computed. ``fmt`` is the scan format of every drive (default: inferred per drive).
    ``progress`` is called with each finished shard's window count."""
    check_backend(backend)
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"threads must be a positive integer, got {threads!r}")
    plans, manifest, pending = _prepare(graph, data, out, shard_windows, fmt)
    start = time.perf_counter()
    used = 0
    with warnings.catch_warnings():
        # Ray Data's own deprecation notices about its settings are not the user's to act on
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"ray(\.|$)")
        if pending:
            used, start = _run_on_ray(graph, pending, manifest, workers, threads, backend, ray_address, progress)
    manifest.write()
    return RunReport(str(out), len(plans), sum(p.count for p in plans), len(pending), sum(p.count for p in pending),
                     used, time.perf_counter() - start, "ray")


def _run_on_ray(graph, pending: list[ShardPlan], manifest: Manifest, workers, threads: int, backend: str,
                ray_address, progress) -> tuple[int, float]:
    """Compute the ``pending`` shards on Ray and record each: (the workers used, when Ray was up)."""
    ray = start_ray(ray_address)
    start = time.perf_counter()                # the timing starts at a running Ray (its start is once per process)
    cpus = int(ray.cluster_resources().get("CPU", 1))
    used = workers if workers is not None else max(1, cpus // threads)
    if isinstance(used, bool) or not isinstance(used, int) or used < 1:
        raise ConfigError(f"workers must be a positive integer, got {workers!r}")
    used = min(used, len(pending))
    by_name = {p.name: p for p in pending}
    for result in _ray_results(ray, str(Path(graph).resolve()), pending, used, threads, backend):
        if result["error"]:
            raise InputError(result["error"])
        plan = by_name[result["name"]]
        manifest.record(plan, bytes(result["parquet"]))
        if progress:
            progress(plan.count)
    return used, start
