"""A synthetic town of streets and junctions, and radar drives along routes through it.

The town (:class:`RoadNetwork`) is a grid of ``NetworkConfig.columns`` x ``rows`` junctions,
neighbours 120-180 m apart (drawn per grid line), each junction moved by up to ``jitter`` m,
joined by straight two-way streets. A share ``drop`` of the streets is left out where the rest
stays connected and no junction becomes a dead end, so blocks differ in size and some junctions
are T-junctions. Along every street stands the roadside of the one-street world of
:mod:`radaredge.data.synthetic` (facades, poles, guard rails, parked cars, vegetation, road
clutter) in 20 m segments, kept ``junction_clear`` m away from the junctions so crossing streets
stay open. The radar sees through buildings (the generator has no occlusion), so content of a
crossing street within range is visible before the turn.

A drive follows a route of junctions. A database circuit (:meth:`RoadNetwork.circuit`) walks
from junction to junction without turning back, preferring the streets it has driven least, so
a long route closes loops and passes junctions in every direction, and then returns to its
start by the shortest way; query routes are sections of it (:mod:`radaredge.data.pr_benchmark`).
The route's centreline is smoothed with a Gaussian of ``corner_sigma`` m (with the default
10 m, corners of about 9 m radius) and the radar drives a lane parallel to
it (:meth:`Path.offset`): x forward, at a constant speed, with the heading offset and traffic of
its day (:class:`radaredge.data.synthetic.SceneConfig`, ``seed``; the static world from
``world_seed``). Every day adds its own transient clutter (barriers and bins along the kerb,
skips and stalls on the sidewalk) to a share ``clutter`` of the segments, and moves or removes
``SceneConfig.parked_change`` of the parked cars.

World frame: x east, y north, z up, metres; the first junction of the grid is near the origin.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..config import card_ranges
from ..errors import ConfigError
from .synthetic import (
    _SEGMENT,
    RadarScan,
    SceneConfig,
    _Boxes,
    _build_segment,
    _clusters,
    _draw_ego,
    _draw_traffic,
    _Ego,
    _Reflectors,
    _rng,
    _RoadFrame,
    _Scene,
    _Surface,
    _surface_reflectors,
    _synthesize,
)

_STREAM_NETWORK, _STREAM_CLUTTER = 16, 17  # generator streams beyond synthetic's own
_STEP = 0.5  # m between the samples of a path
_KERB = (5.5, 7.4)  # |d| m of barriers and bins along the kerb
_SIDEWALK_OBJECTS = (9.6, 11.0)  # |d| m of skips and stalls


@card_ranges(
    columns=(2, 20),
    rows=(2, 20),
    spacing=(60.0, 500.0),
    jitter=(0.0, 40.0),
    drop=(0.0, 0.5),
    junction_clear=(0.0, 40.0),
    corner_sigma=(0.5, 20.0),
    clutter=(0.0, 1.0),
)
@dataclass(frozen=True)
class NetworkConfig:
    """The town's street grid and what changes from day to day (module docstring)."""

    columns: int = 5  # junctions west to east
    rows: int = 4  # junctions south to north
    spacing: tuple = (120.0, 180.0)  # m, range of the distance between neighbouring grid lines
    jitter: float = 10.0  # m, largest offset of a junction from its grid point (each axis)
    drop: float = 0.15  # share of the grid's streets left out (connected, no dead ends)
    junction_clear: float = 18.0  # m from a junction where a street's roadside starts
    corner_sigma: float = 10.0  # m, Gaussian smoothing of a route's centreline (corner radius ~9 m)
    clutter: float = 0.25  # chance per segment and day of transient clutter

    def __post_init__(self):
        if len(self.spacing) != 2 or not self.spacing[0] <= self.spacing[1]:
            raise ConfigError(f"NetworkConfig.spacing must be (low, high) m with low <= high, got {self.spacing!r}")
        if 2 * self.junction_clear + _SEGMENT > self.spacing[0] - 2 * self.jitter:
            raise ConfigError(
                f"NetworkConfig: streets as short as {self.spacing[0] - 2 * self.jitter:g} m "
                f"(spacing - 2 jitter) hold no {_SEGMENT:g} m roadside segment between two junction "
                f"clearances of {self.junction_clear:g} m"
            )


# ----------------------------------------------------------------------------- paths


