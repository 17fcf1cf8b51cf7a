"""Voxel feature encoders: scatter helpers, mean VFE, pillar feature net (PFN).

All encoders take a :class:`models.voxelize.Voxels` (a point list with a point -> voxel index)
and return per-voxel features ``(V, C)`` aligned with ``voxels.coords``. Hard and dynamic
voxelization therefore share the same encoders: the only difference is which points reach them.

Scatter ops use ``index_add`` (sum, mean) and ``scatter_reduce("amax")``, which the dynamo
exporter turns into ONNX ScatterND / ScatterElements with a reduction.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from models.base import training_form
from models.voxelize import Grid, Voxels, take_rows


def scatter_sum(values: Tensor, index: Tensor, n: int) -> Tensor:
    """(n, C) sums of the rows of values (P, C) grouped by index (P,)."""
    return torch.zeros(n, values.shape[1], dtype=values.dtype).index_add(0, index, values)


def scatter_count(index: Tensor, n: int, dtype=torch.float32) -> Tensor:
    """(n,) number of rows per group."""
    return torch.zeros(n, dtype=dtype).index_add(0, index, torch.ones(index.shape[0], dtype=dtype))


def scatter_mean(values: Tensor, index: Tensor, n: int) -> Tensor:
    """(n, C) means of the rows of values grouped by index (0 for an empty group)."""
    count = scatter_count(index, n, values.dtype).clamp(min=1.0)  # (n,)
    return scatter_sum(values, index, n) / count[:, None]


def scatter_max_nonneg(values: Tensor, index: Tensor, n: int) -> Tensor:
    """(n, C) per-group maxima of NON-NEGATIVE values (e.g. after ReLU); 0 for an empty group.

    Starting from zeros and including them in the max is exact for values >= 0 and matches
    ONNX ScatterElements(reduction="max"), which always includes the initial value.
    """
    out = torch.zeros(n, values.shape[1], dtype=values.dtype)
    idx = index[:, None].expand(-1, values.shape[1])
    return out.scatter_reduce(0, idx, values, "amax", include_self=True)


DENSE_SLOTS = 8  # dynamic voxels: points per voxel that voxel_max_nonneg lays out densely


def voxel_max_nonneg(values: Tensor, voxels: Voxels) -> Tensor:
    """(V, C) per-voxel maxima of NON-NEGATIVE point values (P, C).

    The points are laid out as a dense (V, T, C) tensor by their rank in their voxel
    (``voxels.slot``) and reduced over T: a slot -> point table (scatter of P integers), then one
    row gather, which onnxruntime runs much faster than a per-element ScatterElements max or a
    ScatterND of whole rows. Hard voxels hold at most T = max_points points; for dynamic voxels
    T = DENSE_SLOTS, and the few points beyond (dense voxels near the sensor) are added by
    ScatterElements max. Under autograd the scatter form runs: same values and gradients, and its backward touches P rows
    instead of the V * T slots of the dense layout (a PointPillars training step 1.27x).
    """
    if training_form():
        return scatter_max_nonneg(values, voxels.point2voxel, voxels.num_voxels)
    p2v, v, slot = voxels.point2voxel, voxels.num_voxels, voxels.slot
    if voxels.max_points is not None:
        t = voxels.max_points
        return slot_max(values, p2v * t + slot, torch.arange(values.shape[0], dtype=torch.long), v, t)
    dense = torch.nonzero(slot < DENSE_SLOTS)[:, 0]  # (Q,) points in the dense layout
    rest = torch.nonzero(slot >= DENSE_SLOTS)[:, 0]  # (R,) the others (dense voxels near the sensor)
    out = slot_max(values, take_rows(p2v * DENSE_SLOTS + slot, dense), dense, v, DENSE_SLOTS)  # (V, C)
    idx = take_rows(p2v, rest)[:, None].expand(-1, values.shape[1])  # (R, C)
    return out.scatter_reduce(0, idx, take_rows(values, rest), "amax", include_self=True)


def slot_max(values: Tensor, cells: Tensor, points: Tensor, num_voxels: int, t: int) -> Tensor:
    """(V, C) maxima of values (P, C) >= 0 laid out densely as (V, T, C): row ``points`` (Q,) of
    values fills cell ``cells`` (Q,) = voxel * T + slot; empty cells read a zero row."""
    p, c = values.shape
    rows = torch.full((num_voxels * t,), p, dtype=torch.long).scatter(0, cells, points)  # (V * T,)
    padded = torch.cat([values, values.new_zeros(1, c)])  # (P + 1, C)
    dense = torch.index_select(padded, 0, rows)  # (V * T, C)
    return dense.reshape(-1, t, c).amax(dim=1)


class RowBatchNorm(nn.BatchNorm1d):
    """BatchNorm1d over rows (P, C) whose inference form is a plain affine map, so that a
    data-dependent number of rows exports (F.batch_norm guards on the size). Training with fewer
    than two rows (a RoI grid with one occupied cell) normalises with the running statistics."""

    def forward(self, x: Tensor) -> Tensor:
        if self.training and x.shape[0] < 2:
            return nn.functional.batch_norm(x, self.running_mean, self.running_var, self.weight, self.bias,
                                            False, 0.0, self.eps)
        if self.training:
            return super().forward(x)
        scale = self.weight / torch.sqrt(self.running_var + self.eps)  # (C,)
        return x * scale + (self.bias - self.running_mean * scale)


class MeanVFE(nn.Module):
    """Voxel feature = mean of its points (x, y, z, intensity). No parameters."""

    out_channels = 4

    def forward(self, voxels: Voxels) -> Tensor:
        return scatter_mean(voxels.points[:, :4], voxels.point2voxel, voxels.num_voxels)  # (V, 4)


def decorate_points(voxels: Voxels, grid: Grid) -> Tensor:
    """(P, 10) points decorated as PointPillars does: ``[x, y, z, i, x - x_m, y - y_m, z - z_m,
    x - x_c, y - y_c, z - z_c]`` (``_m``: mean of the voxel's points, ``_c``: the voxel centre)."""
    pts, p2v = voxels.points, voxels.point2voxel
    mean = scatter_mean(pts[:, :3], p2v, voxels.num_voxels)  # (V, 3) metres
    centre = take_rows(grid.centres(voxels.coords), p2v)  # (P, 3) metres
    return torch.cat([pts[:, :4], pts[:, :3] - take_rows(mean, p2v), pts[:, :3] - centre], dim=1)


class PillarVFE(nn.Module):
    """PointPillars' pillar feature net.

    Each point is decorated to 10 channels ``[x, y, z, i, x - x_m, y - y_m, z - z_m, x - x_c,
    y - y_c, z - z_c]`` (``_m``: mean of the pillar's points, ``_c``: the pillar centre), then
    Linear -> BatchNorm -> ReLU, and max-pooled over the pillar's points.
    """

    def __init__(self, grid: Grid, out_channels: int = 64):
        super().__init__()
        self.grid = grid
        self.out_channels = out_channels
        self.linear = nn.Linear(10, out_channels, bias=False)
        self.norm = RowBatchNorm(out_channels, eps=1e-3, momentum=0.01)

    def decorate(self, voxels: Voxels) -> Tensor:
        """(P, 10) decorated points."""
        return decorate_points(voxels, self.grid)

    def forward(self, voxels: Voxels) -> Tensor:
        feats = torch.relu(self.norm(self.linear(self.decorate(voxels))))  # (P, C)
        return voxel_max_nonneg(feats, voxels)  # (V, C)
