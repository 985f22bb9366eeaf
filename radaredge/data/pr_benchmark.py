"""A synthetic place-recognition benchmark: one town driven on several days.

The town is one static world (``SceneConfig.world_seed`` = the benchmark ``seed``) along a
flat street that bends gently (``SceneConfig.road_curvature``, a radius of 80-150 m, drawn from
``seed``): facades, poles, parked cars, vegetation and road clutter, the same on every day. Each
drive is another day (its own ``SceneConfig.seed``) through that street, from
the same start, with its own ego speed, lateral velocity (a small heading offset of the radar,
at most ``SceneConfig.ego_lateral_max``), traffic, share of points on moving objects and
measurement noise. On the query days a fraction ``parked_change`` of the parked cars is gone or
shifted along its axis (``SceneConfig.parked_change``); the database day shows the town's
canonical parking.

Drive 0 is the database and drives at the top of the speed range, so the query drives (slower
or as fast, over the same number of frames) stay on the road it covers. Files, written with
:func:`radaredge.data.sequences.write_sequence` in the TransLoc4D ``.npy`` layout::

    out_dir/database/drive-00/{scans/000000.npy ..., gps.csv}
    out_dir/queries/drive-01/...
    out_dir/queries/drive-02/...

Scans are [N, 5] x, y, z (m, radar frame: x forward, y left, z up), v (radial velocity, m/s)
and intensity (the synthetic RCS, dBsm). gps.csv holds per scan the timestamp (s; drive d starts
d days, 86400 d s, after drive 0) and the radar's position in the world frame of
:mod:`radaredge.data.synthetic` as a local planar east-north frame: **easting = world x** (the
direction the street starts in, m) and **northing = world y** (m, to its left). The town of seed
``s`` lies ``s`` x 10 km east (easting + 10,000 s m), so the drives of several towns can share
one training directory (``radaredge train``) without two towns claiming the same place.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError
from .road_network import NetworkConfig, RoadNetwork, RouteDrive, frames_for
from .sequences import MAX_POSITION, write_sequence
from .synthetic import RadarScan, SceneConfig, generate_sequence

DATABASE_DIR = "database"
QUERIES_DIR = "queries"
DAY_S = 86400.0  # s between the starts of consecutive drives
DYNAMIC_FRACTION = (0.1, 0.3)  # range of the per-day share of points on moving objects
CURVE_RADIUS = (80.0, 150.0)  # m, range of the street's radius of curvature
TOWN_SPACING = 10_000.0  # m of easting between the towns of consecutive seeds
# The largest town seed whose drives stay within the +-MAX_POSITION m a gps.csv may hold (100 km to spare
# for the town itself): a larger one would write a benchmark its own reader refuses.
MAX_TOWN_SEED = int((MAX_POSITION - 100_000.0) // TOWN_SPACING)
LANE_OFFSET = 1.75  # m from a street's centreline to the centre of either lane
OPPOSITE = 0.25  # most of a query route's length driven against the database circuit
SECTION_M = (150.0, 400.0)  # m, length range of the sections of a query route


@dataclass(frozen=True)
class BenchmarkDrive:
    """One drive of the benchmark: its directory ``name``, ``role`` ("database" or "query"),
    ``start`` time (s), number of ``frames`` and the scene ``config`` that generates it."""

    name: str
    role: str
    start: float
    frames: int
    config: SceneConfig

    @property
    def subdir(self) -> str:
        """The drive's directory relative to the benchmark root, e.g. ``queries/drive-01``."""
        return f"{DATABASE_DIR if self.role == 'database' else QUERIES_DIR}/{self.name}"

    def scans(self) -> list[RadarScan]:
        """The drive's scans with their ground truth (poses, dynamic flags, boxes)."""
        return generate_sequence(self.frames, self.config)


