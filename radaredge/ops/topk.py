"""TopK for any K in pieces TensorRT takes: its TopK needs K < 3840 (onnx-tensorrt
docs/operators.md; "Values larger than 3840 will result in a runtime error", NvInfer.h).

:func:`topk_indices` takes the K largest in rounds of at most :data:`TOPK_LIMIT`: each round's
winners are set to -inf before the next round, and the rounds' indices are concatenated. For
keys without ties (radaredge's NMS makes them unique) that is ``torch.topk(x, k).indices``
exactly, the reference formulation, in the same order.
"""

from __future__ import annotations

import torch

TOPK_LIMIT = 3839


def topk_indices(x: torch.Tensor, k: int) -> torch.Tensor:
    """Indices [k] of the ``k`` largest values of the 1-D float tensor ``x``, largest first
    (``k`` a Python int, as the exported graph fixes it)."""
    picked = []
    remaining = x
    while k > 0:
        take = min(k, TOPK_LIMIT)
        idx = torch.topk(remaining, take).indices
        picked.append(idx)
        k -= take
        if k > 0:
            remaining = remaining.scatter(0, idx, torch.full_like(idx, float("-inf"), dtype=remaining.dtype))
    return picked[0] if len(picked) == 1 else torch.cat(picked)
