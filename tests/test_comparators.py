"""Parity comparators (radaredge/models/comparators.py) on hand-made outputs."""

import numpy as np

from radaredge.models.comparators import retrieval_top1_agreement


def test_retrieval_agreement_counts_own_case_and_exact_ties():
    ref = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [0.7, 0.7]])  # cases 1 and 2: the same input
    got = ref + 1e-6
    assert retrieval_top1_agreement(got, ref) == 1.0  # a tie with an equal input agrees
    swapped = got[[1, 0, 2, 3]]  # cases 0 and 1 retrieve each other
    assert retrieval_top1_agreement(swapped, ref) == 0.5
