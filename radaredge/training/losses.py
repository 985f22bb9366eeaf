"""Losses of the trained models.

TDFANet (paper section III-D, eq. 10) trains with the lazy quadruplet loss of PointNetVLAD
(Uy & Lee, reference [18] of the paper)::

    L_Q = max_j [alpha + d(q, pos) - d(q, neg_j)]_+ + [beta + d(q, pos) - d(q, neg*)]_+

with d the Euclidean distance between descriptors, pos the *best* positive (the one nearest
the query in descriptor space), neg_j the tuple's negatives (the max picks the hardest) and
neg* the "other negative": a window that is a true negative of the query and of every neg_j.
The paper's eq. 10 compares neg* with the query; PointNetVLAD's original second term compares
it with the negatives, ``max_j [beta + d(q, pos) - d(neg*, neg_j)]_+``, which pushes negatives
apart from each other as well. ``second_term`` picks one: ``"paper"`` (default, eq. 10 as
printed) or ``"pointnetvlad"``.
"""

from __future__ import annotations

import torch

SECOND_TERMS = ("paper", "pointnetvlad")


def lazy_quadruplet_loss(
    query: torch.Tensor,
    positives: torch.Tensor,
    negatives: torch.Tensor,
    other_negative: torch.Tensor,
    alpha: float = 0.2,
    beta: float = 0.1,
    second_term: str = "paper",
) -> torch.Tensor:
    """Eq. 10 for a batch of B tuples: query [B, D], positives [B, P, D], negatives [B, N, D],
    other_negative [B, D] (descriptors, the paper's U) -> the mean loss over the tuples (a
    scalar). ``alpha`` and ``beta`` are the margins (paper: 0.2 and 0.1)."""
    if second_term not in SECOND_TERMS:
        raise ValueError(f"second_term must be one of {SECOND_TERMS}, got {second_term!r}")
    d_pos = torch.linalg.vector_norm(positives - query[:, None], dim=-1).min(1).values  # best positive [B]
    d_neg = torch.linalg.vector_norm(negatives - query[:, None], dim=-1)  # [B, N]
    first = torch.relu(alpha + d_pos[:, None] - d_neg).max(1).values
    if second_term == "paper":
        second = torch.relu(beta + d_pos - torch.linalg.vector_norm(other_negative - query, dim=-1))
    else:
        d_star = torch.linalg.vector_norm(negatives - other_negative[:, None], dim=-1)  # [B, N]
        second = torch.relu(beta + d_pos[:, None] - d_star).max(1).values
    return (first + second).mean()
