"""TDFANet end to end on the tiny card: export formulation == reference, ONNX parity, checkpoints,
divergence localisation. The full cards are exported and parity-checked in test_cli.py."""

import numpy as np
import pytest
import torch
from conftest import TINY_CARD as TINY

import radaredge
from radaredge.cards import load_card
from radaredge.checking.check import check_graph
from radaredge.errors import ConfigError
from radaredge.models import create_model, load_checkpoint, model_spec


@pytest.fixture(scope="module")
def card():
    return load_card(TINY)


@pytest.fixture(scope="module")
def exported(tiny_export):
    _, model, onnx_path, debug_path = tiny_export
    return model, onnx_path, debug_path


def test_export_formulation_equals_reference(card):
    model = create_model(card)
    spec = model_spec(card).graph()
    for name, feeds in spec.make_cases(card, 8, 5):
        with torch.no_grad():
            ref = spec.run_reference(model, feeds)
            exp = spec.run_export(model, {k: torch.from_numpy(v) for k, v in feeds.items()})
        np.testing.assert_allclose(exp["ego_velocity"], ref["ego_velocity"], atol=1e-4, err_msg=name)
        cos = torch.nn.functional.cosine_similarity(exp["descriptor"], ref["descriptor"], dim=0)
        assert cos >= 0.9999, name
        assert torch.equal(exp["ego_valid"], ref["ego_valid"]), name


def test_outputs_are_shaped_and_normalised(card):
    model = create_model(card)
    _, feeds = model_spec(card).graph().make_cases(card, 1, 0)[0]
    with torch.no_grad():
        out = model_spec(card).graph().run_export(model, {k: torch.from_numpy(v) for k, v in feeds.items()})
    assert out["descriptor"].shape == (32,)
    assert abs(float(out["descriptor_normalized"].norm()) - 1.0) < 1e-5
    assert out["ego_velocity"].shape == (3, 3) and out["ego_valid"].shape == (3,)


def test_onnx_parity_passes_on_all_case_kinds(card, exported):
    model, onnx_path, _ = exported
    report = radaredge.parity(card, onnx_path, model=model, cases=8, seed=1)
    assert report, report.to_dict()
    s = report.graph().summary
    assert s["descriptor_normalized"].min_cosine >= 0.9999 and s["descriptor_normalized"].retrieval_top1 == 1.0
    assert s["ego_velocity"].max_abs <= 1e-4
    kinds = {c["case"].split("-", 1)[1] for c in report.graph().cases}
    assert kinds == {"drive", "dynamic-40%", "tiny-scans", "out-of-range"}


def test_parity_names_the_first_diverging_tensor(card, exported):
    model, onnx_path, debug_path = exported
    broken = create_model(card)
    with torch.no_grad():
        broken.vfe.pfn_layers[0].linear.weight.mul_(1.5)  # reference now differs from the ONNX
    graph = model_spec(card).graph()
    report = check_graph(card, graph, broken, onnx_path, cases_n=2, seed=0, debug_onnx=debug_path)
    assert not report
    assert report.divergence["tensor"] == "bev"
    late = create_model(card)
    with torch.no_grad():
        late.dfa[0].ffn[0].weight.mul_(1.5)
    report = check_graph(card, graph, late, onnx_path, cases_n=2, seed=0, debug_onnx=debug_path)
    assert not report and report.divergence["tensor"] == "aggregated_l0"


def test_checkpoint_round_trip_and_mismatch_report(card, tmp_path):
    model = create_model(card)
    torch.save(model.state_dict(), tmp_path / "ok.pth")
    other = create_model(card)
    with torch.no_grad():
        for p in other.parameters():
            p.zero_()
    load_checkpoint(other, tmp_path / "ok.pth")
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), other.state_dict().values()))
    sd = model.state_dict()
    sd["extra.weight"] = torch.zeros(1)
    del sd["mlp.0.bias"]
    sd["gem.p"] = torch.zeros(2)
    torch.save(sd, tmp_path / "bad.pth")
    with pytest.raises(ConfigError) as err:
        load_checkpoint(model, tmp_path / "bad.pth")
    msg = str(err.value)
    assert "mlp.0.bias" in msg and "extra.weight" in msg and "gem.p" in msg


def test_card_errors_name_the_field(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(TINY.read_text().replace("heads: 2", "heads: 3"))
    with pytest.raises(ValueError, match="divisible"):
        create_model(load_card(bad))
    bad.write_text(TINY.read_text().replace("num_hypotheses: 32", "num_hypothesis: 32"))
    with pytest.raises(ConfigError, match="num_hypothesis"):
        create_model(load_card(bad))


def test_debug_export_follows_the_pyramid_depth(tmp_path):
    card_path = tmp_path / "two-stage.yaml"
    card_path.write_text(TINY.read_text().replace("pyramid_stages: 3", "pyramid_stages: 2"))
    card = load_card(card_path)
    res = radaredge.export(card, tmp_path / "two.onnx", model=create_model(card), debug=True)
    import json

    outputs = json.loads(res.debug["tdfanet"].with_suffix(".json").read_text())["debug_outputs"]
    assert outputs == ["ego_velocity", "bev", "aligned_bev", "aggregated_l2", "aggregated_l1", "aggregated_l0"]