class Path(_RoadFrame):
    """A planar path on the road surface (z = 0), parameterised by arc length ``s`` (m) from its
    first point: position, heading (rad, from the x axis, continuous) and curvature (1/m,
    positive turning left). Outside [0, ``length``] it goes on straight. Offers the road
    interface of :mod:`radaredge.data.synthetic` (``heading``, ``to_world``,
    ``to_world_direction``, ``velocity``, ``curvature_at``, ``grade``) with ``d`` (m) to the
    left of the path and ``h`` (m) above the road."""

    grade = 0.0

    def __init__(self, xy: np.ndarray):
        xy = np.asarray(xy, dtype=float)
        xy = xy[np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9]]
        if len(xy) < 2:
            raise ConfigError("a path needs at least two distinct points")
        s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
        n = max(int(math.ceil(s[-1] / _STEP)), 1)
        self.s = np.linspace(0.0, s[-1], n + 1)
        self.xy = np.column_stack([np.interp(self.s, s, xy[:, 0]), np.interp(self.s, s, xy[:, 1])])
        tangent = np.gradient(self.xy, self.s, axis=0)
        self._heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
        self._curvature = np.gradient(self._heading, self.s)

    @classmethod
    def through(cls, points: np.ndarray, corner_sigma: float) -> "Path":
        """The polyline through ``points`` [P, 2] (m) with its corners rounded: sampled every
        0.5 m and smoothed by a Gaussian of ``corner_sigma`` m; the ends stay in place (the
        polyline is extended beyond them by point reflection before smoothing)."""
        raw = cls(points)
        k = max(int(round(corner_sigma / _STEP)), 1)
        kernel = np.exp(-0.5 * (np.arange(-3 * k, 3 * k + 1) / k) ** 2)
        kernel /= kernel.sum()
        padded = np.pad(raw.xy, ((3 * k, 3 * k), (0, 0)), mode="reflect", reflect_type="odd")
        return cls(np.column_stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(2)]))

    def offset(self, d: float) -> "Path":
        """The parallel path ``d`` m to the left (negative: to the right)."""
        return Path(self.xy + d * np.column_stack([-np.sin(self._heading), np.cos(self._heading)]))

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def curvature_at(self, s) -> np.ndarray:
        """Curvature (1/m) at arc length ``s``; 0 beyond the ends."""
        s = np.asarray(s, dtype=float)
        return np.where((s < 0) | (s > self.length), 0.0, np.interp(s, self.s, self._curvature))

    def heading(self, s) -> np.ndarray:
        """World yaw (rad) of the path at arc length ``s`` (m)."""
        return np.interp(np.asarray(s, dtype=float), self.s, self._heading)

    def _point(self, s) -> np.ndarray:
        s = np.asarray(s, dtype=float)
        clamped = np.clip(s, 0.0, self.length)
        beyond = s - clamped
        theta = self.heading(clamped)
        return np.stack(
            [
                np.interp(clamped, self.s, self.xy[:, 0]) + beyond * np.cos(theta),
                np.interp(clamped, self.s, self.xy[:, 1]) + beyond * np.sin(theta),
            ],
            axis=-1,
        )

    def to_world(self, s, d, h) -> np.ndarray:
        """World points [..., 3] (m) of path coordinates (s, d, h), broadcast together."""
        s, d, h = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (s, d, h)))
        theta = self.heading(s)
        xy = self._point(s)
        return np.stack([xy[..., 0] - d * np.sin(theta), xy[..., 1] + d * np.cos(theta), h], axis=-1)


# ----------------------------------------------------------------------------- the street grid


def _connected(n_nodes: int, streets: np.ndarray) -> bool:
    adjacency = [[] for _ in range(n_nodes)]
    for a, b in streets:
        adjacency[a].append(b)
        adjacency[b].append(a)
    seen, todo = {0}, deque([0])
    while todo:
        for b in adjacency[todo.popleft()]:
            if b not in seen:
                seen.add(b)
                todo.append(b)
    return len(seen) == n_nodes


