"""The street-network town (radaredge.data.road_network), its route benchmark and what chance
scores on it (radaredge.eval.recall_stats)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import invoke, one_error_line

from radaredge.data.pr_benchmark import against_circuit, plan_route_drives
from radaredge.data.road_network import NetworkConfig, Path, RoadNetwork
from radaredge.errors import ConfigError
from radaredge.eval.baselines import polar_occupancy
from radaredge.eval.recall_stats import bootstrap_interval, chance_recall

SMALL = NetworkConfig(columns=3, rows=3)


def no_u_turn(route) -> bool:
    return all(a != c for a, c in zip(route[:-2], route[2:]))


def drive_positions(town, day, net=NetworkConfig()):
    """World x, y [T, 2] m of the radar at each scan of a planned day, from its path (no scans)."""
    path = day.drive.path(town, net)
    s = day.drive.config.ego_speed_max * np.arange(day.frames) / day.drive.config.frame_rate
    return path.to_world(s, 0.0, 0.0)[:, :2]


def test_a_path_rounds_corners_and_offsets_in_parallel():
    corner = Path.through(np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0]]), corner_sigma=10.0)
    assert corner.heading(0.0) == pytest.approx(0.0, abs=1e-6)
    assert corner.heading(corner.length) == pytest.approx(math.pi / 2, abs=1e-6)
    assert 6.0 < 1.0 / np.abs(corner.curvature_at(corner.s)).max() < 15.0  # metres of corner radius
    right_lane = corner.offset(-1.75)
    s = np.linspace(0, right_lane.length, 400)
    gap = [np.linalg.norm(corner.xy - p, axis=1).min() for p in right_lane.to_world(s, 0.0, 0.0)[:, :2]]
    np.testing.assert_allclose(gap, 1.75, atol=0.05)
    beyond = corner.to_world(corner.length + 10.0, 0.0, 0.5)  # goes on straight
    np.testing.assert_allclose(beyond, [100.0, 110.0, 0.5], atol=1e-6)


def test_the_town_is_connected_without_dead_ends_and_reproducible():
    town = RoadNetwork.draw(4)
    degree = np.bincount(town.streets.ravel(), minlength=len(town.nodes))
    assert degree.min() >= 2 and len(town.streets) < 31  # some of the 31 grid streets dropped
    lengths = [town.street_length(e) for e in range(len(town.streets))]
    assert 100.0 <= min(lengths) and max(lengths) <= 200.0
    again = RoadNetwork.draw(4)
    np.testing.assert_array_equal(town.nodes, again.nodes)
    np.testing.assert_array_equal(town.streets, again.streets)
    circuit = town.circuit(np.random.default_rng(0), 2000.0)
    assert circuit[0] == circuit[-1] and town.route_length(circuit) >= 2000.0
    assert no_u_turn(circuit + circuit[1:2])  # the seam too


def test_shortest_route_never_turns_back():
    town = RoadNetwork.draw(0, SMALL)
    a, b = (int(v) for v in town.streets[0])
    plain = town.shortest_route(a, b)
    assert plain == [a, b]
    around = town.shortest_route(a, b, came_from=b)  # may not go straight back to b
    assert around[0] == a and around[-1] == b and len(around) > 2 and no_u_turn([b] + around)
    assert town.shortest_route(a, b, then=a)[-2] != a


def test_route_benchmark_plan():
    """Defaults: a database circuit over 2 km, two query days on its streets, the second in the
    other lane, some driving against the database's direction, and chance Recall@1 under 1 %."""
    town, plan = plan_route_drives(seed=3)
    database, queries = plan[0], plan[1:]
    circuit = list(database.drive.route)
    assert database.role == "database" and [q.role for q in queries] == ["query", "query"]
    assert town.route_length(circuit) >= 2200.0 and database.frames >= 2000 and database.against == 0.0
    assert [d.drive.lane for d in plan] == [-1.75, -1.75, 1.75]
    assert all(no_u_turn(list(d.drive.route)) for d in plan)
    assert all(
        d.against == against_circuit(town, circuit, d.drive.route) / town.route_length(d.drive.route) for d in queries
    )
    assert sum(q.against for q in queries) > 0.0
    db_xy = drive_positions(town, database)
    for q in queries:
        xy = drive_positions(town, q)
        near = np.array([np.linalg.norm(db_xy - p, axis=1).min() for p in xy[::10]])
        assert (near <= 5.0).mean() > 0.8  # queries revisit the database
    chance = chance_recall(np.concatenate([drive_positions(town, q) for q in queries]), db_xy, 5.0)
    assert chance["recall"][1] < 1.0


