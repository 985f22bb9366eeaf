"""Quantisation-aware fine-tuning (radaredge train --qat): the fake quantisation is onnxruntime's int8
grid, leaves the network's weights and modules as they are, and the int8 export takes the ranges it learned."""

from __future__ import annotations

import copy
import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from conftest import MAFFNET_TINY_CARD, TINY_CARD, invoke, one_error_line
from onnx import numpy_helper
from onnxruntime.quantization.quant_utils import compute_scale_zp, get_qmin_qmax_for_qType

import radaredge
from radaredge import runtime
from radaredge.cards import load_card, parse_card
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.errors import ConfigError
from radaredge.exporting.quantize import quantize_int8
from radaredge.models import create_model, model_spec
from radaredge.models.factory import save_checkpoint
from radaredge.training.qat import FakeQuantizedLayers, fake_quantize_weight, resume_signature


@pytest.mark.parametrize("seven_bit", [True, False])
def test_weight_fake_quantisation_is_onnxruntimes_per_channel_grid(seven_bit):
    """Per output channel, symmetric: the values onnxruntime's quantiser writes for the same weights
    (its own scale and zero point), and a per-channel factor (a folded batch norm, of either sign)
    commutes with it."""
    w = torch.randn(6, 4, 3, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor(
        [0.01, 0.1, 1.0, 3.0, 0.5, 20.0]
    ).view(6, 1, 1, 1)
    qmin, qmax = get_qmin_qmax_for_qType(onnx.TensorProto.INT8, reduce_range=seven_bit, symmetric=True)
    want = np.empty_like(w.numpy())
    for c, wc in enumerate(w.numpy()):
        zero, scale = compute_scale_zp(wc.min(), wc.max(), qmin, qmax, symmetric=True)
        want[c] = (np.clip(np.round(wc / scale) + zero, qmin, qmax) - zero) * scale
    got = fake_quantize_weight(w, seven_bit)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-6, atol=1e-7)
    k = torch.tensor([0.3, -2.0, 1.7, 0.01, -0.5, 4.0]).view(6, 1, 1, 1)
    torch.testing.assert_close(fake_quantize_weight(w * k, seven_bit), got * k, rtol=1e-5, atol=1e-6)


def _window(card, seed=5):
    feeds = model_spec(card).graph().make_cases(card, 1, seed)[0][1]
    return feeds, [torch.from_numpy(v) for v in feeds.values()]


def test_fake_quantisation_leaves_the_network_as_it_is_and_comes_out_again():
    """Same state-dict keys and modules; in eval mode after observing a window the descriptor moves
    (the int8 rounding), and after remove() it is the fp32 network's again; the card's keep_fp32
    modules are not fake-quantised."""
    card = load_card(TINY_CARD)
    model = create_model(card).eval()
    _, args = _window(card)
    keys = list(model.state_dict())
    with torch.no_grad():
        fp32 = model(*args)[1]
        fq = FakeQuantizedLayers(model, card)
        with fq.observing():
            model(*args)
        quantised = model(*args)[1]
        assert list(model.state_dict()) == keys
        assert 0.9 < float((quantised * fp32).sum()) < 1 - 1e-6
        assert all(len(r["input"]) == 2 for r in fq.ranges().values())
        fq.remove()
        torch.testing.assert_close(model(*args)[1], fp32)
    kept = FakeQuantizedLayers(model, parse_card({**card.data, "quantization": {"keep_fp32": ["dfa.*"]}}))
    assert kept.layers and not any(name.startswith("dfa.") for name in kept.layers)
    kept.remove()


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    root = tmp_path_factory.mktemp("qat-town")
    make_pr_benchmark(root / "town-1", drives=3, frames_per_drive=20, seed=1)
    return root


def _train_tiny(town, out, *extra):
    res = invoke(
        "train",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--data",
        town,
        "--output",
        out,
        "--epochs",
        1,
        "--set",
        "tuples_per_epoch=2",
        "--json",
        *extra,
    )
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout)


def _scale_of(model: onnx.ModelProto, tensor: str) -> float:
    """The scale of the QuantizeLinear that quantises ``tensor`` in a QDQ graph."""
    inits = {i.name: i for i in model.graph.initializer}
    q = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == tensor)
    return float(numpy_helper.to_array(inits[q.input[1]]))


def test_qat_fine_tunes_tdfanet_keeps_its_ranges_and_resumes(town, tmp_path):
    """A --qat run from a checkpoint writes the int8 settings and its ranges into best.pth, its
    observers into last.pth, and --resume goes on with them."""
    card = load_card(TINY_CARD)
    start = tmp_path / "start.pth"
    save_checkpoint(create_model(card), start)
    _train_tiny(town, tmp_path / "run", "--checkpoint", start, "--qat")
    _train_tiny(town, tmp_path / "run", "--resume", "--epochs", 2, "--qat")
    entry = torch.load(tmp_path / "run" / "best.pth", weights_only=True)["qat"]
    assert entry["reduce_range"] is True and entry["keep_fp32"] == []
    fq = FakeQuantizedLayers(create_model(card), card)
    assert set(entry["ranges"]) <= set(fq.layers) and len(entry["ranges"]) > len(fq.layers) / 2  # layers that saw data
    fq.load_state_dict(torch.load(tmp_path / "run" / "last.pth", weights_only=True)["qat"])
    assert sorted(fq.ranges()) == sorted(entry["ranges"])


