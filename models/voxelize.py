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

Points are grouped by voxel through a dense occupancy table (scatter, cumulative sum, gather)
when the grid has at most ``TABLE_CELLS`` voxels, otherwise with ``torch.unique``: both give the
sorted distinct voxels and each point's voxel, but onnxruntime's ``Unique`` is single-threaded
and costs more than the table on the compact grids.

Per-axis arithmetic runs on axis-major ``(3, N)`` views: onnxruntime broadcasts ``(3, N)``
against ``(3, 1)`` row by row but ``(N, 3)`` against ``(3,)`` three elements at a time, about
15x slower over a 120k-point scan.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from models.base import tracing


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

    def centres(self, coords: Tensor, stride=1.0) -> Tensor:
        """(V, 3) x, y, z centres in metres of voxels at (z, y, x) indices ``coords`` (V, 3) of a
        level whose voxels are ``stride`` (scalar or (3,) x, y, z) times this grid's."""
        xyz = torch.flip(coords, dims=[1]).T.to(torch.float32)  # (3, V) axis-major
        stride = torch.as_tensor(stride, dtype=torch.float32).reshape(-1, 1)  # (1, 1) or (3, 1)
        return ((xyz + 0.5) * self.size()[:, None] * stride + self.lower()[:, None]).T


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


def all_axes(mask: Tensor) -> Tensor:
    """``mask.all(dim=0)`` of an axis-major (3, ...) mask, as two ANDs (onnxruntime reduces a
    leading axis slowly)."""
    return mask[0] & mask[1] & mask[2]


def range_mask(points: Tensor, pc_range) -> Tensor:
    """(N,) bool: x0 <= x < x1, y0 <= y < y1, z0 <= z < z1."""
    lo = torch.tensor(pc_range[:3], dtype=points.dtype)[:, None]  # (3, 1)
    hi = torch.tensor(pc_range[3:], dtype=points.dtype)[:, None]
    xyz = points[:, :3].T  # (3, N) metres, axis-major
    return all_axes((xyz >= lo) & (xyz < hi))


def take_rows(t: Tensor, index: Tensor) -> Tensor:
    """``t[index]`` for an integer index of any shape, as one ``index_select`` (ONNX Gather;
    advanced indexing exports as GatherND, which onnxruntime runs row by row)."""
    return torch.index_select(t, 0, index.reshape(-1)).reshape(*index.shape, *t.shape[1:])


def filter_range(points: Tensor, pc_range) -> Tensor:
    """(P, C) the points inside the range."""
    return take_rows(points, torch.nonzero(range_mask(points, pc_range))[:, 0])


def _linear_index(points: Tensor, grid: Grid) -> Tensor:
    """(P,) int64 linear voxel index z * H * W + y * W + x of in-range points."""
    d, h, w = grid.shape
    xyz = points[:, :3].T  # (3, P) axis-major
    idx = torch.floor((xyz - grid.lower()[:, None]) / grid.size()[:, None]).long()  # (3, P) x, y, z
    hi = torch.tensor([w - 1, h - 1, d - 1], dtype=torch.long)[:, None]
    idx = torch.minimum(idx.clamp(min=0), hi)  # float rounding at the upper edge
    return (idx[2] * h + idx[1]) * w + idx[0]


TABLE_CELLS = 1 << 22  # largest grid (voxels) grouped through a dense table (32 MB of int64)


def unique_cells(linear: Tensor, cells: int, return_inverse: bool = False):
    """``torch.unique(linear, return_inverse=...)`` for linear indices in ``[0, cells)``: the
    sorted distinct indices (V,) and, if asked, each entry's position among them (P,)."""
    if cells > TABLE_CELLS:
        out = torch.unique(linear, return_inverse=return_inverse)
        uniq = out[0] if return_inverse else out
    else:
        occupied = torch.zeros(cells, dtype=torch.long).scatter(0, linear, torch.ones_like(linear))  # (cells,)
        uniq = torch.nonzero(occupied)[:, 0]  # (V,) ascending
        if return_inverse:
            out = uniq, take_rows(torch.cumsum(occupied, dim=0) - 1, linear)  # (P,) rank of the entry's cell
        else:
            out = uniq
    torch._check(uniq.shape[0] <= cells)  # keeps export's size bounds in int64
    return out


