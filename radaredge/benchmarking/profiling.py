"""Where onnxruntime spends its time: profiled runs, top ops, per-stage split, peak memory.

Per-stage time: onnxruntime's node profile attributed to the model's pipeline stages.

onnxruntime's profiler times each node of the *optimised* graph. This module maps those nodes
back to the stages a graph spec names (``GraphSpec.onnx_stages``, e.g. MAFF-Net's VFE+SPA, CFA,
CAF, backbone+head, NMS):

1. a node traced inside a stage's module (the exporter's ``pkg.torch.onnx.name_scopes``
   metadata, e.g. ``model.backbone_2d.blocks.2``) belongs to that stage;
2. a node outside every module that (transitively) consumes one of the spec's ``post`` graph
   outputs (the dense head's per-anchor outputs) belongs to the last stage (post-processing);
3. any other node outside the modules (index math, scatters, box decoding) takes the latest
   stage among its ancestors, or, when it has none (preprocessing of the raw points), the
   earliest stage among its consumers.

onnxruntime renames some nodes when it optimises (``X/GatherSliceToSplitFusion``,
``relu_6_nchwc``); those map back to the node ``X`` or to the node producing ``relu_6``. The
layout reorders it inserts for its NCHWc convolutions map to no node and are reported as their
own row, so the split never hides time. Nodes inside a Loop body are not counted separately:
the Loop node's time already includes them.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnx

from ..node_scopes import fused_from, module_names
from ..runtime.session import make_session, run_session

REORDER = "layout reorders (onnxruntime)"
UNMAPPED = "other (unmapped)"


def _module_stage(names: list[str], stages: list[tuple[str, tuple[str, ...]]]) -> str | None:
    """The stage whose module prefix the node's outermost module name starts with, if any."""
    for name in names:
        for stage, prefixes in stages:
            if any(name == p or name.startswith(p + ".") for p in prefixes):
                return stage
    return None


def node_stages(
    model: onnx.ModelProto, stages: list[tuple[str, tuple[str, ...]]], post_outputs: tuple[str, ...] = ()
) -> dict[str, str]:
    """Top-level node name -> stage name, by the three rules of the module docstring."""
    order = [s for s, _ in stages]
    rank = {s: i for i, s in enumerate(order)}
    nodes = list(model.graph.node)  # topologically sorted (ONNX requires it)
    producer = {out: n.name for n in nodes for out in n.output}
    stage: dict[str, str | None] = {n.name: _module_stage(module_names(n), stages) for n in nodes}

    def parents(n):
        return [producer[i] for i in n.input if i in producer]

    post = set()  # nodes downstream of a post graph output
    post_tensors = set(post_outputs)
    for n in nodes:
        if stage[n.name] is None and (post_tensors & set(n.input) or any(p in post for p in parents(n))):
            post.add(n.name)
    for n in nodes:  # rule 2, then rule 3 (ancestors), in topological order
        if stage[n.name] is not None:
            continue
        if n.name in post:
            stage[n.name] = order[-1]
            continue
        ancestors = [stage[p] for p in parents(n) if stage[p] is not None]
        if ancestors:
            stage[n.name] = max(ancestors, key=rank.__getitem__)
    consumers = defaultdict(list)
    for n in nodes:
        for p in parents(n):
            consumers[p].append(n.name)
    for n in reversed(nodes):  # rule 3 (consumers), in reverse topological order
        if stage[n.name] is None:
            below = [stage[c] for c in consumers[n.name] if stage[c] is not None]
            stage[n.name] = min(below, key=rank.__getitem__) if below else order[0]
    return stage


def _resolve(event_node: str, stage: dict[str, str], by_output: dict[str, str]) -> str:
    """Stage of one profiled (possibly renamed) node."""
    if event_node in stage:
        return stage[event_node]
    if event_node.startswith(("ReorderInput", "ReorderOutput")):
        return REORDER
    base = fused_from(event_node)
    if base in stage:
        return stage[base]
    for suffix in ("_nchwc",):
        if base.endswith(suffix):
            base = base[: -len(suffix)]
    for candidate in (base, "node_" + base):
        if candidate in stage:
            return stage[candidate]
    if base in by_output:
        return stage[by_output[base]]
    return UNMAPPED


def _subgraph_node_names(model: onnx.ModelProto) -> set[str]:
    names = set()

    def walk(graph):
        for n in graph.node:
            for attr in n.attribute:
                for g in [attr.g] if attr.type == onnx.AttributeProto.GRAPH else list(attr.graphs):
                    names.update(m.name for m in g.node)
                    walk(g)

    walk(model.graph)
    return names


