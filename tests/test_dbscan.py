"""DBSCAN + CQCA_cfa map: export formulation == sklearn (upstream) == plain reference; capacity; ONNX.

Clouds are float32 (x m, y m, v m/s). Distances are compared in float64 (``<= eps``, as sklearn's
KD-tree does); every generated cloud is checked to keep each pair's distance at least 1e-7 away
from eps, since a pair within rounding of eps may be decided either way by sklearn's tree bounds
or brute-force distances. Two dedicated tests cover eps itself: pairs at exactly eps in float64
are neighbours (sklearn's <=), and pairs within float32 rounding of eps follow sklearn's float64.
"""

import dataclasses

import numpy as np
import pytest
import torch

from radaredge.config import config_from_dict
from radaredge.errors import ConfigError, InputError
from radaredge.ops.dbscan import (
    TJ4D,
    VOD,
    DbscanConfig,
    cqca_cfa_map,
    cqca_cfa_map_reference,
    dbscan_labels,
    dbscan_labels_reference,
    dbscan_rounds,
)
from tests.references.sklearn_cqca_cfa import upstream_dbscan, upstream_map

# 64 x 64 cells of 0.16 m: x in [0.16, 10.4) and y in [-4.96, 5.28) land in the map, the first
# 0.16 m (index -1) wraps to the last column / row.
SMALL = DbscanConfig(eps=0.4, min_samples=5, capacity=512, map_rows=64, map_cols=64, resolution=0.16, y_offset=5.12)
TIE_MARGIN = 1e-7