def _coords_of(linear: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """(V, 3) int64 (z, y, x) from linear indices (V,)."""
    _, h, w = shape
    return torch.stack([linear // (h * w), (linear // w) % h, linear % w], dim=1)


def dynamic_voxelize(points: Tensor, grid: Grid) -> Voxels:
    """All in-range points, grouped into voxels (sorted by linear index)."""
    pts = filter_range(points, grid.pc_range)  # (P, 4)
    linear = _linear_index(pts, grid)  # (P,)
    uniq, inverse = unique_cells(linear, math.prod(grid.shape), return_inverse=True)  # (V,), (P,)
    return Voxels(pts, inverse, _coords_of(uniq, grid.shape), grid.shape)


MAX_POINTS = 2 ** 20  # points per frame that the graph's int32 grouping keys hold (a scan: ~120k)
_POS_BITS = 20  # bits of a point's position, < MAX_POINTS
_DIGIT_BITS = 31 - _POS_BITS  # bits of a group index sorted per pass: digit * 2^20 + position < 2^31


def group_order(group: Tensor, groups: int) -> Tensor:
    """(P,) permutation that sorts ``group`` (P,) int64 in [0, groups) ascending, equal groups in
    input order (a stable argsort).

    In the graph, a least-significant-digit radix sort: each pass sorts by one 11-bit digit of the
    group with the current position as tie-break, ``digit * P + position`` (distinct, < 2^31 for
    P <= MAX_POINTS), so every TopK key fits int32 and no TopK tie rule is relied on (OpenVINO's
    is not stable). Groups below 2^11 take one pass, below 2^22 two.
    """
    if not tracing():
        return torch.sort(group, stable=True).indices
    p = group.shape[0]
    position = torch.arange(p, dtype=torch.long)  # (P,)
    order = position
    for shift in range(0, max(1, (groups - 1).bit_length()), _DIGIT_BITS):
        digit = torch.remainder(torch.div(take_rows(group, order), 2 ** shift, rounding_mode="floor"), 2 ** _DIGIT_BITS)
        order = take_rows(order, torch.argsort(digit * p + position))  # (P,) stable by this digit
    return order


def slot_in_voxel(inverse: Tensor, num_voxels: int, cells: int) -> Tensor:
    """(P,) int64 rank of each point among the points of its voxel, in input order; ``inverse``
    (P,) in [0, num_voxels), num_voxels <= cells."""
    p = inverse.shape[0]
    arange = torch.arange(p, dtype=torch.long)
    order = group_order(inverse, min(cells, MAX_POINTS))  # points grouped by voxel, input order inside
    counts = torch.zeros(num_voxels, dtype=torch.long).index_add(0, inverse, torch.ones_like(inverse))
    starts = torch.cumsum(counts, dim=0) - counts  # (V,) first position of each voxel in `order`
    slot = torch.zeros(p, dtype=torch.long)
    return slot.scatter(0, order, arange - take_rows(starts, take_rows(inverse, order)))


def _first_in_voxel(inverse: Tensor, num_voxels: int) -> Tensor:
    """(V,) int64 input index of the first point of each voxel; ``inverse`` (P,) is each point's voxel."""
    p = inverse.shape[0]
    arange = torch.arange(p, dtype=torch.long)
    return torch.full((num_voxels,), p, dtype=torch.long).scatter_reduce(0, inverse, arange, "amin")


def first_points(inverse: Tensor, num_voxels: int) -> Tensor:
    """(V,) input index of the first point of every voxel, ascending (``inverse`` (P,) is each
    point's voxel): the points that come first in their voxel, found without a sort."""
    first = _first_in_voxel(inverse, num_voxels)  # (V,)
    is_first = take_rows(first, inverse) == torch.arange(inverse.shape[0], dtype=torch.long)  # (P,)
    return torch.nonzero(is_first)[:, 0]


def hard_voxelize(points: Tensor, grid: Grid, max_points: int, max_voxels: int) -> Voxels:
    """Capped voxelization: <= max_points points per voxel, <= max_voxels voxels.

    Voxels are ordered by the input index of their first point; the kept points of a voxel are
    its first ``max_points`` points in input order.
    """
    pts = filter_range(points, grid.pc_range)  # (P, 4)
    linear = _linear_index(pts, grid)  # (P,)
    cells = math.prod(grid.shape)
    uniq, inverse = unique_cells(linear, cells, return_inverse=True)  # (V,), (P,)
    v = uniq.shape[0]
    order = take_rows(inverse, first_points(inverse, v)[:max_voxels])  # (V',) old voxel ids by first appearance
    new_id = torch.full((v,), -1, dtype=torch.long)
    new_id = new_id.index_put((order,), torch.arange(order.shape[0], dtype=torch.long))  # (V,)
    point_voxel = take_rows(new_id, inverse)  # (P,) -1 for points of dropped voxels
    slot = slot_in_voxel(inverse, v, cells)  # (P,)
    keep = (slot < max_points) & (point_voxel >= 0)
    kept = torch.nonzero(keep)[:, 0]  # (P',)
    return Voxels(take_rows(pts, kept), take_rows(point_voxel, kept), _coords_of(take_rows(uniq, order), grid.shape),
                  grid.shape, take_rows(slot, kept), max_points)
