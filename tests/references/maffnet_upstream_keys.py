"""The state_dict layout of upstream MAFF-Net (TRV-Lab/MAFF-Net), computed from its configs.

What was read, and from where (TRV-Lab/MAFF-Net at commit 0bb253f; the fthbng77/MAFF-Net fork's
HEAD eb24f6d changes none of these model files, only CUDA op sources, data paths and the version):

* ``pcdet/models/detectors/MAFF_Net.py``: ``module_topology`` = vfe, backbone_3d, map_to_bev_module,
  image_backbone, fuser, backbone_2d, dense_head, pfe, point_head, roi_head. The configs have no
  BACKBONE_3D, so ``backbone_3d`` is None and has no keys. ``build_fuser`` records
  ``num_bev_features1 = FUSER.OUT_CHANNEL`` (l.36) and ``build_pfe`` passes that, not the 2-D
  backbone's 384, as the pfe's BEV channel count (l.47).
* ``pcdet/models/detectors/detector3d_template.py``: the ``global_step`` buffer, a LongTensor of
  shape (1,) (l.20), the first key of every OpenPCDet detector; the channel plumbing between
  modules (point head on ``num_point_features_before_fusion`` l.149, roi head on the pfe's
  ``num_point_features`` l.168, class-agnostic heads get num_class 1 l.134/156/172).
* Configs ``tools/cfgs/MAFF-Net/MAFF-Net_vod.yaml`` and ``MAFF-Net_TJ4D.yaml`` with their
  ``_BASE_CONFIG_`` ``tools/cfgs/dataset_configs/vod_dataset_radar.yaml`` and
  ``TJ4DRadSet_dataset_radar.yaml``. ``pcdet/config.py`` ``merge_new_config`` (l.51-66) merges
  dicts key by key and replaces lists, so TJ4D's model config replaces the dataset config's
  ``used_feature_list`` with [x, y, z, v_r, SNR]: 5 raw point features (VoD: 7, x y z rcs v_r
  v_r_comp time). ``absolute_coordinates_encoding`` counts ``len(used_feature_list)``
  (``pcdet/datasets/processor/point_feature_encoder.py`` l.57).
* vfe: ``pcdet/models/backbones_3d/vfe/pillar_vfe.py`` (RadarPillarVFE l.196, RadarPillarVFE_TJ
  l.38, PFNLayer l.345) and ``pcdet/models/model_utils/se_module.py`` (SELayer_vfe l.22). Only
  the TJ variant builds ``self.se`` (l.114; its forward never calls it), and with 11 input
  channels and reduction 16 its two Linear layers are (0, 11) and (11, 0): zero-size tensors
  that are still state_dict keys.
* map_to_bev_module: ``pcdet/models/backbones_2d/map_to_bev/pointpillar_scatter.py``
  (PointPillarScatter_spa l.44, PillarAttentionWithRoPE l.92; its width is hard-coded 64).
* image_backbone: ``pcdet/models/backbones_image/CQCA_cfa.py`` (l.53-63: three conv3x3+BN).
* fuser: ``pcdet/models/backbones_2d/fuser/CQCA_caf.py`` (CQCA_caf l.354, TransformerFusionBlock
  l.268, CrossTransformerBlock l.167, CrossAttention l.40, ImageEmbedder l.231,
  DynamicPositionBias l.24), ``fuser/common.py`` (LearnableCoefficient l.544,
  LearnableWeights l.554) and ``fuser/se_module.py`` (SELayer). CrossAttention's
  ``rel_pos_indices`` is registered ``persistent=False`` (l.64) and so is not a key.
* backbone_2d: ``pcdet/models/backbones_2d/base_bev_backbone.py`` (l.8-84).
* dense_head: ``pcdet/models/dense_heads/anchor_head_single.py`` (l.56-92),
  ``anchor_head_template.py`` (anchors are plain attributes, loss modules hold no tensors:
  ``pcdet/utils/loss_utils.py`` keeps ``code_weights`` as a plain attribute),
  ``target_assigner/anchor_generator.py`` (l.32: anchors per location = rotations x sizes x
  heights per class), ``pcdet/utils/box_coder_utils.py`` (ResidualCoder code_size 7).
* pfe: ``pcdet/models/backbones_3d/pfe/voxel_set_abstraction.py`` VoxelSetAbstraction_cda
  (l.579-636): 'bev' adds the BEV channels, 'cluster_points' builds ``SA_clusterpoints`` on
  ``num_rawpoint_features - 3`` input channels, ``SA_layers`` stays an empty ModuleList.
* ``pcdet/ops/pointnet2/pointnet2_stack/pointnet2_modules.py``: ``build_local_aggregation_module``
  (l.10-27) prepends the input channels to each MLPS entry, and StackSAModuleMSG adds 3 for
  use_xyz (l.138). The file defines StackSAModuleMSG twice (l.30, l.114); the second one is
  what the builder resolves at call time; with use_density False both have the same layers
  (Conv2d 1x1 no bias + BatchNorm2d + ReLU per MLP step; QueryAndGroup holds no tensors).
* point_head: ``pcdet/models/dense_heads/point_head_simple.py`` and ``point_head_template.py``
  ``make_fc_layers`` (l.36-47).
* roi_head: ``pcdet/models/roi_heads/pvrcnn_head.py`` (l.8-42; ROI grid pool through
  ``build_local_aggregation_module``, ``pre_channel = GRID_SIZE**3 * num_c_out``, a Dropout after
  every shared FC but the last) and ``roi_head_template.py`` ``make_fc_layers`` (l.29-43: a
  Dropout after the first FC only). ProposalTargetLayer holds no tensors.

Upstream's MAFF_Net always has the second stage: its ``forward`` calls pfe, point_head and roi_head
unconditionally. ``stage_two=False`` describes radaredge's stage-one-only card: the same model
with every ``pfe.*``, ``point_head.*`` and ``roi_head.*`` key dropped.

Written from reading the sources; no upstream code is copied. The key order follows
``nn.Module.state_dict`` (a module's own parameters, then its buffers, then its children in
registration order).
"""