# ----------------------------------------------------------------------------- helpers


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """The [M, M] ops here are small: one torch thread is faster, and two threads on a busy
    2-core machine ran this file 100x slower (OpenMP waiting). Restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def run_export(points, valid, cfg):
    """labels, core, map, cluster_points, converged of the export formulation (numpy)."""
    xyv, ok = torch.from_numpy(points), torch.from_numpy(valid)
    with torch.no_grad():
        labels, core, conv = dbscan_labels(xyv, ok, cfg)
        bev, cluster_points, conv_map = cqca_cfa_map(xyv, ok, cfg)
    assert bool(conv) == bool(conv_map)
    return labels.numpy(), core.numpy(), bev.numpy(), cluster_points.numpy(), bool(conv)


def run_upstream(points, valid, cfg):
    labels, core = upstream_dbscan(points, valid, cfg.eps, cfg.min_samples)
    bev, final = upstream_map(
        points,
        valid,
        cfg.eps,
        cfg.min_samples,
        cfg.map_rows,
        cfg.map_cols,
        cfg.resolution,
        cfg.y_offset,
        cfg.max_cluster_size,
    )
    return labels, core, bev, final != -1


def tie_gap(points, valid, eps):
    """Smallest | ||p_i - p_j|| - eps | over usable pairs (float64), inf for fewer than 2 points."""
    p = points[valid & np.isfinite(points).all(1)].astype(np.float64)
    if len(p) < 2:
        return np.inf
    d = np.sqrt(((p[:, None] - p[None]) ** 2).sum(-1))
    return float(np.abs(d - eps).min())


def check_against_upstream(points, valid, cfg):
    """The export formulation equals sklearn and the plain reference, labels and map, exactly."""
    assert tie_gap(points, valid, cfg.eps) > TIE_MARGIN, "generated cloud has a pair at eps"
    labels, core, bev, cluster_points, converged = run_export(points, valid, cfg)
    up_labels, up_core, up_bev, up_points = run_upstream(points, valid, cfg)
    ref_labels, ref_core, ref_converged = dbscan_labels_reference(points, valid, cfg)
    ref_bev, ref_points, _ = cqca_cfa_map_reference(points, valid, cfg)
    assert converged and ref_converged
    np.testing.assert_array_equal(labels, up_labels)  # same numbering, hence same partition
    np.testing.assert_array_equal(ref_labels, up_labels)
    np.testing.assert_array_equal(core, up_core)
    np.testing.assert_array_equal(ref_core, up_core)
    np.testing.assert_array_equal(bev, up_bev)
    np.testing.assert_array_equal(ref_bev, up_bev)
    np.testing.assert_array_equal(cluster_points, up_points)
    np.testing.assert_array_equal(ref_points, up_points)
    return labels, bev


# ----------------------------------------------------------------------------- clouds


def inside(rng, n, margin=0.5):
    """n (x, y) uniformly inside the small map, margin metres from its edges."""
    return rng.uniform([0.16 + margin, -4.96 + margin], [10.4 - margin, 5.28 - margin], (n, 2))


def blob(rng, n, centre, sigma, v=None, v_sigma=0.1):
    v = rng.uniform(-3, 3) if v is None else v
    return np.c_[centre + rng.normal(0.0, 1.0, (n, 2)) * sigma, v + rng.normal(0.0, v_sigma, n)]


def cloud_blobs(rng):
    centres = inside(rng, int(rng.integers(1, 6)))
    parts = [blob(rng, int(rng.integers(3, 60)), c, rng.uniform(0.05, 0.4)) for c in centres]
    clutter = int(rng.integers(0, 60))
    parts.append(np.c_[inside(rng, clutter, 0.0), rng.normal(0, 3, clutter)])
    return np.concatenate(parts), dict(min_samples=int(rng.choice([3, 4, 5, 10])))


def cloud_chains(rng):
    """Polylines of points 0.2-0.38 apart (min_samples 2-3: every point core), shuffled."""
    parts = []
    for _ in range(int(rng.integers(1, 4))):
        n = int(rng.integers(10, 80))
        steps = rng.uniform(0.2, 0.38, n)
        heading = np.cumsum(rng.normal(0, 0.3, n)) + rng.uniform(0, 2 * np.pi)
        xy = np.cumsum(np.c_[np.cos(heading), np.sin(heading)] * steps[:, None], 0) + inside(rng, 1, 2.0)
        parts.append(np.c_[xy, np.full(n, rng.uniform(-1, 1))])
    return np.concatenate(parts), dict(min_samples=int(rng.choice([2, 3])))


def cloud_rings(rng):
    parts = []
    for _ in range(int(rng.integers(1, 3))):
        r = rng.uniform(0.8, 2.5)
        n = int(np.ceil(2 * np.pi * r / rng.uniform(0.15, 0.3)))
        a = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 1)
        c = inside(rng, 1, 3.0)[0]
        parts.append(np.c_[c + r * np.c_[np.cos(a), np.sin(a)] + rng.normal(0, 0.01, (n, 2)), np.zeros(n)])
        parts.append(blob(rng, 8, c, 0.1, v=0.0))
    return np.concatenate(parts), dict(min_samples=3)


def cloud_touching(rng):
    """Pairs of 5-point core groups (min_samples 5) 0.35 m either side of a shared border point.

    The border point reaches one core point of each group and is not core itself (3 < 5), so it
    takes the smaller cluster id: which one depends on the shuffled order.
    """
    parts = []
    for _ in range(int(rng.integers(1, 4))):
        origin = inside(rng, 1, 1.5)[0]
        direction = np.array([1.0, 0.0]) if rng.random() < 0.5 else np.array([0.0, 1.0])
        offsets = np.r_[np.linspace(-0.7, -0.35, 5), 0.0, np.linspace(0.35, 0.7, 5)] + rng.normal(0, 0.005, 11)
        parts.append(np.c_[origin + offsets[:, None] * direction, np.full(11, rng.uniform(-2, 2))])
    return np.concatenate(parts), dict(min_samples=5)


def cloud_duplicates(rng):
    """Stacks of identical points around min_samples (some core, some not) plus a blob with copies."""
    k = int(rng.choice([3, 5, 10]))
    parts = [
        np.repeat(np.r_[c, rng.uniform(-2, 2)][None], int(rng.integers(k - 2, k + 3)), 0)
        for c in inside(rng, int(rng.integers(1, 6)))
    ]
    b = blob(rng, 20, inside(rng, 1)[0], 0.2)
    parts.append(np.concatenate([b, b[rng.integers(0, 20, 15)]]))
    return np.concatenate(parts), dict(min_samples=k)


def cloud_noise(rng):
    n = int(rng.integers(1, 40))
    return np.c_[inside(rng, n, 0.0), rng.normal(0, 5, n)], dict(min_samples=10)


def cloud_single(rng):
    """One cluster: id 0, so upstream's map stays empty."""
    return blob(rng, int(rng.integers(10, 90)), inside(rng, 1)[0], 0.2), dict(min_samples=int(rng.choice([3, 10])))