def test_days_share_the_town_but_not_the_clutter():
    """Two days through the same town: the same static world in the same places (facades,
    parked cars) apart from the day's clutter and moved cars; other traffic."""
    town, plan = plan_route_drives(days=2, route_m=300.0, seed=2, network=SMALL)
    first, second = (dataclasses.replace(d.drive, frames=30) for d in plan)
    a, b = (d.scans(town, SMALL) for d in (first, second))
    assert len(a) == len(b) == 30
    xy = np.array([s.pose[:2, 3] for s in a])
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    np.testing.assert_allclose(step, first.config.ego_speed_max / first.config.frame_rate, rtol=0.02)
    yaw = np.unwrap([math.atan2(s.pose[1, 0], s.pose[0, 0]) for s in a])
    np.testing.assert_allclose(np.diff(yaw), [s.yaw_rate * 0.1 for s in a[:-1]], atol=0.02)
    static = [
        s.points[~s.dynamic & ~s.ghost, :3].astype(np.float64) @ s.pose[:3, :3].T + s.pose[:3, 3] for s in (a[5], b[5])
    ]
    shared = np.mean([np.linalg.norm(static[1][:, :2] - p[:2], axis=1).min() < 1.0 for p in static[0]])
    assert shared > 0.5


def test_chance_recall_and_bootstrap_have_known_answers():
    db = np.column_stack([np.zeros(10), np.arange(10.0)])  # 10 positions 1 m apart
    c = chance_recall(np.array([[0.0, 0.5]]), db, 0.6, ns=(1, 5))  # 2 within 0.6 m
    assert c["recall"][1] == pytest.approx(20.0)
    assert c["recall"][5] == pytest.approx(100.0 * (1 - math.comb(8, 5) / math.comb(10, 5)))
    assert c["database_within"] == 2.0 and c["skipped"] == 0
    assert bootstrap_interval(np.ones(50, dtype=bool)) == (100.0, 100.0)
    low, high = bootstrap_interval(np.arange(400) % 2 == 0)
    assert low < 50.0 < high and 7.0 < high - low < 12.0  # +-1.96 sqrt(0.25 / 400) = +-4.9 points


def test_make_benchmark_network_layout(tmp_path):
    res = invoke("make-benchmark", "--out", tmp_path / "b", "--layout", "network", "--route-km", 0.4, "--json")
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    assert [d["role"] for d in report["drives"]] == ["database", "query", "query"]
    assert report["layout"] == "network" and report["drives"][2]["lane_m"] == 1.75
    assert set(report["chance_recall"]["."]) == {"5", "25"}
    assert (tmp_path / "b" / "queries" / "drive-02" / "gps.csv").exists()


@pytest.mark.parametrize(
    "args, says",
    [
        (("--layout", "network", "--frames", 10), "--frames is for --layout street"),
        (("--route-km", 1.0), "--route-km is for --layout network"),
        (("--task", "detection", "--layout", "network"), "--layout is for --task places"),
        (("--task", "detection", "--towns", 2, "--route-km", 1.0), "--towns, --route-km are for --task places"),
    ],
)
def test_make_benchmark_layout_errors(tmp_path, args, says):
    one_error_line(invoke("make-benchmark", "--out", tmp_path / "b", *args), says)


def test_network_config_is_validated():
    with pytest.raises(ConfigError, match="junction clearances"):
        NetworkConfig(spacing=(60.0, 80.0))
    with pytest.raises(ConfigError, match="spacing"):
        NetworkConfig(spacing=(200.0, 100.0))


def test_polar_occupancy_bins_the_window_by_range_and_azimuth():
    ahead = np.array([[10.0, 0.1, 0.0], [10.5, 0.2, 1.0], [-5.0, -0.1, 0.0]], dtype=np.float32)  # x, y, z
    left = np.array([[-0.1, 40.0, 0.0], [100.0, 0.0, 0.0]], dtype=np.float32)  # 100 m: out of range
    d = polar_occupancy([ahead, left], rings=7, sectors=4, max_range=70.0).reshape(7, 4)
    expected = np.zeros((7, 4))
    expected[1, 2] = np.log1p(2)  # 10-20 m ring, sector [0, 90) deg
    expected[0, 0] = np.log1p(1)  # behind: sector [-180, -90) deg
    expected[4, 3] = np.log1p(1)  # 40 m to the left: [90, 180) deg
    np.testing.assert_allclose(d, expected / np.linalg.norm(expected), rtol=1e-6)
    np.testing.assert_array_equal(polar_occupancy([left[::-1], ahead[::-1]], rings=7, sectors=4), d.ravel())
    assert not polar_occupancy([np.zeros((0, 3), np.float32)]).any()