from __future__ import annotations

import math
from typing import Dict, Tuple

import torch

Shape = Tuple[int, ...]
Keys = Dict[str, Shape]

STAGE_TWO_MODULES = ("pfe", "point_head", "roi_head")

# Config values, transcribed from the upstream YAML files named in each comment.
CONFIGS = {
    "vod": {
        # MAFF-Net_vod.yaml l.1; dataset_configs/vod_dataset_radar.yaml l.49 (used_feature_list)
        "class_names": ["Car", "Pedestrian", "Cyclist"],
        "used_feature_list": ["x", "y", "z", "rcs", "v_r", "v_r_comp", "time"],
        # MAFF-Net_vod.yaml l.38-48
        "vfe": {
            "NAME": "RadarPillarVFE",
            "USE_RCS": True,
            "USE_VR": True,
            "USE_VR_COMP": True,
            "USE_TIME": True,
            "WITH_DISTANCE": False,
            "USE_ABSLOTE_XYZ": True,
            "USE_NORM": True,
            "NUM_FILTERS": [64],
        },
        # anchor count per class: len(anchor_rotations) * len(anchor_sizes) * len(bottom_heights)
        "anchor_sets": [(2, 1, 1)] * 3,
    },
    "tj4d": {
        # MAFF-Net_TJ4D.yaml l.1 and l.6-10 (overrides the dataset config's used_feature_list)
        "class_names": ["Car", "Pedestrian", "Cyclist", "Truck"],
        "used_feature_list": ["x", "y", "z", "v_r", "SNR"],
        # MAFF-Net_TJ4D.yaml l.43-54
        "vfe": {
            "NAME": "RadarPillarVFE_TJ",
            "USE_RANGE": False,
            "USE_VR": True,
            "USE_SNR": True,
            "USE_ALPHA": False,
            "USE_BETA": False,
            "WITH_DISTANCE": False,
            "USE_ABSLOTE_XYZ": True,
            "USE_NORM": True,
            "NUM_FILTERS": [64],
        },
        "anchor_sets": [(2, 1, 1)] * 4,
    },
}


def _config(dataset) -> dict:
    """The dataset values of ``dataset``: 'vod' or 'tj4d' (:data:`CONFIGS`), or a dict of the same
    keys (class_names, used_feature_list, vfe, anchor_sets; optionally BACKBONE_2D in place of
    :data:`COMMON`'s) for a modified config."""
    if isinstance(dataset, dict):
        return dataset
    if dataset not in CONFIGS:
        raise ValueError(f"dataset must be one of {sorted(CONFIGS)} or a dict of their keys, got {dataset!r}")
    return CONFIGS[dataset]