def cloud_big(rng):
    """A cluster above 100 points (noise, density kept), one of exactly 100 (kept), small ones."""
    parts = [
        blob(rng, int(rng.integers(101, 180)), inside(rng, 1, 2)[0], 0.25, v=1.0),
        blob(rng, 100, inside(rng, 1, 2)[0], 0.03, v=-1.0, v_sigma=0.02),
    ]
    parts += [blob(rng, int(rng.integers(5, 30)), c, 0.15) for c in inside(rng, 3)]
    return np.concatenate(parts)[rng.permutation(sum(len(p) for p in parts))], dict(min_samples=5)


def cloud_edges(rng):
    """Clusters in the first 0.16 m column / row (index -1 wraps), beyond the map (skipped), corners."""
    parts = [
        np.c_[rng.uniform(0.0, 0.16, 8), rng.uniform(-2, 2, 8) * 0.05 + rng.uniform(-4, 4), np.zeros(8)],  # col -1
        np.c_[rng.uniform(2, 2.3, 8), rng.uniform(-5.12, -4.96, 8), np.ones(8)],  # row -1
        np.c_[rng.uniform(0.0, 0.16, 8), rng.uniform(-5.12, -4.96, 8), np.full(8, 2.0)],  # corner
        np.c_[rng.uniform(-0.15, 0.0, 8), rng.uniform(3, 3.2, 8), np.full(8, 3.0)],  # x < 0: -1
        np.c_[rng.uniform(-0.6, -0.17, 8), rng.uniform(0, 0.3, 8), np.full(8, 4.0)],  # col -2
        np.c_[rng.uniform(10.41, 10.7, 8), rng.uniform(0, 0.3, 8), np.full(8, 5.0)],  # col 64
        np.c_[rng.uniform(5, 5.3, 8), rng.uniform(5.29, 5.6, 8), np.full(8, 6.0)],  # row 64
        blob(rng, 10, inside(rng, 1)[0], 0.1),
    ]
    order = rng.permutation(len(parts))
    return np.concatenate([parts[i] for i in order]), dict(min_samples=4)


def cloud_hostile(rng):
    """A radar-like cloud with NaN / Inf rows and a random invalid mask."""
    points, params = cloud_blobs(rng)
    bad = np.array([[np.nan, 1, 0], [2, np.inf, 0], [3, 1, -np.inf], [np.nan] * 3], np.float64)
    at = rng.integers(0, len(points) + 1, len(bad))
    points = np.insert(points, at, bad, axis=0)
    params["valid"] = rng.random(len(points)) > 0.15
    return points, params


def cloud_tiny(rng):
    n = int(rng.integers(0, 4))
    return np.c_[inside(rng, n, 4.0) * 0.05 + 4, np.zeros(n)], dict(min_samples=int(rng.integers(1, 3)))


def cloud_tj4d(rng):
    """TJ4D-like settings (eps 2 in mixed units, min_samples 4): velocity separates overlapping blobs."""
    parts = [blob(rng, int(rng.integers(4, 30)), c, 0.6, v_sigma=0.5) for c in inside(rng, 4)]
    centre = inside(rng, 1)[0]
    parts += [blob(rng, 12, centre, 0.3, v=-6.0), blob(rng, 12, centre, 0.3, v=6.0)]
    return np.concatenate(parts), dict(eps=2.0, min_samples=4)


KINDS = {
    "blobs": cloud_blobs,
    "chains": cloud_chains,
    "rings": cloud_rings,
    "touching": cloud_touching,
    "duplicates": cloud_duplicates,
    "noise": cloud_noise,
    "single": cloud_single,
    "big": cloud_big,
    "edges": cloud_edges,
    "hostile": cloud_hostile,
    "tiny": cloud_tiny,
    "tj4d": cloud_tj4d,
}
SEEDS = 18  # 12 kinds x 18 seeds = 216 clouds


def make_cloud(kind, seed):
    rng = np.random.default_rng([seed, sorted(KINDS).index(kind)])
    for _ in range(20):
        points, params = KINDS[kind](rng)
        points = np.asarray(points, np.float32).reshape(-1, 3)
        valid = params.pop("valid", np.ones(len(points), bool))
        cfg = dataclasses.replace(SMALL, **params)
        if tie_gap(points, valid, cfg.eps) > TIE_MARGIN:
            return points, valid, cfg
    raise AssertionError("could not draw a cloud clear of eps ties")


# ----------------------------------------------------------------------------- (a) semantics


