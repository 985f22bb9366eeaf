"""input_flags: the graph's formulation (ops/input_flags.frame_flags) against the frame-by-frame
reference, on random frames, masks and timestamps that include NaN, Inf and repeats."""

import numpy as np
import pytest
import torch

from radaredge.ops.input_flags import frame_flags, frame_flags_reference
from radaredge.runtime.flags import TIME_ORDER


def _case(seed: int):
    rng = np.random.default_rng(seed)
    sizes = rng.integers(0, 6, size=int(rng.integers(1, 5)))
    frames = [rng.normal(size=(int(n), 4)).astype(np.float32) for n in sizes]
    for f in frames:
        f[rng.random(f.shape) < 0.05] = rng.choice([np.nan, np.inf, -np.inf])
    stamps = np.cumsum(rng.choice([0.1, 0.0, -0.05], size=len(frames), p=[0.7, 0.15, 0.15])).astype(np.float32)
    stamps[rng.random(len(frames)) < 0.2] = rng.choice([np.nan, np.inf, -np.inf])
    outside = [rng.random(len(f)) < 0.1 for f in frames]
    full = [rng.random(len(f)) < 0.1 for f in frames]
    capacity = rng.random(len(frames)) < 0.2
    not_converged = rng.random(1) < 0.3
    return frames, stamps, outside, full, capacity, not_converged


@pytest.mark.parametrize("seed", range(40))
def test_frame_flags_match_the_reference(seed):
    frames, stamps, outside, full, capacity, not_converged = _case(seed)
    points = torch.from_numpy(np.concatenate(frames)) if frames else torch.zeros(0, 4)
    frame = torch.from_numpy(np.repeat(np.arange(len(frames)), [len(f) for f in frames]))
    got = frame_flags(
        points,
        frame,
        len(frames),
        torch.from_numpy(stamps),
        torch.from_numpy(np.concatenate(outside)),
        torch.from_numpy(np.concatenate(full)),
        torch.from_numpy(capacity),
        torch.from_numpy(not_converged),
    )
    want = frame_flags_reference(frames, stamps, outside, full, capacity, not_converged)
    assert got.tolist() == want.tolist()


@pytest.mark.parametrize(
    "stamps, late",
    [
        ([0.0, np.nan, 0.2], [0, 1, 1]),
        ([0.0, 0.1, np.inf], [0, 0, 1]),
        ([np.nan, 0.1, 0.2], [1, 1, 0]),
        ([0.0, 0.1, 0.1], [0, 0, 1]),
    ],
)
def test_a_timestamp_that_is_not_finite_or_not_later_is_flagged(stamps, late):
    frames = [np.zeros((2, 4), np.float32)] * 3
    points, frame = torch.zeros(6, 4), torch.arange(3).repeat_interleave(2)
    got = frame_flags(points, frame, 3, torch.tensor(stamps, dtype=torch.float32))
    assert (got // TIME_ORDER % 2).tolist() == late
    assert frame_flags_reference(frames, stamps).tolist() == got.tolist()
