"""radaredge.fitting.tdfanet_places: the triplet loss, the batch sampler and the fit on the tiny
TDFANet card (the int8 experiment's descriptors are only as good as these)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from radaredge.cards import load_card
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.evaluation import load_windows
from radaredge.exporter import build_model, save_checkpoint
from radaredge.fitting import tdfanet_places as tf

CARD = load_card(Path(__file__).parent / "cards" / "tdfanet-tiny.yaml")


@pytest.fixture(scope="module")
def tiny_town(tmp_path_factory):
    model = build_model(CARD)
    town = tmp_path_factory.mktemp("town")
    make_pr_benchmark(town, drives=2, frames_per_drive=40, seed=1)
    return town, tf.prepare_windows(model, town, CARD.features)


def _unit(v):
    v = torch.tensor(v, dtype=torch.float32)
    return v / v.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("same_drive", [True, False])
def test_triplet_loss_counts_near_positives_and_far_negatives(same_drive):
    positions = torch.tensor([[0.0, 0.0], [0.0, 2.0], [0.0, 40.0], [0.0, 42.0]], dtype=torch.float64)
    drives = torch.tensor([0, 1, 0, 1])
    separated = _unit([[1, 0, 0], [1, 0.05, 0], [0, 1, 0], [0, 1, 0.05]])   # places apart, same place together
    swapped = _unit([[1, 0, 0], [0, 1, 0], [1, 0.05, 0], [0, 1, 0.05]])     # each window looks like the other place
    assert tf.triplet_loss(separated, positions, drives, same_drive).item() == 0.0
    assert tf.triplet_loss(swapped, positions, drives, same_drive).item() > tf.MARGIN
    # windows of one drive 2 m apart are positives only with same_drive; a window is never its own
    one_drive = tf.triplet_loss(swapped, positions, torch.zeros(4, dtype=torch.long), same_drive).item()
    assert one_drive > tf.MARGIN if same_drive else one_drive == 0.0
    assert tf.triplet_loss(swapped[:1].repeat(2, 1), positions[[0, 2]], torch.zeros(2, dtype=torch.long),
                           same_drive).item() == 0.0
    # between the radii (10 m) a window is neither a positive nor a negative
    mid = torch.tensor([[0.0, 0.0], [0.0, 2.0], [0.0, 10.0], [0.0, 12.0]], dtype=torch.float64)
    assert tf.triplet_loss(swapped, mid, drives, same_drive).item() == 0.0


def test_batches_pair_each_anchor_with_another_drive_nearby(tiny_town):
    """Each anchor is followed by a window of another drive within PAIR_RADIUS m, unless it has
    none (an end of the street that only one drive reaches)."""
    _, windows = tiny_town
    pos = np.array([w.position for w in windows])
    drive = np.array([w.drive for w in windows])
    rng = np.random.default_rng(0)
    paired = 0
    for _ in range(5):
        batch = tf.sample_batch(windows, rng, places=4)
        i = anchors = 0
        while i < len(batch):
            a = batch[i]
            near = set(np.flatnonzero((np.linalg.norm(pos - pos[a], axis=1) <= tf.PAIR_RADIUS) & (drive != drive[a])))
            if near:
                assert batch[i + 1] in near
                paired += 1
            i += 2 if near else 1
            anchors += 1
        assert anchors == 4
    assert paired >= 15


def test_prepared_windows_describe_like_the_export_formulation(tiny_town):
    """The cached front (RANSAC, displacement) plus describe() is the export formulation."""
    town, windows = tiny_town
    model = build_model(CARD)
    scans, timestamps = load_windows(town / "database", model.frames).inputs(5, CARD.features)
    with torch.no_grad():
        full = model.run([torch.from_numpy(s) for s in scans], torch.from_numpy(timestamps))["descriptor_normalized"]
        cached = tf.describe(model, windows[5])
    np.testing.assert_allclose(cached.numpy(), full.numpy(), atol=1e-5)


def test_fitting_lowers_the_triplet_loss_and_trains_the_network(tiny_town, tmp_path):
    _, windows = tiny_town
    model = build_model(CARD)
    before = {k: v.clone() for k, v in model.state_dict().items()}

    def mean_loss():
        rng = np.random.default_rng(123)
        with torch.no_grad():
            losses = []
            for _ in range(6):
                idx = tf.sample_batch(windows, rng)
                desc = torch.stack([tf.describe(model, windows[i]) for i in idx])
                losses.append(tf.triplet_loss(desc, torch.tensor(np.array([windows[i].position for i in idx])),
                                              torch.tensor([windows[i].drive for i in idx])).item())
        return float(np.mean(losses))

    start = mean_loss()
    tf.fit(model, windows, steps=40, lr=3e-3, log=lambda *_: None)
    assert mean_loss() < 0.7 * start
    assert not model.training
    changed = {k.split(".")[0] for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    assert {"vfe", "pyramid", "dfa", "mlp"} <= changed
    # the checkpoint the script writes is what `--checkpoint` loads
    fresh = build_model(CARD, save_checkpoint(model, tmp_path / "sub" / "fitted.pth"))
    assert all(torch.equal(v, fresh.state_dict()[k]) for k, v in model.state_dict().items())