@pytest.mark.parametrize("kind", sorted(KINDS))
@pytest.mark.parametrize("seed", range(SEEDS))
def test_matches_sklearn_upstream(kind, seed):
    points, valid, cfg = make_cloud(kind, seed)
    check_against_upstream(points, valid, cfg)


def test_generated_clouds_exercise_the_quirks():
    """Across the generated clouds: cluster 0, the -1 wrap, > 100 clusters, shared borders occur."""
    seen = dict(zero=0, wrapped=0, too_big=0, border_choice=0, invalid=0)
    for kind in ("big", "edges", "touching", "hostile"):
        for seed in range(SEEDS):
            points, valid, cfg = make_cloud(kind, seed)
            labels, core, _, cluster_points, _ = run_export(points, valid, cfg)
            seen["zero"] += int((labels == 0).any())
            seen["too_big"] += int(((labels >= 0) & ~cluster_points).any())
            seen["invalid"] += int((~valid | ~np.isfinite(points).all(1)).any())
            wrap = (labels > 0) & cluster_points & ((points[:, 0] < 0.16) | (points[:, 1] + 5.12 < 0.16))
            seen["wrapped"] += int(wrap.any())
            seen["border_choice"] += int(((labels > 0) & ~core).any())
    assert all(count >= 5 for count in seen.values()), seen


def test_vod_size_scan():
    """A radar-like scan on the VoD map (320 x 320, eps 0.4, min_samples 10, capacity 2048)."""
    rng = np.random.default_rng(11)
    parts = [
        blob(rng, int(rng.integers(30, 90)), c, 0.35, v_sigma=0.2) for c in rng.uniform([2, -22], [48, 22], (8, 2))
    ]
    parts.append(blob(rng, 130, np.array([20.0, 5.0]), 0.3, v=0.5))  # > 100 points
    parts.append(blob(rng, 25, np.array([0.08, 0.0]), 0.05, v=2.0))  # first column
    parts.append(np.c_[rng.uniform([0, -25.6], [51.2, 25.6], (250, 2)), rng.normal(0, 3, 250)])
    points = np.concatenate(parts).astype(np.float32)[rng.permutation(sum(len(p) for p in parts))]
    valid = np.ones(len(points), bool)
    labels, bev = check_against_upstream(points, valid, VOD)
    assert labels.max() >= 8 and (bev[2] > 0).sum() > 100 and bev[:, :, -1].any()


def test_tj4d_size_scan():
    rng = np.random.default_rng(12)
    parts = [blob(rng, int(rng.integers(5, 40)), c, 0.8, v_sigma=1.0) for c in rng.uniform([2, -35], [65, 35], (10, 2))]
    points = np.concatenate(parts).astype(np.float32)
    labels, bev = check_against_upstream(points, np.ones(len(points), bool), TJ4D)
    assert bev.shape == (3, 496, 432) and labels.max() >= 5


def test_upstream_quirks_on_a_hand_built_scan():
    """Cluster 0 is not drawn, cell = int(q) - 1 with -1 wrapping, the last point wins a cell."""
    cfg = dataclasses.replace(SMALL, min_samples=3)
    c0 = [[5.0, 0.0, 0.0]] * 3  # cluster 0
    c1 = [[0.05, 0.5, 1.0], [0.06, 0.5, 1.1], [0.07, 0.5, 1.2]]  # cluster 1, x in [0, 0.16): col -1
    c2 = [[3.3, 1.0, 2.0], [3.31, 1.01, 2.1], [3.32, 1.02, 2.2], [3.33, 1.03, 2.3]]
    points = np.array(c0 + c1 + c2, np.float32)
    valid = np.ones(len(points), bool)
    labels, _, bev, cluster_points, converged = run_export(points, valid, cfg)
    np.testing.assert_array_equal(labels, [0, 0, 0, 1, 1, 1, 2, 2, 2, 2])
    assert converged and cluster_points.all()
    row1 = int((np.float32(0.5) + np.float32(5.12)) / np.float32(0.16)) - 1
    np.testing.assert_array_equal(bev[:, row1, 63], np.float32([1.2, 3, 1]))  # wrapped, last point
    row2 = int((np.float32(1.03) + np.float32(5.12)) / np.float32(0.16)) - 1
    col2 = int(np.float32(3.33) / np.float32(0.16)) - 1
    np.testing.assert_array_equal(bev[:, row2, col2], np.float32([2.3, 4, 2]))
    assert np.count_nonzero(bev.any(0)) == 2  # cluster 0 absent
    check_against_upstream(points, valid, cfg)


