"""Des4Pos's three graph signatures, parity cases and comparators, its dynamic int8 text encoder
and its query / cell-encoding benchmark (see radaredge.models.spec).

Graphs (all opset 18, CPU onnxruntime, no custom ops):

``submap_encoder``  points [cells, T, P, 6] float32 (x, y, z normalised to the cell, r, g, b),
                    num_points [cells, T] float32, object_mask [cells, T] bool
                    -> descriptor [cells, D] (L2-normalised), object_features [cells, T, D]
``text_encoder``    input_ids [hints, tokens] int64, attention_mask [hints, tokens] int64
                    (one row per hint sentence, tokenised with the bundle's tokenizer.json)
                    -> descriptor [D] (L2-normalised), hint_features [hints, D]
``fine_stage``      object_features [candidates, T, D], object_mask [candidates, T] bool,
                    hint_features [hints, D], cell_origin [candidates, 2] float64 (m),
                    cell_size [candidates] float64 (m)
                    -> offset [candidates, 2] (cell units from the centre), position [candidates, 2] float64 (m)
"""

from __future__ import annotations

import numpy as np
import torch

from ..cards import ModelCard
from ..comparators import Dense, Descriptor
from ..data.text_city import make_city
from ..errors import ConfigError
from ..runtime.text_tokens import encode_hints, load_tokenizer, split_hints
from .des4pos import Des4Pos, build_des4pos
from .des4pos_config import CellConfig, TextConfig
from .minilm import backbone_dir
from .spec import EvalInputs, GraphSpec, ModelSpec, TrainInputs



def _cell(card) -> CellConfig:
    return card.section("cell", CellConfig)


def _text(card) -> TextConfig:
    return card.section("text", TextConfig)


def _dim(card) -> int:
    return int(card.get("submap.embed_dim", 256))


def tokenizer_path(card: ModelCard):
    t = _text(card)
    return backbone_dir(t.backbone, t.backbone_dir) / "tokenizer.json"


# ----------------------------------------------------------------------------- submap encoder


def submap_cases(card: ModelCard, n: int, seed: int):
    """One cell per case from a synthetic city: its objects in rotating slot layouts (packed,
    shuffled among the slots, a single object), with random garbage in the padding slots."""
    cell = _cell(card)
    city = make_city(cell.max_objects, cell.points_per_object, seed=seed, size=cell.size, stride=cell.stride, poses=0)
    rng = np.random.default_rng(seed)
    kinds = ("packed", "shuffled-slots", "one-object", "garbage-padding")
    cases = []
    for i in range(n):
        kind = kinds[i % len(kinds)]
        c = i % len(city)
        pts, cnt, mask = city.points[c].copy(), city.num_points[c].copy(), city.object_mask[c].copy()
        if kind == "one-object":
            mask[1:] = False
            pts[1:], cnt[1:] = 0, 0
        if kind in ("shuffled-slots", "garbage-padding"):
            perm = rng.permutation(len(mask))
            pts, cnt, mask = pts[perm], cnt[perm], mask[perm]
        if kind == "garbage-padding":
            pts[~mask] = rng.normal(0, 5, pts[~mask].shape)
            cnt[~mask] = rng.integers(1, 9999, int((~mask).sum()))
        cases.append((f"{i:02d}-{kind}-{int(mask.sum())}obj",
                      {"points": pts[None].astype(np.float32), "num_points": cnt[None].astype(np.float32),
                       "object_mask": mask[None]}))
    return cases


def submap_reference(model, feeds, trace=None):
    pts, cnt, mask = (np.asarray(feeds[k]) for k in ("points", "num_points", "object_mask"))
    descs, objs = [], []
    for b in range(len(pts)):
        d, h = model.reference(pts[b][mask[b]], cnt[b][mask[b]])
        full = torch.zeros(mask.shape[1], h.shape[1])
        full[torch.from_numpy(mask[b])] = h
        descs.append(d)
        objs.append(full)
    return {"descriptor": torch.stack(descs), "object_features": torch.stack(objs)}


def submap_export(model, feeds, trace=None):
    d, h = model(*(torch.as_tensor(np.asarray(feeds[k])) if not torch.is_tensor(feeds[k]) else feeds[k]
                   for k in ("points", "num_points", "object_mask")), trace=trace)
    return {"descriptor": d, "object_features": h}


