"""TDFANet's graph signature and parity cases (see radaredge.models.spec)."""

from __future__ import annotations

import numpy as np
import torch

from ...cards import ModelCard
from ...data.synthetic import generate_sequence
from ...errors import ConfigError
from ..comparators import Dense, Descriptor, Exact
from ..spec import GraphSpec, ModelSpec
from .model import TDFANet, build_tdfanet


def input_names(card: ModelCard) -> list[str]:
    """points_0 .. points_{K-1} (oldest first, [N_k, F] each) and timestamps [K] (s)."""
    return [f"points_{k}" for k in range(int(card.get("frames", 3)))] + ["timestamps"]


def dynamic_axes(card: ModelCard) -> dict:
    """Each frame has its own point count N_k."""
    return {f"points_{k}": {0: f"num_points_{k}"} for k in range(int(card.get("frames", 3)))}


def _select(points: np.ndarray, card: ModelCard) -> np.ndarray:
    """Synthetic scans carry x, y, z, v_r, rcs; pick the card's feature columns by name."""
    cols = ("x", "y", "z", "v_r", "rcs")
    try:
        idx = [cols.index(f) for f in card.features]
    except ValueError:
        raise ConfigError(
            f"{card.where}: synthetic scans provide {cols}; card features {card.features} name a column they lack"
        ) from None
    return np.ascontiguousarray(points[:, idx], np.float32)


def _out_of_range(rng: np.random.Generator, card: ModelCard, n: int = 40) -> np.ndarray:
    """Points beyond every face of the pillar range (must be dropped, not wrapped)."""
    r = card.get("pillars.point_cloud_range", [0.0, -39.68, -3.0, 69.12, 39.68, 10.0])
    pts = np.zeros((n, 5), np.float32)
    pts[:, 0] = rng.choice([r[0] - 3.0, r[3] + 5.0, 20.0], n)
    pts[:, 1] = rng.choice([r[1] - 4.0, r[4] + 4.0, 0.0], n)
    pts[:, 2] = rng.choice([r[2] - 2.0, r[5] + 2.0, 0.0], n)
    pts[:, 3] = rng.normal(0, 3, n)
    pts[:, 4] = rng.normal(5, 5, n)
    keep = (
        (pts[:, 0] < r[0])
        | (pts[:, 0] >= r[3])
        | (pts[:, 1] < r[1])
        | (pts[:, 1] >= r[4])
        | (pts[:, 2] < r[2])
        | (pts[:, 2] >= r[5])
    )
    return pts[keep]


def make_cases(card: ModelCard, n: int, seed: int) -> list[tuple[str, dict[str, np.ndarray]]]:
    """``n`` synthetic K-frame windows: plain drives, 40 % dynamic points, tiny and empty scans,
    and points outside the range, in rotation."""
    k = int(card.get("frames", 3))
    rate = float(card.get("frame_rate", 10.0))
    kinds = ("drive", "dynamic-40%", "tiny-scans", "out-of-range")
    cases = []
    for i in range(n):
        kind = kinds[i % len(kinds)]
        s = seed * 1000 + i
        overrides = {"dynamic_fraction": 0.4} if kind == "dynamic-40%" else {}
        seq = generate_sequence(k, seed=s, frame_rate=rate, **overrides)
        frames = [scan.points.astype(np.float32) for scan in seq]
        rng = np.random.default_rng(s)
        if kind == "tiny-scans":
            frames[0] = frames[0][:0]
            frames[-1] = frames[-1][: int(rng.integers(1, 4))]
        elif kind == "out-of-range":
            frames = [np.concatenate([f, _out_of_range(rng, card)]) for f in frames]
            frames = [f[rng.permutation(len(f))] for f in frames]
        feeds = {f"points_{j}": _select(f, card) for j, f in enumerate(frames)}
        feeds["timestamps"] = np.array([scan.timestamp for scan in seq], np.float32)
        cases.append((f"{i:02d}-{kind}", feeds))
    return cases


def trace_order(card: ModelCard) -> tuple[str, ...]:
    """Intermediates in pipeline order: ego velocity, BEV maps, aligned maps, then (with the
    deformable aggregation) the aggregated map of every pyramid level from the coarsest down to level 0."""
    if card.get("network.aggregation", "deformable") == "sum":
        return "ego_velocity", "bev", "aligned_bev"
    levels = int(card.get("network.pyramid_stages", 3))
    return ("ego_velocity", "bev", "aligned_bev") + tuple(f"aggregated_l{l}" for l in range(levels, -1, -1))


def _frames(feeds, card_frames: int):
    return [torch.as_tensor(feeds[f"points_{k}"]) for k in range(card_frames)], torch.as_tensor(feeds["timestamps"])


def run_reference(model: TDFANet, feeds, trace=None):
    frames, ts = _frames(feeds, model.frames)
    return model.run(frames, ts, reference=True, trace=trace)


def run_export(model: TDFANet, feeds, trace=None):
    frames, ts = _frames(feeds, model.frames)
    return model.run(frames, ts, reference=False, trace=trace)


OUTPUT_NAMES = ["descriptor", "descriptor_normalized", "ego_velocity", "ego_valid", "input_flags"]

# how parity-check judges each output (graph order)
JUDGES = (
    Dense("descriptor", atol=1e-4, rtol=1e-3, quantized_info=True),
    Descriptor("descriptor_normalized", min_cosine=0.9999),
    Dense("ego_velocity", unit="m/s", atol=1e-4, rtol=0.0),
    Exact("ego_valid"),
    Exact("input_flags"),
)

TDFANET_SPEC = ModelSpec(
    build=build_tdfanet,
    graphs=(
        GraphSpec(
            name="tdfanet",
            input_names=input_names,
            dynamic_axes=dynamic_axes,
            frame_inputs=lambda card: input_names(card)[:-1],
            timestamps_input="timestamps",
            output_names=lambda card: list(OUTPUT_NAMES),
            make_cases=make_cases,
            run_reference=run_reference,
            run_export=run_export,
            trace_order=trace_order,
            judges=lambda card: JUDGES,
        ),
    ),
    evaluation="place recognition",
    recipe="places",
)


def spec_for(card: ModelCard | None = None) -> ModelSpec:
    """The one spec of every TDFANet card."""
    return TDFANET_SPEC
