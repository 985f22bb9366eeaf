"""Reductions whose exported graph gives the right answer on an empty axis.

torch exports ``mask.any(dim)`` as a ``ReduceMax`` over the mask cast to a number, and an ONNX
``ReduceMax`` over zero elements yields the lowest value of the type, which casts back to True:
an empty scan "has" a NaN point. :func:`any_true` counts instead (``ReduceSum`` of nothing is 0),
so eager torch and the graph agree for every length, 0 included.
"""

from __future__ import annotations

import torch


def any_true(mask: torch.Tensor, dim: int | None = None) -> torch.Tensor:
    """Whether any element of the bool ``mask`` is set (along ``dim``, or over all of it); False
    for an empty axis in eager torch and in the exported graph alike."""
    count = mask.to(torch.int32)
    return (count.sum() if dim is None else count.sum(dim)) > 0