# Identical in both model configs (line numbers of MAFF-Net_vod.yaml; TJ4D's sit 6 to 17 lines later).
COMMON = {
    "MAP_TO_BEV": {"IS_SPA": True, "NUM_BEV_FEATURES": 64},  # l.50-53
    "FUSER": {"IN_CHANNEL_CROSS": 64, "IN_CHANNEL": 128, "OUT_CHANNEL": 64},  # l.68-72
    "BACKBONE_2D": {
        "LAYER_NUMS": [3, 5, 5],
        "LAYER_STRIDES": [2, 2, 2],  # l.74-80
        "NUM_FILTERS": [64, 128, 512],
        "UPSAMPLE_STRIDES": [1, 2, 4],
        "NUM_UPSAMPLE_FILTERS": [128, 128, 128],
    },
    "DENSE_HEAD": {
        "CLASS_AGNOSTIC": False,
        "USE_DIRECTION_CLASSIFIER": True,  # l.82-89
        "NUM_DIR_BINS": 2,
        "CODE_SIZE": 7,
    },  # ResidualCoder
    "PFE": {
        "NUM_OUTPUT_FEATURES": 128,
        "FEATURES_SOURCE": ["bev", "cluster_points"],  # l.140-157
        "SA_LAYER": {"cluster_points": {"MLPS": [[16, 16], [16, 16]]}},
    },
    "POINT_HEAD": {
        "CLS_FC": [256, 256],
        "CLASS_AGNOSTIC": True,  # l.159-163
        "USE_POINT_FEATURES_BEFORE_FUSION": True,
    },
    "ROI_HEAD": {
        "CLASS_AGNOSTIC": True,
        "SHARED_FC": [256, 256],
        "CLS_FC": [256, 256],  # l.172-197
        "REG_FC": [256, 256],
        "DP_RATIO": 0.3,
        "CODE_SIZE": 7,
        "ROI_GRID_POOL": {"GRID_SIZE": 6, "MLPS": [[64, 64], [64, 64]]},
    },
}


# ---------------------------------------------------------------------------------------------
# Layer helpers (torch.nn key names and shapes)
# ---------------------------------------------------------------------------------------------


def _bn(keys: Keys, prefix: str, c: int) -> None:
    """BatchNorm1d/2d (affine, track_running_stats)."""
    keys[f"{prefix}.weight"] = (c,)
    keys[f"{prefix}.bias"] = (c,)
    keys[f"{prefix}.running_mean"] = (c,)
    keys[f"{prefix}.running_var"] = (c,)
    keys[f"{prefix}.num_batches_tracked"] = ()


def _ln(keys: Keys, prefix: str, c: int) -> None:
    keys[f"{prefix}.weight"] = (c,)
    keys[f"{prefix}.bias"] = (c,)


def _linear(keys: Keys, prefix: str, c_in: int, c_out: int, bias: bool = True) -> None:
    keys[f"{prefix}.weight"] = (c_out, c_in)
    if bias:
        keys[f"{prefix}.bias"] = (c_out,)


def _conv(keys: Keys, prefix: str, c_in: int, c_out: int, kernel: Tuple[int, ...], bias: bool) -> None:
    """Conv1d/Conv2d: weight (out, in, *kernel)."""
    keys[f"{prefix}.weight"] = (c_out, c_in, *kernel)
    if bias:
        keys[f"{prefix}.bias"] = (c_out,)


def _conv_transpose(keys: Keys, prefix: str, c_in: int, c_out: int, k: int) -> None:
    """ConvTranspose2d without bias: weight (in, out, k, k)."""
    keys[f"{prefix}.weight"] = (c_in, c_out, k, k)


def _stack_sa_msg(keys: Keys, prefix: str, input_channels: int, mlps) -> int:
    """build_local_aggregation_module + StackSAModuleMSG (pointnet2_stack/pointnet2_modules.py
    l.10-27, l.114-152): per scale, [input_channels + 3 (use_xyz)] + MLPS[k] through
    Conv2d 1x1 (no bias), BatchNorm2d, ReLU. Returns the output channels (sum of the last
    widths)."""
    for i, mlp in enumerate(mlps):
        spec = [input_channels + 3] + list(mlp)
        for j in range(len(spec) - 1):
            _conv(keys, f"{prefix}.mlps.{i}.{3 * j}", spec[j], spec[j + 1], (1, 1), bias=False)
            _bn(keys, f"{prefix}.mlps.{i}.{3 * j + 1}", spec[j + 1])
    return sum(mlp[-1] for mlp in mlps)


# ---------------------------------------------------------------------------------------------
# Module helpers
# ---------------------------------------------------------------------------------------------


def num_rawpoint_features(dataset: str) -> int:
    """point_feature_encoder.py l.57: len(used_feature_list) (VoD 7, TJ4D 5)."""
    return len(_config(dataset)["used_feature_list"])


