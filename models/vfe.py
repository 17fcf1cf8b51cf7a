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


DENSE_SLOTS = 8  # dynamic voxels: points per chunk that voxel_max_nonneg lays out densely
CHUNKS = 8  # dynamic voxels: chunks per voxel laid out densely (DENSE_SLOTS * CHUNKS points)


def voxel_max_nonneg(values: Tensor, voxels: Voxels) -> Tensor:
    """(V, C) per-voxel maxima of NON-NEGATIVE point values (P, C).

    The points are laid out as a dense (V, T, C) tensor by their rank in their voxel
    (``voxels.slot``) and reduced over T: a slot -> point table (scatter of P integers), then one
    row gather, which onnxruntime runs much faster than a per-element ScatterElements max or a
    ScatterND of whole rows. Hard voxels hold at most T = max_points points; dynamic voxels go
    through :func:`chunked_max`. Under autograd the scatter form runs: same values and gradients,
    and its backward touches P rows instead of the V * T slots of the dense layout (a PointPillars
    training step 1.27x).
    """
    if training_form():
        return scatter_max_nonneg(values, voxels.point2voxel, voxels.num_voxels)
    p2v, v, slot = voxels.point2voxel, voxels.num_voxels, voxels.slot
    if voxels.max_points is None:
        return chunked_max(values, p2v, slot, v)
    t = voxels.max_points
    return slot_max(values, p2v * t + slot, torch.arange(values.shape[0], dtype=torch.long), v, t)


def chunked_max(values: Tensor, p2v: Tensor, slot: Tensor, v: int) -> Tensor:
    """(V, C) per-voxel maxima of values (P, C) >= 0 of voxels of any size; ``slot`` (P,) is the
    rank of each point in its voxel ``p2v`` (P,).

    A voxel's points form chunks of DENSE_SLOTS by rank. Every chunk is reduced densely
    (:func:`slot_max` over V + E rows: chunk 0 of voxel i is row i, the E further chunks of the
    first CHUNKS follow); only the E further chunk maxima and the points past the first CHUNKS
    chunks (voxels next to the sensor) reach a ScatterElements max, which onnxruntime runs element
    by element: at 0.2 m voxels a sixth of the rows that scattering every point past the first
    chunk took.
    """
    t = DENSE_SLOTS
    chunk, within = torch.div(slot, t, rounding_mode="floor"), torch.remainder(slot, t)  # (P,)
    cell = p2v * CHUNKS + chunk.clamp(max=CHUNKS - 1)  # (P,) (voxel, chunk) of the dense chunks
    starts = torch.nonzero((within == 0) & (chunk > 0) & (chunk < CHUNKS))[:, 0]  # (E,) first points of further chunks
    rows = torch.arange(starts.shape[0], dtype=torch.long) + v  # (E,) their chunk rows
    extra = torch.zeros(v * CHUNKS, dtype=torch.long).index_put((take_rows(cell, starts),), rows)  # (V * CHUNKS,)
    row = torch.where(chunk == 0, p2v, take_rows(extra, cell))  # (P,) chunk row of each point
    dense = torch.nonzero(chunk < CHUNKS)[:, 0]  # (Q,)
    maxima = slot_max(values, take_rows(row * t + within, dense), dense, rows.shape[0] + v, t)  # (V + E, C)
    past = torch.nonzero(chunk >= CHUNKS)[:, 0]  # (R,) points past the dense chunks
    rest = torch.cat([maxima[v:], take_rows(values, past)])  # (E + R, C)
    idx = torch.cat([take_rows(p2v, starts), take_rows(p2v, past)])[:, None].expand(-1, values.shape[1])
    return maxima[:v].scatter_reduce(0, idx, rest, "amax", include_self=True)


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
    Linear -> BatchNorm -> ReLU, and max-pooled over the pillar's points (with ``padded_slots``,
    also over the empty slots of a pillar with fewer than ``max_points`` points, as OpenPCDet).
    """

    def __init__(self, grid: Grid, out_channels: int = 64, padded_slots: bool = False):
        super().__init__()
        self.grid = grid
        self.out_channels = out_channels
        self.padded_slots = padded_slots
        self.linear = nn.Linear(10, out_channels, bias=False)
        self.norm = RowBatchNorm(out_channels, eps=1e-3, momentum=0.01)

    def decorate(self, voxels: Voxels) -> Tensor:
        """(P, 10) decorated points."""
        return decorate_points(voxels, self.grid)

    def forward(self, voxels: Voxels) -> Tensor:
        feats = torch.relu(self.norm(self.linear(self.decorate(voxels))))  # (P, C)
        pooled = voxel_max_nonneg(feats, voxels)  # (V, C)
        if not self.padded_slots:
            return pooled
        # OpenPCDet's PFN max-pools a zero-padded (V, max_points, 10) tensor: a pillar with an empty
        # slot also takes relu(BN(Linear(0))) = relu(BN(0)) into its max
        empty = torch.relu(self.norm(feats.new_zeros(1, feats.shape[1])))  # (1, C)
        partial = scatter_count(voxels.point2voxel, voxels.num_voxels) < voxels.max_points  # (V,)
        return torch.where(partial[:, None], torch.maximum(pooled, empty), pooled)
