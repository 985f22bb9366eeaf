"""Des4Pos training (radaredge/training/des4pos.py) on a tiny card and a small synthetic city."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import radaredge
from radaredge.cards import card_from_yaml, load_card
from radaredge.data.text_city import write_cities
from radaredge.data.text_maps import load_text_maps
from radaredge.errors import ConfigError
from radaredge.models import create_model
from radaredge.training.des4pos import (
    TextRecipe,
    _padded_hints,
    backbone_features,
    cell_descriptors,
    coarse_metrics,
    geometry_features,
    hint_fine_features,
    hint_table,
    info_nce,
    text_descriptors,
)

TINY = Path(__file__).parent / "cards" / "des4pos-tiny.yaml"


@pytest.fixture(scope="module")
def card():
    return load_card(TINY)


@pytest.fixture(scope="module")
def city_dir(tmp_path_factory, card):
    d = tmp_path_factory.mktemp("cities")
    write_cities(d, card, 1, seed=7, poses=160)
    return d


def _training_recall(card, model, root) -> float:
    """Cell-retrieval recall@1 (%) of the training descriptions among the city's cells."""
    cell, text = model.cell_config, model.text_config
    maps = load_text_maps(root, cell.max_objects, cell.points_per_object, text.max_hints, None, 0)
    table = hint_table(card, maps)
    tokens, tmask = backbone_features(model, table, "cpu")
    with torch.no_grad():
        prior = model.text.prior_tokens(tokens, tmask)
    geometry = geometry_features(model, maps, "cpu")
    train_q = np.flatnonzero(~maps.validation)
    cells = np.arange(len(maps.cells.ids))
    return coarse_metrics(model, maps, prior, tmask, geometry, train_q, cells, "cpu", table)["cell_R@1"]


def test_coarse_stage_lowers_infonce_and_raises_recall(card, city_dir, tmp_path):
    seeded = create_model(card)
    before = _training_recall(card, seeded, city_dir)
    report = radaredge.train(
        card,
        city_dir,
        tmp_path / "run",
        options={"stages": "coarse", "coarse_epochs": 5, "coarse_batch": 16, "coarse_lr": 2e-3},
    )
    rows = [r for r in report.epochs if r["stage"] == "coarse"]
    assert len(rows) == 5 and report.data["training_poses"] == 144  # 9 steps an epoch, 45 in all
    assert rows[-1]["loss"] < 0.8 * rows[0]["loss"], [r["loss"] for r in rows]
    trained = create_model(card, tmp_path / "run" / "best.pth")
    after = _training_recall(card, trained, city_dir)
    assert after >= before + 10.0, (before, after)
    log = json.loads((tmp_path / "run" / "train-log.json").read_text())
    assert log["stage_best"]["coarse"] == report.best_epoch


def test_all_stages_run_resume_and_keep_each_stages_best(card, city_dir, tmp_path):
    opts = {
        "object_epochs": 1,
        "prior_epochs": 1,
        "coarse_epochs": 1,
        "hints_epochs": 1,
        "fine_epochs": 2,
        "coarse_batch": 16,
    }
    report = radaredge.train(card, city_dir, tmp_path / "run", options=opts)
    assert [r["stage"] for r in report.epochs] == ["objects", "prior", "coarse", "hints", "fine", "fine"]
    assert set(report.stage_best) == {"objects", "prior", "coarse", "hints", "fine"}
    text = "\n".join(report.lines())
    assert "object_acc" in text and "prior_cosine" in text and "cell_R@1" in text and "fine_error_m" in text
    more = radaredge.train(card, city_dir, tmp_path / "run", resume=True, options={**opts, "fine_epochs": 3})
    assert [r["stage"] for r in more.epochs] == ["objects", "prior", "coarse", "hints", "fine", "fine", "fine"]
    best = torch.load(tmp_path / "run" / "best.pth", map_location="cpu", weights_only=False)
    assert "fine_error_m" in best["metrics"] and "cell_R@1" in best["metrics"]


def test_resume_continues_as_the_uninterrupted_run(card, city_dir, tmp_path):
    """A stage stopped after epoch 2 and resumed runs epoch 3 as the run that never stopped
    (weights, Adam moments, random states); a finished stage resumed with more epochs keeps its
    best epoch unless a new one beats it."""
    opts = {"stages": "fine", "fine_lr": 3e-3}
    straight = radaredge.train(card, city_dir, tmp_path / "a", options={**opts, "fine_epochs": 3})
    radaredge.train(card, city_dir, tmp_path / "b", options={**opts, "fine_epochs": 2})
    resumed = radaredge.train(card, city_dir, tmp_path / "b", resume=True, options={**opts, "fine_epochs": 3})
    strip = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa: E731
    assert strip(resumed.epochs) == strip(straight.epochs)
    assert resumed.stage_best == straight.stage_best
    more = radaredge.train(card, city_dir, tmp_path / "b", resume=True, options={**opts, "fine_epochs": 4})
    errors = {r["epoch"]: r["fine_error_m"] for r in more.epochs}
    assert more.stage_best["fine"] == min(errors, key=errors.get), errors


