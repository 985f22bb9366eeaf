"""TDFANet in train mode and `radaredge train`: the loss, the tuples, the lazy gradient pass, batch
statistics of the pillar net, device-agnostic forward, column lookup by name, the ablation switches,
resume, bad training data, and a tiny card that learns."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import TINY_CARD, invoke
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

import radaredge
from radaredge.cards import load_card
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.data.sequences import load_sequence
from radaredge.errors import ConfigError, InputError
from radaredge.models import create_model
from radaredge.models.tdfanet.spec import make_cases
from radaredge.ops.ego_velocity import estimate_ego_velocity
from radaredge.ops.pillars import pillar_features_reference, scatter_pillars_reference
from radaredge.training import tdfanet as T
from radaredge.training.losses import lazy_quadruplet_loss
from radaredge.training.places import TupleMiner, load_place_windows


@pytest.fixture(scope="module")
def card():
    return load_card(TINY_CARD)


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    """One synthetic town driven three times (the last drive held out for validation)."""
    root = tmp_path_factory.mktemp("train-town")
    make_pr_benchmark(root / "town-1", drives=3, frames_per_drive=30, seed=1)
    return root


def _window(card, seed=0):
    feeds = make_cases(card, 1, seed)[0][1]
    return [torch.from_numpy(feeds[f"points_{k}"]) for k in range(3)], torch.from_numpy(feeds["timestamps"])


# ----------------------------------------------------------------------------- eq. 10


def _unit(rows):
    return F.normalize(torch.tensor(rows, dtype=torch.float64), dim=-1)


def test_lazy_quadruplet_loss_by_hand():
    q = _unit([[1.0, 0.0, 0.0]])
    pos = _unit([[[1.0, 0.1, 0.0], [0.0, 1.0, 0.0]]])  # the best positive is the first
    neg = _unit([[[0.9, 0.2, 0.0], [0.0, 0.0, 1.0]]])  # the hardest negative is the first
    star = _unit([[0.95, 0.0, 0.3]])
    d = lambda a, b: float((a - b).norm())  # noqa: E731
    d_pos, d_neg, d_star = d(q[0], pos[0, 0]), d(q[0], neg[0, 0]), d(q[0], star[0])
    expected = max(0.0, 0.2 + d_pos - d_neg) + max(0.0, 0.1 + d_pos - d_star)
    assert float(lazy_quadruplet_loss(q, pos, neg, star)) == pytest.approx(expected, abs=1e-12)
    # PointNetVLAD's second term compares neg* with the negatives instead of the query
    d_sn = min(d(star[0], neg[0, 0]), d(star[0], neg[0, 1]))
    expected_pnv = max(0.0, 0.2 + d_pos - d_neg) + max(0.0, 0.1 + d_pos - d_sn)
    assert float(lazy_quadruplet_loss(q, pos, neg, star, second_term="pointnetvlad")) == pytest.approx(expected_pnv)
    # a tuple that satisfies both margins costs nothing
    far = _unit([[[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]])
    assert float(lazy_quadruplet_loss(q, pos[:, :1], far, _unit([[0.0, 0.0, -1.0]]))) == 0.0


def test_tuples_follow_the_radii(card, town):
    data = load_place_windows(town, 3)
    miner = TupleMiner(data, positives=2, negatives=6, hard=3)
    rng = np.random.default_rng(0)
    miner.set_descriptors(np.random.default_rng(1).normal(size=(len(data), 8)))
    for q in miner.queries[::9]:
        t = miner.tuple_for(int(q), rng)
        dist = data.distances(t.query)
        assert all(dist[p] <= 5.0 and data.drive[p] != data.drive[t.query] for p in t.positives)
        assert all(dist[n] > 10.0 for n in t.negatives) and len(set(t.negatives)) == 6
        assert dist[t.other_negative] > 10.0
        apart = lambda i: all(np.linalg.norm(data.positions[i] - data.positions[n]) > 10.0 for n in t.negatives)  # noqa: E731
        if any(apart(i) for i in np.flatnonzero(~data.validation) if dist[i] > 10.0):
            assert apart(t.other_negative)  # neg* is a negative of every negative when one exists
        assert not any(data.validation[[t.query, *t.positives, *t.negatives, t.other_negative]])


def test_the_hardest_other_negative_is_the_nearest_descriptor_among_the_far_windows(card, town):
    data = load_place_windows(town, 3)
    desc = np.random.default_rng(1).normal(size=(len(data), 8))
    hardest = TupleMiner(data, positives=2, negatives=6, hard=3, hard_pool=10**6, other_negative="hardest")
    hardest.set_descriptors(desc)
    train = np.flatnonzero(~data.validation)
    for q in hardest.queries[::15]:
        t = hardest.tuple_for(int(q), np.random.default_rng(0))
        far = [
            i
            for i in train
            if data.distances(t.query)[i] > 10.0
            and all(np.linalg.norm(data.positions[i] - data.positions[n]) > 10.0 for n in t.negatives)
        ]
        if far:
            gap = np.linalg.norm(desc[far] - desc[t.query], axis=1)
            assert t.other_negative == far[int(np.argmin(gap))]
    with pytest.raises(ValueError, match="other_negative"):
        TupleMiner(data, positives=2, negatives=6, hard=3, other_negative="nearest")


# ----------------------------------------------------------------------------- train mode


def test_tuple_loss_is_the_full_tuples_loss_and_gradient(card, town):
    """Describing only the windows the loss reaches (lazy pass) gives bitwise the loss, the gradient,
    the BatchNorm running statistics and the random state of describing every window with gradients."""
    data = load_place_windows(town, 3)
    model = create_model(card)
    prepared = T.prepare_windows(model, data, torch.device("cpu"))
    miner = TupleMiner(data, 2, 6, 0)
    rng = np.random.default_rng(0)
    recipe = T.PlaceRecipe(negatives=6, hard_negatives=0)
    for trial in range(3):
        tup = miner.tuple_for(int(miner.queries[trial * 11]), rng)
        start = {k: v.clone() for k, v in model.state_dict().items()}
        runs = []
        for lazy in (False, True):
            model.load_state_dict(start)
            model.train()
            model.zero_grad()
            torch.manual_seed(trial)
            if lazy:
                loss, active = T.tuple_loss(model, prepared, tup, recipe)
                assert 0 < active <= 4
            else:
                idx = [tup.query, *tup.positives, *tup.negatives, tup.other_negative]
                d = F.normalize(torch.cat([model.describe([prepared[i]]) for i in idx]), dim=1)
                loss = lazy_quadruplet_loss(d[:1], d[1:3][None], d[3:9][None], d[-1:])
            loss.backward()
            runs.append(
                (
                    loss.detach(),
                    [p.grad.clone() for p in model.parameters()],
                    {k: v.clone() for k, v in model.state_dict().items()},
                    torch.get_rng_state(),
                )
            )
        (l0, g0, s0, r0), (l1, g1, s1, r1) = runs
        assert torch.equal(l0, l1) and float(l0) > 0
        assert all(torch.equal(a, b) for a, b in zip(g0, g1))
        assert all(torch.equal(s0[k], s1[k]) for k in s0)
        assert torch.equal(r0, r1)


def test_pillar_batch_statistics_are_openpcdets_padded_ones(card):
    """In train mode the point-wise pillar net normalises with the statistics of OpenPCDet's padded
    [pillars, slots] tensor, and updates its running statistics as BatchNorm1d does on it."""
    frames, _ = _window(card)
    points = frames[-1]
    a, b = create_model(card), create_model(card)
    a.vfe.train()
    b.vfe.train()
    canvas = a.vfe(points, torch.ones(len(points), dtype=torch.bool))
    feats, coords = pillar_features_reference(b.vfe, points.numpy())  # nn.BatchNorm1d on every slot
    reference = scatter_pillars_reference(feats, coords, b.vfe.config)
    torch.testing.assert_close(canvas, reference, atol=2e-5, rtol=1e-5)
    for name in ("running_mean", "running_var"):
        torch.testing.assert_close(getattr(a.vfe.pfn_layers[0].norm, name), getattr(b.vfe.pfn_layers[0].norm, name))
    a.eval()  # eval outputs are those of the running statistics
    b.eval()
    torch.testing.assert_close(
        a.vfe(points, torch.ones(len(points), dtype=torch.bool)),
        scatter_pillars_reference(*pillar_features_reference(b.vfe, points.numpy()), b.vfe.config),
        atol=2e-5,
        rtol=1e-5,
    )


@pytest.mark.parametrize("name", ["tdfanet", "tdfanet-edge"])
def test_train_mode_and_backward_on_the_full_cards(name):
    model = create_model(load_card(name)).train()
    frames, ts = _window(load_card(name))
    out = model.run([f[:150] for f in frames], ts)
    out["descriptor_normalized"].sum().backward()
    grads = {n: p.grad for n, p in model.named_parameters()}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values())
    assert grads["vfe.pfn_layers.0.linear.weight"].abs().sum() > 0 and grads["gem.p"].abs().sum() > 0


class _CpuTensors(TorchDispatchMode):
    """Records every op that returns a CPU tensor."""

    def __init__(self):
        super().__init__()
        self.ops: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if any(isinstance(t, torch.Tensor) and t.device.type == "cpu" for t in tree_flatten(out)[0]):
            self.ops.append(str(func))
        return out


def test_forward_creates_no_cpu_tensor_on_another_device(card):
    """The meta device stands in for CUDA: every tensor made inside forward takes its device from the input."""
    frames, ts = _window(card)
    model = create_model(load_card("tdfanet-edge")).to("meta")
    with _CpuTensors() as watch:
        torch.zeros(3)  # the watch sees a CPU tensor when one is made
    assert watch.ops
    with _CpuTensors() as watch:
        out = model.run([f.to("meta") for f in frames], ts.to("meta"))
        model.train()
        model.describe([model.prepare([f.to("meta") for f in frames], ts.to("meta"))])
    assert watch.ops == [] and all(v.device.type == "meta" for v in out.values())


# ----------------------------------------------------------------------------- columns by name


def test_doppler_column_is_looked_up_by_name(card, tmp_path):
    swapped = tmp_path / "swapped.yaml"
    swapped.write_text(TINY_CARD.read_text().replace("features: [x, y, z, v_r, rcs]", "features: [x, y, z, rcs, v_r]"))
    frames, ts = _window(card, seed=2)
    plain, other = create_model(card), create_model(load_card(swapped))
    with torch.no_grad():
        a = plain.run(frames, ts)
        b = other.run([f[:, [0, 1, 2, 4, 3]] for f in frames], ts)
        c = other.run([f[:, [0, 1, 2, 4, 3]] for f in frames], ts, reference=True)
    assert bool(a["ego_valid"].all())
    torch.testing.assert_close(a["ego_velocity"], b["ego_velocity"], atol=1e-4, rtol=0)
    torch.testing.assert_close(a["ego_velocity"], c["ego_velocity"], atol=1e-4, rtol=0)
    v_ref, _, _ = estimate_ego_velocity(frames[-1][:, :3].numpy(), frames[-1][:, 3].numpy())
    np.testing.assert_allclose(b["ego_velocity"][-1].numpy(), v_ref, atol=1e-4)
    for features in ("[x, y, z, rcs]", "[v_r, x, y, z, rcs]"):
        bad = tmp_path / "bad.yaml"
        bad.write_text(TINY_CARD.read_text().replace("features: [x, y, z, v_r, rcs]", f"features: {features}"))
        with pytest.raises(ConfigError, match="v_r"):
            create_model(load_card(bad))


# ----------------------------------------------------------------------------- ablations (Table II)


@pytest.mark.parametrize("switch", ["remove_dynamic: false", "align: false", "aggregation: sum"])
def test_ablation_switches_export_with_parity(switch, tmp_path):
    path = tmp_path / "ablation.yaml"
    text = TINY_CARD.read_text().replace("network: {", f"network: {{{switch}, ")
    path.write_text(text)
    card = load_card(path)
    model = create_model(card)
    res = radaredge.export(card, tmp_path / "a.onnx", model=model)
    report = radaredge.parity(card, res.path, model=model, cases=4)
    assert report, report.to_dict()
    frames, ts = _window(card)
    full = create_model(load_card(TINY_CARD))
    with torch.no_grad():
        prepared, reference = model.prepare(frames, ts), full.prepare(frames, ts)
    if switch.startswith("remove_dynamic"):
        assert bool(prepared.keep.all()) and not bool(reference.keep.all())
    if switch.startswith("align"):
        assert float(prepared.cells.abs().max()) == 0.0 and float(reference.cells.abs().max()) > 0.1
    if switch.startswith("aggregation"):
        assert not hasattr(model, "pyramid") and not hasattr(model, "dfa")


# ----------------------------------------------------------------------------- training runs


def _train(town, out, epochs, *extra):
    return invoke(
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
        epochs,
        "--set",
        "negatives=6",
        "--set",
        "hard_negatives=3",
        "--set",
        "tuples_per_epoch=12",
        *extra,
    )


def test_train_writes_an_exportable_checkpoint_and_resumes_exactly(town, tmp_path):
    first = _train(town, tmp_path / "a", 1)
    assert first.exit_code == 0, first.output
    resumed = _train(town, tmp_path / "a", 2, "--resume")
    assert resumed.exit_code == 0, resumed.output
    straight = _train(town, tmp_path / "b", 2, "--json")
    assert straight.exit_code == 0, straight.output
    log_a = json.loads((tmp_path / "a" / "train-log.json").read_text())
    log_b = json.loads(straight.stdout)
    untimed = lambda log: [{k: v for k, v in e.items() if k != "seconds"} for e in log["epochs"]]  # noqa: E731
    assert [e["epoch"] for e in log_a["epochs"]] == [0, 1, 2] and untimed(log_a) == untimed(log_b)
    assert log_b["data"]["queries_per_epoch"] == 12 < log_b["data"]["training_windows"]
    a = torch.load(tmp_path / "a" / "last.pth", weights_only=True)["model_state"]
    b = torch.load(tmp_path / "b" / "last.pth", weights_only=True)["model_state"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    res = invoke(
        "export",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--checkpoint",
        tmp_path / "b" / "best.pth",
        "--output",
        tmp_path / "t.onnx",
    )
    assert res.exit_code == 0, res.output
    par = invoke(
        "parity-check",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--checkpoint",
        tmp_path / "b" / "best.pth",
        "--onnx",
        tmp_path / "t.onnx",
        "--cases",
        4,
    )
    assert par.exit_code == 0, par.output
    again = _train(town, tmp_path / "a", 2, "--resume")
    assert again.exit_code == 2 and "already holds epoch 2" in again.output


def test_a_run_stopped_within_an_epoch_resumes_at_the_next_step(card, town, tmp_path, monkeypatch):
    """With save_minutes 0 last.pth is written after every step; a run killed at step 5 of
    epoch 2 resumes there and ends as the run that never stopped (weights, Adam moments,
    epoch rows); one killed before epoch 1's first step resumes from epoch 0's save."""
    recipe = T.PlaceRecipe(epochs=2, negatives=6, hard_negatives=3, tuples_per_epoch=8, save_minutes=0.0)
    straight = T.train_places(card, create_model(card), town, tmp_path / "b", recipe)
    real, calls = T.tuple_loss, {"n": 0}

    def dies_at(n):
        def loss(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] > n:
                raise KeyboardInterrupt
            return real(*args, **kwargs)

        calls["n"] = 0
        monkeypatch.setattr(T, "tuple_loss", loss)

    for stop in (0, 13):  # before epoch 1's first step; at step 5 of epoch 2
        out = tmp_path / f"a{stop}"
        dies_at(stop)
        with pytest.raises(KeyboardInterrupt):
            T.train_places(card, create_model(card), town, out, recipe)
        state = torch.load(out / "last.pth", weights_only=True)
        assert (state["epoch"], state.get("partial", {}).get("done")) == ((0, None) if stop == 0 else (1, 5))
        monkeypatch.setattr(T, "tuple_loss", real)
        lines = []
        resumed = T.train_places(card, create_model(card), town, out, recipe, resume=True, log=lines.append)
        assert any(("after 5 of epoch 2's tuples" if stop else "after epoch 0 ") in line for line in lines), lines
        untimed = lambda rows: json.dumps([{k: v for k, v in e.items() if k != "seconds"} for e in rows])  # noqa: E731
        assert untimed(resumed.epochs) == untimed(straight.epochs)
        a = torch.load(out / "last.pth", weights_only=True)
        b = torch.load(tmp_path / "b" / "last.pth", weights_only=True)
        assert all(torch.equal(a["model_state"][k], b["model_state"][k]) for k in a["model_state"])
        assert torch.equal(a["optimizer"]["state"][0]["exp_avg"], b["optimizer"]["state"][0]["exp_avg"])
        assert "partial" not in a


def test_reestimated_norm_statistics_follow_the_trained_weights(card, town, tmp_path):
    """batch_norm: reestimate trains epoch 1 exactly as frozen does, then re-estimates the
    statistics from the trained weights: frozen's weights with statistics re-estimated by hand."""
    recipe = dict(epochs=1, negatives=6, hard_negatives=3, tuples_per_epoch=10, norm_windows=20)
    runs = {}
    for mode in ("frozen", "reestimate"):
        T.train_places(card, create_model(card), town, tmp_path / mode, T.PlaceRecipe(batch_norm=mode, **recipe))
        runs[mode] = torch.load(tmp_path / mode / "last.pth", weights_only=True)["model_state"]
    stats = [k for k in runs["frozen"] if k.endswith(("running_mean", "running_var"))]
    weights = [k for k in runs["frozen"] if k not in stats and not k.endswith("num_batches_tracked")]
    assert stats and all(torch.equal(runs["frozen"][k], runs["reestimate"][k]) for k in weights)
    assert not all(torch.equal(runs["frozen"][k], runs["reestimate"][k]) for k in stats)
    by_hand = create_model(card)
    by_hand.load_state_dict(runs["frozen"])
    data = load_place_windows(town, by_hand.frames)
    rows = np.sort(np.random.default_rng(0).choice(np.flatnonzero(~data.validation), 20, replace=False))
    T.estimate_norm_statistics(by_hand, T.prepare_windows(by_hand, data, torch.device("cpu")), rows)
    for k in stats:
        torch.testing.assert_close(by_hand.state_dict()[k], runs["reestimate"][k])


