"""Point-cloud range filtering and voxelization (hard and dynamic), export-friendly.

Every function works on ONE frame of raw points ``(N, 4)`` (x, y, z, intensity; LiDAR frame,
metres), accepts N = 0 and uses only ops the dynamo ONNX exporter translates
(``torch.unique(return_inverse=True)``, ``scatter_reduce`` amin, ``index_add``, ``argsort``).

Voxel coordinates are ``(z, y, x)`` integer indices into a grid of shape ``(D, H, W)``, so that
a dense tensor of the grid is laid out ``[D, H, W]`` like OpenPCDet's ``spatial_shape``.

- :func:`dynamic_voxelize`: every in-range point is kept (no caps), voxels sorted by linear index.
- :func:`hard_voxelize`: at most ``max_points`` points per voxel (the first ones in input order)
  and at most ``max_voxels`` voxels (those whose first point comes first), as in OpenPCDet /
  spconv's ``VoxelGenerator``.

Both return :class:`Voxels`, a point list with a point -> voxel index, which every VFE in
``models/vfe.py`` consumes (a padded ``(V, T, C)`` tensor is never needed).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Grid:
    """A voxel grid over a point-cloud range (LiDAR frame, metres)."""

    pc_range: tuple[float, float, float, float, float, float]  # (x0, y0, z0, x1, y1, z1)
    voxel_size: tuple[float, float, float]  # (dx, dy, dz)

    @property
    def shape(self) -> tuple[int, int, int]:
        """(D, H, W) = number of voxels along (z, y, x)."""
        x0, y0, z0, x1, y1, z1 = self.pc_range
        dx, dy, dz = self.voxel_size
        return (round((z1 - z0) / dz), round((y1 - y0) / dy), round((x1 - x0) / dx))

    def lower(self) -> Tensor:
        return torch.tensor(self.pc_range[:3], dtype=torch.float32)  # (3,) x0, y0, z0

    def size(self) -> Tensor:
        return torch.tensor(self.voxel_size, dtype=torch.float32)  # (3,) dx, dy, dz


@dataclass(frozen=True)
class Voxels:
    """Result of a voxelization of one frame."""

    points: Tensor  # (P, 4) kept points (in range, within the caps)
    point2voxel: Tensor  # (P,) int64 voxel index of each kept point, in [0, V)
    coords: Tensor  # (V, 3) int64 voxel indices (z, y, x)
    shape: tuple[int, int, int]  # (D, H, W) grid shape
    slot: Tensor | None = None  # (P,) int64 rank of the point in its voxel (hard voxelization)
    max_points: int | None = None  # slots per voxel (hard voxelization)

    @property
    def num_voxels(self) -> int:
        return self.coords.shape[0]


def range_mask(points: Tensor, pc_range) -> Tensor:
    """(N,) bool: x0 <= x < x1, y0 <= y < y1, z0 <= z < z1."""
    lo = torch.tensor(pc_range[:3], dtype=points.dtype)
    hi = torch.tensor(pc_range[3:], dtype=points.dtype)
    xyz = points[:, :3]  # (N, 3) metres
    return ((xyz >= lo) & (xyz < hi)).all(dim=1)


def filter_range(points: Tensor, pc_range) -> Tensor:
    """(P, C) the points inside the range."""
    return points[range_mask(points, pc_range)]


def _linear_index(points: Tensor, grid: Grid) -> Tensor:
    """(P,) int64 linear voxel index z * H * W + y * W + x of in-range points."""
    d, h, w = grid.shape
    idx = torch.floor((points[:, :3] - grid.lower()) / grid.size()).long()  # (P, 3) x, y, z
    hi = torch.tensor([w - 1, h - 1, d - 1], dtype=torch.long)
    idx = torch.minimum(idx.clamp(min=0), hi)  # float rounding at the upper edge
    return (idx[:, 2] * h + idx[:, 1]) * w + idx[:, 0]


def _coords_of(linear: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """(V, 3) int64 (z, y, x) from linear indices (V,)."""
    _, h, w = shape
    return torch.stack([linear // (h * w), (linear // w) % h, linear % w], dim=1)


def dynamic_voxelize(points: Tensor, grid: Grid) -> Voxels:
    """All in-range points, grouped into voxels (sorted by linear index)."""
    pts = filter_range(points, grid.pc_range)  # (P, 4)
    linear = _linear_index(pts, grid)  # (P,)
    uniq, inverse = torch.unique(linear, return_inverse=True)  # (V,), (P,)
    torch._check(uniq.shape[0] <= math.prod(grid.shape))  # keeps export's size bounds in int64
    return Voxels(pts, inverse, _coords_of(uniq, grid.shape), grid.shape)


def _slot_in_voxel(inverse: Tensor, num_voxels: int) -> Tensor:
    """(P,) int64 rank of each point among the points of its voxel, in input order."""
    p = inverse.shape[0]
    arange = torch.arange(p, dtype=torch.long)
    order = torch.argsort(inverse * p + arange)  # points grouped by voxel, input order inside
    counts = torch.zeros(num_voxels, dtype=torch.long).index_add(0, inverse, torch.ones_like(inverse))
    starts = torch.cumsum(counts, dim=0) - counts  # (V,) first position of each voxel in `order`
    slot = torch.zeros(p, dtype=torch.long)
    return slot.index_put((order,), arange - starts[inverse[order]])


def hard_voxelize(points: Tensor, grid: Grid, max_points: int, max_voxels: int) -> Voxels:
    """Capped voxelization: <= max_points points per voxel, <= max_voxels voxels.

    Voxels are ordered by the input index of their first point; the kept points of a voxel are
    its first ``max_points`` points in input order.
    """
    pts = filter_range(points, grid.pc_range)  # (P, 4)
    linear = _linear_index(pts, grid)  # (P,)
    uniq, inverse = torch.unique(linear, return_inverse=True)  # (V,), (P,)
    torch._check(uniq.shape[0] <= math.prod(grid.shape))
    v, p = uniq.shape[0], pts.shape[0]
    arange = torch.arange(p, dtype=torch.long)
    first = torch.full((v,), p, dtype=torch.long).scatter_reduce(0, inverse, arange, "amin")  # (V,)
    order = torch.argsort(first)[:max_voxels]  # (V',) old voxel ids by first appearance
    new_id = torch.full((v,), -1, dtype=torch.long)
    new_id = new_id.index_put((order,), torch.arange(order.shape[0], dtype=torch.long))  # (V,)
    point_voxel = new_id[inverse]  # (P,) -1 for points of dropped voxels
    slot = _slot_in_voxel(inverse, v)  # (P,)
    keep = (slot < max_points) & (point_voxel >= 0)
    return Voxels(pts[keep], point_voxel[keep], _coords_of(uniq[order], grid.shape), grid.shape,
                  slot[keep], max_points)
