"""The descriptions Des4Pos's text cases and ``bench`` queries use: synthetic-city pose
descriptions and a few of other wordings and lengths."""

from __future__ import annotations

from ...cards import ModelCard
from ...cards.des4pos import TextConfig
from ...data.text_city import make_city

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
    t = card.section("text", TextConfig)
    city = make_city(
        max(16, t.max_hints), 8, seed=seed, poses=2 * max(n, 4), min_hints=1, max_hints=t.max_hints, objects=60
    )
    poses = iter(dict.fromkeys(str(text) for text in city.pose_text))
    extra = iter(EXTRA_DESCRIPTIONS)
    return [(next(extra, None) if i % 5 == 4 else None) or next(poses) for i in range(n)]
