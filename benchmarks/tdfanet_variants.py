"""TDFANet's open training choices and the paper's ablations, each variant trained the same way.

Every variant is ``radaredge train`` of one card (default tdfanet-edge) on the design towns of
benchmarks/place_recognition.py, with the same recipe: the card's, shortened by ``--set``
(default 3 epochs of 200 tuples, so that seven variants fit in under two hours on 2 cores).

- **choices**, the two training choices the paper leaves open, judged on the design towns only
  by the best epoch's validation Recall@1 at 5 m with its 95 % bootstrap interval:
  ``frozen`` (the recipe's default: BatchNorm statistics estimated once from the untrained
  network, then fixed; neg* a random true negative), ``reestimate`` (the statistics estimated
  again after every epoch), ``window`` (each window's own batch statistics while training) and
  ``hardest`` (neg* the nearest true negative in descriptor space).
- **ablations**, the components of the paper's ablation table (its Table II), each removed
  from the full network in turn: ``full`` (the ``frozen`` run), ``no-dpr`` (dynamic points
  stay in the BEV maps, ``network.remove_dynamic: false``), ``no-fa`` (no trajectory
  alignment, ``network.align: false``), ``sum`` (the K maps summed, no pyramid and no
  deformable attention, ``network.aggregation: sum``). Scored as the exported fp32 graph on the
  test towns: Recall@1/5/10 at 5 m and 25 m with intervals (place_recognition.score).

With ``--seeds 0 1 2`` every variant is trained once per seed (``radaredge train --seed``: the
tuple order, the mining and dropout; every run starts from the card's seeded weights) in
runs/<variant>-seed<S>, and every run is scored at its last epoch (``--score-epoch last``, the
default there): the same training budget for every variant, no checkpoint picked per run. The
results file (``tdfanet-variants-<card>[-<recipe>]-seeds-<date>.json``) then holds each seed's row,
each variant's mean, spread and 95 % t-interval over the seeds (seed_stats.py) and, per ablation,
the paired per-seed difference of test Recall@1 at 5 m from the full model, with whether the
paper's ranking (the full model above each ablation) holds, is reversed or is not resolved.

A recipe other than the short one (``--set epochs=5 --set tuples_per_epoch=500``) writes its own
results file (``tdfanet-variants-<card>-5x500-<date>.json``), rendered beside the short one's.
Each variant's run directory is kept under the work directory (``--work``), with the variant's
measured row (variant.json): a variant measured there with the same recipe is not trained or
scored again, and a run that finished training is not trained again, so ``--variants`` can
measure one variant at a time. Writes benchmarks/results/tdfanet-variants-<card>-<date>.json
with every variant measured under the work directory, which benchmarks/render.py renders.

    python benchmarks/tdfanet_variants.py --card tdfanet-edge --design-towns 1 --design-km 0.5
"""

from __future__ import annotations

import copy
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import place_recognition
import training_run
from result_file import result_path, write_result
from seed_stats import ranking as seed_ranking
from seed_stats import seed_summary

import radaredge
from radaredge.cards import parse_card
from radaredge.eval.recall_stats import bootstrap_interval

SHORT_RECIPE = {"epochs": 3, "tuples_per_epoch": 200}

# name -> (card network fields, recipe options) on top of the card and the shared recipe
VARIANTS = {
    "frozen": ({}, {}),
    "reestimate": ({}, {"batch_norm": "reestimate"}),
    "window": ({}, {"batch_norm": "window"}),
    "hardest": ({}, {"other_negative": "hardest"}),
    "no-dpr": ({"remove_dynamic": False}, {}),
    "no-fa": ({"align": False}, {}),
    "sum": ({"aggregation": "sum"}, {}),
}
CHOICES = ("frozen", "reestimate", "window", "hardest")
ABLATIONS = {"full": "frozen", "no-dpr": "no-dpr", "no-fa": "no-fa", "sum": "sum"}
ROW = "variant.json"  # a variant's measured row, in its run directory


def variant_card(card, network: dict, name: str):
    """``card`` with ``network`` fields replaced, named ``<card>-<name>``."""
    data = copy.deepcopy(card.data)
    data["name"] = f"{card.name}-{name}"
    data["network"] = {**(data.get("network") or {}), **network}
    return parse_card(data, card.path)


def validation_interval(epoch: dict) -> list[float]:
    """95 % bootstrap interval of an epoch's validation Recall@1 over its validation queries
    (a hit vector's bootstrap depends only on its length and its number of hits)."""
    n = int(epoch["val_queries"])
    found = np.zeros(n, dtype=bool)
    found[: int(round(epoch["val_R@1"] * n / 100.0))] = True
    return list(bootstrap_interval(found))


