"""Des4Pos's MFAM, text heads and CRA against plain formulations of the paper's equations
(tests/references/des4pos_paper.py, which shares no code with radaredge), and MFAM's
sensitivity to one object."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from references import des4pos_paper as paper

from radaredge.cards import load_card
from radaredge.data.text_city import make_city_for_card
from radaredge.models import create_model
from radaredge.models.des4pos.model import MFAM

TINY = Path(__file__).parent / "cards" / "des4pos-tiny.yaml"


@pytest.fixture(scope="module")
def card():
    return load_card(TINY)


@pytest.fixture(scope="module")
def model(card):
    torch.manual_seed(11)
    m = create_model(card)
    with torch.no_grad():  # seeded biases are small; make every term count
        for name, p in m.named_parameters():
            if not name.startswith("text.backbone") and name.endswith("bias"):
                p.normal_(0, 0.3)
    return m


def _sd(module) -> dict:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


@pytest.mark.parametrize("form", ["residual", "paper"])
def test_mfam_matches_eq_4_5(form):
    torch.manual_seed(3)
    d, heads = 16, 4
    block = MFAM(d, heads, form).eval()
    rng = np.random.default_rng(0)
    s = torch.from_numpy(rng.normal(size=(2, 7, d)).astype(np.float32))
    mask = torch.tensor([[1, 1, 1, 1, 0, 0, 0], [1, 1, 1, 1, 1, 1, 1]], dtype=torch.bool)
    s_pad = s.clone()
    s_pad[0, 4:] = float("nan")  # padding content never reaches a real object
    with torch.no_grad():
        out = block(s_pad, mask)
    sd = {f"mfam.{k}": v for k, v in _sd(block).items()}
    for b in range(2):
        n = int(mask[b].sum())
        want = paper.mfam(s[b, :n], sd, "mfam", heads, residual=form == "residual")
        np.testing.assert_allclose(out[b, :n].numpy(), want.numpy(), atol=2e-5)
    assert torch.isfinite(out[0, :4]).all()


def test_text_heads_match_the_alignment_head(model, card):
    heads = card.get("text.align_heads")
    rng = np.random.default_rng(1)
    p = card.get("text.prior_dim")
    lengths = [[5, 9, 3], [7, 4, 0]]  # tokens per hint; 0: a padding hint
    tokens = torch.from_numpy(rng.normal(size=(2, 3, 9, p)).astype(np.float32))
    tmask = torch.tensor([[[t < n for t in range(9)] for n in row] for row in lengths])
    hmask = tmask.any(-1)
    tmask_flat = tmask.reshape(6, 9) | ~hmask.reshape(6, 1)  # a padding hint's tokens are masked by its hint
    with torch.no_grad():
        coarse, fine = model.text.heads(tokens.reshape(6, 9, p), tmask_flat)
        desc = model.text.pool(coarse.reshape(2, 3, -1), hmask)
    sd = _sd(model)
    for b in range(2):
        real = [tokens[b, h, :n] for h, n in enumerate(lengths[b]) if n]
        want_desc, want_fine = paper.text_heads(real, sd, "text", heads)
        np.testing.assert_allclose(desc[b].numpy(), want_desc.numpy(), atol=2e-5)
        np.testing.assert_allclose(fine.reshape(2, 3, -1)[b, : len(real)].numpy(), want_fine.numpy(), atol=2e-4)


def test_cra_matches_eq_10_12(model, card):
    heads, layers, d = card.get("fine.heads"), card.get("fine.cra_layers"), card.get("submap.embed_dim")
    rng = np.random.default_rng(2)
    objects = torch.from_numpy(rng.normal(size=(2, 6, d)).astype(np.float32))
    omask = torch.tensor([[1, 1, 1, 0, 0, 0], [1, 1, 1, 1, 1, 1]], dtype=torch.bool)
    hints = torch.from_numpy(rng.normal(size=(2, 4, d)).astype(np.float32))
    hmask = torch.tensor([[1, 1, 1, 1], [1, 1, 0, 0]], dtype=torch.bool)
    with torch.no_grad():
        off = model.fine.offsets(objects, omask, hints, hmask)
    sd = _sd(model)
    for k in range(2):
        want = paper.cra_offset(objects[k][omask[k]], hints[k][hmask[k]], sd, "fine", heads, layers)
        np.testing.assert_allclose(off[k].numpy(), want.numpy(), atol=2e-5)


def test_one_objects_points_move_the_cell_descriptor():
    """With ``mfam: residual`` (the card's default) replacing one object's points moves the
    seeded full card's descriptor by ~1e-2; eq. 4-5 alone (``mfam: paper``) by ~1e-5, which is
    what the default is there to avoid."""
    card = load_card("des4pos")
    model = create_model(card)
    city = make_city_for_card(card, seed=3, poses=0)
    c = int(np.argmax(city.object_mask.sum(1)))
    pts, cnt, mask = city.points[c : c + 1], city.num_points[c : c + 1], city.object_mask[c : c + 1]
    other = city.points[(c + 20) % len(city.ids), 0]
    moved = {}
    for form in ("residual", "paper"):
        model.submap.mfam.form = form
        with torch.no_grad():
            d0 = model.submap(*map(torch.from_numpy, (pts, cnt, mask)))[0]
            for slot in (0, int(mask.sum()) - 1):
                changed = pts.copy()
                changed[0, slot] = other
                d1 = model.submap(*map(torch.from_numpy, (changed, cnt, mask)))[0]
                moved[form, slot] = float((d0 - d1).norm())
    assert all(moved["residual", s] > 2e-3 for s in (0, int(mask.sum()) - 1)), moved
    assert all(moved["residual", s] > 100 * moved["paper", s] for s in (0, int(mask.sum()) - 1)), moved