def test_fine_stage_reruns_from_coarse_weights_with_its_own_encoder(card, city_dir, tmp_path):
    """``coarse_weights``: a fine-stage-only run of a trained model with another fine stage
    (``fine.objects: encoder``) takes every weight outside the fine stage from the checkpoint and
    starts the fine stage seeded; a warm-up epoch at a negligible rate leaves it there, and
    without one it trains. A checkpoint that does not fit outside the fine stage is refused."""
    radaredge.train(
        card, city_dir, tmp_path / "base", options={"stages": "coarse", "coarse_epochs": 1, "coarse_batch": 16}
    )
    ckpt = tmp_path / "base" / "best.pth"
    text = TINY.read_text().replace(
        "fine: {cra_layers: 3, heads: 2, mlp_hidden: 16}",
        "fine: {cra_layers: 4, heads: 2, mlp_hidden: 16, objects: encoder, pool: hints}",
    )
    enc_card = card_from_yaml(text)
    fine = ("fine.", "text.fine_words.", "text.fine_mlp.")
    warm = {
        "stages": "fine",
        "fine_epochs": 1,
        "fine_warmup_epochs": 1,
        "fine_warmup_lr": 1e-9,
        "coarse_weights": str(ckpt),
    }
    radaredge.train(enc_card, city_dir, tmp_path / "warm", options=warm)
    trained, seeded = create_model(card, ckpt).state_dict(), create_model(enc_card).state_dict()
    after = create_model(enc_card, tmp_path / "warm" / "best.pth").state_dict()
    assert any(k.startswith("fine.objects.") for k in after)
    for k, v in after.items():
        if k.startswith(fine):
            torch.testing.assert_close(v, seeded[k], atol=1e-6, rtol=0.0)
        else:
            assert torch.equal(v, trained[k]), k
    run = radaredge.train(
        enc_card,
        city_dir,
        tmp_path / "fine",
        options={**warm, "fine_epochs": 3, "fine_warmup_epochs": 0, "fine_lr": 3e-3},
    )
    losses = [r["loss"] for r in run.epochs]
    assert losses[-1] < losses[0], losses
    moved = create_model(enc_card, tmp_path / "fine" / "best.pth").state_dict()
    assert not torch.equal(moved["fine.objects.pos_encoder.0.weight"], seeded["fine.objects.pos_encoder.0.weight"])
    # fine_text_from: coarse_weights: the fine text branch is the checkpoint's (moved here, so that it
    # differs from the seed), only the CRA starts seeded
    moved_text = {
        k: v + 0.25 if k.startswith(("text.fine_words.", "text.fine_mlp.")) and v.is_floating_point() else v
        for k, v in trained.items()
    }
    torch.save(moved_text, tmp_path / "text.pth")
    radaredge.train(
        enc_card,
        city_dir,
        tmp_path / "text",
        options={**warm, "coarse_weights": str(tmp_path / "text.pth"), "fine_text_from": "coarse_weights"},
    )
    kept = create_model(enc_card, tmp_path / "text" / "best.pth").state_dict()
    for k, v in kept.items():
        if k.startswith("fine."):
            torch.testing.assert_close(v, seeded[k], atol=1e-6, rtol=0.0)
        elif k.startswith(("text.fine_words.", "text.fine_mlp.")) and v.is_floating_point():
            torch.testing.assert_close(v, moved_text[k], atol=1e-6, rtol=0.0)
            assert not torch.equal(v, seeded[k]), k
    with pytest.raises(ConfigError, match="fine_text_from: coarse_weights needs"):
        radaredge.train(
            enc_card, city_dir, tmp_path / "none", options={"stages": "fine", "fine_text_from": "coarse_weights"}
        )
    partial = {k: v for k, v in trained.items() if k != "submap.mfam.v.weight"}
    torch.save(partial, tmp_path / "partial.pth")
    with pytest.raises(ConfigError, match=r"outside the fine stage: missing keys \(1\): submap.mfam.v.weight"):
        radaredge.train(
            enc_card, city_dir, tmp_path / "bad", options={**warm, "coarse_weights": str(tmp_path / "partial.pth")}
        )


