"""The studies over training seeds: benchmarks/detection_seeds.py (a detector's test AP) and
benchmarks/tdfanet_variants.py --seeds (TDFANet's ablations), summarised as mean, spread and the
t-interval of the mean (benchmarks/seed_stats.py) and rendered by benchmarks/render.py."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from conftest import benchmark_module

from radaredge.cards import load_card
from radaredge.data.detection_benchmark import make_detection_benchmark
from radaredge.models import create_model

ROOT = Path(__file__).resolve().parent.parent


def test_seed_summary_is_the_mean_with_its_student_t_interval():
    stats = benchmark_module("seed_stats")
    s = stats.seed_summary([1.0, 2.0, 3.0])
    half = 4.303 / math.sqrt(3)  # t(0.975, 2 df) * std 1 / sqrt(3)
    assert (s["n"], s["mean"], s["std"], s["min"], s["max"]) == (3, 2.0, 1.0, 1.0, 3.0)
    assert s["interval"] == pytest.approx([2.0 - half, 2.0 + half])
    one = stats.seed_summary([5.0])
    assert one["std"] is None and one["interval"] is None and one["mean"] == 5.0
    assert stats.ranking([3.0, 4.0, 5.0]) == "a" and stats.ranking([-3.0, -4.0, -5.0]) == "b"
    assert stats.ranking([-1.0, 4.0, 0.5]) == "not resolved" and stats.ranking([3.0]) == "not resolved"


def test_difference_of_two_cards_means_has_a_welch_interval():
    stats = benchmark_module("seed_stats")
    d = stats.difference_of_means([10.0, 12.0, 14.0], [4.0, 6.0])
    va, vb = 4.0 / 3, 2.0 / 2  # sample variances 4 and 2 over 3 and 2 seeds
    df = (va + vb) ** 2 / (va**2 / 2 + vb**2 / 1)  # Welch-Satterthwaite: 2.9, rounded down to 2
    assert d["mean"] == pytest.approx(7.0) and d["df"] == pytest.approx(df)
    assert d["interval"] == pytest.approx([7.0 - 4.303 * math.sqrt(va + vb), 7.0 + 4.303 * math.sqrt(va + vb)])
    assert stats.difference_of_means([10.0, 12.0], [4.0])["interval"] is None  # one seed: no interval


def _seed_doc(card: str, maps: list[float], ms: float, cpu: str = "AMD EPYC") -> dict:
    """A detection-seeds result as detection_seeds.py writes it, with these per-seed fp32 mAPs."""
    stats = benchmark_module("seed_stats")
    seeds = [
        {
            "seed": i,
            "checkpoint_sha256": f"{i:064x}",
            "scores": {"onnxruntime": {"mAP": {"3d": m}}, "onnxruntime int8": {"mAP": {"3d": m - 1}}},
            "speed": {"fp32": {"p50_ms": ms}, "int8": {"p50_ms": ms / 2}},
        }
        for i, m in enumerate(maps)
    ]
    return {
        "card": card,
        "configuration": {"voxel_size_m": 0.32, "layer_nums": [1, 2], "num_filters": [8, 16]},
        "data": "set",
        "split": "test",
        "area": "entire",
        "machine": {"cpu": cpu},
        "timing": {"frames": 40, "passes": 3, "threads": 2},
        "command": f"radaredge train --model {card} --seed SEED",
        "score_command": f"python benchmarks/detection_seeds.py --card {card}",
        "seeds": seeds,
        "summary": {
            "fp32": {"mAP": stats.seed_summary(maps)},
            "int8": {"mAP": stats.seed_summary([m - 1 for m in maps])},
            "int8 - fp32": {"mAP": stats.seed_summary([-1.0] * len(maps))},
            "p50_ms": {"fp32": stats.seed_summary([ms] * len(maps)), "int8": stats.seed_summary([ms / 2] * len(maps))},
        },
    }


def test_tradeoff_table_compares_every_card_with_the_reference_and_fills_the_model_doc(tmp_path):
    """The newest seed study per card becomes one row, slowest first; each card gets its mAP
    difference from the reference with a Welch interval; render writes the table into the doc."""
    tradeoff, render = benchmark_module("detection_tradeoff"), benchmark_module("render")
    results = tmp_path / "results"
    results.mkdir()
    for name, doc in [
        ("detection-seeds-big-2030-01-01.json", _seed_doc("big", [40.0, 42.0], 500.0)),
        ("detection-seeds-edge-2030-01-01.json", _seed_doc("edge", [10.0, 11.0, 12.0], 50.0)),
        ("detection-seeds-edge-2030-01-02.json", _seed_doc("edge", [30.0, 32.0, 34.0], 50.0)),
    ]:
        (results / name).write_text(json.dumps(doc))
    assert tradeoff.main(["--results", str(results), "--reference", "big"]) == 0
    (written,) = results.glob("detection-tradeoff-*.json")
    doc = json.loads(written.read_text())
    assert [r["card"] for r in doc["rows"]] == ["big", "edge"]  # slowest first
    assert doc["rows"][1]["source"] == "detection-seeds-edge-2030-01-02.json"  # the newest study
    (versus,) = doc["versus_reference"]
    assert versus["fp32_mAP_difference"]["mean"] == pytest.approx(32.0 - 41.0)
    assert versus["fp32_mAP_difference"]["interval"][1] < 0 and versus["fp32_speedup"] == pytest.approx(10.0)
    lines = "\n".join(render.tradeoff_lines(render.Result(written)))
    assert "| `edge` | 0.32 m pillars, [1, 2] x [8, 16] | 3 | 32.0 ± 2.0 [27.0, 37.0] |" in lines
    assert "`edge` against `big`: fp32 test mAP -9.0 points, 78 % of its mean" in lines and "below" in lines
    block = render.GENERATED[0]
    page = f"intro\n{block.begin}\nold table\n{block.end}\nafter\n"
    filled = block.fill(page, render.load(results))
    assert "old table" not in filled and lines in filled and filled.endswith(f"{block.end}\nafter\n")
    with pytest.raises(ValueError, match="expected the lines"):
        block.fill("no markers", render.load(results))
    # a study on another CPU does not join the table
    (results / "detection-seeds-other-2030-01-01.json").write_text(json.dumps(_seed_doc("other", [1.0], 5.0, "Xeon")))
    with pytest.raises(SystemExit, match="detection-seeds-other-2030-01-01.json: machine.cpu"):
        tradeoff.tradeoff(results, "big")
    # nor one on a CPU of the same model string with int8 dot products
    vnni = _seed_doc("other", [1.0], 5.0)
    vnni["machine"]["int8_dot_product"] = ["AVX-512 VNNI"]
    (results / "detection-seeds-other-2030-01-01.json").write_text(json.dumps(vnni))
    with pytest.raises(SystemExit, match="detection-seeds-other-2030-01-01.json: machine.int8_dot_product"):
        tradeoff.tradeoff(results, "big")


def test_weights_arguments_name_what_is_wrong(tmp_path):
    seeds = benchmark_module("detection_seeds")
    ckpt = tmp_path / "best.pth"
    ckpt.write_bytes(b"x")
    assert seeds.parse_weights([f"0={ckpt}", f"3={ckpt}"]) == {0: ckpt, 3: ckpt}
    missing = f"0={tmp_path}/missing.pth"
    for bad, said in (([str(ckpt)], "SEED=FILE"), ([missing], "SEED=FILE"), ([f"1={ckpt}"] * 2, "twice")):
        with pytest.raises(SystemExit, match=said):
            seeds.parse_weights(bad)


def test_two_seeds_are_scored_timed_summarised_and_rendered(tmp_path):
    """Two checkpoints of the tiny card (seeded with different card seeds, standing in for two
    training seeds) on a small labelled set: every seed's scores and checkpoint hash are in the
    JSON, the summary is their mean, and render.py shows the table."""
    seeds = benchmark_module("detection_seeds")
    render = benchmark_module("render")
    card = load_card(ROOT / "tests" / "cards" / "maffnet-tiny.yaml")
    data = tmp_path / "set"
    make_detection_benchmark(data, drives=8, frames=1, seed=0)  # the test split: a few drives
    weights = []
    for seed in (0, 1):
        net, generator = create_model(card), torch.Generator().manual_seed(seed)
        with torch.no_grad():  # seed 1's weights differ from the card's seeded ones
            for p in net.parameters():
                p.add_(seed * 0.05 * torch.randn(p.shape, generator=generator))
        path = tmp_path / f"run-{seed}" / "best.pth"
        path.parent.mkdir()
        torch.save({"model_state": net.state_dict(), "card": card.data, "epoch": 1, "metrics": {}}, path)
        weights += ["--weights", f"{seed}={path}"]
    results = tmp_path / "results"
    args = ["--card", str(card.path), "--data", str(data), *weights, "--command", "train --seed SEED"]
    assert seeds.main([*args, "--frames", "2", "--passes", "1", "--results", str(results)]) == 0
    (written,) = results.glob("detection-seeds-maffnet-tiny-*.json")
    doc = json.loads(written.read_text())
    assert [s["seed"] for s in doc["seeds"]] == [0, 1]
    assert all(len(s["checkpoint_sha256"]) == 64 and s["frames"] > 0 for s in doc["seeds"])
    fp32 = [s["scores"]["onnxruntime"]["mAP"]["3d"] for s in doc["seeds"]]
    assert doc["summary"]["fp32"]["mAP"]["mean"] == pytest.approx(sum(fp32) / 2)
    assert doc["summary"]["p50_ms"]["int8"]["n"] == 2
    text = render.render(results, tmp_path / "no-zoo")
    assert "## MAFF-Net across training seeds: maffnet-tiny" in text
    assert "| seed | checkpoint sha256 | epoch |" in text and f"`{doc['seeds'][1]['checkpoint_sha256'][:12]}`" in text


def _variant_row(val: float, test: float | None, seed: int) -> dict:
    epoch = {"epoch": 2, "val_R@1": val, "val_R@5": val, "val_R@10": val, "val_queries": 50}
    row = {"options": {"seed": seed}, "score_epoch": "last", "best": epoch, "last": epoch, "train_seconds": 60.0}
    if test is not None:
        recall = {"recall": {"1": test, "5": test + 5, "10": test + 8}}
        row["test"] = {"5": recall, "25": recall}
    return row


def test_tdfanet_ablations_over_seeds_say_whether_the_papers_ranking_holds(tmp_path):
    """Per ablation, the full model's test Recall@1 minus the ablation's is paired by seed: a
    difference above 0 on every seed with a narrow spread holds the paper's ranking, one below 0
    reverses it, one that changes sign is not resolved; render.py shows all three."""
    variants = benchmark_module("tdfanet_variants")
    render = benchmark_module("render")
    full, worse, better, mixed = [50.0, 52.0, 54.0], [40.0, 41.0, 43.0], [60.0, 63.0, 64.0], [45.0, 58.0, 52.0]
    rows = {
        "frozen": {str(s): _variant_row(60.0 + s, full[s], s) for s in range(3)},
        "no-dpr": {str(s): _variant_row(55.0, worse[s], s) for s in range(3)},
        "no-fa": {str(s): _variant_row(55.0, better[s], s) for s in range(3)},
        "sum": {str(s): _variant_row(55.0, mixed[s], s) for s in range(3)},
        "window": {str(s): _variant_row(50.0 + 2 * s, None, s) for s in range(3)},
    }
    summary, ranking = variants.seeds_summary(rows)
    assert summary["frozen"]["R@1 at 5 m"]["mean"] == pytest.approx(52.0)
    assert summary["window"]["val R@1"]["mean"] == pytest.approx(52.0) and "R@1 at 5 m" not in summary["window"]
    assert {k: v["paper_ranking"] for k, v in ranking.items()} == {
        "no-dpr": "holds",
        "no-fa": "reversed",
        "sum": "not resolved",
    }
    assert ranking["no-dpr"]["full_minus"]["mean"] == pytest.approx(32.0 / 3)
    results = tmp_path / "results"
    results.mkdir()
    doc = {
        "date": "2030-01-01 00:00",
        "card": "m",
        "machine": {"cpu": "cpu", "threads": 2},
        "command": "python benchmarks/tdfanet_variants.py --card m --seeds 0 1 2",
        "recipe": {"epochs": 2, "tuples_per_epoch": 8},
        "score_epoch": "last",
        "towns": {"design": {"seeds": [1]}, "test": {"seeds": [9]}},
        "choices": list(variants.CHOICES),
        "ablations": variants.ABLATIONS,
        "seeds": [0, 1, 2],
        "variants": rows,
        "summary": summary,
        "ranking": ranking,
    }
    (results / "tdfanet-variants-m-seeds-2030-01-01.json").write_text(json.dumps(doc))
    text = render.render(results, tmp_path / "no-zoo")
    assert "## TDFANet training choices and ablations over seeds: m, 2 epochs of 8 tuples" in text
    assert "| no-dpr | 3 | 10.7 ± 0.6 [9.2, 12.1] | holds |" in text
    assert "| no-fa | 3 | -10.3 ± 0.6 [-11.8, -8.9] | reversed |" in text
    assert "| full | yes | yes | yes | 3 | 52.0 ± 2.0 [47.0, 57.0] |" in text
    assert "| window | each window's own batch statistics while training | 3 | 52.0 ± 2.0 [47.0, 57.0] |" in text


def test_tdfanet_seed_runs_train_apart_score_the_last_epoch_and_are_reused(tmp_path, monkeypatch):
    """With seeds, each (variant, seed) trains in its own run directory with the seed among its
    options, the ablation is exported from last.pth (the last epoch), and a second call with
    the same recipe reuses the kept row instead of training again."""
    variants = benchmark_module("tdfanet_variants")
    trained, exported = [], []

    class Report:
        def __init__(self, options):
            n = options["epochs"]
            val = {"val_R@1": 40.0 + options["seed"], "val_R@5": 50.0, "val_R@10": 60.0, "val_queries": 10}
            self.doc = {
                "epochs": [{"epoch": e, "loss": 1.0, "seconds": 1.0, **val} for e in range(n + 1)],
                "best_epoch": 1,
                "seconds": 2.0,
            }

        def to_dict(self):
            return self.doc

    def train(card, design, run, options, overwrite, log):
        trained.append((card.name, run.name, options["seed"]))
        run.mkdir(parents=True, exist_ok=True)
        return Report(options)

    def score(describe, towns, k):
        recall = {"recall": {"1": 30.0, "5": 40.0, "10": 50.0}}
        return {"5": recall, "25": recall}

    monkeypatch.setattr(variants.radaredge, "train", train)
    monkeypatch.setattr(variants.radaredge, "export", lambda card, graph, checkpoint: exported.append(checkpoint.name))
    monkeypatch.setattr(variants.place_recognition, "graph_descriptors", lambda graph, described: None)
    monkeypatch.setattr(variants.place_recognition, "score", score)
    card = load_card(ROOT / "tests" / "cards" / "tdfanet-tiny.yaml")
    options = {"epochs": 2, "tuples_per_epoch": 4}
    for seed in (0, 1):
        row = variants.measure_variant(card, "sum", tmp_path, options, [], 3, seed, "last")
        assert row["options"]["seed"] == seed and row["score_epoch"] == "last" and row["last"]["epoch"] == 2
    assert trained == [("tdfanet-tiny-sum", "sum-seed0", 0), ("tdfanet-tiny-sum", "sum-seed1", 1)]
    assert exported == ["last.pth", "last.pth"]
    variants.measure_variant(card, "sum", tmp_path, options, [], 3, 1, "last")  # kept: not trained again
    assert len(trained) == 2 and set(variants.measured(tmp_path, options, 1, "last")) == {"sum"}
    assert variants.measured(tmp_path, options, 1, "best") == {}  # another scoring rule is another study
