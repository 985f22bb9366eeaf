"""PointPillars feature net + scatter to a BEV canvas, as OpenPCDet's PillarVFE computes it.

Per point (columns as the model card names them, x, y, z first, radar frame, metres) the net
builds the raw features plus 6 offsets: to the mean xyz of its pillar's points (f_cluster) and
to the centre of its pillar (f_center, z relative to the single vertical voxel's centre), then
Linear (no bias) -> BatchNorm1d -> ReLU, and takes the max over the pillar's point slots. As
upstream, a pillar holding fewer than ``max_points_per_pillar`` points also takes the max with
the value of an all-zero padding slot, relu(BN(0)).

Canvas layout (OpenPCDet's PointPillarScatter): [C, ny, nx], row = y cell, column = x cell, cell
(iy, ix) covering x in [x_min + ix*vx, x_min + (ix+1)*vx), likewise y.

Training formulation (:meth:`PillarFeatureNet.pillars`): the same pillars, only the non-empty
ones, for eager training, whose backward then touches P pillars instead of the whole canvas.

Point policy, identical in every formulation:
- a point is kept when its voxel coordinate floor((p - min) / voxel) lies inside the grid on
  all three axes (half-open range [min, max)); points outside are dropped, never wrapped;
- non-finite points and points with ``valid`` False are dropped;
- within a pillar the first ``max_points_per_pillar`` points in input order are kept, later
  ones are dropped (the spconv/OpenPCDet voxel generator's rule);
- the export formulation never drops whole pillars: its canvas holds every cell. The reference
  keeps OpenPCDet's ``max_pillars`` cap, which defaults to the number of grid cells, so the two
  agree; a smaller cap is reported by :func:`voxelize_reference` as a CapacityError.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..config import card_ranges, positive
from ..errors import CapacityError
from .loops import fixed_point_loop
from .reduce import any_true

MAX_GRID_CELLS = 2**22  # BEV cells (x * y * z) a card may ask for: 4.2 M
# One frame's BEV map (x * y cells x out_channels float32) a card may ask for: the networks keep
# several maps of this size and a few times it in their widest layers, so a card past it fails
# to allocate at run time (a 0.05 m grid did, after exporting), and is refused when read instead.
MAX_BEV_BYTES = 256 * 2**20


@card_ranges(
    point_cloud_range=(-1000.0, 1000.0),
    voxel_size=positive(100.0),
    max_points_per_pillar=(1, 1024),
    max_pillars=(0, 2**22),
    out_channels=(1, 4096),
    bn_eps=positive(1.0),
)
@dataclass(frozen=True)
class PillarConfig:
    """Model-card section ``pillars`` (metres)."""

    point_cloud_range: tuple = (0.0, -39.68, -3.0, 69.12, 39.68, 10.0)  # x_min y_min z_min x_max y_max z_max
    voxel_size: tuple = (0.32, 0.32, 13.0)
    max_points_per_pillar: int = 32
    max_pillars: int = 0  # reference only; 0 = one per grid cell (no cap)
    out_channels: int = 64
    bn_eps: float = 1e-3  # OpenPCDet PFNLayer BatchNorm1d(eps=1e-3, momentum=0.01)

    def __post_init__(self):
        if len(self.point_cloud_range) != 6 or len(self.voxel_size) != 3:
            raise ValueError("point_cloud_range needs 6 values and voxel_size 3")
        lo, hi = self.point_cloud_range[:3], self.point_cloud_range[3:]
        if not all(a < b for a, b in zip(lo, hi)):
            raise ValueError(
                f"point_cloud_range must be [x_min, y_min, z_min, x_max, y_max, z_max] with each "
                f"min < max, got {list(self.point_cloud_range)}"
            )
        if not all(v > 0 for v in self.voxel_size):  # (NaN too) before the grid divides by them
            raise ValueError(f"voxel_size entries must be > 0, got {list(self.voxel_size)}")
        if min(self.grid_size) < 1:
            raise ValueError(f"voxel_size {list(self.voxel_size)} is larger than the point_cloud_range it divides")
        cells = math.prod(self.grid_size)
        if cells > MAX_GRID_CELLS:
            raise ValueError(f"point_cloud_range / voxel_size make {cells} grid cells; at most {MAX_GRID_CELLS}")
        bev = self.grid_size[0] * self.grid_size[1] * self.out_channels * 4
        if bev > MAX_BEV_BYTES:
            raise ValueError(
                f"a {self.grid_size[0]} x {self.grid_size[1]} grid of {self.out_channels} channels is "
                f"a {bev / 2**20:.0f} MiB BEV map per frame; at most {MAX_BEV_BYTES // 2**20} MiB "
                f"(coarser voxel_size, a smaller range or fewer out_channels)"
            )
        if self.max_points_per_pillar < 1:
            raise ValueError("max_points_per_pillar must be >= 1")

    @property
    def grid_size(self) -> tuple[int, int, int]:
        """(nx, ny, nz) cells."""
        r, v = self.point_cloud_range, self.voxel_size
        return tuple(int(round((r[i + 3] - r[i]) / v[i])) for i in range(3))


@dataclass(frozen=True)
class SlotMoments:
    """Moments of a PFN layer's input over OpenPCDet's padded point slots of one or more scans
    (float64): ``sum_x`` [F] and ``sum_xx`` [F, F] over the points (a padding slot is an all-zero
    row and adds nothing), ``slots`` the number of slots, padding included. Scans add up."""

    sum_x: torch.Tensor
    sum_xx: torch.Tensor
    slots: float

    def __add__(self, other: "SlotMoments") -> "SlotMoments":
        return SlotMoments(self.sum_x + other.sum_x, self.sum_xx + other.sum_xx, self.slots + other.slots)


class PFNLayer(nn.Module):
    """Linear (no bias) + BatchNorm1d + ReLU; names match OpenPCDet (``linear``, ``norm``)."""

    def __init__(self, in_channels: int, out_channels: int, eps: float):
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels, bias=False)
        self.norm = nn.BatchNorm1d(out_channels, eps=eps, momentum=0.01)
        self._batch: list | None = None  # [SlotMoments, running statistics updated] in batch_statistics

    @contextlib.contextmanager
    def batch_statistics(self, moments: SlotMoments):
        """Within the block, train-mode :meth:`forward_slots` normalises with the statistics of
        the batch whose input moments are ``moments`` instead of the scan's own: OpenPCDet's
        BatchNorm1d over every slot of every scan of a batch, for scans run one at a time. The
        linear has no bias, so the batch's mean and variance of its output are exact functions
        of ``moments`` and the weight, and the gradient flows through them to the weight as it
        does upstream. The running statistics update once in the block, as for one batch."""
        self._batch = [moments, False]
        try:
            yield
        finally:
            self._batch = None

    def _statistics(self, y: torch.Tensor, weight: torch.Tensor, slots: torch.Tensor):
        """(mean [out], biased variance [out], rows [] float, update the running statistics):
        the scan's own over its slots, or the batch's inside :meth:`batch_statistics`."""
        if self._batch is None:
            w = weight.to(y.dtype).unsqueeze(1)
            rows = torch.clamp(slots.to(y.dtype), min=2.0)
            mean = (y * w).sum(0) / rows
            return mean, torch.clamp((y * y * w).sum(0) / rows - mean * mean, min=0.0), rows, True
        moments, counted = self._batch
        self._batch[1] = True
        rows = max(moments.slots, 2.0)
        w64 = self.linear.weight.to(torch.float64)
        mean = w64 @ (moments.sum_x / rows)
        var = torch.clamp(((w64 @ (moments.sum_xx / rows)) * w64).sum(1) - mean * mean, min=0.0)
        return mean.to(y.dtype), var.to(y.dtype), torch.tensor(rows, dtype=y.dtype, device=y.device), not counted

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [..., in] -> [..., out]: every row is a slot of the batch (train-mode statistics over all rows)."""
        shape = x.shape
        y = self.linear(x.reshape(-1, shape[-1]))
        return torch.relu(self.norm(y)).reshape(*shape[:-1], y.shape[-1])

    def forward_slots(
        self, x: torch.Tensor, weight: torch.Tensor, slots: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The points of padded pillars without the padding: x [N, in] (rows with ``weight`` 0 are
        not points), ``slots`` [] the number of pillar slots the points occupy, OpenPCDet's
        pillars x ``max_points_per_pillar``. Returns (per-point output [N, out], the output of an
        all-zero padding slot [1, out]).

        In eval mode the norm uses its running statistics, as :meth:`forward`. In train mode its
        batch statistics are those of OpenPCDet's padded [pillars, slots] tensor: the points'
        linear outputs plus ``slots - sum(weight)`` zero rows (a padding slot is an all-zero input
        and the linear has no bias), or the batch's in :meth:`batch_statistics`, and the running
        statistics are updated from them as BatchNorm1d would (unbiased variance)."""
        y = self.linear(x)
        zero = torch.zeros(1, y.shape[1], dtype=y.dtype, device=y.device)
        if not self.norm.training:
            return torch.relu(self.norm(y)), torch.relu(self.norm(zero))
        mean, var, rows, update = self._statistics(y, weight, slots)
        norm = self.norm
        if norm.track_running_stats and update:
            with torch.no_grad():
                norm.num_batches_tracked.add_(1)
                # momentum None: the cumulative average, as BatchNorm1d keeps it
                m = 1.0 / float(norm.num_batches_tracked) if norm.momentum is None else norm.momentum
                norm.running_mean.mul_(1 - m).add_(m * mean.detach())
                norm.running_var.mul_(1 - m).add_(m * var.detach() * rows / (rows - 1))
        scale = norm.weight / torch.sqrt(var + norm.eps)
        shift = norm.bias - mean * scale
        return torch.relu(y * scale + shift), torch.relu(zero * scale + shift)


def _voxel_coords(xyz: torch.Tensor, config: PillarConfig) -> torch.Tensor:
    """Integer voxel coordinates (ix, iy, iz) [N, 3] in float32 arithmetic (shared by both paths)."""
    lo = torch.tensor(config.point_cloud_range[:3], dtype=torch.float32, device=xyz.device)
    size = torch.tensor(config.voxel_size, dtype=torch.float32, device=xyz.device)
    return torch.floor((xyz - lo) / size).to(torch.int64)


def _centre_offsets(xyz: torch.Tensor, coords: torch.Tensor, config: PillarConfig) -> torch.Tensor:
    """Offset of each point to the centre of its voxel, [N, 3] metres."""
    lo = torch.tensor(config.point_cloud_range[:3], dtype=torch.float32, device=xyz.device)
    size = torch.tensor(config.voxel_size, dtype=torch.float32, device=xyz.device)
    return xyz - (coords.to(torch.float32) * size + (size / 2 + lo))


def outside_grid(points: torch.Tensor, config: PillarConfig) -> torch.Tensor:
    """[N] bool: finite points whose voxel lies outside the grid (the points every formulation drops)."""
    finite = torch.isfinite(points).all(1)
    coords = _voxel_coords(torch.where(finite.unsqueeze(1), points, torch.zeros_like(points))[:, :3], config)
    size = torch.tensor(config.grid_size, dtype=torch.int64, device=points.device)
    return finite & ~((coords >= 0) & (coords < size)).all(1)


class PillarFeatureNet(nn.Module):
    """Export formulation: fixed-shape pillar encoding of one scan for any N (dynamic axis).

    forward(points [N, F] float32, valid [N] bool) -> canvas [C, ny, nx]. ``pfn_layers.0`` holds
    the weights under OpenPCDet's names so ``vfe.pfn_layers.0.linear.weight`` loads directly.
    """

    def __init__(self, num_point_features: int, config: PillarConfig):
        super().__init__()
        self.config = config
        self.num_point_features = num_point_features
        self.pfn_layers = nn.ModuleList([PFNLayer(num_point_features + 6, config.out_channels, config.bn_eps)])

    def encode(self, feats: torch.Tensor) -> torch.Tensor:
        """Point-wise PFN: [..., F + 6] -> [..., C]."""
        return self.pfn_layers[0](feats)

    def forward(self, points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        return self.scatter(points, valid)[0]

    def scatter(
        self, points: torch.Tensor, valid: torch.Tensor, drops: dict | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(canvas [C, ny, nx], occupied [ny * nx] bool: the pillar holds at least one kept point);
        ``drops`` as in :meth:`scatter_frames`."""
        canvas, occupied = self.scatter_frames(points, valid, None, 1, drops)
        return canvas[0], occupied[0]

    def _first_points(self, cell: torch.Tensor, inside: torch.Tensor, spare: int) -> torch.Tensor:
        """[N] bool: the points among the first ``max_points_per_pillar`` of their pillar in input
        order (``cell`` [N] int64, points not ``inside`` in the ``spare`` cell).

        Without a sort (TensorRT's TopK stops at K = 3839): a pillar holding at most
        ``max_points_per_pillar`` points keeps them all; in a fuller pillar the earliest remaining
        point is peeled off ``max_points_per_pillar`` times (a scatter-min per peel, over the
        pillars labelled by the index of their first point), and a point survives the peels
        exactly when that many points of its pillar come before it. The peels are one ONNX Loop
        that runs no round at all for a scan without full pillars, the usual radar scan."""
        n = cell.shape[0]
        dev = cell.device
        cap = self.config.max_points_per_pillar
        pos = torch.arange(n, dtype=torch.int64, device=dev)
        first = torch.full((spare + 1,), n, dtype=torch.int64, device=dev).scatter_reduce(
            0, cell, pos, reduce="amin", include_self=True
        )
        label = first[cell]  # [N] in [0, N): the pillar's id
        held = torch.zeros(n + 1, dtype=torch.float32, device=dev).scatter_add(0, label, inside.to(torch.float32))
        crowded = inside & (held[label] > cap)

        def more(rounds, remaining, keep):
            return (rounds < cap) & any_true(remaining)

        def peel(rounds, remaining, keep):
            # made in the body: OpenVINO's CPU plugin scatters in place into a tensor captured
            # from outside a Loop, so a captured buffer would carry the earlier rounds' heads
            none = torch.full((n + 1,), n, dtype=torch.int64, device=dev)
            head = none.scatter_reduce(
                0, torch.where(remaining, label, n), torch.where(remaining, pos, n), reduce="amin", include_self=True
            )
            peeled = remaining & (head[label] == pos)
            return rounds + 1, remaining & ~peeled, keep | peeled

        start = (torch.zeros((), dtype=torch.int64, device=dev), crowded, inside & ~crowded)
        return fixed_point_loop(more, peel, start, max_rounds=cap)[2]

    def scatter_frames(
        self,
        points: torch.Tensor,
        valid: torch.Tensor,
        frame: torch.Tensor | None,
        count: int,
        drops: dict | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` scans concatenated along N (``frame`` [N] int64: the scan of each point, as
        :func:`radaredge.ops.scan_batch.concat_scans` gives it; None: all scan 0) ->
        (canvases [count, C, ny, nx], occupied [count, ny * nx] bool), each scan's
        canvas exactly as if it were encoded alone. Scan k's pillars are cells k * ny * nx + cell
        of one canvas, so all scans share one sort and one scatter instead of a graph each.
        ``drops``, when given, receives ``full`` [N] bool: the points inside the range left out
        because their pillar already held ``max_points_per_pillar`` points."""
        nx, ny, _ = self.config.grid_size
        ncell = nx * ny
        spare = count * ncell  # the cell of dropped points
        feats, cell, count_per_cell = self._point_outputs(points, valid, frame, count, drops)
        c = feats.shape[1]
        canvas = torch.zeros(spare + 1, c, dtype=feats.dtype, device=points.device).scatter_reduce(
            0, cell.unsqueeze(1).expand(-1, c), feats, reduce="amax", include_self=True
        )
        canvas = canvas[:spare].reshape(count, ncell, c).transpose(1, 2).reshape(count, c, ny, nx)
        return canvas, (count_per_cell[:spare] > 0).reshape(count, ncell)

    def pillars(self, points: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Training formulation of :meth:`scatter` for one scan: only the non-empty pillars,
        (features [P, C], cells [P] int64 ascending, iy * nx + ix). The canvas of :meth:`scatter`
        is zero everywhere else and holds ``features[k]`` at cell ``cells[k]``; the values are
        the same, and so is the gradient (the same max, ties split alike). The max runs over
        P rows instead of every cell, so its backward does not sweep the whole canvas; the
        unique cells make it data-dependent in shape, hence eager training only."""
        nx, ny, _ = self.config.grid_size
        feats, cell, _ = self._point_outputs(points, valid, None, 1, None)
        cells, row = torch.unique(cell, sorted=True, return_inverse=True)
        c = feats.shape[1]
        pillar = torch.zeros(cells.shape[0], c, dtype=feats.dtype, device=points.device).scatter_reduce(
            0, row.unsqueeze(1).expand(-1, c), feats, reduce="amax", include_self=True
        )
        kept = cells < nx * ny  # not the spare cell of dropped points
        return pillar[kept], cells[kept]

    def _point_outputs(
        self, points: torch.Tensor, valid: torch.Tensor, frame: torch.Tensor | None, count: int, drops: dict | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What each point brings to its pillar's max: (features [N, C], its pillar's cell [N] as
        in :meth:`_slot_inputs`, points per cell [cells + 1])."""
        feats, w, cell, count_per_cell, count_at_point, slots = self._slot_inputs(points, valid, frame, count, drops)
        feats, pad_value = self.pfn_layers[0].forward_slots(feats, w, slots)
        feats = feats * w.unsqueeze(1)
        # A pillar with free slots also takes the max with the padding slot's value; max is
        # associative, so each of its points carries that value into the scatter.
        has_free_slots = (count_at_point < self.config.max_points_per_pillar).unsqueeze(1)
        return torch.where(has_free_slots, torch.maximum(feats, pad_value), feats), cell, count_per_cell

    def _slot_inputs(
        self, points: torch.Tensor, valid: torch.Tensor, frame: torch.Tensor | None, count: int, drops: dict | None
    ):
        """The PFN layer's input of :meth:`scatter_frames`: (features [N, F + 6], weight [N] 1 for
        a kept point, cell [N] its pillar (the spare cell ``count * ny * nx`` for a left-out
        point), points per cell [cells + 1], points in the point's pillar [N], slots [] the
        padded slots of the occupied pillars)."""
        cfg = self.config
        nx, ny, nz = cfg.grid_size
        ncell = nx * ny
        spare = count * ncell  # the cell of dropped points
        dev = points.device
        finite = torch.isfinite(points).all(1)
        points = torch.where(finite.unsqueeze(1), points, torch.zeros_like(points))
        xyz = points[:, :3]
        coords = _voxel_coords(xyz, cfg)
        size = torch.tensor([nx, ny, nz], dtype=torch.int64, device=dev)
        inside = valid & finite & ((coords >= 0) & (coords < size)).all(1)
        cell = coords[:, 1] * nx + coords[:, 0]
        if frame is not None:
            cell = cell + frame * ncell
        cell = torch.where(inside, cell, torch.full_like(coords[:, 0], spare))

        keep = self._first_points(cell, inside, spare)
        cell = torch.where(keep, cell, torch.full_like(cell, spare))
        if drops is not None:
            drops["full"] = inside & ~keep

        # Per-pillar statistics are gathered back to the points and everything after runs per
        # point: the graph touches the N points, not the ny * nx cells (dropped points sit in
        # the spare cell, with count 0 and zero features).
        w = keep.to(points.dtype)
        count_per_cell = torch.zeros(spare + 1, dtype=points.dtype, device=dev).scatter_add(0, cell, w)
        sums = torch.zeros(spare + 1, 3, dtype=points.dtype, device=dev).scatter_add(
            0, cell.unsqueeze(1).expand(-1, 3), xyz * w.unsqueeze(1)
        )
        count_at_point = count_per_cell[cell]
        mean = sums[cell] / torch.clamp(count_at_point, min=1.0).unsqueeze(1)
        feats = torch.cat([points, xyz - mean, _centre_offsets(xyz, coords, cfg)], 1)
        # OpenPCDet pads every occupied pillar to max_points_per_pillar slots (train-mode norm statistics).
        slots = (count_per_cell[:spare] > 0).sum() * cfg.max_points_per_pillar
        return feats, w, cell, count_per_cell, count_at_point, slots

    def input_moments(self, points: torch.Tensor, valid: torch.Tensor) -> SlotMoments:
        """The moments of the PFN layer's input over one scan's padded slots (no gradient), for
        :meth:`PFNLayer.batch_statistics` over several scans."""
        with torch.no_grad():
            feats, w, *_, slots = self._slot_inputs(points, valid, None, 1, None)
            x = feats.to(torch.float64) * w.to(torch.float64).unsqueeze(1)
            return SlotMoments(x.sum(0), x.T @ x, float(slots))


def pillar_canvas(features: torch.Tensor, cells: torch.Tensor, ny: int, nx: int) -> torch.Tensor:
    """The canvas [C, ny, nx] holding ``features`` [P, C] at ``cells`` [P] (iy * nx + ix) and 0
    elsewhere, as a view of a [ny * nx, C] tensor (channels last): one index_copy, whose
    backward gathers the P rows."""
    c = features.shape[1]
    flat = torch.zeros(ny * nx, c, dtype=features.dtype, device=features.device).index_copy(0, cells, features)
    return flat.T.reshape(c, ny, nx)


# ----------------------------------------------------------------------------- reference


def voxelize_reference(points: np.ndarray, config: PillarConfig, valid: np.ndarray | None = None):
    """Dynamic voxelization as OpenPCDet's voxel generator does it (numpy, loops).

    Returns (voxels [P, max_points, F] zero-padded, num_points [P], coords [P, 3] as (ix, iy, iz))
    with pillars in order of first appearance and points in input order. Raises CapacityError
    when ``max_pillars`` (> 0) would be exceeded.
    """
    points = np.asarray(points, np.float32)
    nx, ny, nz = config.grid_size
    keep = np.isfinite(points).all(1) if valid is None else (np.asarray(valid, bool) & np.isfinite(points).all(1))
    coords = _voxel_coords(torch.from_numpy(np.where(keep[:, None], points, 0)[:, :3]), config).numpy()
    slots: dict[tuple[int, int, int], list[int]] = {}
    for i in range(len(points)):
        ix, iy, iz = coords[i]
        if not keep[i] or not (0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz):
            continue
        key = (int(ix), int(iy), int(iz))
        if key not in slots:
            if config.max_pillars and len(slots) >= config.max_pillars:
                raise CapacityError(f"scan needs more than max_pillars={config.max_pillars} pillars")
            slots[key] = []
        if len(slots[key]) < config.max_points_per_pillar:
            slots[key].append(i)
    p, f = len(slots), points.shape[1]
    voxels = np.zeros((p, config.max_points_per_pillar, f), np.float32)
    num = np.zeros(p, np.int64)
    vcoords = np.zeros((p, 3), np.int64)
    for k, (key, idx) in enumerate(slots.items()):
        voxels[k, : len(idx)] = points[idx]
        num[k] = len(idx)
        vcoords[k] = key
    return voxels, num, vcoords


def point_drops_reference(points: np.ndarray, config: PillarConfig, valid: np.ndarray | None = None):
    """(outside, full) [N] bool: the finite, valid points outside the grid, and the points inside
    it that arrive after their pillar holds ``max_points_per_pillar`` (input order), by loops."""
    points = np.asarray(points, np.float32)
    nx, ny, nz = config.grid_size
    usable = np.isfinite(points).all(1) if valid is None else (np.asarray(valid, bool) & np.isfinite(points).all(1))
    coords = _voxel_coords(torch.from_numpy(np.where(usable[:, None], points, 0)[:, :3]), config).numpy()
    outside, full = np.zeros(len(points), bool), np.zeros(len(points), bool)
    held: dict[tuple[int, int], int] = {}
    for i in range(len(points)):
        if not usable[i]:
            continue
        ix, iy, iz = (int(c) for c in coords[i])
        if not (0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz):
            outside[i] = True
            continue
        held[(ix, iy)] = held.get((ix, iy), 0) + 1
        full[i] = held[(ix, iy)] > config.max_points_per_pillar
    return outside, full


def pillar_features_reference(net: PillarFeatureNet, points: np.ndarray, valid: np.ndarray | None = None):
    """Reference formulation of the PillarVFE: (pillar features [P, C], coords [P, 3] as (ix, iy, iz))
    for the pillars of :func:`voxelize_reference`, computed on zero-padded pillars as OpenPCDet."""
    cfg = net.config
    voxels, num, coords = voxelize_reference(points, cfg, valid)
    v = torch.from_numpy(voxels)
    n = torch.from_numpy(num).float().clamp(min=1).view(-1, 1, 1)
    mask = (torch.arange(cfg.max_points_per_pillar).view(1, -1) < torch.from_numpy(num).view(-1, 1)).float()
    xyz = v[:, :, :3]
    f_cluster = xyz - xyz.sum(1, keepdim=True) / n
    c = torch.from_numpy(coords).unsqueeze(1).expand(-1, cfg.max_points_per_pillar, -1)
    f_center = _centre_offsets(xyz.reshape(-1, 3), c.reshape(-1, 3), cfg).reshape(xyz.shape)
    feats = torch.cat([v, f_cluster, f_center], -1) * mask.unsqueeze(-1)
    return net.encode(feats).max(1).values, coords


def scatter_pillars_reference(features: torch.Tensor, coords: np.ndarray, config: PillarConfig) -> torch.Tensor:
    """OpenPCDet's PointPillarScatter: pillar features [P, C] at coords (ix, iy, iz) -> canvas [C, ny, nx]."""
    nx, ny, _ = config.grid_size
    canvas = torch.zeros(features.shape[1], ny * nx)
    canvas[:, torch.from_numpy(coords[:, 1] * nx + coords[:, 0])] = features.T
    return canvas.reshape(features.shape[1], ny, nx)


def pillar_scatter_reference(
    net: PillarFeatureNet, points: np.ndarray, valid: np.ndarray | None = None
) -> torch.Tensor:
    """Reference formulation: voxelize, PillarVFE on padded pillars as OpenPCDet, scatter. [C, ny, nx]."""
    pillar, coords = pillar_features_reference(net, points, valid)
    return scatter_pillars_reference(pillar, coords, net.config)
