"""`radaredge card from-openpcdet`: MAFF-Net cards from OpenPCDet configs, every key accounted for.

The fixtures under tests/fixtures/openpcdet/ hold the keys and values of TRV-Lab/MAFF-Net's VoD and
TJ4D configs and their dataset configs. With ``RADAREDGE_UPSTREAM_MAFFNET`` pointing at a checkout
of TRV-Lab/MAFF-Net, the round trip also runs on upstream's own files.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
from pathlib import Path

import pytest
import torch
import yaml

from radaredge.cards import load_card
from radaredge.cards.openpcdet import _leaves, load_openpcdet_config, maffnet_card
from radaredge.errors import ConfigError
from references.maffnet_upstream_keys import CONFIGS, openpcdet_checkpoint, trained_like_state_dict
from conftest import invoke, one_error_line

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures" / "openpcdet"
PROVENANCE = ("name", "description", "source")
# shipped card -> (fixture config, --stage-one, --cfa)
SHIPPED = {
    "maffnet-vod-full-dbscan": ("maffnet_vod.yaml", False, None),
    "maffnet-vod-full": ("maffnet_vod.yaml", False, "grid_density"),
    "maffnet-vod": ("maffnet_vod.yaml", True, "grid_density"),
    "maffnet-tj4d-full-dbscan": ("maffnet_tj4d.yaml", False, None),
    "maffnet-tj4d-full": ("maffnet_tj4d.yaml", False, "grid_density"),
    "maffnet-tj4d": ("maffnet_tj4d.yaml", True, "grid_density"),
}


def _convert(config: Path, stage_one: bool = False, cfa: str | None = None):
    cfg, files = load_openpcdet_config(config)
    return maffnet_card(cfg, files, stage_two=not stage_one, cfa=cfa), cfg


def _without_provenance(card: dict) -> dict:
    return {k: v for k, v in card.items() if k not in PROVENANCE}


@pytest.mark.parametrize("shipped", sorted(SHIPPED))
def test_upstream_configs_convert_to_the_shipped_cards(shipped):
    config, stage_one, cfa = SHIPPED[shipped]
    conversion, _ = _convert(FIXTURES / config, stage_one, cfa)
    card = load_card(shipped).data
    assert _without_provenance(conversion.card) == _without_provenance(card)
    source = conversion.card["source"]
    assert source.get("options") == card["source"].get("options")
    assert source["config"] == config
    assert source["sha256"] == hashlib.sha256((FIXTURES / config).read_bytes()).hexdigest()
    base = source["base_configs"][0]
    assert base["sha256"] == hashlib.sha256((FIXTURES / base["named"]).read_bytes()).hexdigest()


@pytest.mark.skipif(not os.environ.get("RADAREDGE_UPSTREAM_MAFFNET"),
                    reason="set RADAREDGE_UPSTREAM_MAFFNET to a TRV-Lab/MAFF-Net checkout")
@pytest.mark.parametrize("shipped", sorted(SHIPPED))
def test_upstreams_own_config_files_convert_to_the_shipped_cards(shipped):
    config, stage_one, cfa = SHIPPED[shipped]
    upstream = Path(os.environ["RADAREDGE_UPSTREAM_MAFFNET"]) / "tools" / "cfgs" / "MAFF-Net"
    name = {"maffnet_vod.yaml": "MAFF-Net_vod.yaml", "maffnet_tj4d.yaml": "MAFF-Net_TJ4D.yaml"}[config]
    conversion, _ = _convert(upstream / name, stage_one, cfa)     # its _BASE_CONFIG_ is found above the file
    card = load_card(shipped).data
    assert _without_provenance(conversion.card) == _without_provenance(card)
    assert conversion.card["source"] == card["source"]             # the shipped card names these very files


def test_every_config_key_has_one_fate():
    conversion, cfg = _convert(FIXTURES / "maffnet_vod.yaml")
    fates = {k.key: k for k in conversion.keys}
    assert sorted(fates) == sorted(_leaves(cfg)) and len(conversion.keys) == len(fates)
    assert fates["OPTIMIZATION.LR"].fate == "training-only"
    assert fates["DATA_CONFIG.DATA_AUGMENTOR.AUG_CONFIG_LIST[0].NAME"].fate == "training-only"
    assert fates["MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[2].matched_threshold"].fate == "training-only"
    assert fates["MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[2].anchor_sizes"].detail == "dense_head.anchors[2].anchor_sizes"
    assert fates["MODEL.IMAGE_BACKBONE.POINTX"].fate == "ignored"
    assert fates["MODEL.VFE.USE_NORM"].fate == "checked"
    assert fates["MODEL.ROI_HEAD.NMS_CONFIG.TEST.NMS_PRE_MAXSIZE"].detail == "stage_two.proposals.pre_max"
    assert fates["DATA_CONFIG.DATA_PROCESSOR[2].VOXEL_SIZE"].detail == "pillars.voxel_size"
    assert conversion.counts() == {"mapped": 72, "checked": 38, "training-only": 65, "ignored": 12}


def test_base_configs_merge_as_openpcdet_merges_them(tmp_path):
    (tmp_path / "base.yaml").write_text(yaml.safe_dump({"A": {"x": 1, "y": [1, 2]}, "B": 2}))
    (tmp_path / "model.yaml").write_text(yaml.safe_dump({"D": {"_BASE_CONFIG_": "base.yaml", "A": {"y": [3]}},
                                                         "C": 4}))
    merged, files = load_openpcdet_config(tmp_path / "model.yaml")
    # the base's keys first, the node's own merged over them: mappings key by key, lists replaced
    assert merged == {"D": {"A": {"x": 1, "y": [3]}, "B": 2, "_BASE_CONFIG_": "base.yaml"}, "C": 4}
    assert [f.named for f in files] == ["model.yaml", "base.yaml"]
    (tmp_path / "other.yaml").write_text(yaml.safe_dump({"A": {"x": 9}}))
    merged, _ = load_openpcdet_config(tmp_path / "model.yaml", dataset_config=tmp_path / "other.yaml")
    assert merged["D"]["A"] == {"x": 9, "y": [3]}
    (tmp_path / "base.yaml").write_text(yaml.safe_dump({"_BASE_CONFIG_": "other.yaml"}))
    with pytest.raises(ConfigError, match="a base config's own base is not followed"):
        load_openpcdet_config(tmp_path / "model.yaml")
    (tmp_path / "base.yaml").unlink()
    with pytest.raises(ConfigError, match="not found .* pass it with --dataset-config"):
        load_openpcdet_config(tmp_path / "model.yaml")


def _edited(tmp_path: Path, edit, source: str = "maffnet_vod.yaml") -> Path:
    """The fixture config with ``edit(cfg)`` applied, written beside a copy of its dataset config."""
    cfg = yaml.safe_load((FIXTURES / source).read_text())
    edit(cfg)
    base = cfg["DATA_CONFIG"]["_BASE_CONFIG_"]
    (tmp_path / base).write_text((FIXTURES / base).read_text())
    (tmp_path / "edited.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return tmp_path / "edited.yaml"


def _set(path: str, value):
    def edit(cfg):
        *parents, last = path.split(".")
        node = cfg
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node[p]
        node[last] = value
    return edit


@pytest.mark.parametrize("edit, needles", [
    (_set("MODEL.VFE.USE_DOPPLER", True), ["MODEL.VFE.USE_DOPPLER", "no formulation"]),
    (_set("MODEL.VFE.USE_NORM", False), ["MODEL.VFE.USE_NORM", "False is not supported"]),
    (_set("MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG.BOX_CODER", "PointResidualCoder"),
     ["MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG.BOX_CODER", "ResidualCoder"]),
    (_set("MODEL.POST_PROCESSING.NMS_CONFIG.MULTI_CLASSES_NMS", True), ["MULTI_CLASSES_NMS", "class-agnostic"]),
    (_set("MODEL.IMAGE_BACKBONE.DBSCAN_V", 0), ["MODEL.IMAGE_BACKBONE.DBSCAN_V", "batch points"]),
    (_set("MODEL.FUSER.OUT_CHANNEL", 128), ["MODEL.FUSER.OUT_CHANNEL", "NUM_BEV_FEATURES"]),
    (_set("MODEL.PFE.SAMPLE_METHOD", "FPS"), ["MODEL.PFE.SAMPLE_METHOD", "'FPS' is not supported"]),
    (_set("DATA_CONFIG.DATA_PROCESSOR.1.SHUFFLE_ENABLED", {"train": True, "test": True}),
     ["SHUFFLE_ENABLED.test", "order given"]),
    (_set("DATA_CONFIG.DATA_PROCESSOR.2.MAX_NUMBER_OF_VOXELS", {"train": 16000, "test": 1000}),
     ["MAX_NUMBER_OF_VOXELS.test", "at least 2048"]),
    (lambda cfg: cfg["DATA_CONFIG"]["DATA_PROCESSOR"].append({"NAME": "sample_points", "NUM_POINTS": 1024}),
     ["DATA_CONFIG.DATA_PROCESSOR[3]", "sample_points"]),
    (_set("MODEL.NAME", "PVRCNN"), ["MODEL.NAME", "MAFF_Net"]),
    # a valid-looking config the model cannot build: the CFA map must cover the pillar grid
    (_set("MODEL.IMAGE_BACKBONE.DBSCAN_MAP_W", 300), ["cfa.dbscan is 300 x 320 cells but the pillar grid is 320 x 320"]),
])
def test_unknown_or_unsupported_keys_end_with_one_error_line(tmp_path, edit, needles):
    res = invoke("card", "from-openpcdet", _edited(tmp_path, edit), "--out", tmp_path / "card.yaml")
    one_error_line(res, *needles)
    assert not (tmp_path / "card.yaml").exists()


def _modified(cfg: dict) -> None:
    """Another sensor: a 25.6 m range, a fourth class with its anchors, the point columns in another
    order, the VFE without the time column, the CFA's DBSCAN_V moved to where v_r_comp now is, and
    a lighter 2-D backbone."""
    cfg["CLASS_NAMES"].append("Truck")
    cfg["DATA_CONFIG"]["POINT_CLOUD_RANGE"] = [0, -12.8, -3, 25.6, 12.8, 2]
    cfg["DATA_CONFIG"]["POINT_FEATURE_ENCODING"] = {
        "encoding_type": "absolute_coordinates_encoding",
        "used_feature_list": ["x", "y", "z", "rcs", "v_r_comp", "v_r", "time"],
        "src_feature_list": ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"]}
    cfg["MODEL"]["VFE"]["USE_TIME"] = False
    ib = cfg["MODEL"]["IMAGE_BACKBONE"]
    ib.update(DBSCAN_MAP_W=160, DBSCAN_MAP_H=160, DBSCAN_Y=12.8, DBSCAN_V=5)
    cfg["MODEL"]["BACKBONE_2D"].update(LAYER_NUMS=[1, 2, 2], NUM_FILTERS=[32, 64, 128],
                                       NUM_UPSAMPLE_FILTERS=[64, 64, 64])
    anchors = cfg["MODEL"]["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"]
    anchors[0]["anchor_sizes"] = [[4.2, 1.8, 1.6]]
    anchors.append(dict(copy.deepcopy(anchors[0]), class_name="Truck", anchor_sizes=[[10.8, 2.7, 3.6]], anchor_bottom_heights=[-1.4]))


def test_a_modified_config_converts_exports_with_its_checkpoint_and_passes_parity(tmp_path):
    config = _edited(tmp_path, _modified)
    card_path = tmp_path / "my-maffnet.yaml"
    res = invoke("card", "from-openpcdet", config, "--out", card_path, "--name", "my-maffnet", "--stage-one",
                 "--cfa", "grid_density")
    assert res.exit_code == 0, res.output
    card = load_card(card_path)
    assert card.features == ["x", "y", "z", "rcs", "v_r_comp", "v_r", "time"]
    # upstream's RadarPillarVFE reads columns 3, 4, 5 into its rcs, v_r, v_r_comp inputs, whatever they hold
    assert card.get("vfe_features") == ["x", "y", "z", "rcs", "v_r_comp", "v_r"]
    assert "reads its v_r input from column 4" in res.output and "MAFF-Net#4" in res.output
    assert card.get("cfa.velocity_feature") == "v_r_comp"            # DBSCAN_V 5: batch column 5 = point column 4
    assert card.get("pillars.point_cloud_range") == [0.0, -12.8, -3.0, 25.6, 12.8, 2.0]
    assert [a["class_name"] for a in card.get("dense_head.anchors")] == ["Car", "Pedestrian", "Cyclist", "Truck"]
    assert card.get("backbone_2d.num_filters") == [32, 64, 128]
    assert card.get("source.sha256") == hashlib.sha256(config.read_bytes()).hexdigest()

    # an upstream-format checkpoint of the matching shapes (upstream's stage two included, as its always is)
    upstream = yaml.safe_load(config.read_text())["MODEL"]
    shapes = dict(CONFIGS["vod"], class_names=card.get("classes"), anchor_sets=[(2, 1, 1)] * 4,
                  used_feature_list=card.features, vfe=dict(CONFIGS["vod"]["vfe"], USE_TIME=False),
                  BACKBONE_2D=upstream["BACKBONE_2D"])
    torch.save(openpcdet_checkpoint(trained_like_state_dict(shapes, seed=5)), tmp_path / "ckpt.pth")
    onnx = tmp_path / "my-maffnet.onnx"
    res = invoke("export", "--model", "my-maffnet", "--config", card_path, "--checkpoint", tmp_path / "ckpt.pth",
                 "--output", onnx)
    assert res.exit_code == 0, res.output
    assert "dropped" in res.output and "stage-two modules on a stage-one card" in res.output
    res = invoke("parity-check", "--model", "my-maffnet", "--config", card_path, "--onnx", onnx,
                 "--checkpoint", tmp_path / "ckpt.pth", "--cases", 2, "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.output[res.output.index("{"):])["passed"]
    res = invoke("inspect", onnx)
    assert res.exit_code == 0 and "source: OpenPCDet config edited.yaml (sha256 " in res.output, res.output


def test_the_converted_card_names_its_source_and_the_choices_that_are_not_config_keys(tmp_path):
    res = invoke("card", "from-openpcdet", FIXTURES / "maffnet_tj4d.yaml", "--out", tmp_path / "tj.yaml", "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["name"] == "maffnet-tj4d" and doc["source"]["config"] == "maffnet_tj4d.yaml"
    assert any("past the 5 columns" in n for n in doc["notes"])        # RadarPillarVFE_TJ's SNR, position 5
    text = (tmp_path / "tj.yaml").read_text()
    assert text.startswith("# Written by `radaredge card from-openpcdet` from maffnet_tj4d.yaml + tj4d_dataset_radar.yaml")
    assert "spa.capacity" in text.splitlines()[3]
    assert load_card(tmp_path / "tj.yaml").get("vfe_features") == ["x", "y", "z", "snr", "v_r"]
    assert copy.deepcopy(doc["counts"]) == {"mapped": 79, "checked": 38, "training-only": 67, "ignored": 12}