def test_shared_border_point_takes_the_first_cluster():
    """A non-core point 0.35 m from two clusters takes the one discovered first (smaller id)."""
    cfg = dataclasses.replace(SMALL, min_samples=5)
    left = np.c_[np.linspace(2.3, 2.65, 5), np.zeros(5), np.zeros(5)]
    right = np.c_[np.linspace(3.35, 3.7, 5), np.zeros(5), np.zeros(5)]
    border = np.array([[3.0, 0.0, 0.0]])
    far = np.c_[np.full(5, 8.0), np.linspace(0, 0.2, 5), np.zeros(5)]
    for order in ((right, border, left), (border, left, right), (far, left, border, right), (right, far, border, left)):
        points = np.concatenate(order).astype(np.float32)
        valid = np.ones(len(points), bool)
        labels, core, *_ = run_export(points, valid, cfg)
        at = {
            name: int(np.flatnonzero(points[:, 0] == np.float32(part[0, 0]))[0])
            for name, part in (("left", left), ("right", right), ("border", border))
        }
        first = "left" if at["left"] < at["right"] else "right"
        assert not core[at["border"]] and labels[at["border"]] == labels[at[first]]
        assert labels[at["border"]] == min(labels[at["left"]], labels[at["right"]])
        check_against_upstream(points, valid, cfg)


def test_exact_ties_at_eps_are_neighbours():
    """eps 0.625 and steps (0.375, 0.5): every step is exactly eps in float64; sklearn's <= joins them.

    20 points, so sklearn uses its KD-tree (its brute force for N < 12 may miss exact ties)."""
    cfg = dataclasses.replace(SMALL, eps=0.625, min_samples=3)
    k = np.arange(20)
    points = np.c_[1.0 + 0.375 * k, -4.0 + 0.5 * k, np.zeros(20)].astype(np.float32)
    labels, core, bev, cluster_points, _ = run_export(points, np.ones(20, bool), cfg)
    up_labels, up_core, up_bev, up_points = run_upstream(points, np.ones(20, bool), cfg)
    np.testing.assert_array_equal(labels, up_labels)
    np.testing.assert_array_equal(core, up_core)
    np.testing.assert_array_equal(bev, up_bev)
    assert (labels == 0).all() and core[1:-1].all() and not core[[0, -1]].any()


def test_float64_distances_decide_pairs_near_eps():
    """Pairs with |d^2 - eps^2| < 2e-8 (clear of float64 rounding) are decided as sklearn decides.

    Several of them are decided the other way by float32 arithmetic, which this test would catch."""
    rng = np.random.default_rng(21)
    cfg = dataclasses.replace(SMALL, eps=0.4, min_samples=2)
    e2 = 0.4 * 0.4
    pairs, flips = [], 0
    while len(pairs) < 40:
        a = np.r_[rng.uniform(0.5, 9.5), rng.uniform(-4.5, 4.5), rng.uniform(-2, 2)].astype(np.float32)
        u = rng.normal(size=3)
        b = (a + u / np.linalg.norm(u) * 0.4).astype(np.float32)
        d = a.astype(np.float64) - b.astype(np.float64)
        d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        if not 1e-12 < abs(d2 - e2) < 2e-8 or any(np.abs(a[:2] - p[0][:2]).max() < 1.0 for p in pairs):
            continue
        f = a - b  # the same sum in float32
        flips += (f[0] * f[0] + f[1] * f[1] + f[2] * f[2] <= np.float32(e2)) != (d2 <= e2)
        pairs.append((a, b))
    points = np.array([p for pair in pairs for p in pair], np.float32)
    labels, *_ = run_export(points, np.ones(len(points), bool), cfg)
    up_labels, _ = upstream_dbscan(points, None, cfg.eps, cfg.min_samples)
    np.testing.assert_array_equal(labels, up_labels)
    assert flips >= 3 and 5 <= (up_labels >= 0).sum() // 2 <= 35


