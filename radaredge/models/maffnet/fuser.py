"""MAFF-Net's fuser: upstream TRV-Lab/MAFF-Net's CQCA_caf at test time, with upstream's names.

Upstream: pcdet/models/backbones_2d/fuser/CQCA_caf.py (CQCA_caf, TransformerFusionBlock,
CrossTransformerBlock, CrossAttention), fuser/common.py (AdaptivePool2d, LearnableCoefficient,
LearnableWeights), fuser/se_module.py (SELayer). Inputs are BEV maps [B, C, H, W] on the pillar
grid (row = y cell, column = x cell): the SPA pillar map ("ir" upstream) and the clustering
feature map ("vis"). Only the parameters that reach the output at test time exist here; the
others are listed in :data:`UNUSED_FUSER_KEYS` and dropped when a checkpoint loads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ...config import card_ranges, positive
from ...errors import ConfigError


@card_ranges(
    pool_size=(1, 1024),
    heads=(1, 64),
    ffn_ratio=(1, 16),
    se_reduction=(1, 4096),
    out_channels=(1, 4096),
    bn_eps=positive(1.0),
)
@dataclass(frozen=True)
class CafConfig:
    """Card section ``caf``: upstream CQCA_caf's shape (TransformerFusionBlock defaults)."""

    pool_size: int = 16  # vert_anchors = horz_anchors: tokens are a pool_size x pool_size grid
    heads: int = 8  # h
    ffn_ratio: int = 4  # block_exp of mlp_ir
    se_reduction: int = 16  # SELayer reduction
    out_channels: int = 64  # OUT_CHANNEL
    bn_eps: float = 1e-5  # the fusion conv's BatchNorm2d (torch default; upstream sets none)


