"""Des4Pos benchmark on THREADS cores: query latency and cell-encoding throughput.

* **query**: text encode + FAISS search over the map's cell descriptors + fine stage on the
  top-k cells, per description (tokenisation included), for the torch export formulation, the
  torch reference (optional), onnxruntime fp32, and onnxruntime with the dynamically quantised
  text encoder (when ``text_encoder.int8.onnx`` is in the bundle).
* **cells**: cell-encoding throughput (cells/s) of the submap encoder, batches of 8 cells.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import click
import torch

from ..bench import benchmark, cpu_name, pin_threads, results_table
from ..cards import ModelCard
from ..data.text_city import make_city
from ..locate import Des4PosBundle, MapIndex


def bench_cmd(card: ModelCard, bundle_dir, checkpoint, threads: int, runs: int, warmup: int, no_reference: bool,
              as_json: bool, progress, top_k: int = 3, batch: int = 8) -> None:
    from ..bundle import quantize_dynamic_int8
    from ..export import build_model, export_bundle
    from .des4pos_spec import descriptions
    cores = pin_threads(threads)
    torch.set_num_threads(threads)
    bundle_dir = Path(bundle_dir or f"export/{card.name}")
    net = build_model(card, checkpoint)
    if not (bundle_dir / "bundle.json").is_file():
        click.echo(f"{bundle_dir} missing: exporting it first", err=True)
        export_bundle(card, bundle_dir, net)
    int8 = bundle_dir / "text_encoder.int8.onnx"
    if not int8.is_file():
        click.echo(f"{int8} missing: quantising the text encoder (dynamic int8)", err=True)
        quantize_dynamic_int8(bundle_dir / "text_encoder.onnx", int8)
    cell = card.get("cell", {})
    city = make_city(int(cell.get("max_objects", 28)), int(cell.get("points_per_object", 256)), seed=1,
                     size=float(cell.get("size", 30.0)), stride=float(cell.get("stride", 10.0)), poses=0)
    ort_b = Des4PosBundle(bundle_dir, threads=threads)
    ort_q = Des4PosBundle(bundle_dir, threads=threads, text_encoder=int8)
    with torch.no_grad():
        desc, objs = net.submap(torch.from_numpy(city.points), torch.from_numpy(city.num_points),
                                torch.from_numpy(city.object_mask))
    index = MapIndex(city.ids, city.origins, city.sizes, city.object_mask, desc.numpy(), objs.numpy())
    texts = descriptions(card, 8, 3)

    def torch_query(text, reference=False):
        with torch.no_grad():
            hints, ids, mask = ort_b.tokenize(text)
            if reference:
                d, h = net.text.reference([ids[i][mask[i] > 0] for i in range(len(ids))])
            else:
                d, h = net.text(torch.from_numpy(ids), torch.from_numpy(mask))
            _, cells = index.search(d.numpy()[None], top_k)
            c = cells[0]
            if reference:
                net.fine.reference([torch.from_numpy(index.object_features[j][index.object_mask[j]]) for j in c], h,
                                   index.origins[c], index.sizes[c])
            else:
                net.fine(torch.from_numpy(index.object_features[c]), torch.from_numpy(index.object_mask[c]), h,
                         torch.from_numpy(index.origins[c]), torch.from_numpy(index.sizes[c]))

    backends = {}
    if not no_reference:
        backends["torch reference"] = lambda t: torch_query(t, True)
    backends["torch export"] = torch_query
    backends["onnxruntime"] = lambda t: ort_b.locate(t, index, top_k)
    backends["onnxruntime int8 text"] = lambda t: ort_q.locate(t, index, top_k)
    query = benchmark(backends, texts, runs, warmup, progress=progress("query"))

    # cell encoding: batches of `batch` cells (the reference one cell at a time, real objects only)
    batches = [slice(s, s + batch) for s in range(0, len(city) - batch + 1, batch)][:4]

    def torch_cells(sl, reference=False):
        with torch.no_grad():
            if reference:
                for c in range(sl.start, sl.stop):
                    m = city.object_mask[c]
                    net.submap.reference(city.points[c][m], city.num_points[c][m])
            else:
                net.submap(torch.from_numpy(city.points[sl]), torch.from_numpy(city.num_points[sl]),
                           torch.from_numpy(city.object_mask[sl]))

    sess = ort_b.graphs["submap_encoder"].session
    cell_backends = {}
    if not no_reference:
        cell_backends["torch reference"] = lambda sl: torch_cells(sl, True)
    cell_backends["torch export"] = torch_cells
    cell_backends["onnxruntime"] = lambda sl: sess.run(None, {"points": city.points[sl], "num_points": city.num_points[sl],
                                                             "object_mask": city.object_mask[sl]})
    cell_runs = max(2, min(runs, 6))
    cells = benchmark(cell_backends, batches, cell_runs, 1, progress=progress("cells"))
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    click.echo(f"{card.name} on {threads} thread(s), cores {cores}, {cpu_name()}, {stamp}")
    click.echo(f"query latency (tokenise + text encode + FAISS search over {len(index)} cells + fine stage on "
               f"top-{top_k}), {runs} runs over {len(texts)} descriptions:")
    click.echo(results_table(query, "torch export"))
    click.echo(f"cell encoding, batches of {batch} cells ({int(city.object_mask[:batch].sum())} objects in the first), "
               f"{cell_runs} runs:")
    click.echo("| backend | p50 ms / batch | cells/s |")
    click.echo("|---|---:|---:|")
    for r in cells:
        click.echo(f"| {r.backend} | {r.p50_ms:.1f} | {batch * 1e3 / r.p50_ms:.1f} |")
    if as_json:
        from ..bench import as_dicts, write_results_json
        path = write_results_json(card.name, {
            "model": card.name, "threads": threads, "cores": cores, "cpu": cpu_name(), "date": stamp,
            "query": as_dicts(query), "top_k": top_k, "map_cells": len(index), "cell_batches": as_dicts(cells),
            "cell_batch": batch, "cells_per_s": {r.backend: batch * 1e3 / r.p50_ms for r in cells}})
        click.echo(f"wrote {path}")