def test_cluster_size_limit():
    """101 points: noise (not in cluster_points, not drawn); 100 points: kept with density 100."""
    cfg = dataclasses.replace(SMALL, min_samples=3)
    for size, kept in ((100, True), (101, False)):
        points = np.array([[1.0, 1.0, 0.0]] * 3 + [[6.0, 2.0, 1.0]] * size, np.float32)
        labels, _, bev, cluster_points, _ = run_export(points, np.ones(len(points), bool), cfg)
        assert (labels[3:] == 1).all() and cluster_points[3:].all() == kept
        assert bev[1].max() == (size if kept else 0)
        check_against_upstream(points, np.ones(len(points), bool), cfg)


# ----------------------------------------------------------------------------- rounds and capacity


def serpentine_chain(n, spacing=0.3):
    """n points 0.3 m apart on a zig-zag path: one chain, every point core at min_samples 2."""
    per_row = 30
    i = np.arange(n)
    row, k = i // per_row, i % per_row
    x = np.where(row % 2 == 0, k, per_row - 1 - k) * spacing
    return np.c_[x, row * spacing, np.zeros(n)].astype(np.float32)


def bit_reversal(n):
    bits = max(1, (n - 1).bit_length())
    order = [int(f"{i:0{bits}b}"[::-1], 2) for i in range(2**bits)]
    return np.array([i for i in order if i < n])


def test_round_formula():
    assert len(dbscan_rounds(2048)) == 11 and sum(dbscan_rounds(2048)) == 66
    assert dbscan_rounds(1) == [1] and dbscan_rounds(4) == [2, 1]


@pytest.mark.parametrize("order", ["index", "reversed", "random", "bit_reversal", "even_odd"])
def test_longest_chains_converge_in_the_proven_rounds(order):
    cfg = DbscanConfig(eps=0.4, min_samples=2, capacity=512)
    n = cfg.capacity
    perm = {
        "index": np.arange(n),
        "reversed": np.arange(n)[::-1],
        "random": np.random.default_rng(0).permutation(n),
        "bit_reversal": bit_reversal(n),
        "even_odd": np.r_[np.arange(0, n, 2), np.arange(1, n, 2)],
    }[order]
    points = serpentine_chain(n)[perm]
    labels, core, converged = dbscan_labels(torch.from_numpy(points), torch.ones(n, dtype=torch.bool), cfg)
    assert bool(converged) and core.all() and (labels == 0).all()


def test_converged_is_honest():
    """Too few rounds on a shuffled chain: converged False exactly when the labels are not sklearn's."""
    cfg = DbscanConfig(eps=0.4, min_samples=2, capacity=256)
    points = serpentine_chain(200)[np.random.default_rng(1).permutation(200)]
    valid = torch.ones(200, dtype=torch.bool)
    expected, _ = upstream_dbscan(points, None, cfg.eps, cfg.min_samples)
    flags = []
    for rounds in range(len(dbscan_rounds(cfg.capacity)) + 1):
        labels, _, converged = dbscan_labels(torch.from_numpy(points), valid, cfg, rounds=rounds)
        assert bool(converged) == np.array_equal(labels.numpy(), expected)
        flags.append(bool(converged))
    assert not flags[0] and flags[-1]


def test_capacity_contract():
    """Beyond capacity points are not clustered; converged says whether a usable point was dropped."""
    cfg = dataclasses.replace(SMALL, capacity=64, min_samples=3)
    rng = np.random.default_rng(5)
    points = np.concatenate([blob(rng, 25, c, 0.15) for c in inside(rng, 4)])[rng.permutation(100)]
    points = points.astype(np.float32)
    valid = np.ones(100, bool)
    labels, core, bev, cluster_points, converged = run_export(points, valid, cfg)
    head_labels, head_core = upstream_dbscan(points[:64], None, cfg.eps, cfg.min_samples)
    head_bev, head_final = upstream_map(
        points[:64], None, cfg.eps, cfg.min_samples, cfg.map_rows, cfg.map_cols, cfg.resolution, cfg.y_offset
    )
    assert not converged
    np.testing.assert_array_equal(labels, np.r_[head_labels, np.full(36, -1)])
    np.testing.assert_array_equal(core, np.r_[head_core, np.zeros(36, bool)])
    np.testing.assert_array_equal(bev, head_bev)
    np.testing.assert_array_equal(cluster_points, np.r_[head_final != -1, np.zeros(36, bool)])
    ref_labels, _, ref_converged = dbscan_labels_reference(points, valid, cfg)
    np.testing.assert_array_equal(ref_labels, labels)
    assert not ref_converged
    # exactly at capacity, or only unusable points (invalid or NaN) beyond it: upstream's result
    assert run_export(points[:64], valid[:64], cfg)[4]
    unusable_points, unusable_valid = points.copy(), valid.copy()
    unusable_points[64::2] = np.nan
    unusable_valid[65::2] = False
    out = run_export(unusable_points, unusable_valid, cfg)
    assert out[4] and dbscan_labels_reference(unusable_points, unusable_valid, cfg)[2]
    np.testing.assert_array_equal(out[0], labels)
    np.testing.assert_array_equal(out[2], head_bev)


