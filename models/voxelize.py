"""Point-cloud range filtering and voxelization (hard and dynamic), export-friendly.

Every function works on ONE frame of raw points ``(N, 4)`` (x, y, z, intensity; LiDAR frame,
metres), accepts N = 0 and uses only ops the dynamo ONNX exporter translates
(``scatter``, ``index_put``, ``cumsum``, ``argsort``).

Voxel coordinates are ``(z, y, x)`` integer indices into a grid of shape ``(D, H, W)``, so that
a dense tensor of the grid is laid out ``[D, H, W]`` like OpenPCDet's ``spatial_shape``.

- :func:`dynamic_voxelize`: every in-range point is kept (no caps), voxels sorted by linear index.
- :func:`hard_voxelize`: at most ``max_points`` points per voxel (the first ones in input order)
  and at most ``max_voxels`` voxels (those whose first point comes first), as in OpenPCDet /
  spconv's ``VoxelGenerator``.

Both return :class:`Voxels`, a point list with a point -> voxel index, which every VFE in
``models/vfe.py`` consumes (a padded ``(V, T, C)`` tensor is never needed).

Points are grouped by voxel with one stable sort of their linear voxel index (:func:`group_cells`:
two or three radix passes of TopK over the points), which gives the sorted distinct voxels, each
point's voxel and its rank in the voxel at once. Its cost grows with the points, not with the
grid: an occupancy table of a 2.56M-cell grid (scatter, cumulative sum, NonZero over every cell)
cost onnxruntime 12 ms a frame more, and ``Unique`` is single-threaded.

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
    slot: Tensor  # (P,) int64 rank of the point in its voxel, in input order
    max_points: int | None = None  # slots per voxel (hard voxelization; None: no cap)

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


TABLE_CELLS = 1 << 22  # largest grid (voxels) whose occupied cells are found through a dense table


def unique_cells(linear: Tensor, cells: int) -> Tensor:
    """(V,) ``torch.unique(linear)``, the sorted distinct linear indices in ``[0, cells)``: an
    occupancy table (scatter, NonZero) when the grid has at most ``TABLE_CELLS`` cells, else
    ``Unique`` (single-threaded in onnxruntime)."""
    if cells > TABLE_CELLS:
        uniq = torch.unique(linear)
    else:
        occupied = torch.zeros(cells, dtype=torch.long).scatter(0, linear, torch.ones_like(linear))  # (cells,)
        uniq = torch.nonzero(occupied)[:, 0]  # (V,) ascending
    torch._check(uniq.shape[0] <= cells)  # keeps export's size bounds in int64
    return uniq


@dataclass(frozen=True)
class CellGroups:
    """Entries (P,) grouped by their cell: what voxelization needs, from one stable sort."""

    cells: Tensor  # (V,) int64 sorted distinct linear indices
    inverse: Tensor  # (P,) int64 position of each entry's cell among them
    rank: Tensor  # (P,) int64 rank of each entry among the entries of its cell, in input order


def group_cells(linear: Tensor, cells: int) -> CellGroups:
    """:class:`CellGroups` of linear indices (P,) in ``[0, cells)``.

    One stable sort by cell (:func:`group_order`); cell boundaries are where the sorted index
    changes. Work is O(P) per radix pass, not O(cells): no occupancy table of the whole grid.
    """
    p = linear.shape[0]
    order = group_order(linear, cells)  # (P,) entries grouped by cell, input order inside
    ordered = take_rows(linear, order)  # (P,) ascending
    new = ordered != torch.cat([ordered.new_full((1,), -1), ordered])[:-1]  # (P,) first of its cell
    starts = torch.nonzero(new)[:, 0]  # (V,) first sorted position of each cell
    torch._check(starts.shape[0] <= cells)
    group = torch.cumsum(new.to(torch.long), dim=0) - 1  # (P,) cell of each sorted position
    rank = torch.arange(p, dtype=torch.long) - take_rows(starts, group)  # (P,) in sorted order
    unsort = torch.zeros(p, dtype=torch.long)
    return CellGroups(take_rows(ordered, starts), unsort.scatter(0, order, group), unsort.scatter(0, order, rank))


def _coords_of(linear: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """(V, 3) int64 (z, y, x) from linear indices (V,) (``//`` and ``%``: integer ``Div`` and ``Mod`` in
    the graph, exact at any grid size)."""
    _, h, w = shape
    return torch.stack([linear // (h * w), (linear // w) % h, linear % w], dim=1)


def dynamic_voxelize(points: Tensor, grid: Grid) -> Voxels:
    """All in-range points, grouped into voxels (sorted by linear index)."""
    pts = filter_range(points, grid.pc_range)  # (P, 4)
    groups = group_cells(_linear_index(pts, grid), math.prod(grid.shape))
    return Voxels(pts, groups.inverse, _coords_of(groups.cells, grid.shape), grid.shape, groups.rank)


MAX_POINTS = 2 ** 20  # points per frame that the graph's int32 grouping keys hold (a scan: ~120k)
_POS_BITS = 20  # bits of a point's position, < MAX_POINTS
_DIGIT_BITS = 31 - _POS_BITS  # bits of a group index sorted per pass: digit * 2^20 + position < 2^31


def group_order(group: Tensor, groups: int) -> Tensor:
    """(P,) permutation that sorts ``group`` (P,) int64 in [0, groups) ascending, equal groups in
    input order (a stable argsort).

    In the graph, a least-significant-digit radix sort: each pass sorts by one 11-bit digit of the
    group with the current position as tie-break, ``digit * P + position`` (distinct, < 2^31 for
    P <= MAX_POINTS), so every TopK key fits int32 and no TopK tie rule is relied on (OpenVINO's
    is not stable). Groups below 2^11 take one pass, below 2^22 two. The digits are cut with ``//``
    and ``remainder``, which export as integer ``Div`` and ``Mod`` (``torch.div(rounding_mode=
    "floor")`` exports as a float32 ``Div`` + ``Floor``, wrong above 2^24: the kitti grid has 2^26.4 cells).
    """
    if not tracing():
        return torch.sort(group, stable=True).indices
    p = group.shape[0]
    position = torch.arange(p, dtype=torch.long)  # (P,)
    order = position
    for shift in range(0, max(1, (groups - 1).bit_length()), _DIGIT_BITS):
        digit = torch.remainder(take_rows(group, order) // 2 ** shift, 2 ** _DIGIT_BITS)  # integer Div, Mod
        order = take_rows(order, torch.argsort(digit * p + position))  # (P,) stable by this digit
    return order


def hard_voxelize(points: Tensor, grid: Grid, max_points: int, max_voxels: int) -> Voxels:
    """Capped voxelization: <= max_points points per voxel, <= max_voxels voxels.

    Voxels are ordered by the input index of their first point; the kept points of a voxel are
    its first ``max_points`` points in input order.
    """
    pts = filter_range(points, grid.pc_range)  # (P, 4)
    groups = group_cells(_linear_index(pts, grid), math.prod(grid.shape))
    v = groups.cells.shape[0]
    firsts = torch.nonzero(groups.rank == 0)[:, 0]  # (V,) ascending: the first point of every voxel
    order = take_rows(groups.inverse, firsts[:max_voxels])  # (V',) voxel ids by first appearance
    new_id = torch.full((v,), -1, dtype=torch.long)
    new_id = new_id.index_put((order,), torch.arange(order.shape[0], dtype=torch.long))  # (V,)
    point_voxel = take_rows(new_id, groups.inverse)  # (P,) -1 for points of dropped voxels
    keep = (groups.rank < max_points) & (point_voxel >= 0)
    kept = torch.nonzero(keep)[:, 0]  # (P',)
    return Voxels(take_rows(pts, kept), take_rows(point_voxel, kept),
                  _coords_of(take_rows(groups.cells, order), grid.shape), grid.shape, take_rows(groups.rank, kept),
                  max_points)
