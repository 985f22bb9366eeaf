"""Generalized-mean (GeM) pooling (Radenovic et al.), TDFANet section III-D.

For a map x [B, C, H, W] (any units; BEV cells on the spatial axes) GeM gives, per channel,

    GeM_p(x) = ( mean_{h,w} max(x, eps)^p )^(1/p)    -> [B, C],

the mean pool at p = 1 and tending to the max pool as p -> infinity (power-mean inequality:
non-decreasing in p, never above the max of the clamped map). Clamping to eps > 0 keeps the
power defined for ReLU-free inputs and the gradient in p finite.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..errors import ConfigError, InputError


class GeM(nn.Module):
    """GeM pooling [B, C, H, W] -> [B, C] with exponent ``p`` (a trained parameter if ``learnable``)."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6, learnable: bool = True):
        super().__init__()
        if p <= 0 or eps <= 0:
            raise ConfigError(f"GeM needs p > 0 and eps > 0, got p={p}, eps={eps}")
        self.eps = eps
        exponent = torch.full((1,), float(p))
        if learnable:
            self.p = nn.Parameter(exponent)
        else:
            self.register_buffer("p", exponent)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4:
            raise InputError(f"GeM expects a map [B, C, H, W], got {list(x.shape)}")
        return x.clamp(min=self.eps).pow(self.p).mean((-2, -1)).pow(1.0 / self.p)

    def extra_repr(self) -> str:
        return f"p={float(self.p.detach()):.4g}, eps={self.eps:g}, learnable={isinstance(self.p, nn.Parameter)}"


def gem_reference(x: np.ndarray, p: float, eps: float = 1e-6) -> np.ndarray:
    """Reference GeM in float64 numpy: x [B, C, H, W] -> [B, C]."""
    clamped = np.maximum(np.asarray(x, dtype=np.float64), eps)
    return np.mean(clamped ** float(p), axis=(-2, -1)) ** (1.0 / float(p))