def test_hints_stage_warms_the_text_branch_on_the_lstm_states(card, city_dir, tmp_path):
    """The ``hints`` stage is the fine stage on the LSTM states whatever the card's
    ``fine.object_state`` (its first epoch is a card reading the LSTM states' fine epoch, row for
    row) and keeps its last epoch; the ``fine`` stage after it keeps the trained text branch and
    starts the CRA from its seed again (a warm-up epoch at a negligible rate leaves it there)."""
    assert create_model(card).submap.object_state == "mfam"
    lstm_card = card_from_yaml(TINY.read_text().replace("mlp_hidden: 16}", "mlp_hidden: 16, object_state: lstm}"))
    warm = {"fine_lr": 3e-3, "fine_warmup_epochs": 1, "fine_warmup_lr": 1e-9}  # both stages' first epoch
    lstm = radaredge.train(lstm_card, city_dir, tmp_path / "lstm", options={"stages": "fine", "fine_epochs": 1, **warm})
    run = radaredge.train(
        card, city_dir, tmp_path / "run", options={"stages": "hints,fine", "hints_epochs": 2, "fine_epochs": 1, **warm}
    )
    strip = lambda r: {k: v for k, v in r.items() if k not in ("stage", "seconds")}  # noqa: E731
    assert [r["stage"] for r in run.epochs] == ["hints", "hints", "fine"]
    assert strip(run.epochs[0]) == strip(lstm.epochs[0])
    assert run.stage_best["hints"] == 2
    seeded = create_model(card).state_dict()
    kept = create_model(card, tmp_path / "run" / "best.pth").state_dict()
    text = [k for k in kept if k.startswith(("text.fine_words.", "text.fine_mlp.")) and kept[k].is_floating_point()]
    assert text and all(not torch.equal(kept[k], seeded[k]) for k in text)
    for k in (k for k in kept if k.startswith("fine.")):
        torch.testing.assert_close(kept[k], seeded[k], atol=1e-6, rtol=0.0)


def test_info_nce_masks_copies_of_the_same_cell():
    text = torch.nn.functional.normalize(torch.randn(4, 8), dim=1)
    ids = torch.tensor([0, 0, 1, 2])
    masked = info_nce(text, text.clone(), ids, 0.1, True)
    counted = info_nce(text, text.clone(), ids, 0.1, False)
    assert masked < counted  # the duplicate is no longer a negative
    # a perfect, well-separated pairing approaches zero loss
    eye = torch.eye(4)
    assert float(info_nce(eye, eye, torch.arange(4), 0.01, True)) < 1e-6


@pytest.mark.parametrize(
    "options, match",
    [
        ({"stages": "coarse,warmup"}, "unknown"),
        ({"coarse_lr": -1.0}, "coarse-lr"),
        ({"duplicate_cells": "drop"}, "duplicate_cells"),
        ({"shuffle_hints": 1}, "true or false"),
        ({"negatives": 8}, "unknown Des4Pos training option"),
    ],
)
def test_recipe_options_are_checked(options, match):
    with pytest.raises(ConfigError, match=match):
        TextRecipe.from_options(options)


def test_tensors_made_in_the_training_path_follow_the_input_device(card, city_dir):
    """Every tensor the model and the training helpers make takes its device from their inputs
    (CUDA training): with meta as the default device, a tensor made without one lands on meta and
    mixing it with the CPU inputs fails, so CPU results prove none was made."""
    model = create_model(card)
    cell, text = model.cell_config, model.text_config
    maps = load_text_maps(city_dir, cell.max_objects, cell.points_per_object, text.max_hints, None, 0)
    table = hint_table(card, maps)
    cells = np.arange(4)
    with torch.device("meta"):
        tokens, tmask = backbone_features(model, table, "cpu")
        prior = model.text.prior_tokens(tokens, tmask)
        geometry = geometry_features(model, maps, "cpu")
        outs = [
            *cell_descriptors(model, maps, cells, geometry, "cpu"),
            *cell_descriptors(model, maps, cells, None, "cpu"),
        ]
        model.train()
        desc, objects = cell_descriptors(model, maps, cells, None, "cpu")
        rows, hmask = _padded_hints(maps, table, np.flatnonzero(~maps.validation)[:4], None)
        t = text_descriptors(model, prior, tmask, rows, hmask)
        fine = hint_fine_features(model, prior, tmask, rows)
        offsets = model.fine.offsets(objects, torch.from_numpy(maps.cells.object_mask[cells]), fine, hmask)
        (desc.sum() + t.sum() + offsets.sum()).backward()
        model.eval()
    outs += [tokens, prior, geometry, desc, t, offsets]
    assert all(o.device.type == "cpu" and torch.isfinite(o).all() for o in outs)
    grads = {n: p.grad for n, p in model.submap.named_parameters() if p.grad is not None}
    assert {"mfam.o.weight", "lstm.weight_hh_l0", "objects.mlp_merge.0.0.weight"} <= set(grads) and all(
        g.device.type == "cpu" for g in grads.values()
    ), sorted(grads)
