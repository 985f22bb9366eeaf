"""Train Des4Pos on synthetic text cities and localise descriptions in cities it never saw.

The same steps as the commands in docs/models/des4pos.md ("Training"), through the library
verbs, with their times:

1. training cities: ``radaredge make-city --out <work>/cities --cities C --seed 1 --poses P``
   (one scene each; the last by name validates);
2. ``radaredge train --model des4pos --data <work>/cities`` with the recipe's defaults unless
   ``--set`` says otherwise (object, prior, coarse, hints and fine stages);
3. ``radaredge export --checkpoint best.pth`` and ``parity-check`` of the bundle on the trained
   weights (and of the seeded bundle);
4. held-out cities ``radaredge make-city --out <work>/heldout --cities H --seed 100``: one
   database of all their cells, every described pose a query; ``radaredge eval`` of the seeded
   and the trained bundle, onnxruntime and the torch reference side by side (Table I, with the fine
   stage and with the retrieved cells' centres alone, each with 95 % bootstrap intervals over the
   queries, and Table II).

Writes benchmarks/results/<card>[-<tag>]-training-<date>.json (rendered into benchmarks/README.md
by benchmarks/render.py) and keeps the run directory and exports under --work (default
export/<card>-training; its cities are reused when they exist).

    python benchmarks/des4pos_training.py          # 12 cities x 1000 described poses, 2 held out
    # the fine stage alone, again, on a finished run's weights, with a card whose fine stage differs:
    python benchmarks/des4pos_training.py --card my-des4pos.yaml --tag fine-encoder --work export/fine-encoder \
        --cities-from export/des4pos-training --set stages=fine \
        --set coarse_weights=export/des4pos-training/run/best.pth
    # score a finished run again (export, parity, held-out cities) without training it again:
    python benchmarks/des4pos_training.py --run export/des4pos-training/run
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import training_run
from result_file import save_result

import radaredge
from radaredge.data.text_city import write_cities


def _percent(value):
    return [100 * v for v in value] if isinstance(value, tuple) else 100 * value


def _tables(report) -> dict:
    """Table I (``localization``: the fine stage; ``localization_centre``: the retrieved cells'
    centres; ``..._interval``: their 95 % bootstrap intervals, [low, high]) and Table II of every
    backend of a localisation report, in % (JSON keys as strings)."""
    return {
        name: {
            **{
                key: {str(k): {f"{t:g}": _percent(r) for t, r in by_t.items()} for k, by_t in table.items()}
                for key, table in res.items()
                if key != "retrieval"
            },
            "retrieval": {str(k): 100 * r for k, r in res["retrieval"].items()},
        }
        for name, res in report.results.items()
    }


def _parity(report) -> dict:
    out = {"passed": bool(report), "graphs": {}}
    for name, graph in report.to_dict()["graphs"].items():
        out["graphs"][name] = {
            k: {f: v.get(f) for f in ("passed", "max_abs", "min_cosine", "retrieval_top1")}
            for k, v in graph["summary"].items()
        }
    return out


def main(argv=None) -> int:
    ap = training_run.parser("python benchmarks/des4pos_training.py", __doc__, "des4pos")
    ap.add_argument("--cities", type=int, default=12)
    ap.add_argument("--poses", type=int, default=1000, help="described poses per city")
    ap.add_argument("--heldout", type=int, default=2, help="held-out cities (one database)")
    ap.add_argument("--heldout-poses", type=int, default=200, help="described poses per held-out city (the queries)")
    ap.add_argument("--tag", default="", help="results file <card>-<tag>-training-<date>.json (a variant run)")
    ap.add_argument(
        "--run",
        type=Path,
        metavar="DIR",
        help="score this finished run of the same cities and --set options (its train-log.json is the "
        "training record) instead of training",
    )
    ap.add_argument(
        "--cities-from",
        type=Path,
        metavar="WORK",
        help="copy the training and held-out cities of an earlier run's work directory",
    )
    args = ap.parse_args(argv)
    card, work, options, stamp = training_run.start(args)
    cities, held, run, graphs = work / "cities", work / "heldout", work / "run", work / "graphs"
    if args.cities_from is not None:
        for name in ("cities", "heldout"):
            if not (work / name).exists():
                shutil.copytree(
                    args.cities_from / name, work / name, ignore=shutil.ignore_patterns("*.des4pos-*")
                )  # not the cell caches
    t0 = time.perf_counter()
    if not cities.exists():
        write_cities(cities, card, args.cities, seed=1, poses=args.poses)
    if not held.exists():
        write_cities(held, card, args.heldout, seed=100, poses=args.heldout_poses)
    t_data = time.perf_counter() - t0
    print(
        f"data: {args.cities} cities x {args.poses} described poses, {args.heldout} held out ({t_data:.0f} s)",
        flush=True,
    )
    if args.run is None:
        t0 = time.perf_counter()
        train = radaredge.train(
            card, cities, run, options=options, overwrite=True, log=lambda line: print(line, flush=True)
        ).to_dict()
        t_train = time.perf_counter() - t0
    else:
        run, train = args.run, json.loads((args.run / "train-log.json").read_text())
        t_train = train["seconds"]
        differ = {k: v for k, v in options.items() if train["options"].get(k) != v}
        if differ or Path(train["data"]["root"]).resolve() != cities.resolve():
            raise SystemExit(
                f"{args.run} was trained on {train['data']['root']} with {train['options']}; "
                f"this command gives {cities} and --set {differ or options}"
            )
    best = run / "best.pth"
    trained, seeded = graphs / "trained", graphs / "seeded"
    radaredge.export(card, trained, checkpoint=best)
    radaredge.export(card, seeded)
    parity = {"trained": radaredge.parity(card, trained, checkpoint=best), "seeded": radaredge.parity(card, seeded)}
    for name, p in parity.items():
        print(f"parity, {name} weights: {'PASSED' if p else 'FAILED'}", flush=True)
    t0 = time.perf_counter()
    evals = {
        "seeded": radaredge.evaluate(card, seeded, map_path=held),
        "trained": radaredge.evaluate(card, trained, map_path=held, checkpoint=best),
    }
    t_eval = time.perf_counter() - t0
    for name, r in evals.items():
        print(f"held-out cities, {name}:", flush=True)
        for line in r.lines()[1:]:
            print("  " + line, flush=True)
    first = next(iter(evals.values()))
    out = {
        "date": stamp,
        "card": card.name,
        "tag": args.tag,
        "machine": training_run.machine(),
        "command": f"radaredge make-city --out cities --cities {args.cities} --seed 1 --poses {args.poses}; "
        f"radaredge train --model {card.name} --data cities" + training_run.settings_text(options),
        "eval_command": f"radaredge make-city --out heldout --cities {args.heldout} --seed 100 "
        f"--poses {args.heldout_poses}; "
        f"radaredge eval --model {card.name} --onnx <bundle> --map heldout",
        "data_seconds": round(t_data, 1),
        "train_seconds": round(t_train, 1),
        "eval_seconds": round(t_eval, 1),
        "train": train,
        "parity": {name: _parity(p) for name, p in parity.items()},
        "heldout": {
            "seed": 100,
            "maps": first.maps,
            "cells": first.cells,
            "queries": first.queries,
            **{name: _tables(r) for name, r in evals.items()},
        },
    }
    save_result(f"{card.name}{'-' + args.tag if args.tag else ''}-training", out, keep_same_day=not args.tag)
    return 0


if __name__ == "__main__":
    sys.exit(main())
