"""Train TDFANet on synthetic towns and measure it on a town it never saw, fp32 and int8.

The same steps as the commands in docs/models/tdfanet.md ("Training"), through the library
verbs, with their times:

1. training towns: ``radaredge make-benchmark --out <tmp>/towns --seed 1 --towns T --drives D
   --frames F`` (towns of seeds 1.., several drives each, different days);
2. ``radaredge train --model <card> --data <tmp>/towns`` with the recipe's defaults unless
   ``--set`` says otherwise (the paper's values; validation by drive);
3. ``radaredge export --checkpoint best.pth --quantize int8``, then ``parity-check`` of the fp32
   graph and ``parity-check --quantized`` of the int8 graph on the trained weights;
4. the held-out town ``radaredge make-benchmark --seed 0`` (the benchmark town, never trained on):
   ``radaredge eval`` of the seeded network, the trained fp32 graph and the trained int8 graph.

Writes benchmarks/results/<card>-training-<date>.json (rendered into benchmarks/README.md by
benchmarks/render.py) and keeps the run directory and exports under --work (default
export/<card>-training).

    python benchmarks/tdfanet_training.py                       # tdfanet-edge, 6 towns x 3 drives x 50 scans
"""

from __future__ import annotations

import sys
import time

import training_run
from result_file import save_result

import radaredge
from radaredge.data.pr_benchmark import make_pr_benchmark, make_pr_towns


def _recall(report) -> dict:
    return {
        "recall": {str(n): r for n, r in report.recall("onnxruntime").items()},
        "evaluated": report.evaluated,
        "skipped": report.skipped,
        "top1_agreement_with_reference": report.agreement,
    }


def main(argv=None) -> int:
    ap = training_run.parser("python benchmarks/tdfanet_training.py", __doc__, "tdfanet-edge")
    ap.add_argument("--towns", type=int, default=6)
    ap.add_argument("--drives", type=int, default=3)
    ap.add_argument("--frames", type=int, default=50)
    args = ap.parse_args(argv)
    card, work, options, stamp = training_run.start(args)
    towns, held, run, graphs = work / "towns", work / "heldout-town", work / "run", work / "graphs"
    t0 = time.perf_counter()
    if not towns.exists():
        make_pr_towns(towns, args.towns, 1, lambda path, seed: make_pr_benchmark(path, args.drives, args.frames, seed))
    if not held.exists():
        make_pr_benchmark(held, seed=0)
    t_data = time.perf_counter() - t0
    print(f"data: {args.towns} towns x {args.drives} drives x {args.frames} scans ({t_data:.0f} s)", flush=True)
    t0 = time.perf_counter()
    report = radaredge.train(
        card, towns, run, options=options, overwrite=True, log=lambda line: print(line, flush=True)
    )
    t_train = time.perf_counter() - t0
    best = run / "best.pth"
    fp32 = graphs / f"{card.name}.onnx"
    exported = radaredge.export(card, fp32, checkpoint=best, quantize="int8")
    int8 = exported.int8["tdfanet"]
    parity = radaredge.parity(card, fp32, checkpoint=best)
    parity_int8 = radaredge.parity(card, int8, checkpoint=best, quantized=True)
    seeded_onnx = graphs / f"{card.name}-seeded.onnx"
    radaredge.export(card, seeded_onnx)
    db, q = held / "database", held / "queries"
    evals = {
        "seeded_fp32": radaredge.evaluate(card, seeded_onnx, db, q),
        "trained_fp32": radaredge.evaluate(card, fp32, db, q, checkpoint=best),
        "trained_int8": radaredge.evaluate(card, int8, db, q, checkpoint=best, reference=False),
    }
    for name, r in evals.items():
        print(f"held-out town, {name}: R@1/5/10 " + " / ".join(f"{v:.1f}" for v in r.recall("onnxruntime").values()))
    out = {
        "date": stamp,
        "card": card.name,
        "machine": training_run.machine(),
        "command": f"radaredge make-benchmark --out towns --seed 1 --towns {args.towns} --drives {args.drives} "
        f"--frames {args.frames}; radaredge train --model {card.name} --data towns"
        + training_run.settings_text(options),
        "data_seconds": round(t_data, 1),
        "train_seconds": round(t_train, 1),
        "train": report.to_dict(),
        "parity_fp32": {"passed": bool(parity), "summary": parity.to_dict()["graphs"]["tdfanet"]["summary"]},
        "parity_int8": {"passed": bool(parity_int8), "summary": parity_int8.to_dict()["graphs"]["tdfanet"]["summary"]},
        "heldout_town": {
            "seed": 0,
            **{k: _recall(v) for k, v in evals.items()},
            "int8_top1_agreement_with_fp32": _agreement(evals["trained_fp32"], evals["trained_int8"]),
        },
    }
    save_result(f"{card.name}-training", out, keep_same_day=True)
    return 0


def _agreement(a, b) -> dict:
    """Top-1 agreement of two eval reports' onnxruntime retrievals: same window, and within the radius."""
    from radaredge.eval.places import top1_agreement, top1_place_agreement

    ta, tb = a.results["onnxruntime"]["top1"], b.results["onnxruntime"]["top1"]
    return {
        "same_window": top1_agreement(ta, tb),
        "within_radius": top1_place_agreement(ta, tb, a.database.positions, a.radius),
    }


if __name__ == "__main__":
    sys.exit(main())
