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
import re
from pathlib import Path

import pytest
import torch
import yaml
from conftest import invoke, one_error_line
from references.maffnet_upstream_keys import CONFIGS, openpcdet_checkpoint, trained_like_state_dict

from radaredge.cards import load_card
from radaredge.cards.openpcdet import _leaves, load_openpcdet_config, maffnet_card
from radaredge.errors import ConfigError

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


@pytest.mark.skipif(
    not os.environ.get("RADAREDGE_UPSTREAM_MAFFNET"),
    reason="set RADAREDGE_UPSTREAM_MAFFNET to a TRV-Lab/MAFF-Net checkout",
)
@pytest.mark.parametrize("shipped", sorted(SHIPPED))
def test_upstreams_own_config_files_convert_to_the_shipped_cards(shipped):
    config, stage_one, cfa = SHIPPED[shipped]
    upstream = Path(os.environ["RADAREDGE_UPSTREAM_MAFFNET"]) / "tools" / "cfgs" / "MAFF-Net"
    name = {"maffnet_vod.yaml": "MAFF-Net_vod.yaml", "maffnet_tj4d.yaml": "MAFF-Net_TJ4D.yaml"}[config]
    conversion, _ = _convert(upstream / name, stage_one, cfa)  # its _BASE_CONFIG_ is found above the file
    card = load_card(shipped).data
    assert _without_provenance(conversion.card) == _without_provenance(card)
    assert conversion.card["source"] == card["source"]  # the shipped card names these very files


def test_every_config_key_has_one_fate():
    conversion, cfg = _convert(FIXTURES / "maffnet_vod.yaml")
    fates = {k.key: k for k in conversion.keys}
    assert sorted(fates) == sorted(_leaves(cfg)) and len(conversion.keys) == len(fates)
    assert fates["OPTIMIZATION.LR"].fate == "training-only"
    assert fates["DATA_CONFIG.DATA_AUGMENTOR.AUG_CONFIG_LIST[0].NAME"].fate == "training-only"
    assert fates["MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[2].matched_threshold"].fate == "training-only"
    assert (
        fates["MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[2].anchor_sizes"].detail == "dense_head.anchors[2].anchor_sizes"
    )
    assert fates["MODEL.IMAGE_BACKBONE.POINTX"].fate == "ignored"
    assert fates["MODEL.VFE.USE_NORM"].fate == "checked"
    assert fates["MODEL.ROI_HEAD.NMS_CONFIG.TEST.NMS_PRE_MAXSIZE"].detail == "stage_two.proposals.pre_max"
    assert fates["DATA_CONFIG.DATA_PROCESSOR[2].VOXEL_SIZE"].detail == "pillars.voxel_size"
    assert conversion.counts() == {"mapped": 72, "checked": 37, "training-only": 65, "ignored": 13}


def test_base_configs_merge_as_openpcdet_merges_them(tmp_path):
    (tmp_path / "base.yaml").write_text(yaml.safe_dump({"A": {"x": 1, "y": [1, 2]}, "B": 2}))
    (tmp_path / "model.yaml").write_text(yaml.safe_dump({"D": {"_BASE_CONFIG_": "base.yaml", "A": {"y": [3]}}, "C": 4}))
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


