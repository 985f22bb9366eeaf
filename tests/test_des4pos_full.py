"""The paper card (models/des4pos.yaml) exports as three graphs and passes parity on every part."""

import json

from click.testing import CliRunner
from conftest import assert_parses_in_tensorrt

from radaredge.cli import main


def test_full_card_bundle_export_and_parity(tmp_path):
    out = tmp_path / "des4pos"
    res = CliRunner().invoke(main, ["export", "--model", "des4pos", "--output", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert_parses_in_tensorrt(out)
    manifest = json.loads((out / "bundle.json").read_text())
    assert manifest["card"]["cell"]["max_objects"] == 28 and manifest["card"]["submap"]["embed_dim"] == 256
    side = json.loads((out / "submap_encoder.json").read_text())
    assert side["inputs"][0] == {"name": "points", "shape": ["cells", 28, 256, 6]}
    # the command's default case set (20 cases): distinct descriptions, each retrieving its own
    res = CliRunner().invoke(
        main, ["parity-check", "--model", "des4pos", "--onnx", str(out), "--json"], catch_exceptions=False
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert report["graphs"]["submap_encoder"]["summary"]["descriptor"]["min_cosine"] >= 0.9999
    assert report["graphs"]["text_encoder"]["summary"]["descriptor"]["min_cosine"] >= 0.9999
    assert report["graphs"]["text_encoder"]["summary"]["descriptor"]["retrieval_top1"] == 1.0
    assert report["graphs"]["fine_stage"]["summary"]["position"]["max_abs"] <= 1e-3
