"""Connected components: exact mode == scipy == union-find on hard masks; maxpool mode; ONNX."""

import numpy as np
import pytest
import torch
from scipy import ndimage

from radaredge.errors import InputError
from radaredge.ops.components import connected_components, exact_rounds, exact_schedule
from tests.references.components_ref import same_partition, union_find_labels

EIGHT = np.ones((3, 3), bool)


# ----------------------------------------------------------------------------- masks


def spiral(n: int) -> np.ndarray:
    """One 1-cell-wide path spiralling inwards with 1-cell gaps: the longest geodesic in n x n."""
    mask = np.zeros((n, n), bool)
    legs = [n - 1] * 3 + [length for length in range(n - 3, 0, -2) for _ in range(2)]
    r = c = 0
    mask[0, 0] = True
    for k, length in enumerate(legs):
        dr, dc = ((0, 1), (1, 0), (0, -1), (-1, 0))[k % 4]
        for _ in range(length):
            r, c = r + dr, c + dc
            mask[r, c] = True
    return mask


def serpentine(h: int, w: int) -> np.ndarray:
    """Full even rows joined alternately at the right and left end: one snake of ~h*w/2 cells."""
    mask = np.zeros((h, w), bool)
    mask[::2] = True
    for r in range(1, h, 2):
        mask[r, w - 1 if (r // 2) % 2 == 0 else 0] = True
    return mask


def diagonal_chain(n: int) -> np.ndarray:
    """A staircase connected only through corners, plus a checkerboard patch (one component)."""
    mask = np.eye(n, dtype=bool) | np.eye(n, k=2, dtype=bool)
    mask[n // 2 :, : n // 2] = (np.add.outer(np.arange(n - n // 2), np.arange(n // 2)) % 2) == 0
    return mask


def random_mask(shape, density, seed):
    return np.random.default_rng(seed).random(shape) < density


def label(mask: np.ndarray, mode: str = "exact", iterations=None):
    """Run the op on one 2-D mask; returns (labels [H, W] numpy, converged bool)."""
    labels, converged = connected_components(torch.from_numpy(mask)[None], mode, iterations)
    return labels[0].numpy(), bool(converged[0])


HARD = {
    "spiral_63": spiral(63),
    "spiral_64_rot": np.rot90(spiral(64)).copy(),
    "serpentine_40x57": serpentine(40, 57),
    "serpentine_cols": serpentine(57, 40).T.copy(),
    "diagonal": diagonal_chain(48),
    "empty": np.zeros((17, 23), bool),
    "full": np.ones((17, 23), bool),
    "single_cell": np.pad(np.ones((1, 1), bool), ((3, 5), (7, 2))),
    "one_by_one": np.ones((1, 1), bool),
    "row": np.ones((1, 70), bool),
    "isolated_cells": np.kron(np.ones((6, 6), bool), np.array([[1, 0], [0, 0]], bool)),
    **{f"random_{d}": random_mask((61, 67), d, seed=i) for i, d in enumerate((0.1, 0.3, 0.45, 0.6, 0.8))},
}


# ----------------------------------------------------------------------------- references


@pytest.mark.parametrize("name", sorted(HARD))
def test_union_find_reference_matches_scipy(name):
    mask = HARD[name]
    expected, _ = ndimage.label(mask, EIGHT)
    assert same_partition(union_find_labels(mask), expected)


def test_same_partition_detects_differences():
    a = np.array([[1, 1, 0, 2]])
    assert same_partition(a, np.array([[7, 7, 0, 3]]))
    assert not same_partition(a, np.array([[7, 7, 0, 7]]))  # merged
    assert not same_partition(a, np.array([[7, 8, 0, 3]]))  # split
    assert not same_partition(a, np.array([[7, 7, 5, 3]]))  # background differs


# ----------------------------------------------------------------------------- exact mode


@pytest.mark.parametrize("name", sorted(HARD))
def test_exact_matches_scipy_and_is_canonical(name):
    mask = HARD[name]
    labels, converged = label(mask)
    expected, _ = ndimage.label(mask, EIGHT)
    assert converged
    assert same_partition(labels, expected)
    np.testing.assert_array_equal(labels, union_find_labels(mask))  # largest linear index + 1


def test_exact_batch_of_different_masks():
    masks = np.stack([spiral(40), serpentine(40, 40), random_mask((40, 40), 0.6, 7), np.zeros((40, 40), bool)])
    labels, converged = connected_components(torch.from_numpy(masks))
    assert converged.tolist() == [True] * 4
    for m, lab in zip(masks, labels.numpy()):
        np.testing.assert_array_equal(lab, union_find_labels(m))


@pytest.mark.parametrize(
    "mask",
    [spiral(512), serpentine(512, 512), np.rot90(spiral(511)).copy(), random_mask((512, 512), 0.6, 3)],
    ids=["spiral", "serpentine", "spiral_511_rot", "percolating_0.6"],
)
def test_exact_worst_cases_512(mask):
    labels, converged = label(mask)
    expected, count = ndimage.label(mask, EIGHT)
    assert converged
    assert same_partition(labels, expected)
    assert len(np.unique(labels)) - 1 == count


def test_round_formula():
    assert exact_rounds(512, 512) == 18 and sum(exact_schedule(512, 512)) == 171
    assert exact_rounds(320, 320) == 16 and sum(exact_schedule(320, 320)) == 152
    assert exact_schedule(1, 1) == [1]
    assert exact_schedule(4, 4) == [4, 3, 2, 1]  # ceil(log2(16 >> k)), at least 1


def test_exact_converged_is_honest():
    """converged <=> one more round changes nothing, round by round on a long spiral."""
    mask = spiral(96)
    expected = union_find_labels(mask)
    flags = []
    for rounds in range(5):
        labels, converged = label(mask, iterations=rounds)
        more, _ = label(mask, iterations=rounds + 1)
        assert converged == np.array_equal(labels, more)
        assert converged == np.array_equal(labels, expected)
        flags.append(converged)
    assert flags[0] is False and flags[-1] is True


# ----------------------------------------------------------------------------- maxpool mode


def test_maxpool_equals_exact_on_small_blobs():
    mask = np.zeros((40, 40), bool)
    mask[3:8, 4:9] = True
    mask[20:23, 30:36] = True
    mask[30, 5] = True
    mask[10:14, 20] = True
    mask[14, 21] = True  # diagonal attachment
    labels, converged = label(mask, "maxpool")
    assert converged
    np.testing.assert_array_equal(labels, label(mask)[0])


def test_maxpool_does_not_converge_on_a_60_cell_wall():
    mask = np.zeros((8, 70), bool)
    mask[4, 5:65] = True
    labels, converged = label(mask, "maxpool")  # the fork's 20 iterations
    assert not converged
    assert len(np.unique(labels[mask])) > 1  # the wall is split into several ids
    labels, converged = label(mask, "maxpool", iterations=59)
    assert converged
    np.testing.assert_array_equal(labels, union_find_labels(mask))


def test_invalid_inputs_raise_input_error():
    with pytest.raises(InputError, match="mode"):
        connected_components(torch.zeros(1, 4, 4, dtype=torch.bool), mode="bfs")
    with pytest.raises(InputError, match="bool"):
        connected_components(torch.zeros(1, 4, 4))
    with pytest.raises(InputError, match=r"\[B, H, W\]"):
        connected_components(torch.zeros(4, 4, dtype=torch.bool))
    with pytest.raises(InputError, match="iterations"):
        connected_components(torch.zeros(1, 4, 4, dtype=torch.bool), iterations=-1)


# ----------------------------------------------------------------------------- ONNX


class ComponentsModule(torch.nn.Module):
    def __init__(self, mode):
        super().__init__()
        self.mode = mode

    def forward(self, mask):
        return connected_components(mask, self.mode)


@pytest.mark.parametrize("mode", ["exact", "maxpool"])
@pytest.mark.parametrize("hw", [(64, 64), (96, 160)])
def test_onnx_export_equals_torch(onnx_roundtrip, mode, hw):
    h, w = hw
    example = {"mask": torch.from_numpy(random_mask((2, h, w), 0.6, 0))}
    rt = onnx_roundtrip(ComponentsModule(mode), example, ["labels", "converged"], {"mask": {0: "batch"}})
    cases = [
        random_mask((3, h, w), 0.45, 1),
        np.stack([spiral(max(h, w))[:h, :w], serpentine(h, w)]),
        np.zeros((1, h, w), bool),
    ]
    for masks in cases:
        ref, got = rt({"mask": torch.from_numpy(masks)})
        np.testing.assert_array_equal(got["labels"], ref["labels"])
        np.testing.assert_array_equal(got["converged"], ref["converged"])