def test_a_tiny_card_learns(card, tmp_path):
    """A few dozen steps on a seeded town: the loss falls and the held-out drive's recall rises."""
    root = tmp_path / "data"
    make_pr_benchmark(root / "town-2", drives=3, frames_per_drive=40, seed=2)
    model = create_model(card)
    recipe = T.PlaceRecipe(epochs=3, negatives=6, hard_negatives=3, lr=2e-3)
    report = T.train_places(card, model, root, tmp_path / "run", recipe)
    epochs = report.epochs
    assert [e["epoch"] for e in epochs] == [0, 1, 2, 3]
    assert epochs[-1]["loss"] < epochs[1]["loss"]
    assert epochs[-1]["val_R@1"] > epochs[0]["val_R@1"] + 10.0, epochs
    for e in epochs:  # the recall is a share of val_queries scored queries
        hits = e["val_R@1"] * e["val_queries"] / 100.0
        assert e["val_queries"] > 0 and abs(hits - round(hits)) < 1e-6, e


@pytest.mark.parametrize("switch", ["align: false", "remove_dynamic: false", "aggregation: sum"])
def test_every_ablation_trains(switch, town, tmp_path):
    """Each ablation switch trains: a few tuples step the weights. align: false once corrupted
    memory in the first backward pass, on two or more torch threads only."""
    path = tmp_path / "ablation.yaml"
    path.write_text(TINY_CARD.read_text().replace("network: {", f"network: {{{switch}, "))
    card = load_card(path)
    model = create_model(card)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        report = T.train_places(
            card,
            model,
            town,
            tmp_path / "run",
            T.PlaceRecipe(epochs=1, negatives=6, hard_negatives=3, tuples_per_epoch=20),
        )
    finally:
        torch.set_num_threads(threads)
    assert np.isfinite(report.epochs[-1]["loss"])
    assert any(not torch.equal(before[k], v) for k, v in model.state_dict().items())


