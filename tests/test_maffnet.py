"""MAFF-Net stage one: upstream key names, anchors and decoding, both formulations, export and parity."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import assert_close, assert_parses_in_tensorrt, export_with_cli, invoke, summary_of

from radaredge import runtime
from radaredge.cards import load_card
from radaredge.errors import CapacityError, ConfigError
from radaredge.models import create_model, load_checkpoint
from radaredge.models.maffnet.model import HeadConfig, decode_boxes
from radaredge.models.maffnet.spec import STAGE_ONE_GRAPH

ROOT = Path(__file__).resolve().parents[1]
TINY = Path(__file__).parent / "cards" / "maffnet-tiny.yaml"


def _conv_bn(prefix, cout, cin, k):
    return {
        f"{prefix[0]}.weight": (cout, cin, k, k),
        **{f"{prefix[1]}.{n}": (cout,) for n in ("weight", "bias", "running_mean", "running_var")},
        f"{prefix[1]}.num_batches_tracked": (),
    }


def expected_vod_keys() -> dict[str, tuple]:
    """Upstream OpenPCDet/MAFF-Net state-dict keys and shapes for MAFF-Net_vod.yaml (all but the fuser)."""
    keys = {"vfe.pfn_layers.0.linear.weight": (64, 13)}
    keys.update({f"vfe.pfn_layers.0.norm.{n}": (64,) for n in ("weight", "bias", "running_mean", "running_var")})
    keys["vfe.pfn_layers.0.norm.num_batches_tracked"] = ()
    spa = "map_to_bev_module.pillar_attention_rope."
    for lin in ("q_mlp", "k_mlp", "v_mlp", "ffn.0", "ffn.2"):
        keys.update({spa + lin + ".weight": (64, 64), spa + lin + ".bias": (64,)})
    for norm in ("norm1", "norm2"):
        keys.update({spa + norm + ".weight": (64,), spa + norm + ".bias": (64,)})
    for i, (cin, cout) in enumerate([(3, 16), (16, 32), (32, 64)]):
        keys.update(_conv_bn((f"image_backbone.conv.{3 * i}", f"image_backbone.conv.{3 * i + 1}"), cout, cin, 3))
    chans, filters, nums = [64, 64, 128], [64, 128, 512], [3, 5, 5]
    for b, (cin, f, n) in enumerate(zip(chans, filters, nums)):
        keys.update(_conv_bn((f"backbone_2d.blocks.{b}.1", f"backbone_2d.blocks.{b}.2"), f, cin, 3))
        for j in range(n):
            keys.update(
                _conv_bn((f"backbone_2d.blocks.{b}.{4 + 3 * j}", f"backbone_2d.blocks.{b}.{5 + 3 * j}"), f, f, 3)
            )
    for b, (f, up) in enumerate(zip(filters, [1, 2, 4])):
        keys[f"backbone_2d.deblocks.{b}.0.weight"] = (f, 128, up, up)
        keys.update(
            {f"backbone_2d.deblocks.{b}.1.{n}": (128,) for n in ("weight", "bias", "running_mean", "running_var")}
        )
        keys[f"backbone_2d.deblocks.{b}.1.num_batches_tracked"] = ()
    for name, ch in (("conv_cls", 18), ("conv_box", 42), ("conv_dir_cls", 12)):
        keys.update({f"dense_head.{name}.weight": (ch, 384, 1, 1), f"dense_head.{name}.bias": (ch,)})
    return keys


@pytest.fixture(scope="module")
def vod_model():
    return create_model(load_card(ROOT / "models" / "maffnet-vod.yaml"))


def test_vod_state_dict_follows_upstream_keys(vod_model, tmp_path):
    own = {k: tuple(v.shape) for k, v in vod_model.state_dict().items()}
    expected = expected_vod_keys()
    assert {k: own.get(k) for k in expected} == expected
    assert all(k.startswith("fuser.") for k in set(own) - set(expected))
    # a wrong shape is reported by name, on one line
    ckpt = {"model_state": {k: torch.randn(s) if s else torch.tensor(0) for k, s in own.items()}}
    ckpt["model_state"]["dense_head.conv_cls.weight"] = torch.zeros(9, 384, 1, 1)
    torch.save(ckpt, tmp_path / "bad.pth")
    with pytest.raises(
        ConfigError,
        match=r"dense_head.conv_cls.weight \(checkpoint \(9, 384, 1, 1\), "
        r"model \(18, 384, 1, 1\)\)",
    ) as err:
        load_checkpoint(vod_model, tmp_path / "bad.pth")
    assert "\n" not in str(err.value)


def test_vod_anchors_as_openpcdet(vod_model):
    a = vod_model.anchors.view(160, 160, 3, 2, 7)  # rows y, columns x, class, rotation
    assert_close(a[0, 0, 0, 0].numpy(), [0.0, -25.6, -1.78 + 0.78, 3.9, 1.6, 1.56, 0.0], 1e-6, "first car anchor")
    assert_close(a[0, 0, 1, 1].numpy(), [0.0, -25.6, -0.6 + 0.865, 0.8, 0.6, 1.73, 1.57], 1e-6, "pedestrian, 1.57")
    assert_close(a[-1, -1, 2, 0, :2].numpy(), [51.2, 25.6], 1e-4, "last anchor at the range corner")
    assert_close((a[0, 1, 0, 0, 0] - a[0, 0, 0, 0, 0]).numpy(), 51.2 / 159, 1e-6, "x spacing (align_center false)")


def test_decode_zero_residual_gives_the_anchor():
    anchors = torch.tensor([[1.0, 2.0, -1.0, 3.9, 1.6, 1.56, 0.0], [5.0, -2.0, -1.0, 0.8, 0.6, 1.73, 1.57]])
    cfg = HeadConfig()
    out = decode_boxes(torch.zeros(2, 7), anchors, torch.tensor([[1.0, 0.0], [0.0, 1.0]]), cfg)
    assert_close(out[0, :6].numpy(), anchors[0, :6].numpy(), 1e-6)
    # bin 0 maps headings into [dir_offset, dir_offset + pi): heading 0 becomes pi
    assert_close(out[0, 6].numpy(), math.pi, 1e-5)
    # bin 1 on a 1.57 anchor: heading 1.57 - dir_offset wrapped into [0, pi), + dir_offset + pi
    assert_close(out[1, 6].numpy(), 1.57 + math.pi, 1e-5)


def test_tiny_export_formulation_equals_reference():
    card = load_card(TINY)
    model = create_model(card)
    for name, feeds in STAGE_ONE_GRAPH.make_cases(card, 5, 1):
        with torch.no_grad():
            e = STAGE_ONE_GRAPH.run_export(model, feeds)
            r = STAGE_ONE_GRAPH.run_reference(model, feeds)
        assert len(e["boxes"]) > 0, name
        assert_close(e["anchor_scores"].numpy(), r["anchor_scores"].numpy(), 1e-5, name)
        assert_close(e["boxes"].numpy(), r["boxes"].numpy(), 1e-4, name)
        assert e["labels"].tolist() == r["labels"].tolist()
        assert int(e["num_pillars"]) == int(r["num_pillars"]) > 0 or name.endswith("3-points")


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory):
    return export_with_cli(tmp_path_factory.mktemp("maffnet"), "maffnet-tiny", TINY)


def test_tiny_parity_and_runtime(tiny_onnx):
    side = json.loads(tiny_onnx.with_suffix(".json").read_text())
    assert side["inputs"] == [{"name": "points", "shape": ["num_points", 7]}]
    assert [o["name"] for o in side["outputs"]][:3] == ["boxes", "scores", "labels"]
    res = invoke(
        "parity-check",
        "--model",
        "maffnet-tiny",
        "--config",
        str(TINY),
        "--onnx",
        str(tiny_onnx),
        "--cases",
        "6",
        "--json",
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert summary_of(report)["boxes"]["min_iou"] >= 0.99 and summary_of(report)["boxes"]["mismatches"] == 0
    model = runtime.load(tiny_onnx)
    _, feeds = STAGE_ONE_GRAPH.make_cases(load_card(TINY), 1, 3)[0]
    out = model.run(feeds["points"])
    assert out["boxes"].shape[1] == 7 and len(out["boxes"]) == len(out["scores"]) == len(out["labels"]) > 0
    assert set(out["labels"].tolist()) <= {1, 2, 3}


def test_runtime_reports_spa_overflow(tiny_onnx):
    rng = np.random.default_rng(0)
    pts = np.zeros((600, 7), np.float32)  # 600 points on distinct pillars of the 40 x 40 grid
    cells = rng.choice(1600, 600, replace=False)
    pts[:, 0] = (cells % 40) * 0.32 + 0.16
    pts[:, 1] = -6.4 + (cells // 40) * 0.32 + 0.16
    with pytest.raises(CapacityError, match="600 non-empty pillars.*spa.capacity = 256"):
        runtime.load(tiny_onnx).run(pts)


def test_runtime_rejects_bad_columns(tiny_onnx):
    from radaredge.errors import InputError

    with pytest.raises(InputError, match="expected shape \\[N, 7\\]"):
        runtime.load(tiny_onnx).run(np.zeros((10, 5), np.float32))


@pytest.mark.parametrize("reference", [False, True])
def test_tj4d_vfe_takes_snr_before_v_r_as_upstreams_radarpillarvfe_tj(reference):
    """RadarPillarVFE_TJ selects SNR (USE_SNR) before v_r (USE_VR): its first Linear's input column 3
    is SNR, column 4 v_r, while the points keep used_feature_list's order [x, y, z, v_r, SNR]."""
    card = load_card(ROOT / "models" / "maffnet-tj4d.yaml")
    assert card.features == ["x", "y", "z", "v_r", "snr"] and card.get("vfe_features") == ["x", "y", "z", "snr", "v_r"]
    model = create_model(card)
    with torch.no_grad():
        weight = model.vfe.pfn_layers[0].linear.weight
        weight.zero_()
        weight[:, 3] = 1.0  # a checkpoint whose VFE reads only its SNR input
    rng = np.random.default_rng(0)
    pts = np.stack(
        [
            rng.uniform(5, 40, 50),
            rng.uniform(-20, 20, 50),
            rng.uniform(-1, 1, 50),
            rng.uniform(-10, 10, 50),
            rng.uniform(5, 30, 50),
        ],
        1,
    ).astype(np.float32)

    def canvas(p):
        with torch.no_grad():
            return model.pillar_stage(torch.from_numpy(p), reference=reference)[0]

    base = canvas(pts)
    assert base.abs().sum() > 0
    other_v_r, other_snr = pts.copy(), pts.copy()
    other_v_r[:, 3] += 7.0
    other_snr[:, 4] += 7.0
    assert torch.equal(canvas(other_v_r), base)
    assert not torch.allclose(canvas(other_snr), base)


