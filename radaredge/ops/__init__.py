"""The op library: every op that does not export as the papers write it, in two formulations.

Each module holds an *export* formulation, built from fixed-shape tensor ops that trace to ONNX
opset 18 without custom ops, and beside it a *reference* formulation written plainly (Python
loops, numpy, float64 where that removes doubt). A test proves each pair equal; the same test
file also exports the op alone and compares onnxruntime with torch (its ``test_onnx_*`` tests).
docs/ops.md gives the tolerances. The submodules import torch; this package imports none of
them, so ``import radaredge.ops`` stays cheap and torch-free.

Pairs, as ``module``: export <-> reference, then the tests (``tests/``) that prove them equal:

- ``alignment`` (TDFANet eq. 4-5): :func:`~radaredge.ops.alignment.align_bev` <->
  :func:`~radaredge.ops.alignment.align_bev_reference` (four corners via
  ``bilinear_sample_reference``); test_alignment.py ``test_export_matches_reference``,
  ``test_export_matches_reference_on_paper_grid``.
- ``bev_interp`` (PV-RCNN BEV features at points): ``bev_interpolate`` <->
  ``bev_interpolate_reference``; test_set_abstraction.py ``test_bev_interpolate_matches_reference``.
- ``box_iou`` (OpenPCDet ``boxes_iou_bev``): ``bev_iou_paired`` (``bev_overlap_paired``) <->
  ``bev_iou_reference`` (``bev_iou_matrix_reference`` for all pairs); test_box_iou_nms.py
  ``test_iou_matches_reference``.
- ``components`` (8-connected components): ``connected_components`` in ``exact`` and ``maxpool``
  mode <-> ``tests/references/components_ref.union_find_labels`` and ``scipy.ndimage.label``;
  test_components.py ``test_exact_matches_scipy_and_is_canonical``,
  ``test_maxpool_equals_exact_on_small_blobs``.
- ``dbscan`` (sklearn DBSCAN and MAFF-Net's CQCA_cfa map): ``dbscan_labels`` <->
  ``dbscan_labels_reference`` and ``cqca_cfa_map`` <-> ``cqca_cfa_map_reference``, both also
  against sklearn itself (``tests/references/sklearn_cqca_cfa``); test_dbscan.py
  ``test_matches_sklearn_upstream``. ``cqca_cfa_map_sklearn`` (upstream's own steps, the
  baseline that benchmarks/cfa_speedup.py times) <-> ``cqca_cfa_map_reference``;
  test_cfa_speedup.py ``test_cqca_cfa_map_follows_upstream_rules``.
- ``deform_attn`` (Deformable DETR's ``ms_deform_attn``): ``ms_deform_attn``
  (``ms_deform_attn_heads``; ``MSDeformAttn``) <-> ``ms_deform_attn_reference``
  (``MSDeformAttn(..., reference=True)``); test_deform_attn.py ``test_export_matches_reference``,
  ``test_module_reference_path_matches_export_path``.
- ``ego_velocity`` (TDFANet eq. 1-3, RANSAC on Doppler): ``EgoVelocityRansac``
  (``estimate_ego_velocity``; ``estimate_frames`` for a window's K scans at once) <->
  ``estimate_ego_velocity_reference``; test_ego_velocity.py
  ``test_export_formulation_matches_reference``, ``test_scans_at_once_equal_scans_alone``.
- ``gem`` (GeM pooling): ``GeM`` <-> ``gem_reference``; test_gem.py ``test_matches_reference``.
- ``grid_density`` (MAFF-Net GridDensityBEV): ``GridDensityBEV`` <-> ``grid_density_bev_reference``;
  test_grid_density.py ``test_export_formulation_matches_reference``, and against sklearn DBSCAN
  (``tests/references/dbscan_cfa.dbscan_cfa_labels``) ``test_clusters_agree_with_dbscan``.
- ``nms`` (OpenPCDet class-agnostic NMS): ``class_agnostic_nms`` <->
  ``class_agnostic_nms_reference`` (``greedy_nms_reference``); test_box_iou_nms.py
  ``test_nms_matches_reference_in_torch``, ``test_nms_onnx_matches_reference``.
- ``pillar_attention`` (MAFF-Net SPA): ``SparsePillarAttention`` <->
  ``sparse_pillar_attention_reference``; test_pillar_attention.py
  ``test_matches_reference_and_ignores_padding``.
- ``pillars`` (OpenPCDet PillarVFE + scatter): ``PillarFeatureNet`` (``scatter_frames`` for K
  scans at once) <-> ``pillar_scatter_reference`` (``voxelize_reference``,
  ``pillar_features_reference``, ``scatter_pillars_reference``); test_pillars.py
  ``test_matches_dynamic_voxelization_reference``, ``test_scans_at_once_equal_scans_alone``.
- ``point_sampling`` (PointNet++): ``farthest_point_sample``, ``ball_query``, ``group_points``
  <-> their ``*_reference``; test_point_sampling.py ``test_fps_matches_reference``,
  ``test_ball_query_matches_reference``, ``test_group_points_matches_reference``. The masked
  variants ``farthest_point_sample_masked``, ``ball_query_masked`` <-> their ``*_reference``;
  test_set_abstraction.py ``test_masked_fps_matches_reference``,
  ``test_masked_ball_query_matches_reference``.
- ``set_abstraction`` (OpenPCDet StackSAModuleMSG): ``SAModuleMSG.forward`` <->
  ``SAModuleMSG.reference`` (``group_relative_reference``); test_set_abstraction.py
  ``test_sa_module_matches_reference``.

Helpers without a reference of their own, tested through the ops that use them:
``loops.fixed_point_loop`` (the ONNX ``Loop`` of ``nms``, the masked FPS and the full pillars'
peels), ``reduce.any_true`` (an ``any`` that exports right on an empty axis; test_onnx_export.py
``test_any_true_is_false_on_an_empty_axis_in_the_graph``),
``scan_batch.concat_scans`` (K scans as one point set), ``alignment.grid_displacement`` and
``BevGrid`` (test_alignment.py ``test_grid_displacement_follows_eq_4_and_5``),
``components.exact_schedule`` / ``hook_roots`` (shared with ``dbscan``; test_components.py
``test_round_formula``).
"""
