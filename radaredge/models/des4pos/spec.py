"""Des4Pos's three graph signatures and parity cases (see radaredge.models.spec).

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
                    (card ``fine.objects: encoder``: also object_centres [candidates, T, 3] float32, cell
                    units, object_colours [candidates, T, 3] float32, num_points [candidates, T] float32:
                    the means of each object's points and its point count)
                    -> offset [candidates, 2] (cell units from the centre), position [candidates, 2] float64 (m)
"""

from __future__ import annotations

import numpy as np
import torch

from ...cards import ModelCard
from ...cards.des4pos import CellConfig, TextConfig
from ...data.text_city import make_city
from ...runtime.text_tokens import encode_hints, load_tokenizer, split_hints
from ..comparators import Dense, Descriptor
from ..spec import GraphSpec, Int8Plan, ModelSpec
from .bench import des4pos_tasks
from .descriptions import descriptions
from .minilm import backbone_dir
from .model import FineConfig, build_des4pos


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
        cases.append(
            (
                f"{i:02d}-{kind}-{int(mask.sum())}obj",
                {
                    "points": pts[None].astype(np.float32),
                    "num_points": cnt[None].astype(np.float32),
                    "object_mask": mask[None],
                },
            )
        )
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
    d, h = model(
        *(
            torch.as_tensor(np.asarray(feeds[k])) if not torch.is_tensor(feeds[k]) else feeds[k]
            for k in ("points", "num_points", "object_mask")
        ),
        trace=trace,
    )
    return {"descriptor": d, "object_features": h}


SUBMAP_OUTPUTS = ["descriptor", "object_features"]
SUBMAP_GRAPH = GraphSpec(
    name="submap_encoder",
    module=lambda model: model.submap,
    input_names=lambda card: ["points", "num_points", "object_mask"],
    dynamic_axes=lambda card: {k: {0: "cells"} for k in ("points", "num_points", "object_mask")},
    output_names=lambda card: list(SUBMAP_OUTPUTS),
    make_cases=submap_cases,
    run_reference=submap_reference,
    run_export=submap_export,
    judges=lambda card: (Descriptor("descriptor", min_cosine=0.9999), Dense("object_features", atol=1e-4, rtol=1e-3)),
)


# ----------------------------------------------------------------------------- text encoder


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
    d, h = model(
        *(
            torch.as_tensor(np.asarray(feeds[k])) if not torch.is_tensor(feeds[k]) else feeds[k]
            for k in ("input_ids", "attention_mask")
        )
    )
    return {"descriptor": d, "hint_features": h}


TEXT_OUTPUTS = ["descriptor", "hint_features"]
TEXT_GRAPH = GraphSpec(
    name="text_encoder",
    module=lambda model: model.text,
    input_names=lambda card: ["input_ids", "attention_mask"],
    dynamic_axes=lambda card: {k: {0: "hints", 1: "tokens"} for k in ("input_ids", "attention_mask")},
    output_names=lambda card: list(TEXT_OUTPUTS),
    make_cases=text_cases,
    run_reference=text_reference,
    run_export=text_export,
    # int8 (the dynamically quantised copy): the sentence descriptor holds the descriptor budget;
    # the per-hint features the fine stage reads are reported, not judged
    judges=lambda card: (
        Descriptor("descriptor", min_cosine=0.9999),
        Dense("hint_features", atol=1e-4, rtol=1e-3, quantized_info=True),
    ),
)


# ----------------------------------------------------------------------------- fine stage


def _fine(card) -> FineConfig:
    return card.section("fine", FineConfig)


