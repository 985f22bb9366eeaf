"""TDFANet's network from the paper's equations (sections III-B to III-D), written plainly.

An independent reference for tests: it shares no code with radaredge and reads only a state_dict
(radaredge's parameter names). Maps are [C, H, W] tensors of one frame, H rows along +y, W
columns along +x (the pillar canvas); every frame, head, sampling point and level is an explicit
loop, every bilinear sample an explicit four-corner blend. Evaluation mode: BatchNorm with its
running statistics, dropout the identity.

- eq. 4-5, alignment: the aligned past map at cell (row v, column u) is the past map sampled
  bilinearly at (v + dy, u + dx), (dx, dy) the displacement to the current frame in cells,
  zero outside the map.
- the pyramid: three residual blocks (3x3 stride-2 conv, BN, ReLU, 3x3 conv, BN, plus a 1x1
  stride-2 conv + BN shortcut, ReLU), one level per block, shared by all frames.
- eq. 6: Q_top = F_t,top; Q_l = Linear([F_t,l, Upsample(A_l+1)]) with bilinear upsampling
  (half-pixel centres, edge-clamped).
- eq. 7: D_k = Linear([Q_l, F^a_t-k,l]) per past frame k.
- eq. 8: DeformableA(D_k, F^a_t-k,l): Deformable DETR's single-level attention: per head m a
  softmax over the P points of Linear(D_k), sampling offsets Linear(D_k) in pixels around the
  cell's own centre, the value map Linear(F^a) split into heads, the weighted bilinear samples
  concatenated over heads and projected by a last Linear.
- eq. 9: A_l = FFN(LN(sum_k M_k + Q_l)) with the Transformer's FFN sublayer, x + FFN(x).
- III-D: a per-cell MLP (1x1 convolutions) to the descriptor width, then GeM pooling
  (mean of clamp(x, eps)^p)^(1/p).
"""

from __future__ import annotations

import math

import torch


def _linear(x: torch.Tensor, sd: dict, name: str) -> torch.Tensor:
    """x [..., in] @ W^T + b with ``name.weight`` [out, in] and ``name.bias``."""
    y = x @ sd[f"{name}.weight"].T
    return y + sd[f"{name}.bias"] if f"{name}.bias" in sd else y


def _batch_norm(x: torch.Tensor, sd: dict, name: str, eps: float = 1e-5) -> torch.Tensor:
    """x [C, H, W] normalised with the running statistics of ``name``."""
    mean, var = sd[f"{name}.running_mean"], sd[f"{name}.running_var"]
    w, b = sd[f"{name}.weight"], sd[f"{name}.bias"]
    return ((x - mean[:, None, None]) / torch.sqrt(var[:, None, None] + eps)) * w[:, None, None] + b[:, None, None]


def _conv(x: torch.Tensor, weight: torch.Tensor, stride: int, pad: int) -> torch.Tensor:
    """Cross-correlation of x [Cin, H, W] with weight [Cout, Cin, k, k], zero padding, no bias."""
    cout, cin, k, _ = weight.shape
    h, w = x.shape[1:]
    padded = torch.zeros(cin, h + 2 * pad, w + 2 * pad, dtype=x.dtype)
    padded[:, pad : pad + h, pad : pad + w] = x
    ho, wo = (h + 2 * pad - k) // stride + 1, (w + 2 * pad - k) // stride + 1
    out = torch.zeros(cout, ho, wo, dtype=x.dtype)
    for i in range(k):
        for j in range(k):
            patch = padded[:, i : i + stride * ho : stride, j : j + stride * wo : stride]  # [Cin, Ho, Wo]
            out += torch.einsum("oc,chw->ohw", weight[:, :, i, j], patch)
    return out


def residual_block(x: torch.Tensor, sd: dict, name: str) -> torch.Tensor:
    """One pyramid level: x [C, H, W] -> [2C, ceil(H/2), ceil(W/2)]."""
    y = torch.relu(_batch_norm(_conv(x, sd[f"{name}.conv1.weight"], 2, 1), sd, f"{name}.bn1"))
    y = _batch_norm(_conv(y, sd[f"{name}.conv2.weight"], 1, 1), sd, f"{name}.bn2")
    short = _batch_norm(_conv(x, sd[f"{name}.down.0.weight"], 2, 0), sd, f"{name}.down.1")
    return torch.relu(y + short)