@pytest.mark.parametrize(
    "edit, needles",
    [
        (_set("MODEL.VFE.USE_DOPPLER", True), ["MODEL.VFE.USE_DOPPLER", "no formulation"]),
        (_set("MODEL.VFE.USE_NORM", False), ["MODEL.VFE.USE_NORM", "False is not supported"]),
        (
            _set("MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG.BOX_CODER", "PointResidualCoder"),
            ["MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG.BOX_CODER", "ResidualCoder"],
        ),
        (_set("MODEL.POST_PROCESSING.NMS_CONFIG.MULTI_CLASSES_NMS", True), ["MULTI_CLASSES_NMS", "class-agnostic"]),
        (_set("MODEL.IMAGE_BACKBONE.DBSCAN_V", 0), ["MODEL.IMAGE_BACKBONE.DBSCAN_V", "batch points"]),
        (_set("MODEL.FUSER.OUT_CHANNEL", 128), ["MODEL.FUSER.OUT_CHANNEL", "NUM_BEV_FEATURES"]),
        (_set("MODEL.PFE.SAMPLE_METHOD", "FPS"), ["MODEL.PFE.SAMPLE_METHOD", "'FPS' is not supported"]),
        (
            _set("DATA_CONFIG.DATA_PROCESSOR.1.SHUFFLE_ENABLED", {"train": True, "test": True}),
            ["SHUFFLE_ENABLED.test", "order given"],
        ),
        (
            _set("DATA_CONFIG.DATA_PROCESSOR.2.MAX_NUMBER_OF_VOXELS", {"train": 16000, "test": 1000}),
            ["MAX_NUMBER_OF_VOXELS.test", "at least 2048"],
        ),
        (
            lambda cfg: cfg["DATA_CONFIG"]["DATA_PROCESSOR"].append({"NAME": "sample_points", "NUM_POINTS": 1024}),
            ["DATA_CONFIG.DATA_PROCESSOR[3]", "sample_points"],
        ),
        (_set("MODEL.NAME", "PVRCNN"), ["MODEL.NAME", "MAFF_Net"]),
        # a valid-looking config the model cannot build: the CFA map must cover the pillar grid
        (
            _set("MODEL.IMAGE_BACKBONE.DBSCAN_MAP_W", 300),
            ["cfa.dbscan is 300 x 320 cells but the pillar grid is 320 x 320"],
        ),
    ],
)
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
        "src_feature_list": ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"],
    }
    cfg["MODEL"]["VFE"]["USE_TIME"] = False
    ib = cfg["MODEL"]["IMAGE_BACKBONE"]
    ib.update(DBSCAN_MAP_W=160, DBSCAN_MAP_H=160, DBSCAN_Y=12.8, DBSCAN_V=5)
    cfg["MODEL"]["BACKBONE_2D"].update(
        LAYER_NUMS=[1, 2, 2], NUM_FILTERS=[32, 64, 128], NUM_UPSAMPLE_FILTERS=[64, 64, 64]
    )
    anchors = cfg["MODEL"]["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"]
    anchors[0]["anchor_sizes"] = [[4.2, 1.8, 1.6]]
    anchors.append(
        dict(
            copy.deepcopy(anchors[0]), class_name="Truck", anchor_sizes=[[10.8, 2.7, 3.6]], anchor_bottom_heights=[-1.4]
        )
    )