SUBMAP_OUTPUTS = (Descriptor("descriptor", min_cosine=0.9999), Dense("object_features", atol=1e-4, rtol=1e-3))
SUBMAP_GRAPH = GraphSpec(
    name="submap_encoder",
    module=lambda model: model.submap,
    input_names=lambda card: ["points", "num_points", "object_mask"],
    dynamic_axes=lambda card: {k: {0: "cells"} for k in ("points", "num_points", "object_mask")},
    output_names=lambda card: [c.name for c in SUBMAP_OUTPUTS],
    comparators=lambda card: SUBMAP_OUTPUTS,
    make_cases=submap_cases, run_reference=submap_reference, run_export=submap_export,
)


# ----------------------------------------------------------------------------- text encoder


EXTRA_DESCRIPTIONS = (
    "The pose is north of a red car.",
    "The pose is on-top of a gray road. The pose is west of a tall white building with a flat roof.",
    "A lamp.",
    "The pose is east of a small yellow vending machine standing next to the entrance of a large garage.",
)


def descriptions(card: ModelCard, n: int, seed: int) -> list[str]:
    """``n`` distinct descriptions of 1 .. max_hints hints: synthetic-city poses, every fifth one
    of other wordings and lengths (short, long, beyond the city's templates). Distinct, so that a
    case set's retrieval agreement compares different texts."""
    t = _text(card)
    city = make_city(max(16, t.max_hints), 8, seed=seed, poses=2 * max(n, 4), min_hints=1, max_hints=t.max_hints,
                     objects=60)
    poses = iter(dict.fromkeys(str(text) for text in city.pose_text))
    extra = iter(EXTRA_DESCRIPTIONS)
    return [(next(extra, None) if i % 5 == 4 else None) or next(poses) for i in range(n)]


def text_cases(card: ModelCard, n: int, seed: int):
    t = _text(card)
    tok = load_tokenizer(tokenizer_path(card))
    cases = []
    for i, text in enumerate(descriptions(card, n, seed)):
        hints = split_hints(text)[: t.max_hints]
        ids, mask = encode_hints(tok, hints, t.max_tokens, t.max_hints)
        cases.append((f"{i:02d}-{len(hints)}hints-{ids.shape[1]}tok", {"input_ids": ids, "attention_mask": mask}))
    return cases


def text_reference(model, feeds, trace=None):
    ids, mask = np.asarray(feeds["input_ids"]), np.asarray(feeds["attention_mask"])
    d, h = model.reference([ids[i][mask[i] > 0] for i in range(len(ids))])
    return {"descriptor": d, "hint_features": h}


def text_export(model, feeds, trace=None):
    d, h = model(*(torch.as_tensor(np.asarray(feeds[k])) if not torch.is_tensor(feeds[k]) else feeds[k]
                   for k in ("input_ids", "attention_mask")))
    return {"descriptor": d, "hint_features": h}


TEXT_OUTPUTS = (Descriptor("descriptor", min_cosine=0.9999), Dense("hint_features", atol=1e-4, rtol=1e-3))
TEXT_GRAPH = GraphSpec(
    name="text_encoder",
    module=lambda model: model.text,
    input_names=lambda card: ["input_ids", "attention_mask"],
    dynamic_axes=lambda card: {k: {0: "hints", 1: "tokens"} for k in ("input_ids", "attention_mask")},
    output_names=lambda card: [c.name for c in TEXT_OUTPUTS],
    comparators=lambda card: TEXT_OUTPUTS,
    make_cases=text_cases, run_reference=text_reference, run_export=text_export,
)


# ----------------------------------------------------------------------------- fine stage