def vfe_keys(dataset: str) -> Tuple[Keys, int]:
    """backbones_3d/vfe/pillar_vfe.py. Input width = 6 (cluster + centre offsets) + 3 (absolute xyz)
    + 1 per enabled radar feature (RadarPillarVFE l.221-249: rcs, v_r, v_r_comp, time;
    RadarPillarVFE_TJ l.64-97: SNR, v_r, range, alpha, beta). One PFNLayer per NUM_FILTERS
    entry (Linear without bias + BatchNorm1d when USE_NORM; a non-last layer halves its width,
    l.355-367). RadarPillarVFE_TJ also builds ``se`` = SELayer_vfe(width), reduction 16
    (model_utils/se_module.py l.22-31) before the PFN layers (l.114)."""
    cfg = _config(dataset)["vfe"]
    width = 6 + (3 if cfg["USE_ABSLOTE_XYZ"] else 0)
    if cfg["NAME"] == "RadarPillarVFE":
        flags = ("USE_RCS", "USE_VR", "USE_VR_COMP", "USE_TIME")
    else:
        flags = ("USE_SNR", "USE_VR", "USE_RANGE", "USE_ALPHA", "USE_BETA")
    width += sum(1 for f in flags if cfg[f])
    keys: Keys = {}
    if cfg["NAME"] == "RadarPillarVFE_TJ":
        hidden = width // 16
        _linear(keys, "vfe.se.fc.0", width, hidden, bias=False)
        _linear(keys, "vfe.se.fc.2", hidden, width, bias=False)
    filters = [width] + list(cfg["NUM_FILTERS"])
    for i in range(len(filters) - 1):
        last = i >= len(filters) - 2
        c_out = filters[i + 1] if last else filters[i + 1] // 2
        _linear(keys, f"vfe.pfn_layers.{i}.linear", filters[i], c_out, bias=not cfg["USE_NORM"])
        if cfg["USE_NORM"]:
            _bn(keys, f"vfe.pfn_layers.{i}.norm", c_out)
    return keys, filters[-1]


def map_to_bev_keys() -> Tuple[Keys, int]:
    """backbones_2d/map_to_bev/pointpillar_scatter.py: PointPillarScatter_spa (l.44-54) builds
    PillarAttentionWithRoPE(pillar_dim=64, hidden_dim=64) when IS_SPA (l.92-113): q/k/v Linear,
    ffn Linear-GELU-Linear, two LayerNorms. Returns NUM_BEV_FEATURES."""
    cfg = COMMON["MAP_TO_BEV"]
    keys: Keys = {}
    if cfg["IS_SPA"]:
        p = "map_to_bev_module.pillar_attention_rope"
        dim = hidden = 64  # hard-coded at l.52-53, not read from the config
        for name in ("q_mlp", "k_mlp", "v_mlp"):
            _linear(keys, f"{p}.{name}", dim, hidden)
        _linear(keys, f"{p}.ffn.0", hidden, hidden)
        _linear(keys, f"{p}.ffn.2", hidden, dim)
        _ln(keys, f"{p}.norm1", dim)
        _ln(keys, f"{p}.norm2", dim)
    return keys, cfg["NUM_BEV_FEATURES"]


def image_backbone_keys() -> Keys:
    """backbones_image/CQCA_cfa.py l.53-63: Sequential of Conv2d(3->16->32->64, 3x3, no bias),
    each followed by BatchNorm2d and ReLU (indices 0/1, 3/4, 6/7)."""
    keys: Keys = {}
    chans = [3, 16, 32, 64]
    for i in range(3):
        _conv(keys, f"image_backbone.conv.{3 * i}", chans[i], chans[i + 1], (3, 3), bias=False)
        _bn(keys, f"image_backbone.conv.{3 * i + 1}", chans[i + 1])
    return keys


