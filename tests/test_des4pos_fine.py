"""Des4Pos fine-stage options (card section ``fine``): ``objects: encoder`` (a fine-stage object
encoder with a position MLP on each object's centre) and ``pool: hints`` (the max over the hint
stream); both formulations, the exported graph, the runtime and the evaluation follow them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import invoke

from radaredge.cards import card_from_yaml
from radaredge.data.text_city import make_city
from radaredge.errors import ConfigError, InputError
from radaredge.eval.localisation import evaluate_localization
from radaredge.models import create_model
from radaredge.models.des4pos.model import object_summaries as torch_summaries
from radaredge.models.des4pos.spec import FINE_GRAPH
from radaredge.runtime.cellmap import load_map
from radaredge.runtime.des4pos import Des4PosBundle, MapIndex, object_summaries

TINY = Path(__file__).parent / "cards" / "des4pos-tiny.yaml"
TINY_FINE = "fine: {cra_layers: 3, heads: 2, mlp_hidden: 16}"


def fine_card_text(fine: str) -> str:
    """The tiny card's YAML with another ``fine`` section."""
    text = TINY.read_text()
    assert TINY_FINE in text
    return text.replace(TINY_FINE, f"fine: {{{fine}}}")


def fine_card(fine: str):
    return card_from_yaml(fine_card_text(fine))


ENCODER = "cra_layers: 4, heads: 2, mlp_hidden: 16, objects: encoder"


def _candidates(rng, k=2, t=6, d=32, hints=3):
    mask = np.ones((k, t), bool)
    mask[0, 4:] = False
    feats = (rng.normal(0, 0.3, (k, t, d)) * mask[..., None]).astype(np.float32)
    return {
        "object_features": torch.from_numpy(feats),
        "object_mask": torch.from_numpy(mask),
        "hint_features": torch.from_numpy(rng.normal(size=(hints, d)).astype(np.float32)),
        "cell_origin": torch.tensor([[0.0, 0.0], [30.0, 0.0]], dtype=torch.float64),
        "cell_size": torch.tensor([30.0, 30.0], dtype=torch.float64),
        "object_centres": torch.from_numpy(rng.uniform(0, 1, (k, t, 3)).astype(np.float32)),
        "object_colours": torch.from_numpy(rng.uniform(0, 1, (k, t, 3)).astype(np.float32)),
        "num_points": torch.from_numpy(rng.integers(10, 3000, (k, t)).astype(np.float32)),
    }


@pytest.mark.parametrize(
    "fine, match",
    [
        ("objects: pointnet", "objects must be one of"),
        ("pool: mean", "pool must be one of"),
        ("object_state: points", "object_state must be one of"),
    ],
)
def test_fine_options_are_checked(fine, match):
    with pytest.raises(ConfigError, match=match):
        create_model(fine_card(fine))


def test_the_default_fine_graph_keeps_its_inputs():
    """The paper's fine stage (the default) reads the coarse states only: no new graph inputs,
    no new weights."""
    card = fine_card("cra_layers: 3, heads: 2, mlp_hidden: 16")
    assert FINE_GRAPH.input_names(card) == [
        "object_features",
        "object_mask",
        "hint_features",
        "cell_origin",
        "cell_size",
    ]
    model = create_model(card)
    assert not model.fine.needs_summaries and not hasattr(model.fine, "objects")
    enc = create_model(fine_card(ENCODER))
    assert FINE_GRAPH.input_names(fine_card(ENCODER))[5:] == ["object_centres", "object_colours", "num_points"]
    assert {k for k in enc.state_dict() if k.startswith("fine.objects.")}


