"""TDFANet's network against a plain reference of the paper's eq. 4-9 and section III-D
(tests/references/tdfanet_paper.py, which shares no code with radaredge): the residual pyramid,
the query fusion, the advanced queries, the deformable attention, the FFN, the MLP and GeM, and
their wiring, for both formulations of the model."""

from __future__ import annotations

import pytest
import torch
from conftest import TINY_CARD
from references import tdfanet_paper as paper

from radaredge.cards import load_card
from radaredge.models import create_model


@pytest.fixture(scope="module")
def model():
    """The tiny card with every parameter and running statistic drawn at random, so that no
    initial zero (attention logits, offset weights) or unit statistic hides a wrong wiring."""
    torch.manual_seed(7)
    net = create_model(load_card(TINY_CARD))
    with torch.no_grad():
        for name, p in net.named_parameters():
            if name == "gem.p":
                p.fill_(2.5)
            else:
                p.copy_(
                    torch.randn_like(p) * (0.3 if p.dim() > 1 else 0.1) + (1.0 if name.endswith("norm.weight") else 0.0)
                )
        for name, b in net.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(torch.randn_like(b) * 0.1)
            elif name.endswith("running_var"):
                b.copy_(torch.rand_like(b) + 0.5)
    return net.eval()


def test_residual_stage_is_the_papers_block(model):
    x = torch.randn(1, 8, 32, 32)
    sd = model.state_dict()
    with torch.no_grad():
        ours = model.pyramid[0](x)[0]
    torch.testing.assert_close(ours, paper.residual_block(x[0], sd, "pyramid.0"), atol=1e-4, rtol=1e-4)


def test_dfa_layer_is_eq_6_to_9(model):
    sd = model.state_dict()
    current, past = torch.randn(1, 16, 16, 16), torch.randn(1, 2, 16, 16, 16)
    coarser = torch.randn(1, 32, 8, 8)
    with torch.no_grad():
        for reference in (False, True):
            ours = model.dfa[1](current, past, coarser, reference=reference)[0]
            expected = paper.dfa_layer(current[0], list(past[0]), coarser[0], sd, "dfa.1", heads=2, points=2)
            torch.testing.assert_close(ours, expected, atol=2e-4, rtol=1e-4)
        top = model.dfa[3](torch.randn(1, 64, 4, 4), torch.randn(1, 2, 64, 4, 4), None)
    assert top.shape == (1, 64, 4, 4)


def test_descriptor_is_the_papers_composition(model):
    """The whole aggregation, alignment to GeM, with a displacement per past frame."""
    sd = model.state_dict()
    torch.manual_seed(3)
    bev = torch.relu(torch.randn(3, 8, 32, 32))
    cells = torch.tensor([[2.6, -0.7], [1.3, 0.4], [0.0, 0.0]])
    expected = paper.descriptor(list(bev), [tuple(c.tolist()) for c in cells], sd, heads=2, points=2, stages=3)
    with torch.no_grad():
        for reference in (False, True):
            ours = model.aggregate(bev, cells, reference, None)[0]
            torch.testing.assert_close(ours, expected, atol=2e-4, rtol=1e-3)


def test_batched_windows_are_the_windows_one_by_one(model):
    torch.manual_seed(4)
    bev = torch.relu(torch.randn(6, 8, 32, 32))
    cells = torch.randn(6, 2)
    with torch.no_grad():
        both = model.aggregate(bev, cells, False, None)
        one = torch.cat(
            [model.aggregate(bev[:3], cells[:3], False, None), model.aggregate(bev[3:], cells[3:], False, None)]
        )
    torch.testing.assert_close(both, one, atol=1e-5, rtol=1e-5)
