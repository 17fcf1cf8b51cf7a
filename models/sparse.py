"""Sparse 3D convolution as gather -> GEMM -> scatter over neighbour tables (no dense Conv3d).

A :class:`SparseTensor` is one frame's active voxels: features ``(V, C)``, integer coordinates
``(V, 3)`` as (z, y, x) and the grid shape ``(D, H, W)``. Neighbour tables are built from the
active voxels only: a dense int32 "index grid" (value ``V`` = empty), padded by a margin of
empty cells around the ``(D, H, W)`` grid, is filled by scatter once per resolution, and the
neighbours of every kernel offset are one gather at ``linear index of the voxel + linear offset
of the kernel tap`` (the margin catches the taps that leave the grid, so no bounds tests). The
table ``(V_out, K)`` holds, per output voxel and kernel offset, the input row or ``V_in``
(which points at an appended zero row). The convolution is then one GEMM:
``out = features_padded[table].reshape(V_out, K * C_in) @ weight (K * C_in, C_out)``.

- :class:`SubMConv3d`: submanifold conv, output coords = input coords.
- :class:`SparseConv3d`: strided ("regular") sparse conv; the output voxels are those whose
  receptive field holds an active input, as in spconv's ``SparseConv3d``.
- :class:`SparseInverseConv3d`: the transpose of a strided conv, back to the finer voxels of
  a given :class:`SparseTensor` (spconv's ``SparseInverseConv3d``, used by sparse UNets).
- :func:`to_dense`, :func:`height_compress`: dense ``(C, D, H, W)`` and BEV ``(1, C*D, H, W)``.

Tables and index grids are cached on the tensor (``cache``) so the layers of one resolution
share them; every function accepts V = 0 and exports with the dynamo ONNX exporter.

The transposed conv's table, which needs a divisibility test per axis, runs its coordinate
arithmetic on axis-major ``(3, K, V)`` queries (axis, kernel offset, voxel), so that
onnxruntime broadcasts over long rows (see ``models/voxelize.py``),
and rows are picked with ``index_select`` (ONNX ``Gather``) rather than advanced indexing
(``GatherND``, row by row).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor, nn

from models.base import no_autocast, training_form
from models.vfe import RowBatchNorm
from models.voxelize import all_axes, take_rows, unique_cells


def _triple(v) -> tuple[int, int, int]:
    return tuple(v) if isinstance(v, (tuple, list)) else (v, v, v)


def out_shape(shape, kernel, stride, padding) -> tuple[int, int, int]:
    """Output grid (D, H, W) of a strided conv: floor((n + 2p - k) / s) + 1 per axis."""
    k, s, p = _triple(kernel), _triple(stride), _triple(padding)
    return tuple((n + 2 * p[i] - k[i]) // s[i] + 1 for i, n in enumerate(shape))


def kernel_offsets(kernel) -> Tensor:
    """(K, 3) int64 offsets (dz, dy, dx) in 0..k-1, z slowest (the weight's K order)."""
    k = _triple(kernel)
    return torch.tensor(list(itertools.product(*(range(n) for n in k))), dtype=torch.long)


def _axis_column(v) -> Tensor:
    """(3, 1, 1) int64 per-axis constant (z, y, x) for axis-major (3, K, V) queries."""
    return torch.tensor(_triple(v), dtype=torch.long)[:, None, None]


def _offset_rows(kernel) -> Tensor:
    """(3, K, 1) kernel offsets, axis-major."""
    return kernel_offsets(kernel).T[:, :, None]


@dataclass
class SparseTensor:
    """Active voxels of one frame."""

    features: Tensor  # (V, C)
    coords: Tensor  # (V, 3) int64 (z, y, x)
    shape: tuple[int, int, int]  # (D, H, W)
    cache: dict = field(default_factory=dict, repr=False)  # index grid + neighbour tables

    def with_features(self, features: Tensor) -> "SparseTensor":
        """Same voxels (and shared cache), new features (V, C')."""
        return replace(self, features=features)

    def index_grid(self) -> Tensor:
        """(D*H*W,) int32: row of the voxel at each linear position, V where empty."""
        if "grid" not in self.cache:
            self.cache["grid"] = build_index_grid(self.coords, self.shape)
        return self.cache["grid"]

    def padded_grid(self, margin: tuple[int, int, int]) -> tuple[Tensor, tuple[int, int, int]]:
        """Index grid of the voxels in the grid widened by ``margin`` empty cells on both sides of
        each axis (coords shifted by ``margin``), and that padded shape; cached per margin."""
        key = ("padded", margin)
        shape = tuple(n + 2 * m for n, m in zip(self.shape, margin))
        if key not in self.cache:
            self.cache[key] = build_index_grid(self.coords + torch.tensor(margin), shape)
        return self.cache[key], shape


def _linear_axis_major(query: Tensor, shape) -> Tensor:
    """(...) int64 linear index z * H * W + y * W + x of axis-major coords (3, ...)."""
    _, h, w = shape
    return (query[0] * h + query[1]) * w + query[2]


def linear_index(coords: Tensor, shape) -> Tensor:
    """(...) int64 z * H * W + y * W + x of coords (..., 3)."""
    return _linear_axis_major(coords.movedim(-1, 0), shape)


def build_index_grid(coords: Tensor, shape) -> Tensor:
    """(D*H*W,) int32 grid with the row index of each active voxel, V elsewhere.

    int32, not int64: filling and scattering into the grid writes every cell (2.8M for compact
    SECOND's padded stem grid), and the tables read from it are Gather indices either way."""
    v = coords.shape[0]
    grid = torch.full((shape[0] * shape[1] * shape[2],), v, dtype=torch.int32)
    return grid.index_put_((linear_index(coords, shape),), torch.arange(v, dtype=torch.int32))


def lookup(grid: Tensor, shape, query: Tensor, valid: Tensor | None, missing: int) -> Tensor:
    """(V, K) rows of the voxels at axis-major query coords (3, K, V); ``missing`` where out of
    bounds or not ``valid`` (K, V)."""
    hi = _axis_column(shape)  # (3, 1, 1)
    inside = all_axes((query >= 0) & (query < hi))  # (K, V)
    if valid is not None:
        inside = inside & valid
    lin = _linear_axis_major(torch.minimum(query.clamp(min=0), hi - 1), shape)  # (K, V)
    return torch.where(inside, take_rows(grid, lin), torch.full_like(lin, missing, dtype=grid.dtype)).T


def _margin(low, high) -> tuple[int, int, int]:
    """Empty cells to pad each side of each axis with: enough for taps ``low`` cells before and
    ``high`` after the grid; at least 1, so that the 3x3x3 convs of one resolution share a grid."""
    return tuple(max(1, lo, hi) for lo, hi in zip(low, high))


def padded_lookup(x: SparseTensor, corner: Tensor, kernel, margin) -> Tensor:
    """(V_q, K) rows of ``x``'s voxels at ``corner + kernel offset`` for corners (V_q, 3) (any
    cell within ``margin`` of the grid); ``V`` where empty: one add and one gather."""
    grid, shape = x.padded_grid(margin)
    base = linear_index(corner + torch.tensor(margin), shape)  # (V_q,)
    taps = linear_index(kernel_offsets(kernel), shape)  # (K,)
    return take_rows(grid, taps[:, None] + base[None, :]).T


def subm_table(x: SparseTensor, kernel) -> Tensor:
    """(V, K) neighbour table of a submanifold conv (centred kernel), cached per kernel."""
    key = ("subm", _triple(kernel))
    if key not in x.cache:
        half = tuple(k // 2 for k in _triple(kernel))
        x.cache[key] = padded_lookup(x, x.coords - torch.tensor(half), kernel, _margin(half, half))
    return x.cache[key]


def strided_out_coords(x: SparseTensor, kernel, stride, padding) -> tuple[Tensor, tuple]:
    """(V_out, 3) active output coords of a strided conv, sorted by linear index; out shape.

    Per axis, the taps k with (in + p - k) divisible by s and inside the output grid give the
    candidate outputs (k_axis, V); the three axes combine by broadcasting."""
    k, s, p = _triple(kernel), _triple(stride), _triple(padding)
    shape = out_shape(x.shape, k, s, p)
    _, h, w = shape
    lin, ok = 0, True  # -> (kz, ky, kx, V): output cell of each tap, and whether it exists
    for axis, place in enumerate((h * w, w, 1)):
        cand = x.coords[:, axis][None, :] + p[axis] - torch.arange(k[axis])[:, None]  # (k_axis, V) = out * s
        exists = ((cand % s[axis]) == 0) & (cand >= 0) & (cand < shape[axis] * s[axis])
        axis_view = [1, 1, 1, -1]
        axis_view[axis] = k[axis]
        lin = lin + (cand // s[axis] * place).reshape(axis_view)  # integer Div: exact at any grid size
        ok = ok & exists.reshape(axis_view)
    uniq = unique_cells(lin[ok], math.prod(shape))  # (V_out,) ascending
    coords = torch.stack([uniq // (h * w), (uniq // w) % h, uniq % w], dim=1)
    return coords, shape


def strided_table(x: SparseTensor, out_coords: Tensor, kernel, stride, padding) -> Tensor:
    """(V_out, K) input rows feeding each output voxel: in = out * s - p + k."""
    k, s, p = _triple(kernel), _triple(stride), _triple(padding)
    last = out_shape(x.shape, k, s, p)
    after = [(o - 1) * si - pi + ki - n for o, si, pi, ki, n in zip(last, s, p, k, x.shape)]  # cells past the end
    return padded_lookup(x, out_coords * torch.tensor(s) - torch.tensor(p), k, _margin(p, after))


def inverse_table(coarse: SparseTensor, fine: SparseTensor, kernel, stride, padding) -> Tensor:
    """(V_fine, K) coarse rows feeding each fine voxel in the transposed conv.

    Fine voxel o and coarse voxel i are linked by kernel offset k when o = i * s - p + k.
    """
    s, p = _axis_column(stride), _axis_column(padding)
    num = fine.coords.T[:, None, :] + p - _offset_rows(kernel)  # (3, K, V_fine) = i * s
    valid = all_axes((num % s) == 0)  # (K, V_fine)
    query = num // s  # (3, K, V_fine) integer Div
    return lookup(coarse.index_grid(), coarse.shape, query, valid, coarse.coords.shape[0])


def gather_gemm(features: Tensor, table: Tensor, weight: Tensor, pairs: tuple | None = None) -> Tensor:
    """(V_out, C_out) = sum_k features[table[:, k]] @ weight[k]; table value V_in = zero row.

    Inference (and export) runs :func:`table_gemm`; with autograd on, :func:`pair_gemm` works
    on the occupied entries only (``pairs``: the table's :func:`table_pairs`, when known), which
    the backward pass repays.

    Under autocast (``train --amp bf16``) too it runs in the weights' float32, features cast to it: with one GEMM
    of 4-128 channels per kernel offset, bfloat16 gains nothing here (SECOND's training step took 0.87x the float32
    step's time with bfloat16 sparse GEMMs, 0.81x with float32 ones), and the sums over the offsets stay float32.
    """
    features = features.to(weight.dtype)  # a point encoder's rows come in bfloat16 under autocast
    with no_autocast(features.device.type):
        if training_form():
            return pair_gemm(features, table, weight) if pairs is None else pair_gemm(features, table, weight, pairs)
        return table_gemm(features, table, weight)


def table_pairs(table: Tensor, v_in: int) -> tuple[Tensor, Tensor, list[int]]:
    """The occupied entries of a neighbour table (V_out, K) over ``v_in`` input rows: input rows
    (M,), output rows (M,), grouped by kernel offset, and the count of each offset (K)."""
    offset, out_row = torch.nonzero((table != v_in).T, as_tuple=True)  # (M,) grouped by offset
    return table[out_row, offset], out_row, torch.bincount(offset, minlength=table.shape[1]).tolist()


def subm_pairs(x: SparseTensor, kernel) -> tuple[Tensor, Tensor, list[int]]:
    """:func:`table_pairs` of :func:`subm_table`, cached like it: the submanifold convs of one
    resolution (SECOND's stem, Part-A2's decoder) share them."""
    key = ("subm_pairs", _triple(kernel))
    if key not in x.cache:
        x.cache[key] = table_pairs(subm_table(x, kernel), x.coords.shape[0])
    return x.cache[key]


def table_gemm(features: Tensor, table: Tensor, weight: Tensor) -> Tensor:
    """:func:`gather_gemm` as one gather of the (V_out, K, C_in) table and one GEMM."""
    k, c_in, c_out = weight.shape
    padded = torch.cat([features, features.new_zeros(1, c_in)], dim=0)  # (V_in + 1, C_in)
    gathered = take_rows(padded, table)  # (V_out, K, C_in)
    return gathered.reshape(-1, k * c_in) @ weight.reshape(k * c_in, c_out)


def pair_gemm(features: Tensor, table: Tensor, weight: Tensor, pairs: tuple | None = None) -> Tensor:
    """:func:`table_gemm` over the occupied table entries only (spconv's rule-book form).

    A LiDAR surface fills a quarter to a half of a 3x3x3 neighbourhood; the one-GEMM form also
    multiplies, and back-propagates through, the zero rows of the empty ones. Here the
    (output row, input row) pairs of each kernel offset get one GEMM each, and the products
    are summed into their output rows (:class:`_PairGemm`).
    """
    in_row, out_row, counts = table_pairs(table, features.shape[0]) if pairs is None else pairs
    return _PairGemm.apply(features, weight, in_row, out_row, counts, table.shape[0])


def _segments(counts: list[int]):
    """(kernel offset, row slice) of each offset's non-empty run of pairs."""
    start = 0
    for k, n in enumerate(counts):
        if n:
            yield k, slice(start, start + n)
        start += n


class _PairGemm(torch.autograd.Function):
    """out[o] = sum over pairs (i, o, k) of features[i] @ weight[k], pairs grouped by k.

    The products of all offsets are written into one (M, C_out) buffer and summed into the
    output rows by one ``index_add``; the backward pass writes the gradient rows the same way
    (autograd's split / cat of the per-offset pieces would copy both once more)."""

    @staticmethod
    def forward(ctx, features, weight, in_row, out_row, counts, v_out):
        gathered = features.index_select(0, in_row)  # (M, C_in)
        products = features.new_empty(in_row.shape[0], weight.shape[2])  # (M, C_out)
        for k, rows in _segments(counts):
            torch.mm(gathered[rows], weight[k], out=products[rows])
        ctx.save_for_backward(gathered, weight, in_row, out_row)
        ctx.counts, ctx.v_in = counts, features.shape[0]
        return features.new_zeros(v_out, weight.shape[2]).index_add_(0, out_row, products)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        gathered, weight, in_row, out_row = ctx.saved_tensors
        grad_products = grad_out.index_select(0, out_row)  # (M, C_out)
        grad_features = grad_weight = None
        if ctx.needs_input_grad[1]:
            grad_weight = torch.zeros_like(weight)
            for k, rows in _segments(ctx.counts):
                torch.mm(gathered[rows].T, grad_products[rows], out=grad_weight[k])
        if ctx.needs_input_grad[0]:
            grad_gathered = torch.empty_like(gathered)  # (M, C_in)
            for k, rows in _segments(ctx.counts):
                torch.mm(grad_products[rows], weight[k].T, out=grad_gathered[rows])
            grad_features = grad_out.new_zeros(ctx.v_in, gathered.shape[1]).index_add_(0, in_row, grad_gathered)
        return grad_features, grad_weight, None, None, None, None


class _SparseConvBase(nn.Module):
    def __init__(self, c_in: int, c_out: int, kernel, bias: bool):
        super().__init__()
        self.kernel = _triple(kernel)
        k = math.prod(self.kernel)
        self.weight = nn.Parameter(torch.empty(k, c_in, c_out))  # (K, C_in, C_out)
        nn.init.kaiming_uniform_(self.weight.view(k * c_in, c_out).T, a=math.sqrt(5))
        self.bias = nn.Parameter(torch.zeros(c_out)) if bias else None

    def _conv(self, features: Tensor, table: Tensor, pairs: tuple | None = None) -> Tensor:
        out = gather_gemm(features, table, self.weight, pairs)
        return out if self.bias is None else out + self.bias


class SubMConv3d(_SparseConvBase):
    """Submanifold sparse conv: same active voxels in and out."""

    def __init__(self, c_in: int, c_out: int, kernel=3, bias: bool = False):
        super().__init__(c_in, c_out, kernel, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        pairs = subm_pairs(x, self.kernel) if training_form() else None
        return x.with_features(self._conv(x.features, subm_table(x, self.kernel), pairs))


class SparseConv3d(_SparseConvBase):
    """Strided sparse conv: output voxels = positions whose receptive field holds an input."""

    def __init__(self, c_in: int, c_out: int, kernel=3, stride=2, padding=1, bias: bool = False):
        super().__init__(c_in, c_out, kernel, bias)
        self.stride, self.padding = _triple(stride), _triple(padding)

    def forward(self, x: SparseTensor) -> SparseTensor:
        coords, shape = strided_out_coords(x, self.kernel, self.stride, self.padding)
        table = strided_table(x, coords, self.kernel, self.stride, self.padding)
        return SparseTensor(self._conv(x.features, table), coords, shape)


class SparseInverseConv3d(_SparseConvBase):
    """Transpose of a strided sparse conv, onto the voxels of ``target`` (the finer level)."""

    def __init__(self, c_in: int, c_out: int, kernel=3, stride=2, padding=1, bias: bool = False):
        super().__init__(c_in, c_out, kernel, bias)
        self.stride, self.padding = _triple(stride), _triple(padding)

    def forward(self, x: SparseTensor, target: SparseTensor) -> SparseTensor:
        table = inverse_table(x, target, self.kernel, self.stride, self.padding)
        return target.with_features(self._conv(x.features, table))


class SparseBNReLU(nn.Module):
    """BatchNorm1d + ReLU on the features of a SparseTensor."""

    def __init__(self, channels: int):
        super().__init__()
        self.norm = RowBatchNorm(channels, eps=1e-3, momentum=0.01)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_features(torch.relu(self.norm(x.features)))


def conv_block(conv: nn.Module, c_out: int) -> nn.Sequential:
    """conv -> BN -> ReLU for single-input sparse convs (SubM / strided)."""
    return nn.Sequential(conv, SparseBNReLU(c_out))


def to_dense(x: SparseTensor) -> Tensor:
    """(C, D, H, W) dense features, zeros at inactive voxels."""
    d, h, w = x.shape
    c = x.features.shape[1]
    dense = x.features.new_zeros(d * h * w, c)
    dense = dense.index_put((linear_index(x.coords, x.shape),), x.features)  # (D*H*W, C)
    return dense.reshape(d, h, w, c).permute(3, 0, 1, 2)


def height_compress(x: SparseTensor) -> Tensor:
    """(1, C*D, H, W) BEV map: channels of all heights stacked (OpenPCDet HeightCompression)."""
    dense = to_dense(x)  # (C, D, H, W)
    c, d, h, w = dense.shape
    return dense.reshape(1, c * d, h, w)