def _finished(run: Path, epochs: int) -> dict | None:
    log = run / "train-log.json"
    if not log.exists():
        return None
    report = json.loads(log.read_text())
    return report if report["epochs"][-1]["epoch"] >= epochs and (run / "best.pth").exists() else None


def train_variant(card, design: Path, run: Path, options: dict) -> dict:
    """The training report of ``card`` with ``options`` in ``run`` (trained there unless it finished)."""
    report = _finished(run, int(options["epochs"]))
    if report is not None:
        print(f"{card.name}: reusing the finished run in {run}", flush=True)
        return report
    t0 = time.perf_counter()
    report = radaredge.train(
        card, design, run, options=options, overwrite=True, log=lambda line: print(f"{card.name}: {line}", flush=True)
    ).to_dict()
    report["wall_seconds"] = round(time.perf_counter() - t0, 1)
    return report


def _epoch_row(report: dict, epoch: int) -> dict:
    """One epoch's validation figures with the 95 % interval of its Recall@1."""
    best = next(e for e in report["epochs"] if e["epoch"] == epoch)
    return {
        "epoch": best["epoch"],
        "val_R@1": best["val_R@1"],
        "val_R@5": best["val_R@5"],
        "val_R@10": best["val_R@10"],
        "val_queries": best["val_queries"],
        "val_R@1_interval_95": validation_interval(best),
    }


def run_dir(work: Path, name: str, seed: int | None) -> Path:
    """A variant's run directory: runs/<name>, or runs/<name>-seed<S> in a --seeds study."""
    return work / "runs" / (name if seed is None else f"{name}-seed{seed}")


def variant_options(name: str, options: dict, seed: int | None) -> dict:
    """The recipe options variant ``name`` trains with (``seed`` added in a --seeds study)."""
    return {**options, **VARIANTS[name][1], **({} if seed is None else {"seed": seed})}


def measure_variant(
    card, name: str, work: Path, options: dict, test: list[Path], k: int, seed: int | None = None, score: str = "best"
) -> dict:
    """The table row of variant ``name``: trained under :func:`run_dir` (unless finished there),
    scored on ``test`` when it is an ablation with the weights of the ``score`` epoch (``best``:
    the best validation epoch's best.pth; ``last``: the last epoch's, from last.pth), and kept in
    that run directory as variant.json (a finished variant with the same recipe and scoring is
    not measured again)."""
    network, _ = VARIANTS[name]
    run = run_dir(work, name, seed)
    kept = run / ROW
    if name in measured(work, options, seed, score):
        print(f"{card.name}-{name}: reusing {kept}", flush=True)
        return json.loads(kept.read_text())
    vcard = variant_card(card, network, name)
    opts = variant_options(name, options, seed)
    report = train_variant(vcard, work / "design-towns", run, opts)
    last = report["epochs"][-1]["epoch"]
    row = {
        "network": network,
        "recipe": VARIANTS[name][1],
        "options": opts,
        "score_epoch": score,
        "best": _epoch_row(report, report["best_epoch"]),
        "last": _epoch_row(report, last),
        "train_seconds": report["seconds"],
        "history": [
            {key: e[key] for key in ("epoch", "loss", "val_R@1", "val_R@5", "val_R@10", "seconds")}
            for e in report["epochs"]
        ],
    }
    if name in ABLATIONS.values():
        graph = work / "graphs" / f"{run.name}.onnx"
        radaredge.export(vcard, graph, checkpoint=run / ("best.pth" if score == "best" else "last.pth"))
        described = run / "descriptors"
        shutil.rmtree(described, ignore_errors=True)  # an earlier training's
        row["test"] = place_recognition.score(place_recognition.graph_descriptors(graph, described), test, k)
        print(f"{vcard.name}: test R@1 at 5 m {row['test']['5']['recall']['1']:.1f} %", flush=True)
    write_result(kept, row)
    return row


def measured(work: Path, options: dict, seed: int | None = None, score: str = "best") -> dict[str, dict]:
    """The rows of every variant measured under ``work`` with the recipe ``options``, ``seed`` and
    scoring rule, in table order (rows from before the scoring rule was recorded were ``best``)."""
    rows = {}
    for name in VARIANTS:
        kept = run_dir(work, name, seed) / ROW
        if not kept.exists():
            continue
        row = json.loads(kept.read_text())
        if row.get("options") == variant_options(name, options, seed) and row.get("score_epoch", "best") == score:
            rows[name] = row
    return rows


TEST_FIGURES = {
    "R@1 at 5 m": ("5", "1"),
    "R@5 at 5 m": ("5", "5"),
    "R@10 at 5 m": ("5", "10"),
    "R@1 at 25 m": ("25", "1"),
}