@pytest.mark.parametrize(
    "damage, says",
    [
        ("no-gps", "gps.csv: no such file"),
        ("empty-scans", "no .npy scan files"),
        ("apart", "too few positives"),
        ("nan", "scans/000004.npy: non-finite value nan at point 1, column 'rcs'"),
    ],
)
def test_bad_training_data_is_one_error_line_naming_the_drive(tmp_path, damage, says):
    root = tmp_path / "data"
    make_pr_benchmark(root / "town-1", drives=4, frames_per_drive=16, seed=1)  # drive-03 validates
    drive = root / "town-1" / "queries" / "drive-01"
    if damage == "no-gps":
        (drive / "gps.csv").unlink()
    elif damage == "empty-scans":
        for f in (drive / "scans").iterdir():
            f.unlink()
    elif damage == "nan":
        values = np.load(drive / "scans" / "000004.npy")
        values[1, 4] = np.nan
        np.save(drive / "scans" / "000004.npy", values)
    else:
        lines = (drive / "gps.csv").read_text().splitlines()
        shifted = [lines[0]] + [
            ",".join([r.split(",")[0], str(float(r.split(",")[1]) + 500.0), r.split(",")[2]]) for r in lines[1:]
        ]
        (drive / "gps.csv").write_text("\n".join(shifted) + "\n")
    res = _train(root, tmp_path / "run", 1)
    assert res.exit_code == 2 and "Traceback" not in res.output
    errors = [line for line in res.stderr.splitlines() if line.startswith("error:")]
    last = res.stderr.strip().splitlines()[-1]  # progress lines may come first; the error ends the run
    assert errors == [last] and "drive-01" in last and says in last, res.output
    assert not (tmp_path / "run").exists()


