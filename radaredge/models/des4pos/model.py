"""Des4Pos: text-to-point-cloud localisation (Shang et al., Des4Pos paper, section III).

Three parts, exported as three graphs that share one set of weights:

1. **Submap (cell) encoder** (III-B.1). Per object of a cell: 256 points (x, y, z normalised to
   the cell, r, g, b in [0, 1]). Text2Pos's PointNet++ (three set abstractions, a global layer
   and two linear layers, eq. 2; the object network Text2Loc and upstream Des4Pos reuse) on the
   points in the cell frame (``object_frame``); colour, position (centre in the cell) and
   point-count encoders; the four embeddings, each L2-normalised, fused by Text2Loc's merge MLP
   (eq. 3) into s_i, L2-normalised as upstream does. MFAM (eq. 4-5): 1-, 3- and 5-wide
   convolutions along the object sequence with residuals, multi-head self-attention per branch,
   then softmax(F3 F1^T) * softmax(F3 F5^T) as the attention weight on F3, added to its input
   (``mfam: residual``; upstream's ConvBlock also adds its input back, around a fusion of its
   own: docs/models/des4pos.md) or not (``paper``). A bidirectional LSTM (eq. 6) over the objects,
   eq. 7's step-k downsampling
   over the state's channels (``downsample: channels``, upstream: 512 -> 256) or over the
   objects, a max over the objects -> the L2-normalised descriptor.
2. **Text encoder** (STE, III-B.2). A frozen sentence backbone (all-MiniLM-L6-v2 by default,
   a T5 encoder from a local directory) on every hint sentence; the cross-modal prior head
   (Transformer layers + MLP on the tokens; its max-pooled output is what stage 1 aligns to
   the teacher: CLIP in the paper, the backbone's own sentence embedding here); the alignment
   head Transformer (word level) -> max over tokens -> MLP -> Transformer (across hints) -> max
   over hints -> L2-normalised descriptor. The fine-stage text branch (a Transformer layer +
   max pooling, III-C) gives one feature per hint.
3. **Fine stage** (CRA, III-C, eq. 10-12): R1 = Attn(T, N, N) + T, R2 = Attn(N, R1, R1) + N,
   R_i = Attn(R_i-2, R_i-1, R_i-1) + R_i-2; a max over the last R (``fine.pool: last``) or the
   last hint-stream R (``hints``, Text2Loc's choice) and an MLP give the offset of the pose from
   the cell centre in cell units; position = cell origin + (0.5 + offset) * cell size (Text2Loc's
   pose-in-cell convention), in float64. N is the coarse encoder's per-object states (MFAM's output,
   ``fine.object_state: mfam``; the LSTM's or the object encoder's) or,
   with ``fine.objects: encoder``, a fine-stage object encoder's output on those states and each
   object's centre, mean colour and point count (Text2Loc trains its fine stage's own object
   encoder, with a position MLP).

Both formulations share the weights: ``reference=True`` is the paper's computation on the real
objects / tokens only (Python FPS, per-query ball query, no padding, one hint at a time, an
``nn.LSTM`` on the packed sequence); the export formulation works on fixed object slots with a
padding mask (real objects are moved to the front in-graph, so the slot order of padding does
not matter), padded token batches with an attention mask, and an unrolled LSTM whose backward
direction runs on the prefix-reversed sequence, so padding never reaches a real output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ...cards import ModelCard
from ...cards.des4pos import CellConfig, TextConfig
from ...config import card_ranges, positive
from ...errors import ConfigError
from ...ops.point_sampling import (
    ball_query_masked,
    ball_query_masked_reference,
    farthest_point_sample,
    farthest_point_sample_reference,
    group_points,
    group_points_reference,
)
from .minilm import NEG, _attend, load_backbone

POINT_COLUMNS = ("x", "y", "z", "r", "g", "b")


# ----------------------------------------------------------------------------- configuration


# Text2Pos's object classes (datapreparation/kitti360pose/utils.py CLASS_TO_INDEX, "pad" included):
# the class head of its pretrained PointNet++ has one output each.
TEXT2POS_CLASSES = (
    "building",
    "pole",
    "traffic light",
    "traffic sign",
    "garage",
    "stop",
    "smallpole",
    "lamp",
    "trash bin",
    "vending machine",
    "box",
    "road",
    "sidewalk",
    "parking",
    "wall",
    "fence",
    "guard rail",
    "bridge",
    "tunnel",
    "vegetation",
    "terrain",
    "pad",
)
OBJECT_FRAMES = ("cell", "unit_sphere")
MFAM_FORMS = ("residual", "paper")
DOWNSAMPLES = ("channels", "objects")


@card_ranges(
    embed_dim=(1, 4096),
    sa_npoint=(1, 65_536),
    sa_radius=positive(100.0),
    sa_nsample=(1, 1024),
    sa_mlp=(1, 4096),
    global_mlp=(1, 4096),
    head_mlp=(1, 4096),
    object_colors=(1, 1024),
    encoder_hidden=(1, 4096),
    heads=(1, 64),
    lstm_hidden=(1, 4096),
    downsample_stride=(1, 64),
)
@dataclass(frozen=True)
class SubmapConfig:
    """Card section ``submap``. The object encoder is Text2Pos's (which Text2Loc and upstream
    Des4Pos reuse): PointNet++ with set abstractions ``sa_*`` (every MLP layer Linear +
    BatchNorm + ReLU), a global layer ``global_mlp``, two linear layers ``head_mlp`` to the
    geometry feature, and class / colour heads (used by the object pretraining stage and by
    Text2Pos's published weights)."""

    embed_dim: int = 256
    object_frame: str = "cell"  # "cell": xyz as stored, normalised to the cell (Text2Loc's --no_pc_augment);
    # "unit_sphere": centred and scaled (Text2Pos's NormalizeScale)
    sa_npoint: tuple = (128, 64, 32)  # Text2Pos: FPS ratio 0.5 per level from 256 points
    sa_radius: tuple = (0.2, 0.3, 0.4)
    sa_nsample: tuple = (32, 32, 32)  # PyG radius(): at most 32 neighbours, the first in point order
    sa_mlp: tuple = ((32, 64), (128, 128), (256, 256))
    global_mlp: tuple = (512, 1024)
    head_mlp: tuple = (512, 256)  # lin1, lin2 -> the 256-d geometry feature (Text2Pos features2)
    object_classes: tuple = TEXT2POS_CLASSES
    object_colors: int = 8  # Text2Pos's colour head (never trained upstream)
    encoder_hidden: int = 64  # colour / position / count MLPs [3 or 1, 64, d] (Text2Loc)
    heads: int = 4  # MFAM self-attention heads
    mfam: str = "residual"  # "residual": s + MFAM(s) (upstream's ConvBlock); "paper": eq. 4-5 as printed
    lstm_hidden: int = 256  # per direction
    downsample: str = "channels"  # eq. 7: every k-th channel of the BiLSTM state (upstream) or every k-th object
    downsample_stride: int = 2  # eq. 7 step k

    def __post_init__(self):
        for name, allowed in (("object_frame", OBJECT_FRAMES), ("mfam", MFAM_FORMS), ("downsample", DOWNSAMPLES)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {list(allowed)}, got {getattr(self, name)!r}")
        levels = len(self.sa_npoint)
        if not levels or not len(self.sa_radius) == len(self.sa_nsample) == len(self.sa_mlp) == levels:
            raise ValueError(
                f"sa_npoint, sa_radius, sa_nsample and sa_mlp need one entry per set-abstraction level; "
                f"got {len(self.sa_npoint)}, {len(self.sa_radius)}, {len(self.sa_nsample)}, "
                f"{len(self.sa_mlp)}"
            )
        if any(not isinstance(m, tuple) or not m for m in self.sa_mlp):
            raise ValueError("sa_mlp needs a list of layer widths per level, e.g. [[32, 64], [128, 128]]")
        if not self.global_mlp or len(self.head_mlp) != 2:
            raise ValueError(
                f"global_mlp needs one layer width or more and head_mlp two (Text2Pos's lin1, lin2); "
                f"got {list(self.global_mlp)} and {list(self.head_mlp)}"
            )
        if not self.object_classes or not all(isinstance(c, str) and c for c in self.object_classes):
            raise ValueError("object_classes must be a list of class names")
        width = 2 * self.lstm_hidden // (self.downsample_stride if self.downsample == "channels" else 1)
        if width != self.embed_dim or (self.downsample == "channels" and 2 * self.lstm_hidden % self.downsample_stride):
            rule = "2 x lstm_hidden / downsample_stride" if self.downsample == "channels" else "2 x lstm_hidden"
            raise ValueError(f"the cell descriptor is {rule} = {width} wide, but embed_dim is {self.embed_dim}")


FINE_OBJECTS = ("coarse", "encoder")
FINE_POOLS = ("last", "hints")
OBJECT_STATES = ("lstm", "mfam", "objects")


@card_ranges(cra_layers=(1, 32), heads=(1, 64), mlp_hidden=(1, 4096))
@dataclass(frozen=True)
class FineConfig:
    """Card section ``fine``.

    ``objects``: what the CRA reads as the object stream n_i. ``coarse`` (the paper: "directly
    reuse the point-cloud encoder pre-trained in the coarse stage"): the coarse encoder's object
    states as they are. ``encoder``: a fine-stage object encoder of its own (Text2Loc's fine
    stage trains one, with an explicit position MLP): the coarse state through a linear layer,
    and MLPs on each object's centre in the cell (x, y, z in cell units), mean colour and point
    count, each L2-normalised, merged by an MLP and L2-normalised (the three MLPs as wide as the
    coarse encoder's, ``submap.encoder_hidden``). The graph then also takes ``object_centres``,
    ``object_colours`` and ``num_points`` of the candidate cells.

    ``pool``: what the max before the offset MLP runs over: the last CRA state R_n (``last``,
    eq. 12's output; with an even ``cra_layers`` that is an object-stream state) or the last
    hint-stream state (``hints``: R_n or R_n-1, the stream Text2Loc pools).

    ``object_state``: which per-object state of the coarse encoder is the object stream (the
    submap graph's ``object_features``). The paper names the fine stage's input n_i, eq. 7's name
    for the LSTM's downsampled states, and says only that the coarse encoder is reused:
    ``mfam`` (the default) reads MFAM's output (eq. 5) before the LSTM, ``lstm`` the
    bidirectional LSTM's states (each one summarises the cell's whole object sequence, and a CRA
    on them stays near the cell centre: docs/models/des4pos.md), ``objects`` the object
    encoder's s_i (eq. 3) before MFAM.
    """

    cra_layers: int = 4  # R1 .. Rn of eq. 10-12
    heads: int = 4
    mlp_hidden: int = 128
    objects: str = "coarse"  # "coarse" (the paper) or "encoder" (a fine-stage object encoder, Text2Loc)
    pool: str = "last"  # "last" (R_n, the paper) or "hints" (the last hint-stream state, Text2Loc)
    object_state: str = "mfam"  # the coarse encoder's state read as n_i: "mfam", "lstm" or "objects"

    def __post_init__(self):
        for name, allowed in (("objects", FINE_OBJECTS), ("pool", FINE_POOLS), ("object_state", OBJECT_STATES)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {list(allowed)}, got {getattr(self, name)!r}")


# ----------------------------------------------------------------------------- shared blocks


def mlp(dims, last_act: bool = False) -> nn.Sequential:
    layers = []
    for i in range(len(dims) - 1):
        layers.append(nn.Linear(dims[i], dims[i + 1]))
        if i < len(dims) - 2 or last_act:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class BatchNormMLP(nn.Sequential):
    """Text2Pos's ``get_mlp``: every layer Linear + BatchNorm1d + ReLU (the last one too), on the
    last axis of any [..., C] tensor; keys ``<i>.0`` (Linear) and ``<i>.1`` (BatchNorm) as upstream."""

    def __init__(self, dims):
        super().__init__(
            *[nn.Sequential(nn.Linear(a, b), nn.BatchNorm1d(b), nn.ReLU()) for a, b in zip(dims[:-1], dims[1:])]
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = x.shape
        y = super().forward(x.reshape(-1, shape[-1]))
        return y.reshape(*shape[:-1], y.shape[-1])


class Attention(nn.Module):
    """Multi-head attention with Q/K/V/output projections; ``mask`` [B, Tk] bool marks real keys."""

    def __init__(self, d: int, heads: int):
        super().__init__()
        if d % heads:
            raise ConfigError(f"attention width {d} must be divisible by its heads ({heads})")
        self.heads = heads
        self.q, self.k, self.v, self.o = (nn.Linear(d, d) for _ in range(4))

    def forward(self, q, kv, mask=None):
        return self.o(_attend(self.q(q), self.k(kv), self.v(kv), mask, self.heads))


class TransformerLayer(nn.Module):
    """Post-norm Transformer encoder layer (Vaswani et al.; nn.TransformerEncoderLayer's layout)."""

    def __init__(self, d: int, heads: int, ffn_ratio: int):
        super().__init__()
        self.attn = Attention(d, heads)
        self.ln1, self.ln2 = nn.LayerNorm(d), nn.LayerNorm(d)
        self.ffn = mlp([d, ffn_ratio * d, d])

    def forward(self, x, mask=None):
        x = self.ln1(x + self.attn(x, x, mask))
        return self.ln2(x + self.ffn(x))


def masked_max(x: torch.Tensor, mask: torch.Tensor | None, dim: int) -> torch.Tensor:
    if mask is None:
        return x.max(dim).values
    return torch.where(mask.unsqueeze(-1), x, torch.full_like(x, NEG)).max(dim).values


# ----------------------------------------------------------------------------- submap encoder


class _PointConv(nn.Module):
    """Holds ``local_nn`` under PyG PointConv's attribute name (Text2Pos keys ``sa<i>.point_conv.local_nn``)."""

    def __init__(self, local_nn: nn.Module):
        super().__init__()
        self.local_nn = local_nn


class SetAbstraction(nn.Module):
    """PointNet++ set abstraction as Text2Pos runs it through PyG: FPS -> radius neighbours
    (distance < r, the first ``nsample`` in point order) -> ``local_nn([x_j, pos_j - pos_i])`` ->
    max over the neighbours. FPS starts at point 0 (PyG's ``fps`` starts at random)."""

    def __init__(self, cin: int, dims, npoint: int, radius: float, nsample: int):
        super().__init__()
        self.npoint, self.radius, self.nsample = npoint, radius, nsample
        self.point_conv = _PointConv(BatchNormMLP([cin + 3, *dims]))

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor):
        """Export: xyz [G, N, 3], feats [G, N, C] -> centres [G, S, 3], features [G, S, C']."""
        idx = farthest_point_sample(xyz, min(self.npoint, xyz.shape[1]))
        centres = torch.gather(xyz, 1, idx.unsqueeze(-1).expand(-1, -1, 3))
        nb = ball_query_masked(xyz, None, centres, self.radius, self.nsample, strict=True)[0]
        grouped = torch.cat([group_points(feats, nb), group_points(xyz, nb) - centres.unsqueeze(2)], -1)
        return centres, self.point_conv.local_nn(grouped).max(2).values

    def reference(self, xyz: np.ndarray, feats: torch.Tensor):
        """Reference on one object: xyz [N, 3] numpy, feats [N, C] -> ([S, 3] numpy, [S, C'])."""
        idx = farthest_point_sample_reference(xyz, min(self.npoint, len(xyz)))
        centres = xyz[idx]
        nb = ball_query_masked_reference(xyz, None, centres, self.radius, self.nsample, strict=True)[0]
        rel = group_points_reference(xyz, nb) - centres[:, None, :]
        grouped = torch.cat([torch.from_numpy(group_points_reference(feats.numpy(), nb)), torch.from_numpy(rel)], -1)
        return centres, self.point_conv.local_nn(grouped).max(1).values


class _GlobalSA(nn.Module):
    def __init__(self, cin: int, dims):
        super().__init__()
        self.mlp = BatchNormMLP([cin + 3, *dims])


class PointNet2(nn.Module):
    """Text2Pos's PointNet++ object network (module names and shapes as its state_dict, so its
    published weights load): set abstractions ``sa1``.., the global layer ``ga`` (MLP on
    [features, xyz], max over points), ``lin1`` / ``lin2`` with ReLU to the geometry feature, and
    the ``class_classifier`` / ``color_classifier`` heads."""

    def __init__(self, cfg: SubmapConfig):
        super().__init__()
        cin = 3  # rgb
        for i, (npoint, radius, nsample, dims) in enumerate(
            zip(cfg.sa_npoint, cfg.sa_radius, cfg.sa_nsample, cfg.sa_mlp), 1
        ):
            setattr(self, f"sa{i}", SetAbstraction(cin, dims, npoint, radius, nsample))
            cin = dims[-1]
        self.levels = len(cfg.sa_npoint)
        self.ga = _GlobalSA(cin, cfg.global_mlp)
        self.lin1 = nn.Linear(cfg.global_mlp[-1], cfg.head_mlp[0])
        self.lin2 = nn.Linear(cfg.head_mlp[0], cfg.head_mlp[1])
        self.class_classifier = nn.Linear(cfg.head_mlp[1], len(cfg.object_classes))
        self.color_classifier = nn.Linear(cfg.head_mlp[1], cfg.object_colors)

    def _head(self, xyz, feats, reduce):
        g = reduce(self.ga.mlp(torch.cat([feats, xyz], -1)))
        return torch.relu(self.lin2(torch.relu(self.lin1(g))))

    def forward(self, xyz: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
        """Export: xyz [G, P, 3], rgb [G, P, 3] -> geometry features [G, head_mlp[-1]]."""
        feats = rgb
        for i in range(1, self.levels + 1):
            xyz, feats = getattr(self, f"sa{i}")(xyz, feats)
        return self._head(xyz, feats, lambda x: x.max(1).values)

    def reference(self, xyz: np.ndarray, rgb: torch.Tensor) -> torch.Tensor:
        """Reference on one object: xyz [P, 3] numpy, rgb [P, 3] -> [head_mlp[-1]]."""
        feats = rgb
        for i in range(1, self.levels + 1):
            xyz, feats = getattr(self, f"sa{i}").reference(xyz, feats)
        return self._head(torch.from_numpy(xyz), feats, lambda x: x.max(0).values)


class ObjectEncoder(nn.Module):
    """Per-object embedding s_i (eq. 2-3) as Text2Loc's ObjectEncoder (module names as its
    state_dict): ``mlp_pointnet`` on the PointNet++ geometry feature, ``color_encoder`` on the mean
    colour, ``pos_encoder`` on the mean position in the cell, ``num_encoder`` on the normalised
    point count, each L2-normalised, then ``mlp_merge`` (eq. 3, sigma(W[f, c, p, r] + b)) and an
    L2 normalisation of s_i (upstream's cell encoder; the paper does not say)."""

    def __init__(self, cell: CellConfig, cfg: SubmapConfig):
        super().__init__()
        self.cell, self.frame, d, h = cell, cfg.object_frame, cfg.embed_dim, cfg.encoder_hidden
        self.pointnet = PointNet2(cfg)
        self.mlp_pointnet = BatchNormMLP([cfg.head_mlp[-1], d])
        self.color_encoder = BatchNormMLP([3, h, d])
        self.pos_encoder = BatchNormMLP([3, h, d])
        self.num_encoder = BatchNormMLP([1, h, d])
        self.mlp_merge = BatchNormMLP([4 * d, d])

    @staticmethod
    def unit_sphere(xyz: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """PyG NormalizeScale: centre the object and scale its largest |coordinate| to 1."""
        rel = xyz - centre
        scale = rel.abs().amax(dim=(-2, -1), keepdim=True).clamp(min=1e-6)
        return rel / scale

    def local(self, xyz: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """The object's points in the frame PointNet++ sees (``object_frame``)."""
        return xyz if self.frame == "cell" else self.unit_sphere(xyz, centre)

    def fuse_embeddings(self, geom, rgb_mean, centre, count):
        c = (count.to(torch.float32).unsqueeze(-1) - self.cell.count_mean) / self.cell.count_std
        parts = [self.mlp_pointnet(geom), self.color_encoder(rgb_mean), self.pos_encoder(centre), self.num_encoder(c)]
        # s_i is L2-normalised after the merge, as Text2Loc's and upstream Des4Pos's cell encoders
        # do before the object sequence goes on (the paper's eq. 3 stops at the merge)
        return F.normalize(self.mlp_merge(torch.cat([F.normalize(p, dim=-1) for p in parts], -1)), dim=-1)

    def forward(self, points: torch.Tensor, counts: torch.Tensor, geometry: torch.Tensor | None = None) -> torch.Tensor:
        """Export: points [G, P, 6], counts [G] -> s [G, D]. ``geometry`` [G, 256], when given,
        replaces the PointNet++ pass (its output, computed once while it stays frozen)."""
        xyz, rgb = points[..., :3], points[..., 3:]
        centre = xyz.mean(1, keepdim=True)
        geom = self.pointnet(self.local(xyz, centre), rgb) if geometry is None else geometry
        return self.fuse_embeddings(geom, rgb.mean(1), centre[:, 0], counts)

    def reference(self, points: np.ndarray, count: float) -> torch.Tensor:
        """Reference on one object: points [P, 6] numpy -> s [D]."""
        pts = torch.from_numpy(np.ascontiguousarray(points, np.float32))
        xyz, rgb = pts[:, :3], pts[:, 3:]
        centre = xyz.mean(0, keepdim=True)
        geom = self.pointnet.reference(self.local(xyz, centre).numpy(), rgb)
        return self.fuse_embeddings(geom[None], rgb.mean(0)[None], centre, torch.tensor([count]))[0]


class MFAM(nn.Module):
    """Multi-scale fusion attention (eq. 4-5) over the object sequence [B, T, D].

    ``form`` "paper": eq. 4-5 as printed, F_k = MHSA(ReLU(Conv_k(s)) + s) for k = 1, 3, 5 (convolutions
    along the object sequence), R3 = softmax(F3 F1^T / sqrt(d)) * softmax(F3 F5^T / sqrt(d)), out =
    R3 V(F3). Each row of R3 sums to far less than 1 and mixes every object, so the output
    barely depends on any one object (a test measures it). ``form`` "residual" (default) adds the
    input back, s + eq. 5, as upstream's ConvBlock wraps its fusion; the per-object information
    then survives.
    """

    def __init__(self, d: int, heads: int, form: str = "residual"):
        super().__init__()
        self.form = form
        self.convs = nn.ModuleList(nn.Conv1d(d, d, k, padding=k // 2) for k in (1, 3, 5))
        self.self_attn = nn.ModuleList(Attention(d, heads) for _ in range(3))
        self.q1, self.k1, self.q5, self.k5 = (nn.Linear(d, d) for _ in range(4))
        self.v, self.o = nn.Linear(d, d), nn.Linear(d, d)
        self.scale = 1.0 / math.sqrt(d)

    def forward(self, s: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """s [B, T, D]; ``mask`` [B, T] (real objects first) or None (reference: all real)."""
        keep = mask.unsqueeze(-1) if mask is not None else None
        if keep is not None:  # padding is zero, exactly like the convolution's border
            s = torch.where(keep, s, torch.zeros_like(s))  # (a NaN in a padding slot stays out)
        feats = []
        for conv, attn in zip(self.convs, self.self_attn):
            x = torch.relu(conv(s.transpose(1, 2)).transpose(1, 2)) + s  # eq. 4
            if keep is not None:
                x = torch.where(keep, x, torch.zeros_like(x))
            feats.append(attn(x, x, mask))
        f1, f3, f5 = feats

        def weights(q, k):
            a = q @ k.transpose(1, 2) * self.scale
            if mask is not None:
                a = torch.where(mask.unsqueeze(1), a, torch.full_like(a, NEG))
            return torch.softmax(a, -1)

        r3 = weights(self.q1(f3), self.k1(f1)) * weights(self.q5(f3), self.k5(f5))  # R3 = R1 * R2
        out = self.o(r3 @ self.v(f3))  # eq. 5
        return s + out if self.form == "residual" else out


def _lstm_unrolled(x, w_ih, w_hh, b_ih, b_hh):
    """One LSTM direction (PyTorch gate order i, f, g, o), unrolled over T: x [B, T, D] -> [B, T, H]."""
    b, t, _ = x.shape
    hid = w_hh.shape[1]
    xw = x @ w_ih.t() + (b_ih + b_hh)
    h = x.new_zeros(b, hid)
    c = x.new_zeros(b, hid)
    out = []
    for step in range(t):
        g = xw[:, step] + h @ w_hh.t()
        i, f, gg, o = g.split(hid, -1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(gg)
        h = torch.sigmoid(o) * torch.tanh(c)
        out.append(h)
    return torch.stack(out, 1)


class SubmapEncoder(nn.Module):
    """Cell -> (descriptor [D], per-object features [T, D] for the fine stage)."""

    def __init__(self, cell: CellConfig, cfg: SubmapConfig, object_state: str = "mfam"):
        super().__init__()
        if object_state not in OBJECT_STATES:
            raise ConfigError(f"fine.object_state must be one of {list(OBJECT_STATES)}, got {object_state!r}")
        self.cell, self.cfg, self.object_state = cell, cfg, object_state
        self.objects = ObjectEncoder(cell, cfg)
        self.mfam = MFAM(cfg.embed_dim, cfg.heads, cfg.mfam)
        self.lstm = nn.LSTM(cfg.embed_dim, cfg.lstm_hidden, batch_first=True, bidirectional=True)

    def _select(self, t: int, device=None) -> torch.Tensor:
        """Objects kept by eq. 7: all (``downsample: channels``) or 1, 1+k, 1+2k ... (``objects``)."""
        if self.cfg.downsample == "channels":
            return torch.ones(t, dtype=torch.bool, device=device)
        return torch.arange(t, device=device) % self.cfg.downsample_stride == 0

    def _channels(self, h: torch.Tensor) -> torch.Tensor:
        """Eq. 7 over channels (``downsample: channels``, upstream's reading): every k-th channel
        of the [forward, backward] state, e.g. 512 -> 256; the identity for ``objects``."""
        return h[..., :: self.cfg.downsample_stride] if self.cfg.downsample == "channels" else h

    def _objects(self, points, counts, real, geometry):
        """s of every slot [G, D]. In train mode only the real objects go through the object
        encoder (its BatchNorm statistics never see a padding slot, as Text2Loc's flat object
        batch) and padding slots are zero; in eval mode every slot, fixed shapes for the export."""
        if not self.training:
            return self.objects(points, counts, geometry)
        s_real = self.objects(points[real], counts[real], None if geometry is None else geometry[real])
        s = s_real.new_zeros(len(real), s_real.shape[-1])
        s[real] = s_real
        return s

    def forward(self, points, num_points, object_mask, trace=None, geometry=None, stream=None):
        """Export: points [B, T, P, 6], num_points [B, T], object_mask [B, T] bool ->
        descriptor [B, D] (L2-normalised), object_features [B, T, D] (the ``object_state``
        stream, or ``stream`` when given: LSTM states, MFAM output or object encoder output; zero
        at padding slots). ``geometry`` [B, T, 256], when given, is the PointNet++ output of every
        slot (training with a frozen PointNet++ computes it once)."""
        b, t, p, _ = points.shape
        ar = torch.arange(t, dtype=torch.int64, device=points.device).unsqueeze(0)
        order = torch.argsort(torch.where(object_mask, ar, ar + t), dim=1)  # real objects first
        inverse = torch.argsort(order, dim=1)
        mask = torch.gather(object_mask, 1, order)
        pts = torch.gather(points, 1, order.view(b, t, 1, 1).expand(b, t, p, 6))
        cnt = torch.gather(num_points, 1, order)
        if geometry is not None:
            geometry = torch.gather(geometry, 1, order.unsqueeze(-1).expand_as(geometry)).reshape(b * t, -1)
        s = self._objects(pts.reshape(b * t, p, 6), cnt.reshape(b * t), mask.reshape(b * t), geometry).reshape(b, t, -1)
        d = self.mfam(s, mask)
        n = mask.sum(1, keepdim=True)
        rev = torch.where(ar < n, n - 1 - ar, ar)  # prefix reversal
        lstm = self.lstm
        fwd = _lstm_unrolled(d, lstm.weight_ih_l0, lstm.weight_hh_l0, lstm.bias_ih_l0, lstm.bias_hh_l0)
        d_rev = torch.gather(d, 1, rev.unsqueeze(-1).expand_as(d))
        bwd = _lstm_unrolled(
            d_rev,
            lstm.weight_ih_l0_reverse,
            lstm.weight_hh_l0_reverse,
            lstm.bias_ih_l0_reverse,
            lstm.bias_hh_l0_reverse,
        )
        bwd = torch.gather(bwd, 1, rev.unsqueeze(-1).expand_as(bwd))
        h = self._channels(torch.cat([fwd, bwd], -1)) * mask.unsqueeze(-1).to(d.dtype)
        desc = F.normalize(masked_max(h, mask & self._select(t, mask.device).unsqueeze(0), 1), dim=-1)
        if trace is not None:
            trace.update(objects=s, mfam=d, lstm=h)
        stream = stream or self.object_state
        state = {"lstm": h, "mfam": d, "objects": s}[stream]
        if stream != "lstm":  # h is zero at padding already
            state = torch.where(mask.unsqueeze(-1), state, torch.zeros_like(state))
        return desc, torch.gather(state, 1, inverse.unsqueeze(-1).expand_as(state))

    def reference(self, points: np.ndarray, num_points: np.ndarray):
        """Reference on one cell's real objects only: points [n, P, 6], num_points [n] ->
        (descriptor [D], object features [n, D] of the ``object_state`` stream)."""
        if len(points) == 0:
            raise ConfigError("a cell needs at least one object")
        s = torch.stack([self.objects.reference(o, c) for o, c in zip(points, num_points)])
        d = self.mfam(s[None])
        h = self._channels(self.lstm(d)[0][0])  # packed: no padding at all
        desc = F.normalize(h[self._select(len(h))].max(0).values, dim=-1)
        return desc, {"lstm": h, "mfam": d[0], "objects": s}[self.object_state]


# ----------------------------------------------------------------------------- text encoder


class TextEncoder(nn.Module):
    """STE: frozen backbone + cross-modal prior head + alignment head (+ the fine hint branch)."""

    def __init__(self, cfg: TextConfig, embed_dim: int):
        super().__init__()
        self.cfg = cfg
        self.backbone = load_backbone(cfg.backbone, cfg.backbone_dir, cfg.backbone_layers)
        c, p = self.backbone.dim, cfg.prior_dim
        self.prior = nn.ModuleList(TransformerLayer(c, cfg.prior_heads, cfg.ffn_ratio) for _ in range(cfg.prior_layers))
        self.prior_mlp = mlp([c, p, p])
        self.align_words = TransformerLayer(p, cfg.align_heads, cfg.ffn_ratio)
        self.align_mlp = mlp([p, embed_dim, embed_dim])
        self.align_hints = TransformerLayer(embed_dim, cfg.align_heads, cfg.ffn_ratio)
        self.fine_words = TransformerLayer(p, cfg.align_heads, cfg.ffn_ratio)
        self.fine_mlp = nn.Linear(p, embed_dim)

    def _hints(self, input_ids, attention_mask):
        """Token ids [H, L] -> (pre-MLP coarse per-hint vectors, fine per-hint features)."""
        mask = attention_mask > 0
        return self.heads(self.prior_tokens(self.backbone(input_ids, attention_mask), mask), mask)

    def prior_tokens(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The cross-modal prior head on backbone token features x [H, L, C] -> [H, L, prior_dim];
        its max over the real tokens is what stage 1 aligns to the teacher (eq. 8)."""
        for layer in self.prior:
            x = layer(x, mask)
        return self.prior_mlp(x)

    def heads(self, x: torch.Tensor, mask: torch.Tensor):
        """Prior token features [H, L, prior_dim] -> (coarse per-hint vectors [H, D] before the
        across-hint Transformer, fine per-hint features [H, D])."""
        coarse = self.align_mlp(masked_max(self.align_words(x, mask), mask, 1))
        fine = self.fine_mlp(masked_max(self.fine_words(x, mask), mask, 1))
        return coarse, fine

    def pool(self, coarse: torch.Tensor, hint_mask: torch.Tensor | None = None) -> torch.Tensor:
        """Per-hint vectors of B descriptions [B, H, D] (``hint_mask`` [B, H], None: all real) ->
        their L2-normalised descriptors [B, D]: the across-hint Transformer, then a max."""
        return F.normalize(masked_max(self.align_hints(coarse, hint_mask), hint_mask, 1), dim=-1)

    def _pool(self, coarse):
        return self.pool(coarse[None])[0]

    def forward(self, input_ids, attention_mask):
        """Export: input_ids [H, L] int64, attention_mask [H, L] int64 ->
        descriptor [D] (L2-normalised), hint_features [H, D]."""
        coarse, fine = self._hints(input_ids, attention_mask)
        return self._pool(coarse), fine

    def reference(self, hints: list[np.ndarray]):
        """Reference: each hint's token ids (no padding) on its own."""
        if not hints:
            raise ConfigError("a description needs at least one hint")
        outs = [
            self._hints(torch.as_tensor(h, dtype=torch.int64)[None], torch.ones(1, len(h), dtype=torch.int64))
            for h in hints
        ]
        coarse = torch.cat([o[0] for o in outs])
        return self._pool(coarse), torch.cat([o[1] for o in outs])


# ----------------------------------------------------------------------------- fine stage


def object_summaries(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(centres [..., 3], mean colours [..., 3]) of objects ``points`` [..., P, 6] (x, y, z in cell
    units, r, g, b): the means over each object's P stored points, as the object encoder takes them."""
    return points[..., :3].mean(-2), points[..., 3:].mean(-2)


class FineObjectEncoder(nn.Module):
    """The fine stage's own object encoder (``fine.objects: encoder``): the coarse object state
    through a linear layer, MLPs on the object's centre in the cell, mean colour and normalised
    point count (Text2Loc's position, colour and count encoders), each L2-normalised, merged by an
    MLP and L2-normalised. The position reaches the CRA through its own MLP, not only through
    the coarse encoder's states, which retrieval trained."""

    def __init__(self, cell: CellConfig, d: int, hidden: int):
        super().__init__()
        self.count_mean, self.count_std = cell.count_mean, cell.count_std
        self.feature = nn.Linear(d, d)
        self.pos_encoder = mlp([3, hidden, d])
        self.color_encoder = mlp([3, hidden, d])
        self.num_encoder = mlp([1, hidden, d])
        self.merge = mlp([4 * d, d, d])

    def forward(self, features, centres, colours, counts):
        """features [..., D], centres [..., 3], colours [..., 3], counts [...] -> [..., D]."""
        c = (counts.to(features.dtype).unsqueeze(-1) - self.count_mean) / self.count_std
        parts = [self.feature(features), self.pos_encoder(centres), self.color_encoder(colours), self.num_encoder(c)]
        return F.normalize(self.merge(torch.cat([F.normalize(p, dim=-1) for p in parts], -1)), dim=-1)


class FineStage(nn.Module):
    """Cascaded residual attention (eq. 10-12) + offset MLP + position in the world frame; with
    ``objects: encoder`` a fine-stage object encoder first (:class:`FineObjectEncoder`)."""

    def __init__(self, cfg: FineConfig, d: int, cell: CellConfig | None = None, encoder_hidden: int = 64):
        super().__init__()
        if cfg.cra_layers < 1:
            raise ConfigError("fine.cra_layers must be >= 1")
        self.cfg = cfg
        self.attn = nn.ModuleList(Attention(d, cfg.heads) for _ in range(cfg.cra_layers))
        self.offset = mlp([d, cfg.mlp_hidden, 2])
        if cfg.objects == "encoder":  # made last: the other weights seed as without it
            self.objects = FineObjectEncoder(cell or CellConfig(), d, encoder_hidden)

    @property
    def needs_summaries(self) -> bool:
        """True when the stage reads the objects' centres, colours and point counts."""
        return self.cfg.objects == "encoder"

    def encode_objects(self, objects, object_mask, summaries):
        """The object stream n_i: ``objects`` [K, T, D] as they are (``objects: coarse``) or through
        the fine object encoder with ``summaries`` = (centres [K, T, 3], colours [K, T, 3], counts
        [K, T]). Padding slots (``object_mask`` False) are zeroed first: whatever they hold (NaN
        included) reaches no real output."""
        if not self.needs_summaries:
            return objects
        if summaries is None:
            raise ConfigError(
                "fine.objects: encoder needs the candidate cells' object centres, colours and point "
                "counts (object_centres, object_colours, num_points)"
            )
        parts = (objects, *summaries)
        if object_mask is not None:
            parts = [
                torch.where(object_mask.view(*object_mask.shape, *([1] * (p.dim() - 2))), p, torch.zeros_like(p))
                for p in parts
            ]
        return self.objects(*parts)

    def offsets(self, objects, object_mask, hints, hint_mask=None, summaries=None):
        """objects [K, T, D] (mask [K, T] or None), hints [K, H, D] (mask [K, H] or None), and with
        ``objects: encoder`` ``summaries`` (:meth:`encode_objects`) -> offset [K, 2] (cell units from
        the cell centre)."""
        objects = self.encode_objects(objects, object_mask, summaries)
        seq = [(hints, hint_mask), (objects, object_mask)]  # R_-1 = T, R_0 = N
        for attn in self.attn:
            (q, qmask), (kv, kvmask) = seq[-2], seq[-1]
            seq.append((attn(q, kv, kvmask) + q, qmask))  # Residual(Attention(...), query)
        # seq[i] belongs to the hint stream for even i: the last is R_n, the last even one the last hint state
        last, mask = seq[-1] if self.cfg.pool == "last" else seq[len(seq) - 1 - (len(seq) - 1) % 2]
        return self.offset(masked_max(last, mask, 1))

    @staticmethod
    def place(offset, cell_origin, cell_size):
        return cell_origin + (0.5 + offset.to(torch.float64)) * cell_size.unsqueeze(-1)

    def forward(
        self,
        object_features,
        object_mask,
        hint_features,
        cell_origin,
        cell_size,
        object_centres=None,
        object_colours=None,
        num_points=None,
    ):
        """Export: object_features [K, T, D], object_mask [K, T] bool, hint_features [H, D],
        cell_origin [K, 2] float64 (m), cell_size [K] float64 (m); with ``objects: encoder`` also
        object_centres [K, T, 3] (cell units), object_colours [K, T, 3], num_points [K, T]
        -> offset [K, 2], position [K, 2]."""
        k = object_features.shape[0]
        summaries = None if object_centres is None else (object_centres, object_colours, num_points)
        off = self.offsets(
            object_features, object_mask, hint_features.unsqueeze(0).expand(k, -1, -1), summaries=summaries
        )
        return off, self.place(off, cell_origin, cell_size)

    def reference(self, objects: list[torch.Tensor], hints: torch.Tensor, cell_origin, cell_size, summaries=None):
        """Reference: each candidate's real objects [n_k, D] on its own (with ``objects: encoder``,
        ``summaries``: per candidate (centres [n_k, 3], colours [n_k, 3], counts [n_k]))."""
        if self.needs_summaries and summaries is None:
            raise ConfigError("fine.objects: encoder needs each candidate's object centres, colours and point counts")
        off = torch.cat(
            [
                self.offsets(
                    o[None],
                    None,
                    hints[None],
                    summaries=None if summaries is None else tuple(x[None] for x in summaries[j]),
                )
                for j, o in enumerate(objects)
            ]
        )
        return off, self.place(
            off, torch.as_tensor(cell_origin, dtype=torch.float64), torch.as_tensor(cell_size, dtype=torch.float64)
        )


# ----------------------------------------------------------------------------- the model


class Des4Pos(nn.Module):
    """The three parts; ``submap``, ``text`` and ``fine`` are exported as separate graphs."""

    def __init__(self, cell: CellConfig, submap: SubmapConfig, text: TextConfig, fine: FineConfig):
        super().__init__()
        self.cell_config, self.text_config = cell, text
        self.submap = SubmapEncoder(cell, submap, fine.object_state)
        self.text = TextEncoder(text, submap.embed_dim)
        self.fine = FineStage(fine, submap.embed_dim, cell, submap.encoder_hidden)


def des4pos_configs(card: ModelCard):
    if tuple(card.features) != POINT_COLUMNS:
        raise ConfigError(
            f"{card.where}: Des4Pos object points have the columns {list(POINT_COLUMNS)} "
            f"(x, y, z normalised to the cell, r, g, b in [0, 1]); card features are {card.features}"
        )
    return (
        card.section("cell", CellConfig),
        card.section("submap", SubmapConfig),
        card.section("text", TextConfig),
        card.section("fine", FineConfig),
    )


def build_des4pos(card: ModelCard) -> Des4Pos:
    """Des4Pos from a card: the pretrained frozen backbone, every other weight seeded (card ``seed``)."""
    cell, submap, text, fine = des4pos_configs(card)
    torch.manual_seed(int(card.get("seed", 0)))
    return Des4Pos(cell, submap, text, fine).eval()