def seeds_summary(rows: dict[str, dict[str, dict]]) -> tuple[dict, dict]:
    """(variant -> figure -> :func:`seed_stats.seed_summary` over the seeds: the scored epoch's
    validation Recall@1 and, for ablations, the test figures; ablation -> the paired per-seed
    difference of test Recall@1 at 5 m of the full model minus it, summarised, with the verdict
    on the paper's ranking) from ``rows`` (variant -> seed -> row)."""
    summary = {}
    for name, by_seed in rows.items():
        runs = list(by_seed.values())
        figures = {"val R@1": seed_summary([r[r.get("score_epoch", "best")]["val_R@1"] for r in runs])}
        if all("test" in r for r in runs):
            for label, (radius, n) in TEST_FIGURES.items():
                figures[label] = seed_summary([r["test"][radius]["recall"][n] for r in runs])
        summary[name] = figures
    ranking = {}
    full = rows.get(ABLATIONS["full"], {})
    for label, name in ABLATIONS.items():
        if label == "full" or name not in rows:
            continue
        common = sorted(set(full) & set(rows[name]), key=int)
        if not common:
            continue
        diffs = [full[s]["test"]["5"]["recall"]["1"] - rows[name][s]["test"]["5"]["recall"]["1"] for s in common]
        verdict = {"a": "holds", "b": "reversed", "not resolved": "not resolved"}[seed_ranking(diffs)]
        ranking[label] = {
            "seeds": [int(s) for s in common],
            "full_minus": seed_summary(diffs),
            "paper_ranking": verdict,
        }
    return summary, ranking


def main(argv=None) -> int:
    ap = training_run.parser("python benchmarks/tdfanet_variants.py", __doc__, "tdfanet-edge")
    ap.add_argument("--design-towns", type=int, default=1)
    ap.add_argument("--design-km", type=float, default=0.5)
    ap.add_argument("--test-towns", type=int, default=1)
    ap.add_argument("--test-km", type=float, default=2.2)
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--seeds", nargs="+", type=int, help="train every variant once per seed (module docstring)")
    ap.add_argument(
        "--score-epoch",
        choices=("best", "last"),
        help="the weights scored: the best validation epoch's or the last epoch's [default: last with --seeds, "
        "else best]",
    )
    args = ap.parse_args(argv)
    card, work, options, stamp = training_run.start(args)
    options = {**SHORT_RECIPE, **options}
    score = args.score_epoch or ("last" if args.seeds else "best")
    work = args.work or training_run.ROOT / "export" / f"{card.name}-variants"
    work.mkdir(parents=True, exist_ok=True)
    design = place_recognition.towns(work / "design-towns", args.design_towns, 1, args.design_km)
    test = place_recognition.towns(work / "test-towns", args.test_towns, place_recognition.TEST_SEED, args.test_km)
    k = int(card.get("frames", 1))
    out = {
        "date": stamp,
        "card": card.name,
        "machine": training_run.machine(),
        "command": f"python benchmarks/tdfanet_variants.py --card {card.name} --design-towns {args.design_towns} "
        f"--design-km {args.design_km} --test-towns {args.test_towns} --test-km {args.test_km}"
        + training_run.settings_text({k_: v for k_, v in options.items() if SHORT_RECIPE.get(k_) != v})
        + (f" --seeds {' '.join(map(str, args.seeds))}" if args.seeds else "")
        + (f" --score-epoch {args.score_epoch}" if args.score_epoch else ""),
        "recipe": options,
        "score_epoch": score,
        "towns": {
            "design": {
                "seeds": [int(t.name.split("-")[1]) for t in design],
                "route_km": args.design_km,
                "used_for": "training, and the validation recall that judges the choices",
            },
            "test": {
                "seeds": [int(t.name.split("-")[1]) for t in test],
                "route_km": args.test_km,
                "used_for": "the ablation table only",
            },
        },
        "frames_per_window": k,
        "choices": list(CHOICES),
        "ablations": ABLATIONS,
        "variants": {},
    }
    # another recipe is another study: its own results file, rendered beside the short recipe's
    recipe = (
        ""
        if all(options[k] == v for k, v in SHORT_RECIPE.items())
        else f"-{options['epochs']}x{options['tuples_per_epoch']}"
    )
    path = result_path(f"tdfanet-variants-{card.name}{recipe}{'-seeds' if args.seeds else ''}", stamp)
    for seed in args.seeds or [None]:
        for name in args.variants:
            measure_variant(card, name, work, options, test, k, seed, score)
            if args.seeds:  # after every run, so a stopped study keeps what it measured
                rows = {}
                for s_ in args.seeds:
                    for v, row in measured(work, options, s_, score).items():
                        rows.setdefault(v, {})[str(s_)] = row
                out.update(seeds=args.seeds, variants=rows)
                out["summary"], out["ranking"] = seeds_summary(rows)
            else:
                out["variants"] = measured(work, options, None, score)
            write_result(path, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