def fine_cases(card: ModelCard, n: int, seed: int):
    """1-4 candidate cells of 1..T objects, 1..max_hints hints, world origins up to 10 km; with
    ``fine.objects: encoder`` also object centres, colours and point counts, garbage (large
    values) in their padding slots."""
    cell, t, d = _cell(card), _text(card), _dim(card)
    summaries = _fine(card).objects == "encoder"
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
        feeds = {
            "object_features": objs,
            "object_mask": mask,
            "hint_features": rng.normal(0, 1, (h, d)).astype(np.float32),
            "cell_origin": rng.uniform(-1e4, 1e4, (k, 2)),
            "cell_size": np.full(k, cell.size),
        }
        if summaries:

            def garbage(shape):
                return rng.normal(0, 1e3, shape)

            centres = np.where(
                mask[..., None], rng.uniform(-0.1, 1.1, (k, cell.max_objects, 3)), garbage((k, cell.max_objects, 3))
            )
            colours = np.where(
                mask[..., None], rng.uniform(0, 1, (k, cell.max_objects, 3)), garbage((k, cell.max_objects, 3))
            )
            counts = np.where(mask, rng.integers(8, 5000, (k, cell.max_objects)), garbage((k, cell.max_objects)))
            feeds.update(
                object_centres=centres.astype(np.float32),
                object_colours=colours.astype(np.float32),
                num_points=counts.astype(np.float32),
            )
        cases.append((f"{i:02d}-{k}cells-{h}hints", feeds))
    return cases


def fine_reference(model, feeds, trace=None):
    objs, mask = np.asarray(feeds["object_features"]), np.asarray(feeds["object_mask"])
    summaries = None
    if "object_centres" in feeds:
        parts = [np.asarray(feeds[k]) for k in SUMMARY_INPUTS]
        summaries = [tuple(torch.from_numpy(p[j][mask[j]]) for p in parts) for j in range(len(objs))]
    off, pos = model.reference(
        [torch.from_numpy(objs[j][mask[j]]) for j in range(len(objs))],
        torch.as_tensor(np.asarray(feeds["hint_features"])),
        np.asarray(feeds["cell_origin"]),
        np.asarray(feeds["cell_size"]),
        summaries,
    )
    return {"offset": off, "position": pos}


FINE_INPUTS = ["object_features", "object_mask", "hint_features", "cell_origin", "cell_size"]
SUMMARY_INPUTS = ["object_centres", "object_colours", "num_points"]  # fine.objects: encoder


def fine_inputs(card: ModelCard) -> list[str]:
    """The fine-stage graph's inputs: the summaries of the candidate cells' objects too when the
    card's fine stage has its own object encoder."""
    return FINE_INPUTS + (SUMMARY_INPUTS if _fine(card).objects == "encoder" else [])


def fine_export(model, feeds, trace=None):
    names = FINE_INPUTS + [k for k in SUMMARY_INPUTS if k in feeds]
    off, pos = model(
        *(torch.as_tensor(np.asarray(feeds[k])) if not torch.is_tensor(feeds[k]) else feeds[k] for k in names)
    )
    return {"offset": off, "position": pos}


FINE_OUTPUTS = ["offset", "position"]
FINE_GRAPH = GraphSpec(
    name="fine_stage",
    module=lambda model: model.fine,
    input_names=fine_inputs,
    dynamic_axes=lambda card: {
        name: {0: "hints" if name == "hint_features" else "candidates"} for name in fine_inputs(card)
    },
    output_names=lambda card: list(FINE_OUTPUTS),
    make_cases=fine_cases,
    run_reference=fine_reference,
    run_export=fine_export,
    judges=lambda card: (Dense("offset", atol=1e-5, rtol=1e-4), Dense("position", unit="m", atol=1e-3, rtol=0.0)),
)


DES4POS_SPEC = ModelSpec(
    build=build_des4pos,
    graphs=(SUBMAP_GRAPH, TEXT_GRAPH, FINE_GRAPH),
    files=lambda card: {"tokenizer.json": tokenizer_path(card)},
    # a dynamically quantised copy of the text encoder (int8 MatMul/Gemm weights, no
    # calibration); the point and fine graphs stay fp32
    int8=Int8Plan("dynamic", graphs=("text_encoder",)),
    bench_tasks=des4pos_tasks,
    evaluation="localisation",
    recipe="text-to-cells",
)


def spec_for(card: ModelCard | None = None) -> ModelSpec:
    """The one spec of every Des4Pos card: three graphs sharing one set of weights."""
    return DES4POS_SPEC
