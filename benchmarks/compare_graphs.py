"""Time two exported graphs of one model family against each other on 2 cores, alternating.

For the question "did this change make the graph slower?": both ``.onnx`` files run in
onnxruntime on the same synthetic cases, timed in one loop that alternates them every run
(:func:`radaredge.benchmarking.timing.benchmark`), then each is profiled once more and its kernel time split by
stage (:func:`radaredge.benchmarking.profiling.stage_times_from_profile`, the stages of the card given with
``--model``): the median over several profiled passes, which alternate between the graphs, since
one profiled pass per graph moves stages of identical code by tens of percent. Writes
``benchmarks/results/compare-<label>-<date>.json`` and prints a table.

    python benchmarks/compare_graphs.py --model maffnet-vod --a old.onnx --b export/maffnet-vod.onnx \\
        --label fuser --runs 20
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import onnx
from result_file import save_result

from radaredge.benchmarking.profiling import profile_runs, stage_times_from_profile
from radaredge.benchmarking.timing import benchmark, cpu_name, pin_threads, require_ok
from radaredge.cards import load_card
from radaredge.models import model_spec
from radaredge.runtime.session import make_session, run_session


def compare(
    model: str,
    a: Path,
    b: Path,
    runs: int,
    threads: int,
    cases_n: int = 4,
    keep: list[int] | None = None,
    rounds: int = 5,
) -> dict:
    """Alternating p50/p90 of graphs ``a`` and ``b`` over the card's first ``cases_n`` synthetic
    cases (only the indices in ``keep`` when given), and per stage the median over ``rounds``
    profiled passes (alternating a and b) of the mean kernel ms per case."""
    card = load_card(model)
    spec = model_spec(card).graph()
    named = spec.make_cases(card, cases_n, 1)
    named = [named[i] for i in keep] if keep else named
    cases = [feeds for _, feeds in named]
    sessions = {str(p): make_session(p, threads=threads) for p in (a, b)}
    backends = {name: (lambda feeds, s=s: run_session(s, feeds)) for name, s in sessions.items()}
    results = {r.backend: r for r in require_ok(benchmark(backends, cases, runs))}
    graphs = {str(p): onnx.load(str(p), load_external_data=False) for p in (a, b)}
    passes: dict[str, list[dict]] = {str(p): [] for p in (a, b)}
    for _ in range(rounds if spec.onnx_stages else 0):  # a card without stages: whole-graph times only
        for path in (a, b):
            events = profile_runs(path, cases, threads, len(cases))
            passes[str(path)].append(
                stage_times_from_profile(
                    events, graphs[str(path)], list(spec.onnx_stages), spec.onnx_post_outputs, len(cases)
                )
            )
    out = {
        "model": model,
        "cases": [name for name, _ in named],
        "points": [int(len(next(iter(f.values())))) for f in cases],
        "runs": runs,
        "threads": threads,
        "profile_rounds": rounds,
        "graphs": [],
    }
    for path in (a, b):
        rows = passes[str(path)]
        stages = {k: statistics.median(r.get(k, 0.0) for r in rows) for k in dict.fromkeys(k for r in rows for k in r)}
        r = results[str(path)]
        out["graphs"].append({"onnx": str(path), "p50_ms": r.p50_ms, "p90_ms": r.p90_ms, "stage_ms": stages})
    return out


def table(result: dict) -> str:
    names = list(dict.fromkeys(k for g in result["graphs"] for k in g["stage_ms"]))
    lines = [
        "| graph | p50 ms | p90 ms |" + "".join(f" {n} |" for n in names),
        "|---|---:|---:|" + "---:|" * len(names),
    ]
    for g in result["graphs"]:
        stages = "".join(f" {g['stage_ms'].get(k, 0.0):.1f} |" for k in names)
        lines.append(f"| {Path(g['onnx']).name} | {g['p50_ms']:.1f} | {g['p90_ms']:.1f} |{stages}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="card whose cases and stages to use")
    ap.add_argument("--a", type=Path, required=True)
    ap.add_argument("--b", type=Path, required=True)
    ap.add_argument("--label", required=True, help="names the JSON file")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cases", type=int, default=4, help="synthetic cases of the card (VoD's fifth: a 5-frame cloud)")
    ap.add_argument("--case", type=int, action="append", help="time only this case index (repeatable)")
    ap.add_argument("--rounds", type=int, default=5, help="profiled passes per graph for the stage split")
    args = ap.parse_args(argv)
    cores = pin_threads(args.threads)
    result = compare(args.model, args.a, args.b, args.runs, args.threads, args.cases, args.case, args.rounds)
    result.update(cpu=cpu_name(), cores=cores)
    print(table(result))
    save_result(f"compare-{args.label}", result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