def test_a_modified_config_converts_exports_with_its_checkpoint_and_passes_parity(tmp_path):
    config = _edited(tmp_path, _modified)
    card_path = tmp_path / "my-maffnet.yaml"
    res = invoke(
        "card",
        "from-openpcdet",
        config,
        "--out",
        card_path,
        "--name",
        "my-maffnet",
        "--stage-one",
        "--cfa",
        "grid_density",
    )
    assert res.exit_code == 0, res.output
    card = load_card(card_path)
    assert card.features == ["x", "y", "z", "rcs", "v_r_comp", "v_r", "time"]
    # upstream's RadarPillarVFE reads columns 3, 4, 5 into its rcs, v_r, v_r_comp inputs, whatever they hold
    assert card.get("vfe_features") == ["x", "y", "z", "rcs", "v_r_comp", "v_r"]
    assert "reads its v_r input from column 4" in res.output and "MAFF-Net#4" in res.output
    assert card.get("cfa.velocity_feature") == "v_r_comp"  # DBSCAN_V 5: batch column 5 = point column 4
    assert card.get("pillars.point_cloud_range") == [0.0, -12.8, -3.0, 25.6, 12.8, 2.0]
    assert [a["class_name"] for a in card.get("dense_head.anchors")] == ["Car", "Pedestrian", "Cyclist", "Truck"]
    assert card.get("backbone_2d.num_filters") == [32, 64, 128]
    assert card.get("source.sha256") == hashlib.sha256(config.read_bytes()).hexdigest()

    # an upstream-format checkpoint of the matching shapes (upstream's stage two included, as its always is)
    upstream = yaml.safe_load(config.read_text())["MODEL"]
    shapes = dict(
        CONFIGS["vod"],
        class_names=card.get("classes"),
        anchor_sets=[(2, 1, 1)] * 4,
        used_feature_list=card.features,
        vfe=dict(CONFIGS["vod"]["vfe"], USE_TIME=False),
        BACKBONE_2D=upstream["BACKBONE_2D"],
    )
    torch.save(openpcdet_checkpoint(trained_like_state_dict(shapes, seed=5)), tmp_path / "ckpt.pth")
    onnx = tmp_path / "my-maffnet.onnx"
    res = invoke(
        "export",
        "--model",
        "my-maffnet",
        "--config",
        card_path,
        "--checkpoint",
        tmp_path / "ckpt.pth",
        "--output",
        onnx,
    )
    assert res.exit_code == 0, res.output
    assert "dropped" in res.output and "stage-two modules on a stage-one card" in res.output
    res = invoke(
        "parity-check",
        "--model",
        "my-maffnet",
        "--config",
        card_path,
        "--onnx",
        onnx,
        "--checkpoint",
        tmp_path / "ckpt.pth",
        "--cases",
        2,
        "--json",
    )
    assert res.exit_code == 0, res.output
    assert json.loads(res.output[res.output.index("{") :])["passed"]
    res = invoke("inspect", onnx)
    assert res.exit_code == 0 and "source: OpenPCDet config edited.yaml (sha256 " in res.output, res.output


