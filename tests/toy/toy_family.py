"""A toy model family registered from the tests, outside radaredge/: a point-wise MLP whose
max over the scan's points is the descriptor. It declares what each verb needs (docs/layout.md,
"Add a model") and nothing in radaredge/ names it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from radaredge.models.comparators import Dense
from radaredge.models.spec import GraphSpec, ModelSpec
from radaredge.registry import ModelFamily, register_family


@dataclass(frozen=True)
class ToyConfig:
    """The card's ``toy`` section: the MLP's hidden width."""

    hidden: int = 16


class PointMax(torch.nn.Module):
    """descriptor = max over a scan's points of MLP(point) ([N, F] -> [hidden])."""

    def __init__(self, features: int, hidden: int):
        super().__init__()
        self.mlp = torch.nn.Sequential(
            torch.nn.Linear(features, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, hidden)
        )

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """The export formulation: one batched MLP and a max over the point axis."""
        return self.mlp(points).amax(dim=0)

    def reference(self, points: torch.Tensor) -> torch.Tensor:
        """The reference formulation: one point at a time, a running maximum."""
        best = None
        for p in points:
            y = self.mlp(p[None])[0]
            best = y if best is None else torch.maximum(best, y)
        return best


def build(card) -> PointMax:
    torch.manual_seed(int(card.get("seed", 0)))
    return PointMax(len(card.features), card.section("toy", ToyConfig).hidden).eval()


def make_cases(card, n: int, seed: int):
    rng = np.random.default_rng(seed)
    return [
        (f"{i:02d}", {"points": rng.normal(size=(int(rng.integers(5, 40)), len(card.features))).astype(np.float32)})
        for i in range(n)
    ]


def _points(feeds):
    return torch.as_tensor(np.asarray(feeds["points"]))


SPEC = ModelSpec(
    build=build,
    graphs=(
        GraphSpec(
            name="toy",
            input_names=lambda card: ["points"],
            dynamic_axes=lambda card: {"points": {0: "points"}},
            frame_inputs=lambda card: ["points"],
            output_names=lambda card: ["descriptor"],
            make_cases=make_cases,
            run_reference=lambda model, feeds, trace=None: {"descriptor": model.reference(_points(feeds))},
            run_export=lambda model, feeds, trace=None: {"descriptor": model(_points(feeds))},
            judges=lambda card: (Dense("descriptor", atol=1e-5, rtol=1e-4),),
        ),
    ),
)


def spec_for(card) -> ModelSpec:
    return SPEC


FAMILY = register_family(ModelFamily("toy", sections=("toy",), spec=f"{__name__}:spec_for"))