def fine_cases(card: ModelCard, n: int, seed: int):
    """1-4 candidate cells of 1..T objects, 1..max_hints hints, world origins up to 10 km."""
    cell, t, d = _cell(card), _text(card), _dim(card)
    rng = np.random.default_rng(seed)
    cases = []
    for i in range(n):
        k = 1 + i % 4
        h = 1 + (i * 3) % t.max_hints
        mask = np.zeros((k, cell.max_objects), bool)
        for j in range(k):
            real = rng.choice(cell.max_objects, int(rng.integers(1, cell.max_objects + 1)), replace=False)
            mask[j, real] = True
        objs = (rng.normal(0, 0.3, (k, cell.max_objects, d)) * mask[..., None]).astype(np.float32)
        cases.append((f"{i:02d}-{k}cells-{h}hints", {
            "object_features": objs, "object_mask": mask,
            "hint_features": rng.normal(0, 1, (h, d)).astype(np.float32),
            "cell_origin": rng.uniform(-1e4, 1e4, (k, 2)), "cell_size": np.full(k, cell.size)}))
    return cases


def fine_reference(model, feeds, trace=None):
    objs, mask = np.asarray(feeds["object_features"]), np.asarray(feeds["object_mask"])
    off, pos = model.reference([torch.from_numpy(objs[j][mask[j]]) for j in range(len(objs))],
                               torch.as_tensor(np.asarray(feeds["hint_features"])),
                               np.asarray(feeds["cell_origin"]), np.asarray(feeds["cell_size"]))
    return {"offset": off, "position": pos}


FINE_INPUTS = ["object_features", "object_mask", "hint_features", "cell_origin", "cell_size"]


def fine_export(model, feeds, trace=None):
    off, pos = model(*(torch.as_tensor(np.asarray(feeds[k])) if not torch.is_tensor(feeds[k]) else feeds[k]
                       for k in FINE_INPUTS))
    return {"offset": off, "position": pos}


FINE_OUTPUTS = (Dense("offset", atol=1e-5, rtol=1e-4), Dense("position", unit="m", atol=1e-3, rtol=0.0))
FINE_GRAPH = GraphSpec(
    name="fine_stage",
    module=lambda model: model.fine,
    input_names=lambda card: list(FINE_INPUTS),
    dynamic_axes=lambda card: {"object_features": {0: "candidates"}, "object_mask": {0: "candidates"},
                               "hint_features": {0: "hints"}, "cell_origin": {0: "candidates"},
                               "cell_size": {0: "candidates"}},
    output_names=lambda card: [c.name for c in FINE_OUTPUTS],
    comparators=lambda card: FINE_OUTPUTS,
    make_cases=fine_cases, run_reference=fine_reference, run_export=fine_export,
)


# ----------------------------------------------------------------------------- hooks


def text_int8(card: ModelCard, spec: ModelSpec, paths: dict, options) -> dict:
    """``export --quantize int8``: a dynamically quantised copy of the text encoder
    (text_encoder.int8.onnx: int8 MatMul/Gemm weights, no calibration). The point and fine
    graphs stay fp32."""
    from ..quantize import quantize_dynamic_int8
    path = paths["text_encoder"]
    return {"text_encoder": quantize_dynamic_int8(path, path.with_suffix(".int8.onnx"))}


