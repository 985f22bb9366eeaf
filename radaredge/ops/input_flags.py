"""``input_flags`` in the graph: per frame, the bits of :mod:`radaredge.runtime.flags` (what the
graph masked or dropped of its input). :func:`frame_flags` is the export formulation
(fixed-shape, one-hot over frames); :func:`frame_flags_reference` computes the same per frame
with numpy loops from the raw frames.

Implausible points: :func:`drop_implausible` (export) and :func:`drop_implausible_reference`
turn every point with a value outside its column's plausible range (the card's ``plausible``,
:func:`radaredge.cards.plausible_ranges`) into a row of NaN, which every stage of a model
leaves out as it does a non-finite point; the flags then report ``implausible``, not
``non_finite``, for it. A frame's cost is therefore bounded by what a plausible frame costs,
whatever value a sensor driver writes into one point.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..cards import ModelCard, plausible_ranges
from ..runtime.flags import CAPACITY, IMPLAUSIBLE, NON_FINITE, NOT_CONVERGED, OUT_OF_RANGE, TIME_ORDER
from .reduce import any_true


def column_bounds(card: ModelCard) -> tuple[list[float], list[float]]:
    """Per feature column (card order) the plausible low and high; -inf/inf for x, y, z."""
    ranges = plausible_ranges(card)
    lo = [ranges.get(f, (-np.inf, np.inf))[0] for f in card.features]
    hi = [ranges.get(f, (-np.inf, np.inf))[1] for f in card.features]
    return lo, hi


def drop_implausible(points: torch.Tensor, lo, hi) -> tuple[torch.Tensor, torch.Tensor]:
    """Export formulation: (points [N, F] with the implausible rows set to NaN, implausible [N]
    bool): a row is implausible when a value lies below ``lo`` or above ``hi`` of its column."""
    low = torch.tensor(lo, dtype=points.dtype, device=points.device)
    high = torch.tensor(hi, dtype=points.dtype, device=points.device)
    bad = any_true((points < low) | (points > high), 1)
    return torch.where(bad.unsqueeze(1), torch.full_like(points, float("nan")), points), bad


def drop_implausible_reference(points: np.ndarray, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Reference of :func:`drop_implausible`, row by row."""
    out = np.array(points, np.float32, copy=True)
    bad = np.zeros(len(out), bool)
    for i, row in enumerate(out):
        bad[i] = any(v < a or v > b for v, a, b in zip(row, lo, hi))
        if bad[i]:
            row[:] = np.nan
    return out, bad


def frame_flags(
    points: torch.Tensor,
    frame: torch.Tensor,
    count: int,
    timestamps: torch.Tensor | None = None,
    outside: torch.Tensor | None = None,
    full: torch.Tensor | None = None,
    capacity: torch.Tensor | None = None,
    not_converged: torch.Tensor | None = None,
    implausible: torch.Tensor | None = None,
) -> torch.Tensor:
    """Export formulation: int32 [count] flags of ``count`` scans concatenated as ``points`` [N, F]
    with their scan index ``frame`` [N]; per point ``outside``, ``full`` and ``implausible`` [N]
    bool (dropped for the range, dropped from a full pillar, set to NaN by
    :func:`drop_implausible`); per scan ``timestamps`` [count] s, and ``capacity``,
    ``not_converged`` [count] or [] bool from the model's own stages."""
    dev = points.device
    member = frame.unsqueeze(0) == torch.arange(count, dtype=torch.int64, device=dev).unsqueeze(1)  # [K, N]

    def any_point(mask: torch.Tensor) -> torch.Tensor:
        return any_true(member & mask.unsqueeze(0), 1).to(torch.int32)

    non_finite = ~torch.isfinite(points).all(1)
    if implausible is not None:
        non_finite = non_finite & ~implausible
    flags = any_point(non_finite) * NON_FINITE
    if timestamps is not None:
        after = torch.cat([torch.ones(1, dtype=torch.bool, device=dev), timestamps[1:] > timestamps[:-1]])
        late = ~(after & torch.isfinite(timestamps))  # (a NaN compares False: flagged too)
        flags = flags + late.to(torch.int32) * TIME_ORDER
    if outside is not None:
        flags = flags + any_point(outside) * OUT_OF_RANGE
    over = any_point(full) if full is not None else torch.zeros(count, dtype=torch.int32, device=dev)
    if capacity is not None:
        over = torch.maximum(over, capacity.to(torch.int32).expand(count))
    flags = flags + over * CAPACITY
    if not_converged is not None:
        flags = flags + not_converged.to(torch.int32).expand(count) * NOT_CONVERGED
    if implausible is not None:
        flags = flags + any_point(implausible) * IMPLAUSIBLE
    return flags


def frame_flags_reference(
    frames: Sequence[np.ndarray],
    timestamps=None,
    outside: Sequence[np.ndarray] | None = None,
    full: Sequence[np.ndarray] | None = None,
    capacity=None,
    not_converged=None,
    implausible: Sequence[np.ndarray] | None = None,
) -> torch.Tensor:
    """Reference formulation of :func:`frame_flags`, frame by frame: ``frames`` [N_k, F] arrays,
    per-frame point masks ``outside``, ``full`` and ``implausible``, per-frame (or one)
    ``capacity`` and ``not_converged`` booleans."""
    out = []
    for k, f in enumerate(frames):
        bits = 0
        bad = np.asarray(implausible[k]) if implausible is not None else np.zeros(len(f), bool)
        if ((~np.isfinite(np.asarray(f))).any(1) & ~bad).any():
            bits |= NON_FINITE
        if bad.any():
            bits |= IMPLAUSIBLE
        if timestamps is not None and (
            not np.isfinite(float(timestamps[k])) or k > 0 and not float(timestamps[k]) > float(timestamps[k - 1])
        ):
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