# ----------------------------------------------------------------------------- config and input errors


def test_config():
    where = "maffnet-vod.yaml: image_backbone.dbscan"
    cfg = config_from_dict(
        DbscanConfig, {"eps": 2, "min_samples": 4, "map_rows": 496, "map_cols": 432, "y_offset": 39.68}, where
    )
    assert cfg == TJ4D and isinstance(cfg.eps, float)
    assert (VOD.eps, VOD.min_samples, VOD.map_rows, VOD.map_cols, VOD.capacity) == (0.4, 10, 320, 320, 2048)
    for bad in (
        {"eps": 0},
        {"min_samples": 0},
        {"capacity": 0},
        {"map_rows": 0},
        {"resolution": -1.0},
        {"max_cluster_size": -1},
        {"radius": 1.0},
    ):
        with pytest.raises(ConfigError, match="image_backbone"):
            config_from_dict(DbscanConfig, bad, where)


def test_input_errors():
    ok = torch.ones(4, dtype=torch.bool)
    with pytest.raises(InputError, match="float32"):
        dbscan_labels(torch.zeros(4, 3, dtype=torch.float64), ok, SMALL)
    with pytest.raises(InputError, match=r"\[N, 3\]"):
        cqca_cfa_map(torch.zeros(4, 2), ok, SMALL)
    with pytest.raises(InputError, match="valid"):
        cqca_cfa_map(torch.zeros(4, 3), torch.ones(4), SMALL)
    with pytest.raises(InputError, match="N = 4"):
        dbscan_labels(torch.zeros(4, 3), torch.ones(5, dtype=torch.bool), SMALL)


# ----------------------------------------------------------------------------- (b) ONNX


class CqcaCfaMap(torch.nn.Module):
    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg

    def forward(self, points_xyv, valid):
        return cqca_cfa_map(points_xyv, valid, self.cfg)


def test_onnx_export_dynamic_n(onnx_roundtrip):
    cfg = dataclasses.replace(SMALL, capacity=256, min_samples=4)
    points, valid, _ = make_cloud("blobs", 100)
    example = {"points_xyv": torch.from_numpy(points), "valid": torch.from_numpy(valid)}
    rt = onnx_roundtrip(
        CqcaCfaMap(cfg),
        example,
        ["map", "cluster_points", "converged"],
        {"points_xyv": {0: "num_points"}, "valid": {0: "num_points"}},
    )
    rng = np.random.default_rng(3)
    big = np.concatenate([blob(rng, 40, c, 0.2) for c in inside(rng, 8)]).astype(np.float32)  # 320 > capacity
    clouds = [
        make_cloud(kind, seed)[:2]
        for kind, seed in (("hostile", 1), ("edges", 2), ("chains", 3), ("big", 4), ("touching", 5), ("duplicates", 6))
    ]
    clouds += [
        (np.zeros((0, 3), np.float32), np.zeros(0, bool)),
        (points[:1], valid[:1]),
        (points[:2], valid[:2]),
        (big[:256], np.ones(256, bool)),
        (big, np.ones(len(big), bool)),
    ]
    for pts, ok in clouds:
        ref, got = rt({"points_xyv": torch.from_numpy(pts), "valid": torch.from_numpy(ok)})
        for name in ("map", "cluster_points", "converged"):
            np.testing.assert_array_equal(got[name], ref[name], err_msg=f"{name} (N={len(pts)})")
        assert bool(got["converged"]) == (len(pts) <= cfg.capacity)
        if len(pts) <= cfg.capacity:
            bev, _ = upstream_map(
                pts, ok, cfg.eps, cfg.min_samples, cfg.map_rows, cfg.map_cols, cfg.resolution, cfg.y_offset
            )
            np.testing.assert_array_equal(got["map"], bev, err_msg=f"map vs sklearn (N={len(pts)})")
