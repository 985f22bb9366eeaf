"""What ``bench`` times for Des4Pos instead of each graph on its own: queries through its three
graphs and the submap encoder's cell-encoding throughput (the spec's ``bench_tasks``)."""

from __future__ import annotations

import torch

from ...cards import ModelCard
from ...cards.des4pos import CellConfig
from ...data.text_city import make_city
from ...errors import ConfigError
from ...runtime.des4pos import Des4PosBundle, MapIndex, object_summaries
from ..spec import BenchTask
from .descriptions import descriptions


def des4pos_tasks(card: ModelCard, model, paths: dict, options) -> list[BenchTask]:
    """What ``bench`` times for Des4Pos:

    * **query**: text encode + FAISS search over a synthetic map's cell descriptors + fine stage
      on the top-k cells, per description (tokenisation included), for the torch export
      formulation, the torch reference (optional), onnxruntime fp32 and, when the export has
      one (``options.int8``), onnxruntime with the int8 copy of the text encoder;
    * **cells**: cell-encoding throughput of the submap encoder, batches of 8 cells.
    """
    if options.openvino:
        raise ConfigError(
            f"--openvino times the graphs of one-graph models; {card.name}'s bench times "
            f"queries through its three graphs in onnxruntime"
        )
    top_k, batch = 3, 8
    bundle_dir = paths["text_encoder"].parent
    cell = card.section("cell", CellConfig)
    city = make_city(cell.max_objects, cell.points_per_object, seed=1, size=cell.size, stride=cell.stride, poses=0)
    ort_b = Des4PosBundle(bundle_dir, threads=options.threads)
    int8 = options.int8.get("text_encoder")
    with torch.no_grad():
        desc, objs = model.submap(
            torch.from_numpy(city.points), torch.from_numpy(city.num_points), torch.from_numpy(city.object_mask)
        )
    centres, colours = object_summaries(city.points)
    index = MapIndex(
        city.ids,
        city.origins,
        city.sizes,
        city.object_mask,
        desc.numpy(),
        objs.numpy(),
        object_centres=centres,
        object_colours=colours,
        num_points=city.num_points.astype("float32"),
    )
    summaries = model.fine.needs_summaries
    texts = descriptions(card, 8, 3)

    def torch_query(text, reference=False):
        with torch.no_grad():
            hints, ids, mask = ort_b.tokenize(text)
            if reference:
                d, h = model.text.reference([ids[i][mask[i] > 0] for i in range(len(ids))])
            else:
                d, h = model.text(torch.from_numpy(ids), torch.from_numpy(mask))
            _, cells = index.search(d.numpy()[None], top_k)
            c = cells[0]
            parts = (index.object_centres, index.object_colours, index.num_points)
            if reference:
                real = [index.object_mask[j] for j in c]
                model.fine.reference(
                    [torch.from_numpy(index.object_features[j][m]) for j, m in zip(c, real)],
                    h,
                    index.origins[c],
                    index.sizes[c],
                    [tuple(torch.from_numpy(p[j][m]) for p in parts) for j, m in zip(c, real)] if summaries else None,
                )
            else:
                model.fine(
                    torch.from_numpy(index.object_features[c]),
                    torch.from_numpy(index.object_mask[c]),
                    h,
                    torch.from_numpy(index.origins[c]),
                    torch.from_numpy(index.sizes[c]),
                    *((torch.from_numpy(p[c]) for p in parts) if summaries else ()),
                )

    query = {}
    if options.reference:
        query["torch reference"] = lambda t: torch_query(t, True)
    query["torch export"] = torch_query
    query["onnxruntime"] = lambda t: ort_b.locate(t, index, top_k)
    if int8 is not None:
        ort_q = Des4PosBundle(bundle_dir, threads=options.threads, text_encoder=int8)
        query["onnxruntime int8 text"] = lambda t: ort_q.locate(t, index, top_k)

    # cell encoding: batches of `batch` cells (the reference one cell at a time, real objects only)
    batches = [slice(s, s + batch) for s in range(0, len(city) - batch + 1, batch)][:4]

    def torch_cells(sl, reference=False):
        with torch.no_grad():
            if reference:
                for c in range(sl.start, sl.stop):
                    m = city.object_mask[c]
                    model.submap.reference(city.points[c][m], city.num_points[c][m])
            else:
                model.submap(
                    torch.from_numpy(city.points[sl]),
                    torch.from_numpy(city.num_points[sl]),
                    torch.from_numpy(city.object_mask[sl]),
                )

    sess = ort_b.graphs["submap_encoder"].session
    cells = {}
    if options.reference:
        cells["torch reference"] = lambda sl: torch_cells(sl, True)
    cells["torch export"] = torch_cells
    cells["onnxruntime"] = lambda sl: sess.run(
        None, {"points": city.points[sl], "num_points": city.num_points[sl], "object_mask": city.object_mask[sl]}
    )
    return [
        BenchTask(
            "query",
            f"query latency (tokenise + text encode + FAISS search over {len(index)} cells + fine "
            f"stage on top-{top_k}), {options.runs} runs over {len(texts)} descriptions",
            query,
            texts,
            options.runs,
            options.warmup,
            baseline="torch export",
            facts={"top_k": top_k, "map_cells": len(index), "descriptions": len(texts)},
        ),
        BenchTask(
            "cells",
            f"cell encoding, batches of {batch} cells ({int(city.object_mask[:batch].sum())} objects in the first)",
            cells,
            batches,
            max(2, min(options.runs, 6)),
            1,
            baseline="torch export",
            items_per_case=batch,
            item_unit="cells",
            facts={"cell_batch": batch},
        ),
    ]