def stage_times_from_profile(
    events: list[dict],
    model: onnx.ModelProto,
    stages: list[tuple[str, tuple[str, ...]]],
    post_outputs: tuple[str, ...],
    runs: int,
) -> dict[str, float]:
    """Mean milliseconds per stage and run, from the onnxruntime profile events of ``runs`` runs
    of ``model`` (:func:`profile_runs`).

    Rows are the spec's stages in order, then the reorder and unmapped rows when non-zero.
    """
    stage = node_stages(model, stages, post_outputs)
    by_output = {out: n.name for n in model.graph.node for out in n.output}
    inner = _subgraph_node_names(model) - set(stage)
    total: dict[str, float] = {s: 0.0 for s, _ in stages}
    for e in events:
        name = e.get("name", "")
        if e.get("cat") != "Node" or not name.endswith("_kernel_time"):
            continue
        node = name[: -len("_kernel_time")]
        if node in inner:
            continue
        key = _resolve(node, stage, by_output)
        total[key] = total.get(key, 0.0) + e.get("dur", 0) / 1e3
    return {k: v / runs for k, v in total.items() if v > 0 or k in dict(stages)}


def profile_runs(onnx_path, cases: list[dict], threads: int, runs: int) -> list[dict]:
    """Run ``onnx_path`` ``runs`` times over ``cases`` in a profiled onnxruntime session of its
    own; return onnxruntime's profile events. The JSON file onnxruntime writes them to (20-30 MB
    for a MAFF-Net bench) is read and deleted, so repeated benches do not fill the temp directory."""
    session = make_session(onnx_path, threads=threads, profile=True)
    for i in range(runs):
        run_session(session, cases[i % len(cases)])
    path = Path(session.end_profiling())
    try:
        return json.loads(path.read_text())
    finally:
        path.unlink(missing_ok=True)


_RSS_CHILD = """
import resource, sys
import numpy as np
from radaredge.runtime.session import make_session, run_session
session = make_session(sys.argv[1], threads=int(sys.argv[3]))
cases = np.load(sys.argv[2])
names = sorted({k.split("/", 1)[1] for k in cases.files})
count = len({k.split("/", 1)[0] for k in cases.files})
for i in range(count):
    run_session(session, {n: cases[f"{i}/{n}"] for n in names})
try:      # this process's own high-water mark; ru_maxrss can carry the parent's size across fork + exec
    print(next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:")))
except OSError:
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def onnxruntime_peak_rss_mb(onnx_path, cases: list[dict], threads: int) -> float:
    """Peak resident memory (MiB) of a fresh process that only loads ``onnx_path`` in onnxruntime
    (numpy + onnxruntime, no torch) and runs every case once: what an embedded app would need."""
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "cases.npz"
        np.savez(npz, **{f"{i}/{k}": v for i, feeds in enumerate(cases) for k, v in feeds.items()})
        done = subprocess.run(
            [sys.executable, "-c", _RSS_CHILD, str(onnx_path), str(npz), str(threads)],
            capture_output=True,
            text=True,
            check=True,
        )
    return int(done.stdout.split()[-1]) / 1024.0  # VmHWM and Linux ru_maxrss are in KiB


def node_kernel_ms(events: list[dict], runs: int = 1) -> dict[tuple[str, str], float]:
    """(node name, op type) -> kernel ms per run, from the onnxruntime profile events of ``runs``
    runs (:func:`profile_runs`)."""
    tot: dict[tuple[str, str], float] = {}
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            key = (e["name"][: -len("_kernel_time")], e.get("args", {}).get("op_name", "?"))
            tot[key] = tot.get(key, 0.0) + e.get("dur", 0) / 1e3 / runs
    return tot


def top_nodes(events: list[dict], k: int = 5, runs: int = 1) -> list[tuple[str, str, float]]:
    """The ``k`` nodes with the most kernel time (:func:`node_kernel_ms`): (node name, op type, ms
    per run), the heaviest first. The layer that dominates a graph is where an int8 copy gains or
    loses its speed."""
    ranked = sorted(node_kernel_ms(events, runs).items(), key=lambda kv: -kv[1])[:k]
    return [(node, op, ms) for (node, op), ms in ranked]


def top_ops(events: list[dict], k: int = 10, runs: int = 1) -> list[tuple[str, float]]:
    """Top ``k`` op types by kernel time (:func:`node_kernel_ms`), in ms per run."""
    tot: dict[str, float] = {}
    for (_, op), ms in node_kernel_ms(events, runs).items():
        tot[op] = tot.get(op, 0.0) + ms
    return sorted(tot.items(), key=lambda kv: -kv[1])[:k]
