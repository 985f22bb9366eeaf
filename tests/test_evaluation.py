"""Recall@N (TDFANet / TransLoc4D protocol) on hand-made descriptors and positions with known answers."""

import numpy as np
import pytest

from radaredge.errors import ConfigError, InputError
from radaredge.eval.places import nearest_neighbours, recall_at_n, top1_agreement, top1_place_agreement

BACKENDS = [pytest.param(True, id="faiss"), pytest.param(False, id="numpy")]


def one_hot_database(n: int, spacing: float = 10.0):
    """Database entry i: descriptor e_i (one-hot, D = n) at (northing 0, easting spacing * i) m."""
    return np.eye(n, dtype=np.float32), np.column_stack([np.zeros(n), spacing * np.arange(n)])


def query_ranking(order, n: int) -> np.ndarray:
    """A descriptor whose nearest database entries (one-hot e_i) are ``order``, in that order.

    ||q - e_i||^2 = ||q||^2 + 1 - 2 q_i, so a larger q_i ranks e_i nearer.
    """
    q = np.zeros(n, np.float32)
    q[list(order)] = 1.0 - 0.05 * np.arange(len(order))
    return q


@pytest.mark.parametrize("use_faiss", BACKENDS)
def test_recall_by_hand(use_faiss):
    """Four answerable queries, each at database place p (10 m apart, so p is its only positive):
    q0 ranks p first, q1 second, q2 seventh, q3 first -> Recall@1 = 2/4 = 50 %, Recall@5 = 3/4
    = 75 %, Recall@10 = 4/4 = 100 %. q4 is 1 km away from every place: skipped, not a miss."""
    db_desc, db_pos = one_hot_database(12)
    rankings = [[0, 1, 2], [3, 1, 0], [5, 6, 7, 8, 9, 10, 2], [3, 0, 1], [4, 5]]
    places = [0, 1, 2, 3]
    q_desc = np.stack([query_ranking(r, 12) for r in rankings])
    q_pos = np.vstack([db_pos[places], [[1000.0, 0.0]]])
    res = recall_at_n(q_desc, q_pos, db_desc, db_pos, use_faiss=use_faiss)
    assert res["recall"] == {1: 50.0, 5: 75.0, 10: 100.0}
    assert (res["evaluated"], res["skipped"]) == (4, 1)
    np.testing.assert_array_equal(res["evaluated_mask"], [True, True, True, True, False])
    np.testing.assert_array_equal(res["top1"], [0, 3, 5, 3, 4])
    np.testing.assert_array_equal(res["top1_correct"], [True, False, False, True, False])
    np.testing.assert_allclose(res["top1_distance"], [0.0, 20.0, 30.0, 0.0, np.hypot(1000.0, 40.0)])
    assert res["ranked"].shape == (5, 10)


@pytest.mark.parametrize("use_faiss", BACKENDS)
def test_radius_boundary_is_inclusive(use_faiss):
    """A database entry exactly 5 m away (a 3-4-5 triangle) is a true positive; 4.99 m is too short."""
    db_desc, db_pos = one_hot_database(3, spacing=20.0)
    q_desc = query_ranking([0, 1], 3)[None]
    q_pos = np.array([[3.0, 4.0]])  # 5 m from entry 0 at (0, 0)
    res = recall_at_n(q_desc, q_pos, db_desc, db_pos, ns=(1,), radius=5.0, use_faiss=use_faiss)
    assert res["recall"] == {1: 100.0} and res["top1_distance"][0] == 5.0
    with pytest.raises(InputError, match="within 4.99 m"):
        recall_at_n(q_desc, q_pos, db_desc, db_pos, ns=(1,), radius=4.99, use_faiss=use_faiss)


@pytest.mark.parametrize("use_faiss", BACKENDS)
def test_ties_rank_the_lower_database_index_first(use_faiss):
    """Entries 0 and 1 have the same descriptor; the query sits at entry 1's place."""
    db_desc = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]], np.float32)
    db_pos = np.array([[0.0, 0.0], [0.0, 50.0], [0.0, 100.0]])
    q_desc = np.array([[0.9, 0.0]], np.float32)
    res = recall_at_n(q_desc, db_pos[[1]], db_desc, db_pos, ns=(1, 2), use_faiss=use_faiss)
    np.testing.assert_array_equal(res["ranked"], [[0, 1]])
    assert res["recall"] == {1: 0.0, 2: 100.0}