def bench_tasks(card: ModelCard, model: Des4Pos, paths: dict, options) -> list:
    """What ``bench`` times for Des4Pos:

    * **query**: text encode + FAISS search over a synthetic map's cell descriptors + fine stage
      on the top-k cells, per description (tokenisation included), for the torch export
      formulation, the torch reference (optional), onnxruntime fp32 and onnxruntime with the
      dynamically quantised text encoder (``text_encoder.int8.onnx``, written first when missing);
    * **cells**: cell-encoding throughput of the submap encoder, batches of 8 cells.
    """
    from ..runtime.des4pos import Des4PosBundle, MapIndex
    from ..timing import BenchTask
    if options.openvino:
        raise ConfigError(f"--openvino times the graphs of one-graph models; {card.name}'s bench times "
                          f"queries through its three graphs in onnxruntime")
    top_k, batch = 3, 8
    bundle_dir = paths["text_encoder"].parent
    cell = card.section("cell", CellConfig)
    city = make_city(cell.max_objects, cell.points_per_object, seed=1, size=cell.size, stride=cell.stride, poses=0)
    ort_b = Des4PosBundle(bundle_dir, threads=options.threads)
    int8 = paths["text_encoder"].with_suffix(".int8.onnx")
    if not int8.is_file():
        options.log(f"{int8} missing: quantising the text encoder (dynamic int8)")
        text_int8(card, None, paths, options)
    with torch.no_grad():
        desc, objs = model.submap(torch.from_numpy(city.points), torch.from_numpy(city.num_points),
                                  torch.from_numpy(city.object_mask))
    index = MapIndex(city.ids, city.origins, city.sizes, city.object_mask, desc.numpy(), objs.numpy())
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
            if reference:
                model.fine.reference([torch.from_numpy(index.object_features[j][index.object_mask[j]]) for j in c], h,
                                     index.origins[c], index.sizes[c])
            else:
                model.fine(torch.from_numpy(index.object_features[c]), torch.from_numpy(index.object_mask[c]), h,
                           torch.from_numpy(index.origins[c]), torch.from_numpy(index.sizes[c]))

    query = {}
    if options.reference:
        query["torch reference"] = lambda t: torch_query(t, True)
    query["torch export"] = torch_query
    query["onnxruntime"] = lambda t: ort_b.locate(t, index, top_k)
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
                model.submap(torch.from_numpy(city.points[sl]), torch.from_numpy(city.num_points[sl]),
                             torch.from_numpy(city.object_mask[sl]))

    sess = ort_b.graphs["submap_encoder"].session
    cells = {}
    if options.reference:
        cells["torch reference"] = lambda sl: torch_cells(sl, True)
    cells["torch export"] = torch_cells
    cells["onnxruntime"] = lambda sl: sess.run(None, {"points": city.points[sl], "num_points": city.num_points[sl],
                                                      "object_mask": city.object_mask[sl]})
    return [
        BenchTask("query", f"query latency (tokenise + text encode + FAISS search over {len(index)} cells + fine "
                           f"stage on top-{top_k}), {options.runs} runs over {len(texts)} descriptions",
                  query, texts, options.runs, options.warmup, baseline="torch export",
                  facts={"top_k": top_k, "map_cells": len(index), "descriptions": len(texts)}),
        BenchTask("cells", f"cell encoding, batches of {batch} cells "
                           f"({int(city.object_mask[:batch].sum())} objects in the first)",
                  cells, batches, max(2, min(options.runs, 6)), 1, baseline="torch export",
                  items_per_case=batch, item_unit="cells", facts={"cell_batch": batch}),
    ]


def evaluate_localization(card: ModelCard, onnx, inputs: EvalInputs):
    """Table I (localisation recall) and Table II (cell-retrieval recall) of the export, and of the
    torch reference unless ``--no-reference``, over the cell maps at ``--map``
    (:func:`radaredge.des4pos_eval.evaluate_localization`)."""
    from ..des4pos_eval import evaluate_localization as localize
    inputs.require("localisation recall", ("map",), card.name, ("checkpoint", "reference"))
    return localize(onnx, inputs.map, progress=inputs.progress, model=card.name, reference=inputs.reference,
                    checkpoint=inputs.checkpoint)


def train_text(card: ModelCard, model: Des4Pos, data, inputs: TrainInputs):
    """Des4Pos's training stages (:mod:`radaredge.training.des4pos`) on the cell maps under ``data``."""
    from ..training.des4pos import TextRecipe, train_text as run
    from ..training.run import no_progress
    drive_only = [f"--{k.replace('_', '-')}" for k, v in (inputs.bag or {}).items() if v is not None]
    if inputs.data_format:
        drive_only.append("--format")
    if drive_only:
        raise ConfigError(f"{', '.join(drive_only)} describe radar drives; {card.name} trains on cell maps with "
                          f"described poses (`radaredge make-city`, KITTI360Pose cells/ + poses/)")
    recipe = TextRecipe.from_options(inputs.options or {})
    return run(card, model, data, inputs.output, recipe, inputs.device, inputs.resume, inputs.validation,
               inputs.progress or no_progress, inputs.log or (lambda line: None))


DES4POS_SPEC = ModelSpec(
    build=build_des4pos,
    graphs=(SUBMAP_GRAPH, TEXT_GRAPH, FINE_GRAPH),
    files=lambda card: {"tokenizer.json": tokenizer_path(card)},
    int8=text_int8,
    int8_calibrated=False,
    bench_tasks=bench_tasks,
    evaluate=evaluate_localization,
    train=train_text,
)