def test_the_converted_card_names_its_source_and_the_choices_that_are_not_config_keys(tmp_path):
    res = invoke("card", "from-openpcdet", FIXTURES / "maffnet_tj4d.yaml", "--out", tmp_path / "tj.yaml", "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["name"] == "maffnet-tj4d" and doc["source"]["config"] == "maffnet_tj4d.yaml"
    assert any("past the 5 columns" in n for n in doc["notes"])  # RadarPillarVFE_TJ's SNR, position 5
    text = (tmp_path / "tj.yaml").read_text()
    assert text.startswith(
        "# Written by `radaredge card from-openpcdet` from maffnet_tj4d.yaml + tj4d_dataset_radar.yaml"
    )
    assert "spa.capacity" in text.splitlines()[3]
    assert load_card(tmp_path / "tj.yaml").get("vfe_features") == ["x", "y", "z", "snr", "v_r"]
    assert copy.deepcopy(doc["counts"]) == {"mapped": 79, "checked": 37, "training-only": 67, "ignored": 13}


# ----------------------------------------------------------------------------- exactness audit
# Each test below names the upstream code (TRV-Lab/MAFF-Net 0bb253f) that decides it.


def _write_upstream_layout(root: Path, edit=None) -> Path:
    """The VoD fixture laid out as upstream's repository: tools/cfgs/MAFF-Net/MAFF-Net_vod.yaml
    naming its base ``tools/cfgs/dataset_configs/vod_dataset_radar.yaml`` from the repository root."""
    cfgs = root / "tools" / "cfgs"
    (cfgs / "MAFF-Net").mkdir(parents=True)
    (cfgs / "dataset_configs").mkdir()
    cfg = yaml.safe_load((FIXTURES / "maffnet_vod.yaml").read_text())
    cfg["DATA_CONFIG"]["_BASE_CONFIG_"] = "tools/cfgs/dataset_configs/vod_dataset_radar.yaml"
    if edit is not None:
        edit(cfg)
    (cfgs / "dataset_configs" / "vod_dataset_radar.yaml").write_text((FIXTURES / "vod_dataset_radar.yaml").read_text())
    (cfgs / "MAFF-Net" / "MAFF-Net_vod.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return cfgs / "MAFF-Net" / "MAFF-Net_vod.yaml"


def test_a_relative_config_path_finds_its_base_from_the_configs_folder_upwards(tmp_path, monkeypatch):
    # (a) run from tools/ as OpenPCDet's docs do: the relative cfgs/... path is resolved before the
    # folders above it are searched for tools/cfgs/dataset_configs/...
    _write_upstream_layout(tmp_path)
    monkeypatch.chdir(tmp_path / "tools")
    merged, files = load_openpcdet_config(Path("cfgs/MAFF-Net/MAFF-Net_vod.yaml"))
    assert files[1].path.resolve() == (tmp_path / "tools/cfgs/dataset_configs/vod_dataset_radar.yaml").resolve()
    conversion = maffnet_card(merged, files, stage_two=False, cfa="grid_density")
    assert _without_provenance(conversion.card) == _without_provenance(load_card("maffnet-vod").data)


def _convert_edit(tmp_path, edit, *, stage_one=False, cfa=None, source="maffnet_vod.yaml"):
    cfg, files = load_openpcdet_config(_edited(tmp_path, edit, source))
    return maffnet_card(cfg, files, stage_two=not stage_one, cfa=cfa)


@pytest.mark.parametrize("head", ["MODEL.ROI_HEAD.TARGET_CONFIG", "MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG"])
def test_box_coder_configs_are_mapped_when_they_keep_the_7_value_code_and_refused_otherwise(tmp_path, head):
    # (b) roi_head_template.py / anchor_head_template.py build the test-time decoder as
    # ResidualCoder(**BOX_CODER_CONFIG): encode_angle_by_sincos True regresses 8 values
    def with_coder(coder):
        def edit(cfg):
            node = cfg
            for part in head.split("."):
                node = node[part]
            node["BOX_CODER_CONFIG"] = coder

        return edit

    conversion = _convert_edit(tmp_path, with_coder({"encode_angle_by_sincos": False, "code_size": 7}))
    assert _without_provenance(conversion.card) == _without_provenance(load_card("maffnet-vod-full-dbscan").data)
    fates = {k.key: k.fate for k in conversion.keys}
    assert fates[f"{head}.BOX_CODER_CONFIG.encode_angle_by_sincos"] == "checked"
    for coder, needle in (
        ({"encode_angle_by_sincos": True}, "encode_angle_by_sincos: True makes upstream decode"),
        ({"code_size": 8}, "code_size: 8"),
        ({"angle_bins": 12}, "angle_bins: not a ResidualCoder setting"),
    ):
        with pytest.raises(ConfigError, match=needle.replace(": ", ".*").replace("(", r"\(")) as err:
            _convert_edit(tmp_path, with_coder(coder))
        assert f"edited.yaml: {head}.BOX_CODER_CONFIG." in str(err.value) and "\n" not in str(err.value)


def test_the_roi_heads_sincos_coder_ends_with_one_error_line(tmp_path):
    edit = _set("MODEL.ROI_HEAD.TARGET_CONFIG.BOX_CODER_CONFIG", {"encode_angle_by_sincos": True})
    res = invoke("card", "from-openpcdet", _edited(tmp_path, edit), "--out", tmp_path / "card.yaml")
    one_error_line(
        res,
        "edited.yaml",
        "MODEL.ROI_HEAD.TARGET_CONFIG.BOX_CODER_CONFIG.encode_angle_by_sincos",
        "8 values",
        "7-value",
    )
    assert not (tmp_path / "card.yaml").exists()


@pytest.mark.parametrize("cfa", [None, "grid_density"])
@pytest.mark.parametrize(
    "edit, needles",
    [
        # CQCA_cfa.generate_map: column int(x / RESOLUTION) - 1, row int((y + DBSCAN_Y) / RESOLUTION) - 1
        (_set("MODEL.IMAGE_BACKBONE.RESOLUTION", 0.2), ["MODEL.IMAGE_BACKBONE.RESOLUTION", "0.16 x 0.16"]),
        (_set("MODEL.IMAGE_BACKBONE.DBSCAN_Y", 20.0), ["MODEL.IMAGE_BACKBONE.DBSCAN_Y", "must be 25.6"]),
        # the same 320 x 320 cells, but the pillar grid starts at x = -25.6 and the map at x = 0
        (
            _set("DATA_CONFIG.POINT_CLOUD_RANGE", [-25.6, -25.6, -3, 25.6, 25.6, 2]),
            ["DATA_CONFIG.POINT_CLOUD_RANGE", "x_min -25.6", "starts at x = 0"],
        ),
    ],
)
def test_the_clustering_map_must_share_the_pillar_grids_origin_and_cells(tmp_path, edit, needles, cfa):
    # (c) cell counts alone passed before: each of these maps has the pillar grid's 320 x 320 cells
    with pytest.raises(ConfigError) as err:
        _convert_edit(tmp_path, edit, cfa=cfa)
    message = str(err.value)
    assert message.startswith("edited.yaml: ") and "\n" not in message
    for n in needles:
        assert n in message, (n, message)


def test_card_comments_name_the_upstream_key_each_map_size_comes_from():
    # (d) CQCA_cfa allocates zeros((DBSCAN_MAP_W, DBSCAN_MAP_H, 3)) and writes [bev_y, bev_x]: the
    # first axis (rows, y) is DBSCAN_MAP_W. TJ4D's sizes differ (496, 432), so the converter's
    # mapping can be read off its cards.
    ib = yaml.safe_load((FIXTURES / "maffnet_tj4d.yaml").read_text())["MODEL"]["IMAGE_BACKBONE"]
    by_value = {ib["DBSCAN_MAP_W"]: "DBSCAN_MAP_W", ib["DBSCAN_MAP_H"]: "DBSCAN_MAP_H"}
    expected = {}
    for cfa, section in (("dbscan", "dbscan"), ("grid_density", "grid")):
        card = _convert(FIXTURES / "maffnet_tj4d.yaml", True, cfa)[0].card["cfa"][section]
        for field_name in ("map_rows", "map_cols", "map_h", "map_w"):
            if field_name in card:
                expected[field_name] = by_value[card[field_name]]
    assert expected == {
        "map_rows": "DBSCAN_MAP_W",
        "map_cols": "DBSCAN_MAP_H",
        "map_h": "DBSCAN_MAP_W",
        "map_w": "DBSCAN_MAP_H",
    }
    named = re.compile(r"^\s*(map_rows|map_cols|map_h|map_w):[^#]*#.*?\b(DBSCAN_MAP_[WH])\b")
    inline = re.compile(r"\b(map_rows|map_cols|map_h|map_w):[^,}#]*[,}][^#]*#.*?\b(DBSCAN_MAP_[WH])\b")
    wrong = []
    for path in sorted((ROOT / "models").glob("*.yaml")) + sorted((ROOT / "tests" / "cards").glob("*.yaml")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for m in (named.match(line), inline.search(line)):
                if m and expected[m.group(1)] != m.group(2):
                    wrong.append(
                        f"{path.relative_to(ROOT)}:{n}: {m.group(1)} is {expected[m.group(1)]}, "
                        f"the comment says {m.group(2)}"
                    )
    assert not wrong, "\n".join(wrong)


def test_keys_that_upstream_reads_differently_than_they_read_are_mapped_as_upstream_computes(tmp_path):
    # (e) anchor_head_single.py: conv_dir_cls exists whenever USE_DIRECTION_CLASSIFIER is present
    # (`.get(...) is not None`), and anchor_head_template.py applies it, so False computes as True;
    # pointnet2_modules.build_local_aggregation_module passes pool_method='max_pool' whatever
    # ROI_GRID_POOL.POOL_METHOD says; anchor_generator.py reads align_center with .get(.., False).
    def edit(cfg):
        cfg["MODEL"]["DENSE_HEAD"]["USE_DIRECTION_CLASSIFIER"] = False
        cfg["MODEL"]["ROI_HEAD"]["ROI_GRID_POOL"]["POOL_METHOD"] = "avg_pool"
        for a in cfg["MODEL"]["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"]:
            del a["align_center"]

    conversion = _convert_edit(tmp_path, edit)
    assert _without_provenance(conversion.card) == _without_provenance(load_card("maffnet-vod-full-dbscan").data)
    fates = {k.key: k for k in conversion.keys}
    assert fates["MODEL.ROI_HEAD.ROI_GRID_POOL.POOL_METHOD"].fate == "ignored"
    assert fates["MODEL.DENSE_HEAD.USE_DIRECTION_CLASSIFIER"].fate == "checked"
    assert any("USE_DIRECTION_CLASSIFIER: False still builds" in n for n in conversion.notes)
    assert any("POOL_METHOD: 'avg_pool' is never read" in n for n in conversion.notes)


@pytest.mark.parametrize(
    "edit, needles",
    [
        # detector3d_template.post_processing: class-agnostic NMS only `if isinstance(NMS_THRESH, float)`;
        # otherwise per-class thresholds NMS_THRESH.CAR / PED / CYC (an int fails there)
        (_set("MODEL.POST_PROCESSING.NMS_CONFIG.NMS_THRESH", 0), ["NMS_CONFIG.NMS_THRESH", "integer", "0.0"]),
        (
            _set("MODEL.POST_PROCESSING.NMS_CONFIG.NMS_THRESH", {"CAR": 0.1, "PED": 0.1, "CYC": 0.1}),
            ["NMS_CONFIG.NMS_THRESH", "per-class NMS thresholds"],
        ),
        # data_processor.py: without the mask step upstream's CFA and stage two see the points outside
        # the range; radaredge's graph always crops them
        (
            lambda cfg: cfg["DATA_CONFIG"]["DATA_PROCESSOR"].pop(0),
            ["DATA_CONFIG.DATA_PROCESSOR", "no mask_points_and_boxes_outside_range"],
        ),
        # anchor_generator.py: grid_size // feature_map_stride anchor locations; the head predicts on
        # BaseBEVBackbone's output (stride LAYER_STRIDES[0] / UPSAMPLE_STRIDES[0] = 2 here)
        (
            lambda cfg: [a.update(feature_map_stride=4) for a in cfg["MODEL"]["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"]],
            ["ANCHOR_GENERATOR_CONFIG[0].feature_map_stride", "80 x 80", "160 x 160"],
        ),
        (
            _set("MODEL.BACKBONE_2D.UPSAMPLE_STRIDES", [2, 4, 8]),
            ["ANCHOR_GENERATOR_CONFIG[0].feature_map_stride", "320 x 320 map"],
        ),
        (_set("MODEL.BACKBONE_2D.UPSAMPLE_STRIDES", [1, 2, 2]), ["MODEL.BACKBONE_2D.UPSAMPLE_STRIDES", "one size"]),
    ],
)
def test_test_time_keys_upstream_would_compute_otherwise_are_refused_by_name(tmp_path, edit, needles):
    # (e) each of these converted to a card before (silently computing something else)
    res = invoke("card", "from-openpcdet", _edited(tmp_path, edit), "--out", tmp_path / "card.yaml")
    one_error_line(res, "edited.yaml", *needles)
    assert not (tmp_path / "card.yaml").exists()


@pytest.mark.parametrize(
    "edit, needles",
    [
        (
            _set("MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG.0.anchor_rotations", []),
            ["MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[0].anchor_rotations", "non-empty"],
        ),
        (
            _set("MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG.1.anchor_sizes", []),
            ["MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[1].anchor_sizes", "non-empty"],
        ),
        (
            _set("MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG.0.anchor_bottom_heights", [-1.78, -1.0]),
            ["MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG[0].anchor_bottom_heights", "one bottom height"],
        ),
        (
            _set("DATA_CONFIG.POINT_CLOUD_RANGE", [0, -25.6, -3, float("nan"), 25.6, 2]),
            ["DATA_CONFIG.POINT_CLOUD_RANGE[3]", "nan is not a finite number"],
        ),
        (
            _set("DATA_CONFIG.POINT_CLOUD_RANGE", [51.2, -25.6, -3, 0, 25.6, 2]),
            ["DATA_CONFIG.POINT_CLOUD_RANGE", "x_min < x_max"],
        ),
        (
            _set("MODEL.POST_PROCESSING.SCORE_THRESH", float("inf")),
            ["MODEL.POST_PROCESSING.SCORE_THRESH", "inf is not a finite number"],
        ),
    ],
)
def test_bad_values_end_with_one_error_line_naming_the_file_and_key(tmp_path, edit, needles):
    # (f) the first two ended in a RuntimeError / ValueError traceback; the others named the card
    # field (card.yaml: ...) rather than the config's file and key
    res = invoke("card", "from-openpcdet", _edited(tmp_path, edit), "--out", tmp_path / "card.yaml")
    one_error_line(res, "error: edited.yaml: ", *needles)
    assert not (tmp_path / "card.yaml").exists()


@pytest.fixture
def never_read(monkeypatch):
    """Fail the test if a file named in the returned set is opened or read (its size must be
    checked with stat first)."""
    import builtins
    import pathlib

    names: set[str] = set()

    def guard(path):
        if Path(str(path)).name in names:
            raise AssertionError(f"{path} was read; its size should have been checked with stat first")

    real_read_bytes, real_read_text, real_path_open = (
        pathlib.Path.read_bytes,
        pathlib.Path.read_text,
        pathlib.Path.open,
    )
    real_open = builtins.open

    def read_bytes(self):
        guard(self)
        return real_read_bytes(self)

    def read_text(self, *a, **k):
        guard(self)
        return real_read_text(self, *a, **k)

    def path_open(self, *a, **k):
        guard(self)
        return real_path_open(self, *a, **k)

    def open_(file, *a, **k):
        if isinstance(file, (str, os.PathLike)):
            guard(file)
        return real_open(file, *a, **k)

    monkeypatch.setattr(pathlib.Path, "read_bytes", read_bytes)
    monkeypatch.setattr(pathlib.Path, "read_text", read_text)
    monkeypatch.setattr(pathlib.Path, "open", path_open)
    monkeypatch.setattr(builtins, "open", open_)
    return names


@pytest.mark.parametrize("which", ["config", "base"])
def test_a_huge_config_file_is_refused_by_its_size_before_it_is_read(tmp_path, never_read, which):
    # (f) a 4 GiB sparse file: the card loader's limit (MAX_CARD_BYTES), checked with stat
    from radaredge.cards import MAX_CARD_BYTES

    config = _edited(tmp_path, lambda cfg: None)
    huge = config if which == "config" else tmp_path / "vod_dataset_radar.yaml"
    with open(huge, "r+b") as f:
        f.truncate(4 * 1024**3)
    never_read.add(huge.name)
    res = invoke("card", "from-openpcdet", config, "--out", tmp_path / "card.yaml")
    where = "edited.yaml" if which == "config" else "edited.yaml: DATA_CONFIG._BASE_CONFIG_ vod_dataset_radar.yaml"
    one_error_line(res, f"error: {where}: {4 * 1024**3} bytes", f"at most {MAX_CARD_BYTES} bytes")


@pytest.mark.parametrize(
    "content, needle",
    [
        (b"\x00" * 64 + b"DATASET: x\n", "a binary file"),  # valid UTF-8, NUL bytes
        (bytes(range(128, 256)) * 8, "not a UTF-8 text file"),
        (b"- x\n- y\n", "this file holds a YAML list"),
        (b"just words\n", "this file holds a YAML string"),
        (b"", "this file holds nothing (an empty file)"),
        (b"A: [1, 2\n", "invalid YAML"),
    ],
)
def test_a_base_config_that_is_not_a_yaml_mapping_ends_with_one_error_line_naming_the_key(tmp_path, content, needle):
    # (f) the base's messages named the base file alone (or, for NUL bytes, a YAML reader error)
    config = _edited(tmp_path, lambda cfg: None)
    (tmp_path / "vod_dataset_radar.yaml").write_bytes(content)
    res = invoke("card", "from-openpcdet", config, "--out", tmp_path / "card.yaml")
    one_error_line(res, "error: edited.yaml: DATA_CONFIG._BASE_CONFIG_ vod_dataset_radar.yaml: ", needle)