def test_transloc4d_layout_matches_rows_to_timestamp_named_files(tmp_path):
    drive = tmp_path / "query"
    (drive / "pointclouds").mkdir(parents=True)
    stamps = [1646303235000000 + 100_000 * i for i in range(5)]
    for i, s in enumerate(stamps):
        np.save(drive / "pointclouds" / f"{s}.npy", np.full((4, 5), i, np.float32))
    np.save(drive / "pointclouds" / "1646303299000000.npy", np.zeros((4, 5), np.float32))  # no row: ignored
    rows = ["timestamp,northing,easting,yaw"] + [f"{s},{100 + i},{200 - i},0.1" for i, s in enumerate(stamps)]
    (drive / "gps.csv").write_text("\n".join(rows) + "\n")
    seq = load_sequence(drive)
    np.testing.assert_allclose(np.diff(seq.timestamps), 0.1, rtol=0, atol=1e-6)  # float64 epoch s: 0.24 us steps
    assert seq.scan(3, ["x", "v_r"]).tolist() == [[3.0, 3.0]] * 4
    np.testing.assert_allclose(seq.positions[2], [102.0, 198.0])
    (drive / "pointclouds" / f"{stamps[2]}.npy").unlink()
    with pytest.raises(InputError, match="row 2 .* has no scan"):
        load_sequence(drive)