def fuser_keys() -> Tuple[Keys, int]:
    """backbones_2d/fuser/CQCA_caf.py. CQCA_caf (l.354-367): crossfusion =
    TransformerFusionBlock(IN_CHANNEL_CROSS) with its defaults 16 x 16 anchors, h=8, block_exp=4,
    n_layer=1; se = SELayer(IN_CHANNEL_CROSS) (fuser/se_module.py, reduction 16); conv =
    Conv2d(IN_CHANNEL -> OUT_CHANNEL, 3x3, no bias) + BatchNorm2d + ReLU.

    TransformerFusionBlock (l.268-306): pos_emb_vis/pos_emb_ir (1, 256, d); avg/max
    AdaptivePool2d (no tensors); bev_embedder = ImageEmbedder(dim=d, image_size=320,
    patch_size=20, channels=d) (l.231-253: LayerNorm(d*400), Linear(d*400 -> d), LayerNorm(d),
    pos_embedding (1, 257, d)); vis_/ir_coefficient = LearnableWeights (w1, w2 of shape (1,));
    crosstransformer.0 = CrossTransformerBlock (l.167-212: ln_input, ln_output, crossatt,
    mlp_vis / mlp_ir / mlp = Linear(d -> 4d), GELU, Linear(4d -> d), Dropout; LN1, LN2;
    coefficient1..8 = LearnableCoefficient with ``bias`` (1,)); CrossAttention (l.40-84):
    dpb = DynamicPositionBias(d // 4) (l.24-37: Linear(2->c), LN, ReLU, Linear(c->c), LN, ReLU,
    Linear(c->c), LN, ReLU, Linear(c->1)), que/key/val_proj_vis and _ir and out_proj_vis/_ir all
    Linear(d -> d) (h * d/h = d), LN1, LN2."""
    cfg = COMMON["FUSER"]
    d = cfg["IN_CHANNEL_CROSS"]
    anchors, block_exp, patch, image = 16 * 16, 4, 20, 320
    keys: Keys = {}
    p = "fuser.crossfusion"
    keys[f"{p}.pos_emb_vis"] = (1, anchors, d)
    keys[f"{p}.pos_emb_ir"] = (1, anchors, d)
    e = f"{p}.bev_embedder"
    keys[f"{e}.pos_embedding"] = (1, (image // patch) ** 2 + 1, d)
    _ln(keys, f"{e}.to_patch_embedding.1", d * patch * patch)
    _linear(keys, f"{e}.to_patch_embedding.2", d * patch * patch, d)
    _ln(keys, f"{e}.to_patch_embedding.3", d)
    for name in ("vis_coefficient", "ir_coefficient"):
        keys[f"{p}.{name}.w1"] = (1,)
        keys[f"{p}.{name}.w2"] = (1,)
    b = f"{p}.crosstransformer.0"
    _ln(keys, f"{b}.ln_input", d)
    _ln(keys, f"{b}.ln_output", d)
    a = f"{b}.crossatt"
    c = d // 4
    _linear(keys, f"{a}.dpb.0", 2, c)
    _ln(keys, f"{a}.dpb.1", c)
    _linear(keys, f"{a}.dpb.3", c, c)
    _ln(keys, f"{a}.dpb.4", c)
    _linear(keys, f"{a}.dpb.6", c, c)
    _ln(keys, f"{a}.dpb.7", c)
    _linear(keys, f"{a}.dpb.9", c, 1)
    for name in (
        "que_proj_vis",
        "key_proj_vis",
        "val_proj_vis",
        "que_proj_ir",
        "key_proj_ir",
        "val_proj_ir",
        "out_proj_vis",
        "out_proj_ir",
    ):
        _linear(keys, f"{a}.{name}", d, d)
    _ln(keys, f"{a}.LN1", d)
    _ln(keys, f"{a}.LN2", d)
    for name in ("mlp_vis", "mlp_ir", "mlp"):
        _linear(keys, f"{b}.{name}.0", d, block_exp * d)
        _linear(keys, f"{b}.{name}.2", block_exp * d, d)
    _ln(keys, f"{b}.LN1", d)
    _ln(keys, f"{b}.LN2", d)
    for i in range(1, 9):
        keys[f"{b}.coefficient{i}.bias"] = (1,)
    _linear(keys, "fuser.se.fc.0", d, d // 16, bias=False)
    _linear(keys, "fuser.se.fc.2", d // 16, d, bias=False)
    _conv(keys, "fuser.conv.0", cfg["IN_CHANNEL"], cfg["OUT_CHANNEL"], (3, 3), bias=False)
    _bn(keys, "fuser.conv.1", cfg["OUT_CHANNEL"])
    return keys, cfg["OUT_CHANNEL"]


# fuser keys with no effect on CQCA_caf's output in eval mode (CQCA_caf.py): the fusion block
# returns only the pillar ("ir") branch (l.351), so everything that only feeds the image ("vis")
# branch after the cross attention is dead; the dynamic position bias is computed but never added
# (l.146-149); bev_embedder is only referenced in commented-out lines (l.327, l.333); ln_input,
# ln_output, block LN1 and ``mlp`` are never called; with n_layer=1 the block's rgb output
# (coefficient1/2/5/6, mlp_vis) is dropped. Prefixes, matched against the key names.
FUSER_KEYS_WITHOUT_EFFECT_PREFIXES = (
    "fuser.crossfusion.bev_embedder.",  # l.290, uses commented out
    "fuser.crossfusion.crosstransformer.0.ln_input.",  # l.178, never called
    "fuser.crossfusion.crosstransformer.0.ln_output.",  # l.179, never called
    "fuser.crossfusion.crosstransformer.0.LN1.",  # l.201, never called
    "fuser.crossfusion.crosstransformer.0.mlp.",  # l.193, never called
    "fuser.crossfusion.crosstransformer.0.mlp_vis.",  # l.226, rgb output only
    "fuser.crossfusion.crosstransformer.0.coefficient1.",  # l.224, rgb output only
    "fuser.crossfusion.crosstransformer.0.coefficient2.",  # l.224
    "fuser.crossfusion.crosstransformer.0.coefficient5.",  # l.226
    "fuser.crossfusion.crosstransformer.0.coefficient6.",  # l.226
    "fuser.crossfusion.crosstransformer.0.crossatt.dpb.",  # l.146-149, bias computed, never added
    "fuser.crossfusion.crosstransformer.0.crossatt.key_proj_vis.",  # l.125 -> att_vis (l.138)
    "fuser.crossfusion.crosstransformer.0.crossatt.val_proj_vis.",  # l.127 -> out_vis (l.157)
    "fuser.crossfusion.crosstransformer.0.crossatt.que_proj_ir.",  # l.131 -> att_vis (l.138)
    "fuser.crossfusion.crosstransformer.0.crossatt.out_proj_vis.",  # l.159 -> out_vis
)


def fuser_keys_without_effect() -> list:
    """The fuser.* keys whose values cannot change CQCA_caf's eval-mode output."""
    keys, _ = fuser_keys()
    return [k for k in keys if k.startswith(FUSER_KEYS_WITHOUT_EFFECT_PREFIXES)]


def backbone_2d_keys(input_channels: int, cfg: dict | None = None) -> Tuple[Keys, int]:
    """backbones_2d/base_bev_backbone.py l.29-84: block i = ZeroPad2d, Conv2d(c_in -> f_i, 3x3,
    stride s_i, no bias), BN, ReLU, then LAYER_NUMS[i] x (Conv2d 3x3 no bias, BN, ReLU); deblock
    i (stride >= 1) = ConvTranspose2d(f_i -> u_i, k = stride, no bias), BN, ReLU. Returns
    sum(NUM_UPSAMPLE_FILTERS)."""
    cfg = cfg or COMMON["BACKBONE_2D"]
    keys: Keys = {}
    filters = cfg["NUM_FILTERS"]
    c_in = [input_channels, *filters[:-1]]
    for i, n in enumerate(cfg["LAYER_NUMS"]):
        _conv(keys, f"backbone_2d.blocks.{i}.1", c_in[i], filters[i], (3, 3), bias=False)
        _bn(keys, f"backbone_2d.blocks.{i}.2", filters[i])
        for k in range(n):
            _conv(keys, f"backbone_2d.blocks.{i}.{4 + 3 * k}", filters[i], filters[i], (3, 3), bias=False)
            _bn(keys, f"backbone_2d.blocks.{i}.{5 + 3 * k}", filters[i])
    for i, (stride, up) in enumerate(zip(cfg["UPSAMPLE_STRIDES"], cfg["NUM_UPSAMPLE_FILTERS"])):
        assert stride >= 1
        _conv_transpose(keys, f"backbone_2d.deblocks.{i}.0", filters[i], up, stride)
        _bn(keys, f"backbone_2d.deblocks.{i}.1", up)
    return keys, sum(cfg["NUM_UPSAMPLE_FILTERS"])


def dense_head_keys(dataset: str, input_channels: int) -> Keys:
    """dense_heads/anchor_head_single.py l.73-91: A = sum of anchors per location over classes
    (anchor_generator.py l.32); conv_cls 1x1 -> A * num_class, conv_box -> A * code_size (7),
    conv_dir_cls -> A * NUM_DIR_BINS, all with bias."""
    cfg = COMMON["DENSE_HEAD"]
    num_class = 1 if cfg["CLASS_AGNOSTIC"] else len(_config(dataset)["class_names"])
    a = sum(r * s * h for r, s, h in _config(dataset)["anchor_sets"])
    keys: Keys = {}
    _conv(keys, "dense_head.conv_cls", input_channels, a * num_class, (1, 1), bias=True)
    _conv(keys, "dense_head.conv_box", input_channels, a * cfg["CODE_SIZE"], (1, 1), bias=True)
    if cfg["USE_DIRECTION_CLASSIFIER"]:
        _conv(keys, "dense_head.conv_dir_cls", input_channels, a * cfg["NUM_DIR_BINS"], (1, 1), bias=True)
    return keys


def pfe_keys(dataset: str, num_bev_features1: int) -> Tuple[Keys, int, int]:
    """backbones_3d/pfe/voxel_set_abstraction.py VoxelSetAbstraction_cda l.587-636.
    c_in = BEV channels (FUSER.OUT_CHANNEL, via MAFF_Net.py l.36/47) + SA_clusterpoints output
    (on num_rawpoint_features - 3 channels); vsa_point_feature_fusion = Linear(c_in -> 128, no
    bias), BatchNorm1d, ReLU. Returns (keys, num_point_features, num_point_features_before_fusion)."""
    cfg = COMMON["PFE"]
    keys: Keys = {}
    c_in = 0
    if "bev" in cfg["FEATURES_SOURCE"]:
        c_in += num_bev_features1
    if "cluster_points" in cfg["FEATURES_SOURCE"]:
        c_in += _stack_sa_msg(
            keys, "pfe.SA_clusterpoints", num_rawpoint_features(dataset) - 3, cfg["SA_LAYER"]["cluster_points"]["MLPS"]
        )
    out = cfg["NUM_OUTPUT_FEATURES"]
    _linear(keys, "pfe.vsa_point_feature_fusion.0", c_in, out, bias=False)
    _bn(keys, "pfe.vsa_point_feature_fusion.1", out)
    return keys, out, c_in


def point_head_keys(dataset: str, input_channels: int) -> Keys:
    """dense_heads/point_head_template.py make_fc_layers l.36-47: per CLS_FC entry Linear (no bias),
    BatchNorm1d, ReLU; then Linear(-> num_class) with bias. CLASS_AGNOSTIC -> 1 class."""
    cfg = COMMON["POINT_HEAD"]
    num_class = 1 if cfg["CLASS_AGNOSTIC"] else len(_config(dataset)["class_names"])
    keys: Keys = {}
    c = input_channels
    for k, width in enumerate(cfg["CLS_FC"]):
        _linear(keys, f"point_head.cls_layers.{3 * k}", c, width, bias=False)
        _bn(keys, f"point_head.cls_layers.{3 * k + 1}", width)
        c = width
    _linear(keys, f"point_head.cls_layers.{3 * len(cfg['CLS_FC'])}", c, num_class)
    return keys


def _roi_fc(keys: Keys, prefix: str, c: int, fc_list, out: int, dp_ratio: float) -> None:
    """roi_head_template.py make_fc_layers l.29-43: Conv1d 1x1 (no bias), BN1d, ReLU per entry, a
    Dropout after the first entry when DP_RATIO >= 0, then Conv1d(-> out) with bias."""
    idx = 0
    for k, width in enumerate(fc_list):
        _conv(keys, f"{prefix}.{idx}", c, width, (1,), bias=False)
        _bn(keys, f"{prefix}.{idx + 1}", width)
        idx += 3
        if dp_ratio >= 0 and k == 0:
            idx += 1
        c = width
    _conv(keys, f"{prefix}.{idx}", c, out, (1,), bias=True)


def roi_head_keys(dataset: str, input_channels: int) -> Keys:
    """roi_heads/pvrcnn_head.py l.13-41: roi_grid_pool_layer = StackSAModuleMSG on the pfe's
    point features (input_channels = 128, + 3 xyz); pre_channel = GRID_SIZE**3 * its output;
    shared_fc_layer = Conv1d(no bias), BN1d, ReLU per SHARED_FC entry with a Dropout after every
    entry but the last (DP_RATIO > 0); cls_layers / reg_layers via make_fc_layers, outputs
    num_class (1, class agnostic) and code_size * num_class (7)."""
    cfg = COMMON["ROI_HEAD"]
    keys: Keys = {}
    num_class = 1 if cfg["CLASS_AGNOSTIC"] else len(_config(dataset)["class_names"])
    c_out = _stack_sa_msg(keys, "roi_head.roi_grid_pool_layer", input_channels, cfg["ROI_GRID_POOL"]["MLPS"])
    c = cfg["ROI_GRID_POOL"]["GRID_SIZE"] ** 3 * c_out
    idx = 0
    n = len(cfg["SHARED_FC"])
    for k, width in enumerate(cfg["SHARED_FC"]):
        _conv(keys, f"roi_head.shared_fc_layer.{idx}", c, width, (1,), bias=False)
        _bn(keys, f"roi_head.shared_fc_layer.{idx + 1}", width)
        idx += 3
        if k != n - 1 and cfg["DP_RATIO"] > 0:
            idx += 1
        c = width
    _roi_fc(keys, "roi_head.cls_layers", c, cfg["CLS_FC"], num_class, cfg["DP_RATIO"])
    _roi_fc(keys, "roi_head.reg_layers", c, cfg["REG_FC"], cfg["CODE_SIZE"] * num_class, cfg["DP_RATIO"])
    return keys


# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------


def upstream_state_dict_shapes(dataset: str, stage_two: bool = True) -> Dict[str, Tuple[int, ...]]:
    """Every key of ``model.state_dict()`` of upstream's MAFF_Net built from the ``dataset``
    ('vod' or 'tj4d', or a dict as :func:`_config` takes) config, with its shape, in state_dict order.

    Upstream always has the second stage (MAFF_Net.forward runs pfe, point_head and roi_head
    unconditionally); ``stage_two=False`` gives the keys of radaredge's stage-one-only card,
    i.e. the same dict without the ``pfe.*``, ``point_head.*`` and ``roi_head.*`` keys.
    """
    _config(dataset)
    keys: Keys = {"global_step": (1,)}  # detector3d_template.py l.20
    vfe, _ = vfe_keys(dataset)
    keys.update(vfe)
    bev, num_bev_features = map_to_bev_keys()
    keys.update(bev)
    keys.update(image_backbone_keys())
    fuser, num_bev_features1 = fuser_keys()
    keys.update(fuser)
    # backbone_2d reads num_bev_features = map_to_bev's NUM_BEV_FEATURES (the fuser does not change
    # it in model_info_dict); the fused map has OUT_CHANNEL = 64 channels too.
    b2d, num_bev_2d = backbone_2d_keys(num_bev_features, _config(dataset).get("BACKBONE_2D"))
    keys.update(b2d)
    keys.update(dense_head_keys(dataset, num_bev_2d))
    if stage_two:
        pfe, num_point_features, before_fusion = pfe_keys(dataset, num_bev_features1)
        keys.update(pfe)
        use_before = COMMON["POINT_HEAD"]["USE_POINT_FEATURES_BEFORE_FUSION"]
        keys.update(point_head_keys(dataset, before_fusion if use_before else num_point_features))
        keys.update(roi_head_keys(dataset, num_point_features))
    return keys


def upstream_state_dict(dataset: str, stage_two: bool = True, seed: int = 0) -> Dict[str, torch.Tensor]:
    """A random state_dict with upstream's keys and shapes: float32 normal values for parameters
    and running means, positive running variances, int64 ``num_batches_tracked`` scalars and an
    int64 ``global_step`` of shape (1,)."""
    g = torch.Generator().manual_seed(seed)
    state: Dict[str, torch.Tensor] = {}
    for key, shape in upstream_state_dict_shapes(dataset, stage_two).items():
        if key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(int(torch.randint(1, 100000, (), generator=g)), dtype=torch.int64)
        elif key == "global_step":
            state[key] = torch.randint(1, 100000, shape, generator=g, dtype=torch.int64)
        elif key.endswith("running_var"):
            state[key] = torch.rand(shape, generator=g) + 0.5
        else:
            state[key] = torch.randn(shape, generator=g)
    return state


# Upstream's last layers of each head, initialised small in upstream (OpenPCDet's init_weights):
# the box, direction and class convolutions of the dense head and the roi/point heads' outputs.
HEAD_OUTPUTS = (
    "dense_head.conv_box.",
    "dense_head.conv_dir_cls.",
    "dense_head.conv_cls.",
    "roi_head.reg_layers.",
    "roi_head.cls_layers.",
    "point_head.cls_layers.",
)


def trained_like_state_dict(dataset: str, stage_two: bool = True, seed: int = 0) -> Dict[str, torch.Tensor]:
    """A random state_dict with upstream's keys and shapes and the value scales of a trained
    network (unlike :func:`upstream_state_dict`, whose unit-variance weights overflow float32
    through the 13-layer backbone): He-normal weights of rank >= 2 (std sqrt(2 / fan_in)), the
    last layer of each head at std 0.01, normalisation scales 1 + 0.1 N, biases and running means
    0.05 N, running variances uniform in [0.5, 1.5], counters as in :func:`upstream_state_dict`."""
    g = torch.Generator().manual_seed(seed)
    state = upstream_state_dict(dataset, stage_two, seed)
    for key, value in state.items():
        if not value.is_floating_point() or not value.numel():
            continue
        n = torch.randn(value.shape, generator=g)
        if key.endswith("running_var"):
            state[key] = torch.rand(value.shape, generator=g) + 0.5
        elif value.dim() >= 2:
            last = key.startswith(HEAD_OUTPUTS) and (
                key.startswith("dense_head.") or key.rsplit(".", 2)[-2] == str(_last_index(state, key))
            )
            fan_in = value[0].numel()
            state[key] = n * (0.01 if last else math.sqrt(2.0 / max(fan_in, 1)))
        elif key.endswith("weight"):
            state[key] = 1.0 + 0.1 * n
        else:
            state[key] = 0.05 * n
    return state


def _last_index(state: Dict[str, torch.Tensor], key: str) -> int:
    """The highest layer index of the Sequential that ``key`` (``prefix.<i>.weight``) belongs to."""
    prefix = key.rsplit(".", 2)[0]
    return max(
        int(k[len(prefix) + 1 :].split(".")[0])
        for k in state
        if k.startswith(prefix + ".") and k[len(prefix) + 1 :].split(".")[0].isdigit()
    )


def openpcdet_checkpoint(state: Dict[str, torch.Tensor]) -> dict:
    """The dict OpenPCDet's ``checkpoint_state`` saves (tools/train_utils/train_utils.py l.155-171)
    around ``state``, with a small placeholder optimizer state."""
    return {
        "model_state": state,
        "optimizer_state": {
            "state": {},
            "param_groups": [{"lr": 0.01, "betas": (0.95, 0.99), "weight_decay": 0.01, "params": [0]}],
        },
        "epoch": 80,
        "it": 1000,
        "version": "pcdet+0.6.0",
    }


def module_counts(keys) -> Dict[str, int]:
    """Number of keys per top-level module (the part before the first dot)."""
    counts: Dict[str, int] = {}
    for k in keys:
        top = k.split(".", 1)[0]
        counts[top] = counts.get(top, 0) + 1
    return counts