def test_the_int8_export_takes_the_learned_ranges_and_follows_the_simulation(tiny_export, tmp_path):
    """quantize_int8 with a --qat entry quantises the learned tensors with the learned scales
    (the metadata counts them), and the int8 descriptor is nearer the fake-quantised torch
    network's than the fp32 network's is."""
    card, exported_model, fp32_path, _ = tiny_export
    model = copy.deepcopy(exported_model).eval()
    fq = FakeQuantizedLayers(model, card)
    with torch.no_grad(), fq.observing():
        for seed in range(20, 24):
            model(*_window(card, seed)[1])
    entry, state = fq.checkpoint_entry(), fq.state_dict()
    int8_path = quantize_int8(card, fp32_path, tmp_path / "t.int8.onnx", calibration_cases=4, qat=entry)
    meta = json.loads(runtime.load(int8_path).metadata["radaredge.quantization"])["qat"]
    assert meta["layers"] == len(entry["ranges"]) and meta["tensors"] >= meta["layers"]
    graph = onnx.load(str(int8_path))
    scales = [_scale_of(graph, n.input[0]) for n in graph.graph.node if n.op_type == "QuantizeLinear"]
    for layer in ("pyramid.0.conv1", "mlp.0"):
        lo, hi = min(entry["ranges"][layer]["input"][0], 0.0), max(entry["ranges"][layer]["input"][1], 0.0)
        assert any(abs(s - (hi - lo) / 255) <= 1e-6 * (hi - lo) for s in scales), layer
    session = ort.InferenceSession(str(int8_path), providers=["CPUExecutionProvider"])
    nearer = []
    for seed in range(4):
        feeds, args = _window(card, seed)
        int8 = session.run(["descriptor_normalized"], feeds)[0][0]
        with torch.no_grad():
            simulated = model(*args)[1][0].numpy()
            fq.remove()
            fp32 = model(*args)[1][0].numpy()
            fq = FakeQuantizedLayers(model, card)
            fq.load_state_dict(state)
        nearer.append(np.linalg.norm(int8 - simulated) < np.linalg.norm(int8 - fp32))
    assert sum(nearer) >= 3, nearer


def test_qat_refuses_what_it_cannot_simulate(town, tmp_path):
    res = invoke(
        "train", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--data", town, "--output", tmp_path / "r", "--qat"
    )
    one_error_line(res, "--qat fine-tunes trained weights: pass --checkpoint")


def test_qat_fine_tunes_maffnet_and_an_export_with_another_weight_range_is_refused(tmp_path):
    """The MAFF-Net recipe takes --qat too; a card whose quantization.reduce_range differs from the
    one fine-tuned for is refused before an export."""
    data = tmp_path / "set"
    res = invoke(
        *("make-benchmark", "--task", "detection", "--out", data),
        *("--drives", 3, "--frames", 8, "--seed", 3, "--version", 1),
    )
    assert res.exit_code == 0, res.output
    card = load_card(MAFFNET_TINY_CARD)
    start = tmp_path / "start.pth"
    save_checkpoint(create_model(card), start)
    res = invoke(
        "train",
        "--model",
        "maffnet-tiny",
        "--config",
        MAFFNET_TINY_CARD,
        "--data",
        data,
        "--output",
        tmp_path / "run",
        "--checkpoint",
        start,
        "--qat",
        "--epochs",
        1,
        "--batch-size",
        2,
        "--set",
        "train_frames=4",
        "--set",
        "qat_scans=4",
        "--set",
        "bn_scans=4",
    )
    assert res.exit_code == 0, res.output
    entry = torch.load(tmp_path / "run" / "best.pth", weights_only=True)["qat"]
    assert "backbone_2d.blocks.0.1" in entry["ranges"] and entry["ranges"]["backbone_2d.blocks.0.1"]["output"][0] == 0
    full_range = tmp_path / "card.yaml"
    text = MAFFNET_TINY_CARD.read_text()
    assert "reduce_range" not in text
    full_range.write_text(text + "\nquantization:\n  reduce_range: false\n")
    with pytest.raises(ConfigError, match="fine-tuned with fake quantisation for quantization.reduce_range = True"):
        radaredge.export(full_range, tmp_path / "x.onnx", checkpoint=tmp_path / "run" / "best.pth", quantize="int8")


def test_a_run_from_before_the_qat_options_still_resumes():
    """The resume signature leaves the qat options out while qat is off (a last.pth written before
    they existed matches), and keeps them when it is on."""
    assert resume_signature({"lr": 0.01, "qat": False, "qat_scans": 32}) == {"lr": 0.01}
    assert resume_signature({"lr": 0.01, "qat": True, "qat_scans": 8}) == {"lr": 0.01, "qat": True, "qat_scans": 8}