def bilinear(image: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """image [C, H, W] sampled at continuous pixel coordinates (centres at integers) -> [C, *rows.shape];
    neighbours outside the image read as zero."""
    c, h, w = image.shape
    r0, c0 = torch.floor(rows), torch.floor(cols)
    out = torch.zeros(c, *rows.shape, dtype=image.dtype)
    for dr in (0, 1):
        for dc in (0, 1):
            rr, cc = r0 + dr, c0 + dc
            weight = (1 - (rows - rr).abs()) * (1 - (cols - cc).abs())
            inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            ri, ci = rr.clamp(0, h - 1).long(), cc.clamp(0, w - 1).long()
            out += torch.where(inside, weight, torch.zeros_like(weight)) * image[:, ri, ci]
    return out


def upsample(image: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Bilinear resize of image [C, H', W'] to [C, h, w] with half-pixel centres: output pixel i
    reads source coordinate max((i + 0.5) * H'/h - 0.5, 0), neighbours clamped to the edge."""
    _, hi, wi = image.shape
    out = torch.zeros(image.shape[0], h, w, dtype=image.dtype)
    for i in range(h):
        sy = max((i + 0.5) * hi / h - 0.5, 0.0)
        y0 = min(int(math.floor(sy)), hi - 1)
        y1, fy = min(y0 + 1, hi - 1), sy - math.floor(sy)
        for j in range(w):
            sx = max((j + 0.5) * wi / w - 0.5, 0.0)
            x0 = min(int(math.floor(sx)), wi - 1)
            x1, fx = min(x0 + 1, wi - 1), sx - math.floor(sx)
            out[:, i, j] = (1 - fy) * ((1 - fx) * image[:, y0, x0] + fx * image[:, y0, x1]) + fy * (
                (1 - fx) * image[:, y1, x0] + fx * image[:, y1, x1]
            )
    return out


def align(past: torch.Tensor, dx: float, dy: float) -> torch.Tensor:
    """eq. 4-5: the past map [C, H, W] warped into the current frame by (dx, dy) cells."""
    _, h, w = past.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    return bilinear(past.double(), v + dy, u + dx).to(past.dtype)


def deformable_attention(
    d: torch.Tensor, value_map: torch.Tensor, sd: dict, name: str, heads: int, points: int
) -> torch.Tensor:
    """eq. 8 for every cell: advanced queries d [H*W, C] (row-major cells) over one value map
    [C, H, W] -> M [H*W, C]. Each query's reference point is its own cell's centre."""
    c, h, w = value_map.shape
    ch = c // heads
    value = _linear(value_map.reshape(c, h * w).T, sd, f"{name}.value_proj").T.reshape(c, h, w)
    offsets = _linear(d, sd, f"{name}.sampling_offsets").reshape(h * w, heads, 1, points, 2)
    logits = _linear(d, sd, f"{name}.attention_weights").reshape(h * w, heads, points)
    rows = torch.arange(h * w) // w
    cols = torch.arange(h * w) % w
    out = torch.zeros(h * w, c, dtype=d.dtype)
    for m in range(heads):
        weights = torch.softmax(logits[:, m], dim=-1)  # [HW, P]
        for p in range(points):
            # reference (x, y) = ((col + 0.5) / W, (row + 0.5) / H); location = ref + offset / (W, H);
            # pixel coordinates (location * size - 0.5): col + offset_x, row + offset_y
            sample = bilinear(
                value[m * ch : (m + 1) * ch], rows + offsets[:, m, 0, p, 1], cols + offsets[:, m, 0, p, 0]
            )
            out[:, m * ch : (m + 1) * ch] += weights[:, p : p + 1] * sample.T
    return _linear(out, sd, f"{name}.output_proj")


def _layer_norm(x: torch.Tensor, sd: dict, name: str, eps: float = 1e-5) -> torch.Tensor:
    mean = x.mean(-1, keepdim=True)
    var = ((x - mean) ** 2).mean(-1, keepdim=True)
    return (x - mean) / torch.sqrt(var + eps) * sd[f"{name}.weight"] + sd[f"{name}.bias"]


def dfa_layer(
    current: torch.Tensor,
    past: list[torch.Tensor],
    coarser: torch.Tensor | None,
    sd: dict,
    name: str,
    heads: int,
    points: int,
) -> torch.Tensor:
    """eq. 6-9 at one level: F_t,l [C, H, W], the K-1 aligned past maps F^a_t-k,l, A_l+1 (None at
    the top) -> A_l [C, H, W]."""
    c, h, w = current.shape
    q = current.reshape(c, h * w).T  # [HW, C]
    if coarser is not None:  # eq. 6
        q = _linear(torch.cat([q, upsample(coarser, h, w).reshape(-1, h * w).T], 1), sd, f"{name}.query_fuse")
    total = torch.zeros_like(q)
    for frame in past:
        f = frame.reshape(c, h * w).T
        d = _linear(torch.cat([q, f], 1), sd, f"{name}.advanced_query")  # eq. 7
        total = total + deformable_attention(d, frame, sd, f"{name}.attn", heads, points)  # eq. 8
    x = _layer_norm(total + q, sd, f"{name}.norm")  # eq. 9 (dropout: identity)
    hidden = torch.relu(_linear(x, sd, f"{name}.ffn.0"))
    a = x + _linear(hidden, sd, f"{name}.ffn.3")
    return a.T.reshape(c, h, w)


def descriptor(
    maps: list[torch.Tensor],
    cells: list[tuple[float, float]],
    sd: dict,
    heads: int,
    points: int,
    stages: int,
    gem_eps: float = 1e-6,
) -> torch.Tensor:
    """The descriptor [D] (before L2 normalisation) of K BEV maps [C, H, W] (oldest first) with
    the displacement (dx, dy) in cells of each to the last one."""
    aligned = [align(m, dx, dy) for m, (dx, dy) in zip(maps[:-1], cells[:-1])] + [maps[-1]]
    pyramid = [aligned]
    for s in range(stages):
        pyramid.append([residual_block(m, sd, f"pyramid.{s}") for m in pyramid[-1]])
    a = None
    for level in range(stages, -1, -1):
        frames = pyramid[level]
        a = dfa_layer(frames[-1], frames[:-1], a, sd, f"dfa.{level}", heads, points)
    c, h, w = a.shape
    mlp = {k: v.flatten(1) if v.dim() == 4 else v for k, v in sd.items() if k.startswith("mlp.")}  # 1x1 convs
    hidden = torch.relu(_linear(a.reshape(c, h * w).T, mlp, "mlp.0"))
    out = _linear(hidden, mlp, "mlp.2")  # [HW, D]
    p = sd["gem.p"]
    return out.clamp(min=gem_eps).pow(p).mean(0).pow(1.0 / p)
