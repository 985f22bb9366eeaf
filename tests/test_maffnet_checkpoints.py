"""Upstream MAFF-Net checkpoints load into every MAFF-Net card with every key accounted for.

The upstream key inventory (tests/references/maffnet_upstream_keys.py) was written from upstream's
modules and configs and checked against upstream's own ``MAFF_Net.state_dict()``.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import invoke, one_error_line
from references.maffnet_upstream_keys import openpcdet_checkpoint, upstream_state_dict, upstream_state_dict_shapes

from radaredge.cards import load_card
from radaredge.models import create_model, load_checkpoint
from radaredge.models.maffnet.model import STAGE_TWO_PREFIXES, UNUSED_FUSER_KEYS, UNUSED_VFE_KEYS

ROOT = Path(__file__).resolve().parents[1]
FUSER_RULE = "upstream fuser parameters with no effect at test time"
VFE_RULE = "upstream RadarPillarVFE_TJ's zero-width SE layer, never called"
STAGE_ONE_RULE = "stage-two modules on a stage-one card"


@pytest.mark.parametrize(
    "card, dataset",
    [
        ("maffnet-vod-full", "vod"),
        ("maffnet-vod", "vod"),
        ("maffnet-tj4d", "tj4d"),
        ("maffnet-tj4d-full", "tj4d"),
        ("maffnet-vod-full-dbscan", "vod"),
        ("maffnet-tj4d-full-dbscan", "tj4d"),
    ],
)
def test_upstream_checkpoint_loads_with_every_key_accounted_for(card, dataset, tmp_path):
    model = create_model(load_card(ROOT / "models" / f"{card}.yaml"))
    own = model.state_dict()
    upstream = upstream_state_dict(dataset, seed=3)
    torch.save(openpcdet_checkpoint(upstream), tmp_path / "ckpt.pth")
    report = load_checkpoint(model, tmp_path / "ckpt.pth")
    dropped = {rule: set(keys) for rule, keys in report.dropped.items()}
    assert report.ignored == ["global_step"]
    assert report.loaded == len(own)
    assert len(dropped.pop(FUSER_RULE)) == 47
    summary = report.summary()
    assert summary.startswith(f"loaded {len(own)} tensors from {tmp_path / 'ckpt.pth'}; ")
    assert f"dropped 47 ({FUSER_RULE})" in summary and summary.endswith("ignored global_step")
    if dataset == "tj4d":
        assert dropped.pop(VFE_RULE) == {"vfe.se.fc.0.weight", "vfe.se.fc.2.weight"}
    if "-full" not in card:
        assert {k.split(".")[0] for k in dropped.pop(STAGE_ONE_RULE)} == {"pfe", "point_head", "roi_head"}
    assert not dropped
    # the loaded tensors are upstream's, bit for bit
    for k, v in model.state_dict().items():
        assert torch.equal(v, upstream[k]), k
    # every dropped key is named by a documented prefix, and the docs list each prefix
    docs = (ROOT / "docs" / "models" / "maffnet.md").read_text()
    for prefix in (*UNUSED_FUSER_KEYS, *UNUSED_VFE_KEYS, *STAGE_TWO_PREFIXES):
        assert f"`{prefix}" in docs, prefix


def test_stage_two_keys_of_the_full_cards_are_upstreams():
    for card, dataset in (("maffnet-vod-full", "vod"), ("maffnet-tj4d-full", "tj4d")):
        own = {
            k: tuple(v.shape) for k, v in create_model(load_card(ROOT / "models" / f"{card}.yaml")).state_dict().items()
        }
        up = upstream_state_dict_shapes(dataset)
        two = {k: s for k, s in up.items() if k.startswith(STAGE_TWO_PREFIXES)}
        assert {k: own.get(k) for k in two} == two, card


class ModelCardLike:
    """Any object a weights-only load must refuse to unpickle."""


def test_bad_checkpoints_end_with_one_clear_error(tmp_path):
    tiny = ROOT / "tests" / "cards" / "maffnet-tiny.yaml"
    model = create_model(load_card(tiny))
    state = model.state_dict()

    def export(path):
        return invoke(
            "export", "--model", "maffnet-tiny", "--config", tiny, "--checkpoint", path, "--output", tmp_path / "x.onnx"
        )

    torch.save({"model_state": state}, tmp_path / "good.pth")
    data = (tmp_path / "good.pth").read_bytes()
    (tmp_path / "truncated.pth").write_bytes(data[: len(data) // 2])
    one_error_line(export(tmp_path / "truncated.pth"), "truncated.pth", "not a file written by torch.save")
    torch.save([1, 2, 3], tmp_path / "list.pth")
    one_error_line(export(tmp_path / "list.pth"), "list.pth", "expected a state_dict mapping, got list")
    torch.save({"model_state": state, "optimizer": ModelCardLike()}, tmp_path / "object.pth")
    one_error_line(export(tmp_path / "object.pth"), "object.pth", "objects other than tensors", "no pickled code")
    import pickle

    (tmp_path / "plain.pkl").write_bytes(pickle.dumps({"a": 1}))
    one_error_line(export(tmp_path / "plain.pkl"), "plain.pkl", "not a file written by torch.save")
    torch.save({"model_state": {**state, "dense_head.conv_cls.weight": torch.zeros(3, 3)}}, tmp_path / "shape.pth")
    one_error_line(export(tmp_path / "shape.pth"), "dense_head.conv_cls.weight (checkpoint (3, 3), model")
    torch.save(
        {"model_state": {k: v for k, v in state.items() if k != "vfe.pfn_layers.0.linear.weight"}},
        tmp_path / "missing.pth",
    )
    one_error_line(export(tmp_path / "missing.pth"), "missing keys (1): vfe.pfn_layers.0.linear.weight")
    torch.save({"model_state": {**state, "fuser.extra.weight": torch.zeros(2)}}, tmp_path / "extra.pth")
    one_error_line(export(tmp_path / "extra.pth"), "unexpected keys (1): fuser.extra.weight")
    torch.save({"model_state": {**state, "vfe.pfn_layers.0.linear.weight": 3}}, tmp_path / "value.pth")
    one_error_line(export(tmp_path / "value.pth"), "named tensors", "vfe.pfn_layers.0.linear.weight")
    one_error_line(export(tmp_path / "nowhere.pth"), "nowhere.pth does not exist")
    # TJ4D's never-called SE layer is dropped only as upstream builds it, zero-width
    torch.save({"model_state": {**state, "vfe.se.fc.0.weight": torch.zeros(2, 11)}}, tmp_path / "se.pth")
    one_error_line(export(tmp_path / "se.pth"), "unexpected keys (1): vfe.se.fc.0.weight")
    torch.save({"model_state": {**state, "vfe.se.fc.0.weight": torch.zeros(0, 11)}}, tmp_path / "se0.pth")
    assert load_checkpoint(model, tmp_path / "se0.pth").dropped == {VFE_RULE: ["vfe.se.fc.0.weight"]}
    assert not (tmp_path / "x.onnx").exists()
