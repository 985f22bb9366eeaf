"""Des4Pos's MFAM, text heads and CRA from the paper's equations (section III), written plainly.

An independent reference for tests: it shares no code with radaredge and reads only a state_dict
(radaredge's parameter names), on one cell / one description at a time with no padding. Every
convolution tap, attention head and cascade step is an explicit loop.

- Attention(Q, K, V) (eq. 5, 10-12): projections W_q, W_k, W_v, the heads' scaled dot products
  softmax(q k^T / sqrt(d_h)) v, concatenated and projected by W_o.
- MFAM (eq. 4-5): F_k = MHSA(ReLU(Conv_k(s)) + s), k = 1, 3, 5, Conv_k a k-wide convolution
  along the object sequence with zero borders; R1 = softmax(Q1(F3) K1(F1)^T / sqrt(d)), R2 =
  softmax(Q5(F3) K5(F5)^T / sqrt(d)), R3 = R1 * R2 element-wise, out = W_o(R3 V(F3)); the
  card's ``mfam: residual`` adds s (upstream's ConvBlock), ``paper`` does not.
- Text heads (III-B.2, alignment head): per hint a post-norm Transformer layer over its prior
  token features, a max over tokens and an MLP; a Transformer layer across the hints, a max
  over them and an L2 normalisation. The fine branch: a Transformer layer, a max, a linear map.
- CRA (eq. 10-12): R1 = Attn(T, N, N) + T, R2 = Attn(N, R1, R1) + N, R_i = Attn(R_i-2, R_i-1,
  R_i-1) + R_i-2; the offset is an MLP of the max over the last R's rows.
"""

from __future__ import annotations

import math

import torch


def _linear(x: torch.Tensor, sd: dict, name: str) -> torch.Tensor:
    return x @ sd[f"{name}.weight"].T + sd[f"{name}.bias"]


def _softmax_rows(a: torch.Tensor) -> torch.Tensor:
    e = torch.exp(a - a.max(dim=-1, keepdim=True).values)
    return e / e.sum(-1, keepdim=True)


def attention(q_in: torch.Tensor, kv_in: torch.Tensor, sd: dict, name: str, heads: int) -> torch.Tensor:
    """Multi-head attention of queries [Tq, D] over keys / values [Tk, D]."""
    q, k, v = (_linear(x, sd, f"{name}.{p}") for x, p in ((q_in, "q"), (kv_in, "k"), (kv_in, "v")))
    d = q.shape[1]
    dh = d // heads
    outs = []
    for h in range(heads):
        cols = slice(h * dh, (h + 1) * dh)
        w = _softmax_rows(q[:, cols] @ k[:, cols].T / math.sqrt(dh))
        outs.append(w @ v[:, cols])
    return _linear(torch.cat(outs, 1), sd, f"{name}.o")


def _layer_norm(x: torch.Tensor, sd: dict, name: str, eps: float = 1e-5) -> torch.Tensor:
    mu = x.mean(-1, keepdim=True)
    var = ((x - mu) ** 2).mean(-1, keepdim=True)
    return (x - mu) / torch.sqrt(var + eps) * sd[f"{name}.weight"] + sd[f"{name}.bias"]


def transformer_layer(x: torch.Tensor, sd: dict, name: str, heads: int) -> torch.Tensor:
    """Post-norm encoder layer: LN(x + MHSA(x)), then LN(y + W2 ReLU(W1 y))."""
    y = _layer_norm(x + attention(x, x, sd, f"{name}.attn", heads), sd, f"{name}.ln1")
    ffn = _linear(torch.relu(_linear(y, sd, f"{name}.ffn.0")), sd, f"{name}.ffn.2")
    return _layer_norm(y + ffn, sd, f"{name}.ln2")


def _two_layer_mlp(x: torch.Tensor, sd: dict, name: str) -> torch.Tensor:
    return _linear(torch.relu(_linear(x, sd, f"{name}.0")), sd, f"{name}.2")


def conv_along_objects(s: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """A k-wide convolution over the object sequence s [T, D] (zero outside): out[t] = b +
    sum_j W[:, :, j] s[t + j - k // 2]."""
    t_len, k = s.shape[0], weight.shape[2]
    out = []
    for t in range(t_len):
        acc = bias.clone()
        for j in range(k):
            src = t + j - k // 2
            if 0 <= src < t_len:
                acc = acc + weight[:, :, j] @ s[src]
        out.append(acc)
    return torch.stack(out)


def mfam(s: torch.Tensor, sd: dict, prefix: str, heads: int, residual: bool) -> torch.Tensor:
    """Eq. 4-5 on one cell's object embeddings s [n, D] -> [n, D]."""
    feats = []
    for i in range(3):
        conv = conv_along_objects(s, sd[f"{prefix}.convs.{i}.weight"], sd[f"{prefix}.convs.{i}.bias"])
        x = torch.relu(conv) + s
        feats.append(attention(x, x, sd, f"{prefix}.self_attn.{i}", heads))
    f1, f3, f5 = feats
    d = s.shape[1]
    r1 = _softmax_rows(_linear(f3, sd, f"{prefix}.q1") @ _linear(f1, sd, f"{prefix}.k1").T / math.sqrt(d))
    r2 = _softmax_rows(_linear(f3, sd, f"{prefix}.q5") @ _linear(f5, sd, f"{prefix}.k5").T / math.sqrt(d))
    out = _linear((r1 * r2) @ _linear(f3, sd, f"{prefix}.v"), sd, f"{prefix}.o")
    return s + out if residual else out


def text_heads(prior_tokens: list[torch.Tensor], sd: dict, prefix: str, heads: int):
    """One description: per hint its prior token features [L_h, p] (real tokens only) ->
    (descriptor [D], fine per-hint features [H, D])."""
    coarse, fine = [], []
    for x in prior_tokens:
        words = transformer_layer(x, sd, f"{prefix}.align_words", heads)
        coarse.append(_two_layer_mlp(words.max(0).values, sd, f"{prefix}.align_mlp"))
        fw = transformer_layer(x, sd, f"{prefix}.fine_words", heads)
        fine.append(_linear(fw.max(0).values, sd, f"{prefix}.fine_mlp"))
    across = transformer_layer(torch.stack(coarse), sd, f"{prefix}.align_hints", heads)
    pooled = across.max(0).values
    return pooled / pooled.norm(), torch.stack(fine)


def cra_offset(objects: torch.Tensor, hints: torch.Tensor, sd: dict, prefix: str, heads: int, layers: int):
    """Eq. 10-12 on one candidate cell: its real objects' features N [n, D], the hints' T [H, D]
    -> the offset [2] from the cell centre, in cell units."""
    r = [hints, objects]  # R_-1 = T, R_0 = N
    for i in range(layers):
        older, newer = r[-2], r[-1]
        r.append(attention(older, newer, sd, f"{prefix}.attn.{i}", heads) + older)
    return _two_layer_mlp(r[-1].max(0).values, sd, f"{prefix}.offset")