def _check_options(drives: int, frames_per_drive: int, seed: int, speed: tuple[float, float]) -> None:
    for name, value, low in (("drives", drives, 2), ("frames_per_drive", frames_per_drive, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ConfigError(f"{name} must be an integer >= {low}, got {value!r}")
    _check_town_seeds(seed, 1)
    if len(speed) != 2 or not 0 < speed[0] <= speed[1]:
        raise ConfigError(f"speed must be (low, high) m/s with 0 < low <= high, got {speed!r}")


def plan_drives(
    drives: int = 3,
    frames_per_drive: int = 60,
    seed: int = 0,
    speed: tuple[float, float] = (7.0, 10.0),
    parked_change: float = 0.3,
) -> list[BenchmarkDrive]:
    """The benchmark's drives, without generating them: drive 0 (database) at ``speed[1]`` m/s
    with the canonical parking, drives 1.. (queries) at speeds uniform in ``speed`` m/s with
    ``parked_change`` of the parked cars changed. The street's curvature, and for every day its
    scene seed and share of moving-object points (in ``DYNAMIC_FRACTION``), are drawn from ``seed``."""
    _check_options(drives, frames_per_drive, seed, speed)
    rng = np.random.default_rng(seed)
    curvature = rng.choice([-1.0, 1.0]) / rng.uniform(*CURVE_RADIUS)
    day_seeds = rng.integers(0, 2**31, drives)
    plan = []
    for d in range(drives):
        v = speed[1] if d == 0 else rng.uniform(*speed)
        config = SceneConfig(
            seed=int(day_seeds[d]),
            world_seed=seed,
            road_curvature=curvature,
            ego_vertical_max=0.0,
            ego_speed_min=v,
            ego_speed_max=v,
            dynamic_fraction=rng.uniform(*DYNAMIC_FRACTION),
            parked_change=0.0 if d == 0 else parked_change,
        )
        plan.append(
            BenchmarkDrive(f"drive-{d:02d}", "database" if d == 0 else "query", DAY_S * d, frames_per_drive, config)
        )
    return plan


def drive_track(scans: list[RadarScan], start: float, easting_offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps [T] s = ``start`` + scan time, positions [T, 2] (northing = world y, easting =
    world x + ``easting_offset``) m of the radar) of a generated drive."""
    xy = np.array([scan.pose[:2, 3] for scan in scans])
    return start + np.array([scan.timestamp for scan in scans]), xy[:, ::-1] + np.array([0.0, easting_offset])


def make_pr_benchmark(
    out_dir: str | os.PathLike,
    drives: int = 3,
    frames_per_drive: int = 60,
    seed: int = 0,
    speed: tuple[float, float] = (7.0, 10.0),
    parked_change: float = 0.3,
    progress=None,
) -> list[BenchmarkDrive]:
    """Generate the drives of :func:`plan_drives` and write them under ``out_dir`` (layout in
    the module docstring). ``progress`` optionally wraps the iteration over drives (a progress
    bar). Returns the plan; drive ``d`` is in ``out_dir / d.subdir``."""
    plan = plan_drives(drives, frames_per_drive, seed, speed, parked_change)
    for drive in (progress or iter)(plan):
        scans = drive.scans()
        timestamps, positions = drive_track(scans, drive.start, TOWN_SPACING * seed)
        write_sequence(Path(out_dir) / drive.subdir, [scan.points for scan in scans], timestamps, positions)
    return plan


def _check_town_seeds(seed: int, towns: int) -> None:
    """ConfigError when a town of seed ``seed`` .. ``seed + towns - 1`` would lie beyond the
    positions a gps.csv may hold (the town of seed s lies s x 10 km east)."""
    if seed + towns - 1 > MAX_TOWN_SEED:
        raise ConfigError(
            f"seed {seed}" + (f" with {towns} towns" if towns > 1 else "") + f": the town of seed s lies "
            f"s x {TOWN_SPACING / 1000:g} km east, and gps.csv holds positions within "
            f"{MAX_POSITION:g} m; use seeds up to {MAX_TOWN_SEED}"
        )


def make_pr_towns(
    out_dir: str | os.PathLike, towns: int, seed: int, make_town: Callable[[Path, int], list]
) -> dict[str, list]:
    """``towns`` benchmarks of consecutive seeds ``seed``, ``seed + 1``, ... in ``out_dir/town-<seed>``,
    each written by ``make_town(directory, seed)`` (:func:`make_pr_benchmark` or
    :func:`make_route_benchmark` with their other arguments bound); one training directory for
    ``radaredge train``, as the towns lie 10 km apart. Returns {town directory name: its plan}."""
    if isinstance(towns, bool) or not isinstance(towns, (int, np.integer)) or towns < 1:
        raise ConfigError(f"towns must be an integer >= 1, got {towns!r}")
    _check_town_seeds(seed, towns)
    return {f"town-{s}": make_town(Path(out_dir) / f"town-{s}", s) for s in range(seed, seed + int(towns))}


# ----------------------------------------------------------------------------- the street network


@dataclass(frozen=True)
class RouteBenchmarkDrive:
    """One day of a street-network benchmark (:mod:`.road_network`): its directory ``name``,
    ``role``, ``start`` time (s), the :class:`~.road_network.RouteDrive` that generates it and the
    share of its route driven against the database circuit (``against``, 0 to 1)."""

    name: str
    role: str
    start: float
    drive: RouteDrive
    against: float = 0.0

    @property
    def subdir(self) -> str:
        return f"{DATABASE_DIR if self.role == 'database' else QUERIES_DIR}/{self.name}"

    @property
    def frames(self) -> int:
        return self.drive.frames

    @property
    def config(self) -> SceneConfig:
        return self.drive.config


def against_circuit(town: RoadNetwork, circuit: list[int], route: list[int]) -> float:
    """Metres of ``route`` driven on streets of ``circuit`` against its direction only."""
    steps = RoadNetwork.steps(circuit)
    return sum(
        float(np.linalg.norm(town.nodes[b] - town.nodes[a]))
        for a, b in zip(route[:-1], route[1:])
        if (b, a) in steps and (a, b) not in steps
    )


def _query_route(
    town: RoadNetwork, circuit: list[int], length: float, rng: np.random.Generator, opposite: float
) -> list[int]:
    """A query day's route of at least ``length`` m: sections of 150-400 m of the database's
    closed ``circuit`` (junctions), the first from a junction drawn at random, each next one
    from the junction of the circuit with the shortest join, a route there that never turns
    back (:meth:`RoadNetwork.shortest_route`, where driving against the circuit or off it counts
    three times its length). A section runs against the circuit with chance 1/2 where the
    route's length driven against the circuit so far plus the section's stays within the share
    ``opposite`` of ``length``; joins may add to that (:func:`against_circuit` measures it)."""
    loop, along_circuit = circuit[:-1], RoadNetwork.steps(circuit)
    route = [loop[int(rng.integers(len(loop)))]]
    while town.route_length(route) < length:
        want, budget = rng.uniform(*SECTION_M), opposite * length - against_circuit(town, circuit, route)
        best, joined = math.inf, None
        for step in (-1, 1) if rng.random() < 0.5 else (1,):
            for i in rng.permutation(len(loop)):
                section = [loop[i]]
                while town.route_length(section) < want:
                    section.append(loop[(i + step * len(section)) % len(loop)])
                if step < 0 and town.route_length(section) > budget:
                    continue
                join = town.shortest_route(
                    route[-1],
                    section[0],
                    came_from=route[-2] if len(route) > 1 else None,
                    then=section[1],
                    prefer=along_circuit,
                )
                if join is not None and town.route_length(join) < best:
                    joined, best = route + join[1:] + section[1:], town.route_length(join)
            if joined is not None:
                break
        if joined is None:
            raise ConfigError("no query route without a U-turn found on this town's circuit; use another seed")
        route = joined
    return route


def plan_route_drives(
    days: int = 3,
    route_m: float = 2200.0,
    seed: int = 0,
    speed: tuple[float, float] = (7.0, 10.0),
    parked_change: float = 0.3,
    opposite: float = OPPOSITE,
    network: NetworkConfig = NetworkConfig(),
) -> tuple[RoadNetwork, list[RouteBenchmarkDrive]]:
    """The town of ``seed`` and its drives, without generating scans. Day 0 (the database) drives
    a circuit of at least ``route_m`` m through the town (:meth:`RoadNetwork.circuit`: back where it
    started) at ``speed[1]`` m/s in the right-hand lane, with the canonical parking. Days 1.. (queries) each
    drive a route
    of half that length made of sections of the database circuit, up to a share ``opposite``
    of them driven against the circuit (:func:`_query_route`), at speeds uniform in ``speed``; odd query days
    keep right, even ones drive the other lane. Each
    day has its own traffic, heading offset, transient clutter and share ``parked_change`` of the
    parked cars moved; every route starts at a junction drawn from ``seed``."""
    _check_options(days, 1, seed, speed)
    if not np.isfinite(route_m) or route_m < 200:
        raise ConfigError(f"route_m must be at least 200 m, got {route_m!r}")
    rng = np.random.default_rng([seed, 1])
    town = RoadNetwork.draw(seed, network)
    day_seeds = rng.integers(0, 2**31, days)
    plan, circuit = [], None
    for d in range(days):
        v = speed[1] if d == 0 else float(rng.uniform(*speed))
        route = town.circuit(rng, route_m) if d == 0 else _query_route(town, circuit, route_m / 2, rng, opposite)
        circuit = circuit or route
        lane = LANE_OFFSET if d > 0 and d % 2 == 0 else -LANE_OFFSET
        config = SceneConfig(
            seed=int(day_seeds[d]),
            world_seed=seed,
            ego_vertical_max=0.0,
            ego_speed_min=v,
            ego_speed_max=v,
            dynamic_fraction=float(rng.uniform(*DYNAMIC_FRACTION)),
            parked_change=0.0 if d == 0 else parked_change,
        )
        drive = RouteDrive(tuple(int(n) for n in route), lane, 1, config)
        drive = dataclasses.replace(drive, frames=frames_for(drive.path(town, network), v, config.frame_rate))
        against = against_circuit(town, circuit, route) / town.route_length(route)
        plan.append(RouteBenchmarkDrive(f"drive-{d:02d}", "database" if d == 0 else "query", DAY_S * d, drive, against))
    return town, plan


def make_route_benchmark(
    out_dir: str | os.PathLike,
    days: int = 3,
    route_m: float = 2200.0,
    seed: int = 0,
    speed: tuple[float, float] = (7.0, 10.0),
    parked_change: float = 0.3,
    network: NetworkConfig = NetworkConfig(),
    progress=None,
) -> list[RouteBenchmarkDrive]:
    """Generate the drives of :func:`plan_route_drives` and write them under ``out_dir`` in the
    layout of :func:`make_pr_benchmark` (database/drive-00, queries/drive-01, ...; the town of
    seed ``s`` lies ``s`` x 10 km east). Returns the plan."""
    town, plan = plan_route_drives(days, route_m, seed, speed, parked_change, network=network)
    for day in (progress or iter)(plan):
        scans = day.drive.scans(town, network)
        timestamps, positions = drive_track(scans, day.start, TOWN_SPACING * seed)
        write_sequence(Path(out_dir) / day.subdir, [scan.points for scan in scans], timestamps, positions)
    return plan