@pytest.mark.parametrize(
    "columns, needle",
    [
        (["x", "y", "z", "rcs", "doppler"], "name each of the card's features"),
        (["y", "x", "z"], "must start with x, y, z"),
        (["x", "y", "z", "rcs", "rcs"], "at most once"),
        ("x, y, z", "must be a list"),
    ],
)
def test_bad_vfe_features_are_refused_by_name(columns, needle, tmp_path):
    data = load_card(TINY).data
    data["vfe_features"] = columns
    (tmp_path / "card.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="vfe_features") as err:
        create_model(load_card(tmp_path / "card.yaml"))
    assert needle in str(err.value)


@pytest.mark.parametrize("model", ["maffnet-vod", "maffnet-tj4d", "maffnet-vod-edge"])
def test_full_card_export_and_parity(model, tmp_path):
    onnx = tmp_path / f"{model}.onnx"
    res = invoke("export", "--model", model, "--output", str(onnx))
    assert res.exit_code == 0, res.output
    assert_parses_in_tensorrt(onnx)
    cases = "5" if model.startswith("maffnet-vod") else "2"  # VoD's fifth case is a dense 5-frame cloud
    res = invoke("parity-check", "--model", model, "--onnx", str(onnx), "--cases", cases, "--json")
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert summary_of(report)["boxes"]["mismatches"] == 0


def test_bench_reports_fps_and_stages(tiny_onnx, tmp_path):
    res = invoke(
        "bench",
        "--model",
        "maffnet-tiny",
        "--config",
        str(TINY),
        "--onnx",
        str(tiny_onnx),
        "--runs",
        "3",
        "--warmup",
        "1",
        "--save",
        tmp_path / "bench.json",
    )
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "bench.json").read_text())
    assert {r["backend"] for r in report["tasks"]["maffnet"]["rows"]} == {
        "torch reference",
        "torch export",
        "onnxruntime",
        "openvino",
    }
    saved = report["graphs"]["maffnet"]
    stages = ["VFE+SPA", "CFA", "CAF", "backbone+head", "NMS"]
    for formulation in ("torch export", "torch reference"):
        assert list(saved["stage_ms"][formulation]) == stages
        assert all(v > 0 for v in saved["stage_ms"][formulation].values())
    ort_stages = saved["stage_ms"]["onnxruntime"]
    assert list(ort_stages)[:5] == stages and all(ort_stages[s] > 0 for s in stages)
    assert set(ort_stages) - set(stages) <= {"layout reorders (onnxruntime)", "other (unmapped)"}
    assert ort_stages.get("other (unmapped)", 0.0) < 0.05 * sum(ort_stages.values())
    assert "onnxruntime" in res.output


def test_onnx_nodes_attributed_to_stages(tiny_onnx):
    """Every graph node lands in one MAFF-Net stage, by module scope or by graph position."""
    import onnx

    from radaredge.benchmarking.profiling import node_stages

    model = onnx.load(str(tiny_onnx), load_external_data=False)
    stage = node_stages(model, list(STAGE_ONE_GRAPH.onnx_stages), STAGE_ONE_GRAPH.onnx_post_outputs)
    nodes = {n.name: n for n in model.graph.node}
    assert set(stage) == set(nodes)
    by_op = {}
    for name, s in stage.items():
        by_op.setdefault(nodes[name].op_type, set()).add(s)
    assert by_op["Loop"] == {"VFE+SPA", "NMS"}  # full pillars' peels, the greedy fixed point
    assert by_op["ConvTranspose"] == {"backbone+head"}  # the deblocks
    assert "CFA" in by_op["MaxPool"]  # GridDensityBEV's components
    producers = {o: nodes[n] for n in nodes for o in nodes[n].output}
    assert stage[producers["anchor_scores"].name] == "backbone+head"
    assert stage[producers["boxes"].name] == "NMS"