@dataclass(frozen=True)
class RoadNetwork:
    """Junctions ``nodes`` [J, 2] (world x, y m) joined by straight two-way ``streets`` [E, 2]
    (junction rows, lower first)."""

    nodes: np.ndarray
    streets: np.ndarray

    @classmethod
    def draw(cls, seed: int, config: NetworkConfig = NetworkConfig()) -> "RoadNetwork":
        """The town of ``seed`` (module docstring)."""
        rng = _rng(seed, _STREAM_NETWORK)
        xs = np.r_[0.0, np.cumsum(rng.uniform(*config.spacing, config.columns - 1))]
        ys = np.r_[0.0, np.cumsum(rng.uniform(*config.spacing, config.rows - 1))]
        grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
        nodes = grid + rng.uniform(-config.jitter, config.jitter, grid.shape)
        index = np.arange(config.columns * config.rows).reshape(config.columns, config.rows)
        streets = np.concatenate(
            [
                np.stack([index[:-1].ravel(), index[1:].ravel()], 1),
                np.stack([index[:, :-1].ravel(), index[:, 1:].ravel()], 1),
            ]
        )
        keep = np.ones(len(streets), dtype=bool)
        degree = np.bincount(streets.ravel(), minlength=len(nodes))
        for e in rng.permutation(len(streets))[: round(config.drop * len(streets))]:
            a, b = streets[e]
            keep[e] = False
            if min(degree[a], degree[b]) <= 2 or not _connected(len(nodes), streets[keep]):
                keep[e] = True
            else:
                degree[[a, b]] -= 1
        return cls(nodes, streets[keep])

    def street_length(self, e: int) -> float:
        a, b = self.streets[e]
        return float(np.linalg.norm(self.nodes[b] - self.nodes[a]))

    def street_path(self, e: int) -> Path:
        """Street ``e`` as a path from its lower junction to its higher one."""
        return Path(self.nodes[self.streets[e]])

    def route_length(self, route) -> float:
        """Length (m) of a route of junctions."""
        return float(np.linalg.norm(np.diff(self.nodes[list(route)], axis=0), axis=1).sum())

    def walk(self, rng: np.random.Generator, length: float) -> list[int]:
        """A route of at least ``length`` m as the junctions it passes: from a junction drawn at
        random, at each junction onto a street other than the one it came by, the least driven
        first (ties drawn at random)."""
        links: list[list[tuple[int, int]]] = [[] for _ in range(len(self.nodes))]
        for e, (a, b) in enumerate(self.streets):
            links[a].append((int(b), e))
            links[b].append((int(a), e))
        route, driven, came_by, total = [int(rng.choice(len(self.nodes)))], np.zeros(len(self.streets)), -1, 0.0
        while total < length:
            options = [(b, e) for b, e in links[route[-1]] if e != came_by] or links[route[-1]]
            least = min(driven[e] for _, e in options)
            b, e = options[int(rng.choice([i for i, (_, e) in enumerate(options) if driven[e] == least]))]
            driven[e] += 1
            total += self.street_length(e)
            route.append(b)
            came_by = e
        return route

    def shortest_route(
        self,
        start: int,
        goal: int,
        came_from: int | None = None,
        then: int | None = None,
        prefer: set[tuple[int, int]] | None = None,
    ) -> list[int] | None:
        """The junctions of the shortest route (street length) from ``start`` to ``goal`` that
        never turns back: not to ``came_from`` first (the junction before ``start``), not back
        along a street just driven, and not arriving from ``then`` (the junction after
        ``goal``). With ``prefer`` ((from, to) junction steps), other steps count three times
        their length. None if there is no such route."""
        links = [[] for _ in range(len(self.nodes))]
        for e, (a, b) in enumerate(self.streets):
            links[a].append((int(b), self.street_length(e)))
            links[b].append((int(a), self.street_length(e)))
        first = (start, -1 if came_from is None else came_from)
        best, previous, todo = {first: 0.0}, {}, [(0.0, first)]
        while todo:
            cost, state = heapq.heappop(todo)
            here, before = state
            if here == goal and (then is None or before != then) and (state != first or then != came_from):
                route = [here]
                while state != first:
                    state = previous[state]
                    route.append(state[0])
                return route[::-1]
            if cost > best[state]:
                continue
            for b, metres in links[here]:
                nxt = (b, here)
                metres *= 1.0 if prefer is None or (here, b) in prefer else 3.0
                if b != before and cost + metres < best.get(nxt, math.inf):
                    best[nxt], previous[nxt] = cost + metres, state
                    heapq.heappush(todo, (cost + metres, nxt))
        return None

    def circuit(self, rng: np.random.Generator, length: float) -> list[int]:
        """A closed route: a :meth:`walk` of ``length`` m, then the shortest way back to its start."""
        route = self.walk(rng, length)
        back = self.shortest_route(route[-1], route[0], came_from=route[-2], then=route[1])
        return route + back[1:]

    @staticmethod
    def steps(route: list[int]) -> set[tuple[int, int]]:
        """The (from, to) junction pairs a route drives."""
        return {(int(a), int(b)) for a, b in zip(route[:-1], route[1:])}


# ----------------------------------------------------------------------------- the static world