@pytest.mark.parametrize("use_faiss", BACKENDS)
def test_n_beyond_the_database_size_is_recall_at_b(use_faiss):
    db_desc, db_pos = one_hot_database(3)
    res = recall_at_n(
        query_ranking([2, 1, 0], 3)[None], db_pos[[0]], db_desc, db_pos, ns=(1, 3, 10), use_faiss=use_faiss
    )
    assert res["recall"] == {1: 0.0, 3: 100.0, 10: 100.0} and res["ranked"].shape == (1, 3)


def test_faiss_and_numpy_agree_on_a_random_drive():
    """60 queries (enough for FAISS's BLAS search path) against 300 database entries along a
    track, descriptors noisy copies of a per-place code."""
    import faiss

    rng = np.random.default_rng(0)
    db_pos = np.column_stack([np.zeros(300), np.arange(300.0)])
    code = rng.normal(size=(300, 64)).astype(np.float32)
    db_desc = code + rng.normal(0, 0.5, code.shape).astype(np.float32)
    places = rng.integers(0, 300, 60)
    q_pos = db_pos[places] + rng.normal(0, 2.0, (60, 2))
    q_desc = code[places] + rng.normal(0, 1.5, (60, 64)).astype(np.float32)
    index = faiss.IndexFlatL2(64)
    index.add(db_desc)
    ns = range(1, 26)
    a = recall_at_n(q_desc, q_pos, db_desc, db_pos, ns, index=index)
    b = recall_at_n(q_desc, q_pos, db_desc, db_pos, ns, use_faiss=False)
    np.testing.assert_array_equal(a["ranked"], b["ranked"])
    assert a["recall"] == b["recall"] and 0 < a["recall"][1] < 100
    np.testing.assert_array_equal(nearest_neighbours(q_desc, db_desc, 5), b["ranked"][:, :5])


def test_top1_agreement():
    assert top1_agreement([1, 2, 3, 4], [1, 2, 0, 4]) == 0.75
    assert top1_agreement(np.arange(5), np.arange(5)) == 1.0
    with pytest.raises(InputError, match="one shape"):
        top1_agreement([1, 2], [1, 2, 3])


def test_top1_place_agreement_counts_top1_windows_within_the_radius():
    db_pos = np.array([[0.0, 0.0], [0.0, 1.0], [0.0, 5.0], [0.0, 30.0]])  # (northing, easting) m
    # same window; 1 m apart; exactly 5 m apart (boundary counts); 29 m apart
    assert top1_place_agreement([0, 0, 0, 1], [0, 1, 2, 3], db_pos, 5.0) == 0.75
    assert top1_place_agreement([0, 0, 0, 1], [0, 1, 2, 3], db_pos, 0.5) == 0.25
    with pytest.raises(InputError, match="one shape"):
        top1_place_agreement([0], [0, 1], db_pos, 5.0)
    with pytest.raises(ConfigError, match="radius"):
        top1_place_agreement([0], [1], db_pos, 0.0)
    with pytest.raises(InputError, match="4 database positions"):
        top1_place_agreement([0], [4], db_pos, 5.0)


def test_bad_arguments_are_named():
    import faiss

    db_desc, db_pos = one_hot_database(4)
    with pytest.raises(InputError, match="positions"):
        recall_at_n(db_desc, db_pos[:, :1], db_desc, db_pos)
    with pytest.raises(InputError, match="same dimension"):
        recall_at_n(db_desc[:, :3], db_pos, db_desc, db_pos)
    with pytest.raises(InputError, match="finite"):
        recall_at_n(np.full_like(db_desc, np.nan), db_pos, db_desc, db_pos)
    with pytest.raises(ConfigError, match="ns"):
        recall_at_n(db_desc, db_pos, db_desc, db_pos, ns=(0, 5))
    with pytest.raises(ConfigError, match="radius"):
        recall_at_n(db_desc, db_pos, db_desc, db_pos, radius=-1.0)
    with pytest.raises(ConfigError, match="index holds 0 vectors of dimension 2"):
        recall_at_n(db_desc, db_pos, db_desc, db_pos, index=faiss.IndexFlatL2(2))
