"""Several scans as one point set, for the ops that process a window's scans in one pass
(:meth:`radaredge.ops.ego_velocity.EgoVelocityRansac.estimate_frames`,
:meth:`radaredge.ops.pillars.PillarFeatureNet.scatter_frames`)."""

from __future__ import annotations

import torch


def concat_scans(scans: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Scans [N_k, F] (any N_k, 0 allowed) -> (points [sum N_k, F] in scan order, frame [sum N_k]
    int64: the index k of the scan each point came from). Traces with dynamic N_k."""
    frame = torch.cat([torch.full((s.shape[0],), k, dtype=torch.int64, device=s.device) for k, s in enumerate(scans)])
    return torch.cat(scans, 0), frame
