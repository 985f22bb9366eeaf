"""``input_flags`` in the graph: per frame, the bits of :mod:`radaredge.runtime.flags` (what the
graph masked or dropped of its input). :func:`frame_flags` is the export formulation
(fixed-shape, one-hot over frames); :func:`frame_flags_reference` computes the same per frame
with numpy loops from the raw frames.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..runtime.flags import CAPACITY, NON_FINITE, NOT_CONVERGED, OUT_OF_RANGE, TIME_ORDER
from .reduce import any_true


def frame_flags(points: torch.Tensor, frame: torch.Tensor, count: int, timestamps: torch.Tensor | None = None,
                outside: torch.Tensor | None = None, full: torch.Tensor | None = None,
                capacity: torch.Tensor | None = None, not_converged: torch.Tensor | None = None) -> torch.Tensor:
    """Export formulation: int32 [count] flags of ``count`` scans concatenated as ``points`` [N, F]
    with their scan index ``frame`` [N]; per point ``outside`` and ``full`` [N] bool (dropped for
    the range, dropped from a full pillar); per scan ``timestamps`` [count] s, and ``capacity``,
    ``not_converged`` [count] or [] bool from the model's own stages."""
    dev = points.device
    member = frame.unsqueeze(0) == torch.arange(count, dtype=torch.int64, device=dev).unsqueeze(1)   # [K, N]

    def any_point(mask: torch.Tensor) -> torch.Tensor:
        return any_true(member & mask.unsqueeze(0), 1).to(torch.int32)

    flags = any_point(~torch.isfinite(points).all(1)) * NON_FINITE
    if timestamps is not None:
        after = torch.cat([torch.ones(1, dtype=torch.bool, device=dev), timestamps[1:] > timestamps[:-1]])
        late = ~(after & torch.isfinite(timestamps))         # (a NaN compares False: flagged too)
        flags = flags + late.to(torch.int32) * TIME_ORDER
    if outside is not None:
        flags = flags + any_point(outside) * OUT_OF_RANGE
    over = any_point(full) if full is not None else torch.zeros(count, dtype=torch.int32, device=dev)
    if capacity is not None:
        over = torch.maximum(over, capacity.to(torch.int32).expand(count))
    flags = flags + over * CAPACITY
    if not_converged is not None:
        flags = flags + not_converged.to(torch.int32).expand(count) * NOT_CONVERGED
    return flags


def frame_flags_reference(frames: Sequence[np.ndarray], timestamps=None, outside: Sequence[np.ndarray] | None = None,
                          full: Sequence[np.ndarray] | None = None, capacity=None, not_converged=None) -> torch.Tensor:
    """Reference formulation of :func:`frame_flags`, frame by frame: ``frames`` [N_k, F] arrays,
    per-frame point masks ``outside`` and ``full``, per-frame (or one) ``capacity`` and
    ``not_converged`` booleans."""
    out = []
    for k, f in enumerate(frames):
        bits = 0
        if (~np.isfinite(np.asarray(f))).any():
            bits |= NON_FINITE
        if timestamps is not None and (not np.isfinite(float(timestamps[k]))
                                       or k > 0 and not float(timestamps[k]) > float(timestamps[k - 1])):
            bits |= TIME_ORDER
        if outside is not None and np.asarray(outside[k]).any():
            bits |= OUT_OF_RANGE
        over = full is not None and np.asarray(full[k]).any()
        if capacity is not None and bool(np.asarray(capacity).reshape(-1)[min(k, np.asarray(capacity).size - 1)]):
            over = True
        if over:
            bits |= CAPACITY
        if not_converged is not None and bool(np.asarray(not_converged).reshape(-1)[0]):
            bits |= NOT_CONVERGED
        out.append(bits)
    return torch.tensor(out, dtype=torch.int32)