class SELayer(nn.Module):
    """Squeeze-and-excitation (upstream se_module.SELayer): x * sigmoid(FC(ReLU(FC(mean over H, W))))."""

    def __init__(self, channels: int, reduction: int):
        super().__init__()
        hidden = channels // reduction
        if hidden < 1:
            raise ConfigError(
                f"caf.se_reduction {reduction} exceeds the {channels} channels (upstream's SE "
                "would have a zero-width hidden layer)"
            )
        self.fc = nn.Sequential(
            nn.Linear(channels, hidden, bias=False), nn.ReLU(), nn.Linear(hidden, channels, bias=False), nn.Sigmoid()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.fc(x.mean((2, 3))).unsqueeze(-1).unsqueeze(-1)


class Scalar(nn.Module):
    """A learnable scalar factor (upstream LearnableCoefficient: x * bias, bias initialised to 1)."""

    def __init__(self):
        super().__init__()
        self.bias = nn.Parameter(torch.ones(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.bias


class PoolMix(nn.Module):
    """Upstream LearnableWeights: w1 * average-pooled + w2 * max-pooled tokens (both start at 0.5)."""

    def __init__(self):
        super().__init__()
        self.w1 = nn.Parameter(torch.full((1,), 0.5))
        self.w2 = nn.Parameter(torch.full((1,), 0.5))

    def forward(self, avg: torch.Tensor, peak: torch.Tensor) -> torch.Tensor:
        return avg * self.w1 + peak * self.w2


def pool_window(size: int, tokens: int) -> tuple[int, int]:
    """(kernel, stride) of upstream's AdaptivePool2d along one axis: stride = size // tokens,
    kernel = size - (tokens - 1) * stride (the last window ends at the border); (1, 1) when the
    axis is already ``tokens`` long (upstream then skips pooling)."""
    if size < tokens:
        raise ConfigError(f"caf.pool_size {tokens} exceeds the BEV map side {size}")
    stride = size // tokens
    return size - (tokens - 1) * stride, stride


class ClusterQueryAttention(nn.Module):
    """The eval-path part of upstream's CrossAttention that reaches CQCA_caf's output: queries from
    LN1 of the clustering-feature (CFA) tokens, keys and values from LN2 of the pillar tokens,
    ``heads`` heads of width C / heads, softmax(q k^T / sqrt(C / heads)) v, output projection.

    Upstream also computes the opposite direction (pillar queries on CFA keys) and a dynamic
    position bias whose sum is commented out; neither reaches the output (see UNUSED_FUSER_KEYS)."""

    def __init__(self, channels: int, heads: int):
        super().__init__()
        if channels % heads:
            raise ConfigError(f"caf.heads ({heads}) must divide the pillar channels ({channels})")
        self.heads = heads
        self.LN1 = nn.LayerNorm(channels)
        self.LN2 = nn.LayerNorm(channels)
        self.que_proj_vis = nn.Linear(channels, channels)
        self.key_proj_ir = nn.Linear(channels, channels)
        self.val_proj_ir = nn.Linear(channels, channels)
        self.out_proj_ir = nn.Linear(channels, channels)

    def forward(self, cfa_tokens: torch.Tensor, pillar_tokens: torch.Tensor) -> torch.Tensor:
        """cfa_tokens, pillar_tokens [B, T, C] -> attended pillar values [B, T, C]."""
        b, t, c = pillar_tokens.shape
        d = c // self.heads

        def heads(x):
            return x.reshape(b, t, self.heads, d).transpose(1, 2)  # [B, heads, T, d]

        q = heads(self.que_proj_vis(self.LN1(cfa_tokens)))
        kv = self.LN2(pillar_tokens)
        att = torch.softmax(q @ heads(self.key_proj_ir(kv)).transpose(-1, -2) / math.sqrt(d), -1)
        return self.out_proj_ir((att @ heads(self.val_proj_ir(kv))).transpose(1, 2).reshape(b, t, c))


class CrossTransformerLayer(nn.Module):
    """The pillar branch of upstream's CrossTransformerBlock (one layer, one loop):
    a = c3 * ir + c4 * attention(cfa, ir); out = c7 * a + c8 * MLP_ir(LN2(a)), MLP = Linear, GELU, Linear."""

    def __init__(self, channels: int, heads: int, ffn_ratio: int):
        super().__init__()
        self.crossatt = ClusterQueryAttention(channels, heads)
        self.LN2 = nn.LayerNorm(channels)
        self.mlp_ir = nn.Sequential(
            nn.Linear(channels, ffn_ratio * channels), nn.GELU(), nn.Linear(ffn_ratio * channels, channels)
        )
        self.coefficient3, self.coefficient4 = Scalar(), Scalar()
        self.coefficient7, self.coefficient8 = Scalar(), Scalar()

    def forward(self, cfa_tokens: torch.Tensor, pillar_tokens: torch.Tensor) -> torch.Tensor:
        a = self.coefficient3(pillar_tokens) + self.coefficient4(self.crossatt(cfa_tokens, pillar_tokens))
        return self.coefficient7(a) + self.coefficient8(self.mlp_ir(self.LN2(a)))


class TransformerFusion(nn.Module):
    """Upstream TransformerFusionBlock, eval path: both maps [B, C, H, W] -> s x s tokens
    (w1 * avg-pool + w2 * max-pool with upstream's fixed windows, :func:`pool_window`) plus their
    own position embedding (``pos_emb_vis`` for CFA, ``pos_emb_ir`` for pillars); one
    :class:`CrossTransformerLayer`; pillar tokens -> s x s map -> bilinear upsampling to H x W
    (half-pixel centres, upstream's eval mode; training upsamples nearest) + the pillar map."""

    def __init__(self, channels: int, cfg: CafConfig):
        super().__init__()
        s = cfg.pool_size
        self.pool_size = s
        self.pos_emb_vis = nn.Parameter(torch.randn(1, s * s, channels) * 0.02)
        self.pos_emb_ir = nn.Parameter(torch.randn(1, s * s, channels) * 0.02)
        self.vis_coefficient, self.ir_coefficient = PoolMix(), PoolMix()
        self.crosstransformer = nn.Sequential(CrossTransformerLayer(channels, cfg.heads, cfg.ffn_ratio))

    def _tokens(self, x: torch.Tensor, mix: PoolMix, pos: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        (kh, sh), (kw, sw) = pool_window(h, self.pool_size), pool_window(w, self.pool_size)
        pooled = mix(F.avg_pool2d(x, (kh, kw), (sh, sw)), F.max_pool2d(x, (kh, kw), (sh, sw)))
        return pooled.flatten(2).transpose(1, 2) + pos  # [B, s*s, C]

    def forward(self, pillar: torch.Tensor, cfa: torch.Tensor) -> torch.Tensor:
        b, c, h, w = pillar.shape
        tokens = self.crosstransformer[0](
            self._tokens(cfa, self.vis_coefficient, self.pos_emb_vis),
            self._tokens(pillar, self.ir_coefficient, self.pos_emb_ir),
        )
        s = self.pool_size
        grid = tokens.transpose(1, 2).reshape(b, c, s, s)
        return F.interpolate(grid, size=(h, w), mode="bilinear", align_corners=False) + pillar


class CrossAttentionFusion(nn.Module):
    """CAF = upstream ``fuser`` (CQCA_caf) at test time, with upstream's parameter names: for pillar
    features P [B, C, H, W] (the SPA map) and CFA features Q [B, C, H, W],
    out = ReLU(BN(Conv3x3([P, SE(TransformerFusion(P, Q))]))) [B, out_channels, H, W].

    Only the parameters that reach the output exist here; a checkpoint's others are listed in
    :data:`UNUSED_FUSER_KEYS` and dropped by the loader."""

    def __init__(self, pillar_channels: int, cfa_channels: int, cfg: CafConfig):
        super().__init__()
        if cfa_channels != pillar_channels:
            raise ConfigError(
                f"caf: the CFA map has {cfa_channels} channels, the pillar map {pillar_channels}; "
                "upstream's fusion needs equal widths (IN_CHANNEL_CROSS)"
            )
        c = pillar_channels
        self.crossfusion = TransformerFusion(c, cfg)
        self.se = SELayer(c, cfg.se_reduction)
        self.conv = nn.Sequential(
            nn.Conv2d(2 * c, cfg.out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(cfg.out_channels, eps=cfg.bn_eps),
            nn.ReLU(),
        )

    def forward(self, pillar: torch.Tensor, cfa: torch.Tensor) -> torch.Tensor:
        return self.conv(torch.cat([pillar, self.se(self.crossfusion(pillar, cfa))], 1))


# Upstream CQCA_caf parameters with no effect on its output at test time (one fusion layer, one
# loop, CQCA_caf returning only the pillar branch): the unused patch embedder, the commented-out
# dynamic position bias, the CFA-query direction of the attention, the CFA branch's MLP and the
# block's third MLP, the norms that are never called and the coefficients of the CFA branch.
UNUSED_FUSER_KEYS = (
    "fuser.crossfusion.bev_embedder.",
    "fuser.crossfusion.crosstransformer.0.ln_input.",
    "fuser.crossfusion.crosstransformer.0.ln_output.",
    "fuser.crossfusion.crosstransformer.0.LN1.",
    "fuser.crossfusion.crosstransformer.0.crossatt.dpb.",
    "fuser.crossfusion.crosstransformer.0.crossatt.key_proj_vis.",
    "fuser.crossfusion.crosstransformer.0.crossatt.val_proj_vis.",
    "fuser.crossfusion.crosstransformer.0.crossatt.que_proj_ir.",
    "fuser.crossfusion.crosstransformer.0.crossatt.out_proj_vis.",
    "fuser.crossfusion.crosstransformer.0.mlp_vis.",
    "fuser.crossfusion.crosstransformer.0.mlp.",
    "fuser.crossfusion.crosstransformer.0.coefficient1.",
    "fuser.crossfusion.crosstransformer.0.coefficient2.",
    "fuser.crossfusion.crosstransformer.0.coefficient5.",
    "fuser.crossfusion.crosstransformer.0.coefficient6.",
)