def _day_clutter(rng: np.random.Generator, config: SceneConfig, road: Path, s0: float) -> _Reflectors:
    """One day's transient clutter on the segment [``s0``, ``s0`` + 20) m of street ``road``:
    one to three barriers or rows of bins along a kerb, or skips and stalls on a sidewalk."""
    parts = []
    for _ in range(int(rng.integers(1, 4))):
        side, s = float(rng.choice([-1.0, 1.0])), s0 + rng.uniform(0, _SEGMENT - 6.0)
        if rng.random() < 0.5:
            along = np.arange(s, s + rng.uniform(2.0, 6.0), 0.3)
            surface = _Surface(
                along,
                np.full(along.size, side * rng.uniform(*_KERB)),
                rng.uniform(0.5, 1.0) + rng.uniform(-0.05, 0.05, along.size),
                -side,
                "guard_rail",
            )
        else:
            centre = np.array([[s, side * rng.uniform(*_SIDEWALK_OBJECTS), rng.uniform(0.5, 1.2)]])
            pts = _clusters(rng, centre, (0.3, 0.6), (20, 50))
            surface = _Surface(pts[:, 0], pts[:, 1], np.maximum(pts[:, 2], 0.1), 0.0, "pole")
        parts.append(_surface_reflectors(rng, config, road, surface))
    return _Reflectors.concat(parts, [0] * len(parts))


class NetworkWorld:
    """The static world of a town on one day, built lazily per street segment and cached:
    segment k of street e spans s in [s0, s0 + 20) m of :meth:`RoadNetwork.street_path`, its
    roadside from the town's stream (index 1000 e + k), parking changes and clutter from the day's."""

    def __init__(self, config: SceneConfig, network: RoadNetwork, net_config: NetworkConfig):
        self._config, self._network, self._net = config, network, net_config
        self._paths = [network.street_path(e) for e in range(len(network.streets))]
        self._segments: list[tuple[int, int, float]] = []
        for e, path in enumerate(self._paths):
            span = path.length - 2 * net_config.junction_clear
            count = int(span // _SEGMENT)
            first = net_config.junction_clear + (span - count * _SEGMENT) / 2
            self._segments += [(e, k, first + k * _SEGMENT) for k in range(count)]
        self._centres = np.array(
            [self._paths[e].to_world(s0 + _SEGMENT / 2, 0.0, 0.0)[:2] for e, _, s0 in self._segments]
        ).reshape(-1, 2)
        self._built: dict[int, tuple[_Reflectors, _Boxes]] = {}

    def _build(self, i: int) -> tuple[_Reflectors, _Boxes]:
        e, k, s0 = self._segments[i]
        reflectors, cars = _build_segment(self._config, self._paths[e], 1000 * e + k, s0)
        rng = _rng(self._config.seed, _STREAM_CLUTTER, 1000 * e + k)
        if rng.random() < self._net.clutter:
            reflectors = _Reflectors.concat([reflectors, _day_clutter(rng, self._config, self._paths[e], s0)], [0, 0])
        return reflectors, cars

    def visible(self, s_ego: float, position: np.ndarray) -> tuple[_Reflectors, _Boxes]:
        """Reflectors and parked cars of every segment whose centre lies within the radar's
        maximum range plus a segment of ``position`` (world m); ``s_ego`` is not needed."""
        near = np.flatnonzero(
            np.linalg.norm(self._centres - np.asarray(position)[:2], axis=1) <= self._config.max_range + _SEGMENT
        )
        for i in near:
            if i not in self._built:
                self._built[int(i)] = self._build(int(i))
        segments = [self._built[int(i)] for i in near]
        offsets = np.cumsum([0] + [len(cars) for _, cars in segments[:-1]])
        return (_Reflectors.concat([r for r, _ in segments], offsets), _Boxes.concat([cars for _, cars in segments]))


# ----------------------------------------------------------------------------- drives


@dataclass(frozen=True)
class RouteDrive:
    """One day's drive through a town: the junctions of its ``route``, its ``lane`` (m left of
    the centreline, negative = right of it), ``frames`` scans and the day's scene ``config``
    (speed ``ego_speed_max``; ``world_seed`` is the town's seed)."""

    route: tuple[int, ...]
    lane: float
    frames: int
    config: SceneConfig

    def path(self, network: RoadNetwork, net_config: NetworkConfig) -> Path:
        """The radar's path: the route's rounded centreline moved to the drive's lane."""
        return Path.through(network.nodes[list(self.route)], net_config.corner_sigma).offset(self.lane)

    def scans(self, network: RoadNetwork, net_config: NetworkConfig) -> list[RadarScan]:
        """The drive's scans with their ground truth (poses, dynamic flags, boxes)."""
        drawn = _draw_ego(self.config)
        ego = _Ego(self.path(network, net_config), drawn.speed, drawn.lateral, self.config.mount_height)
        scene = _Scene(self.config, ego, NetworkWorld(self.config, network, net_config), _draw_traffic(self.config))
        return [_synthesize(scene, k) for k in range(self.frames)]


def frames_for(path: Path, speed: float, frame_rate: float) -> int:
    """Scans of a drive at ``speed`` m/s and ``frame_rate`` Hz that stay on ``path``."""
    return max(int(path.length / speed * frame_rate), 1)