def test_the_position_mlp_sees_where_each_object_is():
    """With ``objects: encoder``, moving one real object in its cell moves the estimate, while
    whatever a padding slot holds (NaN included) changes nothing; the reference formulation on
    the real objects alone agrees; without the summaries the stage refuses to run."""
    model = create_model(fine_card(ENCODER))
    feeds = _candidates(np.random.default_rng(0))
    names = FINE_GRAPH.input_names(fine_card(ENCODER))
    with torch.no_grad():
        off, pos = model.fine(*(feeds[n] for n in names))
        moved = dict(feeds, object_centres=feeds["object_centres"].clone())
        moved["object_centres"][0, 1, :2] += torch.tensor([0.4, -0.3])
        off_moved, _ = model.fine(*(moved[n] for n in names))
        padded = {k: v.clone() for k, v in feeds.items()}
        for key in ("object_centres", "object_colours", "num_points", "object_features"):
            padded[key][0, 4:] = float("nan")
        off_padded, _ = model.fine(*(padded[n] for n in names))
        mask = feeds["object_mask"].numpy()
        summaries = [
            tuple(feeds[k][j][mask[j]] for k in ("object_centres", "object_colours", "num_points")) for j in range(2)
        ]
        off_ref, pos_ref = model.fine.reference(
            [feeds["object_features"][j][mask[j]] for j in range(2)],
            feeds["hint_features"],
            feeds["cell_origin"].numpy(),
            feeds["cell_size"].numpy(),
            summaries,
        )
    assert float((off_moved[0] - off[0]).abs().max()) > 1e-4  # the moved object's cell moves
    torch.testing.assert_close(off_moved[1], off[1])  # the other cell does not
    torch.testing.assert_close(off_padded, off)
    torch.testing.assert_close(off_ref, off, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(pos_ref, pos, atol=1e-4, rtol=1e-7)
    with pytest.raises(ConfigError, match="object centres, colours and point counts"):
        model.fine(*(feeds[n] for n in names[:5]))


def test_pool_hints_reads_the_last_hint_stream_state():
    """With 2 CRA layers, R1 = Attn(T, N) + T is the last hint-stream state and R2 the last state:
    ``pool: hints`` then does not depend on the second attention at all, ``pool: last`` does,
    and the offset is the MLP of R1's max over the hints."""
    rng = np.random.default_rng(1)
    feeds = _candidates(rng)
    args = [feeds[n] for n in ("object_features", "object_mask", "hint_features", "cell_origin", "cell_size")]
    outs = {}
    for pool in ("hints", "last"):
        model = create_model(fine_card(f"cra_layers: 2, heads: 2, mlp_hidden: 16, pool: {pool}"))
        with torch.no_grad():
            before = model.fine(*args)[0]
            for p in model.fine.attn[1].parameters():
                p.add_(torch.randn_like(p))
            outs[pool] = (before, model.fine(*args)[0])
            if pool == "hints":
                hints = feeds["hint_features"].unsqueeze(0).expand(2, -1, -1)
                r1 = model.fine.attn[0](hints, feeds["object_features"], feeds["object_mask"]) + hints
                torch.testing.assert_close(model.fine.offset(r1.max(1).values), before)
    torch.testing.assert_close(outs["hints"][0], outs["hints"][1])
    assert float((outs["last"][0] - outs["last"][1]).abs().max()) > 1e-4


def _red_object_task(rng, k: int, t: int = 6, d: int = 32):
    """Candidates where the pose is at the red object of each cell (no other object is red), as a
    hint names one; the objects' coarse states say what colour each object is, not where it is:
    (inputs, hint features [k, H, D], object summaries, target offset [k, 2])."""
    feeds = _candidates(rng, k=k, t=t, d=d)
    fixed = np.random.default_rng(99)
    feeds["object_mask"] = torch.ones(k, t, dtype=torch.bool)
    feeds["num_points"] = torch.full((k, t), 500.0)
    red = torch.from_numpy(rng.integers(0, t, k))
    colours = feeds["object_colours"]
    colours[..., 0] *= 0.4
    colours[torch.arange(k), red] = torch.tensor([0.9, 0.1, 0.1])
    feeds["object_features"] = colours @ torch.from_numpy(fixed.normal(size=(3, d)).astype(np.float32))
    target = feeds["object_centres"][torch.arange(k), red, :2] - 0.5  # from the cell centre, cell units
    hint = torch.from_numpy(fixed.normal(size=(1, d)).astype(np.float32))
    hints = hint.unsqueeze(0).expand(k, -1, -1)  # the same hint everywhere
    return feeds, hints, (feeds["object_centres"], colours, feeds["num_points"]), target


def test_the_encoder_learns_an_offset_from_object_positions():
    """Trained on such cells, the fine stage with its own encoder places the poses of new cells
    far better than the cell centre does; the coarse-state stage, whose inputs here carry no
    position, cannot (it only memorises its training cells)."""
    torch.manual_seed(0)
    rng = np.random.default_rng(2)
    train, held = _red_object_task(rng, 128), _red_object_task(rng, 128)
    centre = float(held[3].norm(dim=1).mean())  # the error of a zero offset

    def error(model, task):
        feeds, hints, summaries, target = task
        off = model.fine.offsets(
            feeds["object_features"],
            feeds["object_mask"],
            hints,
            summaries=summaries if model.fine.needs_summaries else None,
        )
        return (off - target).norm(dim=1).mean()

    held_out = {}
    for fine in (ENCODER + ", pool: hints", "cra_layers: 4, heads: 2, mlp_hidden: 16"):
        model = create_model(fine_card(fine)).train()
        opt = torch.optim.Adam(model.fine.parameters(), lr=3e-3)
        for _ in range(150):
            loss = error(model, train)
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            held_out[fine] = float(error(model.eval(), held))
    encoder, coarse = held_out.values()
    assert encoder < 0.5 * centre and coarse > 0.8 * centre, (centre, held_out)


@pytest.fixture(scope="module")
def encoder_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("des4pos-fine")
    card = d / "des4pos-tiny-fine.yaml"
    card.write_text(fine_card_text(ENCODER + ", pool: hints").replace("name: des4pos-tiny", "name: des4pos-tiny-fine"))
    res = invoke("export", "--model", "des4pos-tiny-fine", "--config", card, "--output", d / "bundle")
    assert res.exit_code == 0, res.output
    return card, d / "bundle"


def test_encoder_bundle_exports_passes_parity_and_locates(encoder_bundle, tmp_path):
    """The fine graph takes the candidates' object centres, colours and point counts, is in
    parity with the torch reference, and the runtime feeds them from the map: the bundle and
    the torch reference place every pose alike."""
    card, bundle = encoder_bundle
    res = invoke(
        "parity-check", "--model", "des4pos-tiny-fine", "--config", card, "--onnx", bundle, "--cases", "6", "--json"
    )
    report = json.loads(res.stdout)
    assert res.exit_code == 0 and report["passed"], res.output
    assert report["graphs"]["fine_stage"]["summary"]["position"]["max_abs"] <= 1e-3
    b = Des4PosBundle(bundle)
    assert b.graphs["fine_stage"].input_names[5:] == ["object_centres", "object_colours", "num_points"]
    city = make_city(6, 32, seed=3, objects=30, poses=6, max_hints=5).save(tmp_path / "city.npz")
    m = load_map(city)
    index = MapIndex.build(b, city, cells=m)
    centres, _ = object_summaries(m.points)
    np.testing.assert_array_equal(index.object_centres, centres)
    np.testing.assert_allclose(centres, m.points[..., :3].mean(2), atol=1e-6)
    hits = b.locate(str(m.pose_text[0]), index, top_k=3)
    assert len(hits) == 3
    bare = MapIndex(index.ids, index.origins, index.sizes, index.object_mask, index.descriptors, index.object_features)
    with pytest.raises(InputError, match="centres, colours and point counts"):
        b.locate(str(m.pose_text[0]), bare, top_k=3)
    report = evaluate_localization(bundle, city, reference=True)
    onnx, ref = report.results["onnxruntime"], report.results["torch reference"]
    assert onnx["localization"] == ref["localization"] and onnx["localization_centre"] == ref["localization_centre"]


def test_the_encoder_makes_its_tensors_on_the_inputs_device():
    """With meta as the default device, a tensor the fine stage made without one would land on
    meta and fail against the CPU inputs: CPU results (and gradients) prove none was made."""
    model = create_model(fine_card(ENCODER + ", pool: hints"))
    feeds = _candidates(np.random.default_rng(3))
    hints = feeds["hint_features"].unsqueeze(0).expand(2, -1, -1)
    with torch.device("meta"):
        centres, colours = torch_summaries(torch.from_numpy(np.random.default_rng(0).random((2, 6, 8, 6), np.float32)))
        off = model.fine.offsets(
            feeds["object_features"], feeds["object_mask"], hints, summaries=(centres, colours, feeds["num_points"])
        )
        off.sum().backward()
    assert off.device.type == "cpu" and torch.isfinite(off).all()
    assert model.fine.objects.pos_encoder[0].weight.grad.device.type == "cpu"


def test_bench_runs_a_fine_stage_with_its_own_object_encoder(encoder_bundle):
    """`radaredge bench` feeds the fine stage the cells' object centres, colours and point counts
    in every backend, the torch reference included."""
    card, bundle = encoder_bundle
    res = invoke(
        "bench",
        "--model",
        "des4pos-tiny-fine",
        "--config",
        card,
        "--onnx",
        bundle,
        "--runs",
        "1",
        "--warmup",
        "0",
        "--no-openvino",
        "--json",
    )
    assert res.exit_code == 0, res.output
    rows = {r["backend"]: r for r in json.loads(res.stdout)["tasks"]["query"]["rows"]}
    assert {"torch reference", "torch export", "onnxruntime"} <= set(rows)
    assert all(r.get("status", "ok") == "ok" for r in rows.values()), rows


@pytest.mark.parametrize("state", ["mfam", "objects"])
def test_object_state_picks_the_coarse_stream_the_fine_stage_reads(state, tmp_path):
    """``fine.object_state`` makes the submap graph's object_features MFAM's (the default) or the
    object encoder's per-object output instead of the LSTM states: the same descriptor, the
    chosen stream (zero at padding), equal in both formulations, and the bundle passes parity."""
    card = fine_card(f"cra_layers: 3, heads: 2, mlp_hidden: 16, object_state: {state}")
    assert create_model(fine_card(TINY_FINE[7:-1])).submap.object_state == "mfam"  # a card's default
    lstm = fine_card("cra_layers: 3, heads: 2, mlp_hidden: 16, object_state: lstm")
    model, lstm_model = create_model(card).eval(), create_model(lstm).eval()
    assert model.state_dict().keys() == lstm_model.state_dict().keys()
    lstm_model.load_state_dict(model.state_dict())
    rng = np.random.default_rng(4)
    pts = torch.from_numpy(rng.uniform(0, 1, (2, 6, 32, 6)).astype(np.float32))
    counts = torch.tensor([[32.0, 20, 10, 32, 0, 0], [8.0, 32, 32, 32, 32, 32]])
    mask = counts > 0
    trace: dict = {}
    with torch.no_grad():
        desc, feats = model.submap(pts, counts, mask)
        lstm_desc, lstm_feats = lstm_model.submap(pts, counts, mask, trace=trace)
        ref_desc, ref_feats = model.submap.reference(pts[0, :4].numpy(), counts[0, :4].numpy())
    torch.testing.assert_close(desc, lstm_desc)
    assert not torch.allclose(feats[mask], lstm_feats[mask]) and (feats[~mask] == 0).all()
    torch.testing.assert_close(feats[1], trace[state][1])  # cell 1 is all real: no reordering
    torch.testing.assert_close(feats[0, :4], ref_feats, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(desc[0], ref_desc, atol=1e-5, rtol=1e-4)
    path = tmp_path / "des4pos-tiny-state.yaml"
    path.write_text(
        fine_card_text(f"cra_layers: 3, heads: 2, mlp_hidden: 16, object_state: {state}").replace(
            "name: des4pos-tiny", "name: des4pos-tiny-state"
        )
    )
    assert (
        invoke("export", "--model", "des4pos-tiny-state", "--config", path, "--output", tmp_path / "b").exit_code == 0
    )
    res = invoke(
        "parity-check",
        "--model",
        "des4pos-tiny-state",
        "--config",
        path,
        "--onnx",
        tmp_path / "b",
        "--cases",
        "4",
        "--json",
    )
    assert res.exit_code == 0 and json.loads(res.stdout)["passed"], res.output
