"""PointNet++ point operators in plain torch, exportable to standard ONNX ops.

One frame, no batch axis; FPS and ball query also take a leading batch axis (PointRCNN's
refinement runs them inside every RoI at once). Every operator accepts empty inputs:

- ``farthest_point_sample``: iterative FPS, a ``while_loop`` (ONNX ``Loop``) when exported and
  a Python loop in eager mode (same arithmetic, same result). Eager on the CPU, FPS and ball
  query run the numba kernels of ``models.point_kernels`` (same indices). The points are held as three
  coordinate rows: onnxruntime broadcasts ``(B, N) - (B, 1)`` row by row but ``(N, 3) - (3,)``
  three elements at a time.
- ``ball_queries``: the first ``nsample`` in-radius indices (``TopK`` of the index) of every
  centre, for several radii over one distance matrix, padded with the first neighbour like the
  CUDA op; a ball with no neighbour points at the zero row that ``group_points`` appends. The
  distances are the direct ``(c - x)^2`` sums, summed axis by axis from ``(M, 1) - (N,)`` rows.
- ``three_nn_interpolate``: 3-NN inverse-distance interpolation for feature propagation, its
  distance matrix summed axis by axis from ``(N, 1) - (M,)`` broadcasts (an ``(N, 1, 3) - (1, M, 3)``
  one runs three elements at a time: 71 of PointRCNN's 217 ms a frame).
- ``SetAbstraction``: multi-scale grouping (several radii), shared MLP, max-pool.
- ``FeaturePropagation``: interpolation + skip concatenation + shared MLP.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn
from torch._higher_order_ops.while_loop import while_loop

from models.base import tracing
from models.point_kernels import ball_queries_cpu, farthest_point_sample_cpu, three_nn_cpu
from models.vfe import RowBatchNorm

_FAR = 1.0e4  # metres; position of the padding points used by three_nn_interpolate


def _rows(xyz: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(B, N, 3) -> x, y, z rows (B, N + 1) with a padding point at the origin in column N."""
    padded = torch.cat([xyz, xyz.new_zeros(xyz.shape[0], 1, 3)], 1).transpose(1, 2)  # (B, 3, N + 1)
    return padded[:, 0].clone(), padded[:, 1].clone(), padded[:, 2].clone()  # while_loop: no aliases


def _fps_start(xyz: Tensor, num: int) -> tuple[Tensor, Tensor]:
    """Distances (B, N + 1) to the chosen set (the padding column at -1 never wins unless N == 0)
    and the index buffer (B, num), first pick point 0."""
    b, n = xyz.shape[0], xyz.shape[1]
    dist = torch.cat([xyz.new_full((b, n), float("inf")), xyz.new_full((b, 1), -1.0)], 1)
    return dist, torch.zeros(b, num, dtype=torch.long, device=xyz.device)


def _fps_step(rows, dist: Tensor, last: Tensor) -> tuple[Tensor, Tensor]:
    """Distances updated with the point ``last`` (B,) and the next pick (B,)."""
    x, y, z = rows
    col = last[:, None]  # (B, 1)
    d = (x - x.gather(1, col)) ** 2 + (y - y.gather(1, col)) ** 2 + (z - z.gather(1, col)) ** 2
    dist = torch.minimum(dist, d)  # (B, N + 1) m^2
    return dist, torch.argmax(dist, dim=1)


def fps_loop(xyz: Tensor, num: int) -> Tensor:
    """FPS as a while_loop (exports to an ONNX Loop). xyz (B, N, 3) -> (B, num) long."""
    rows = _rows(xyz)
    dist, idx = _fps_start(xyz, num)
    step = torch.ones((), dtype=torch.long, device=xyz.device)
    last = torch.zeros(xyz.shape[0], dtype=torch.long, device=xyz.device)

    def cond(i: Tensor, last: Tensor, idx: Tensor, dist: Tensor) -> Tensor:
        return i < num

    def body(i: Tensor, last: Tensor, idx: Tensor, dist: Tensor):
        dist, nxt = _fps_step(rows, dist, last)
        col = i.reshape(1, 1).expand(idx.shape[0], 1)  # (B, 1)
        return i + 1, nxt, idx.scatter(1, col, nxt[:, None]), dist

    _, _, idx, _ = while_loop(cond, body, (step, last, idx, dist))
    return idx


def _fps_eager(xyz: Tensor, num: int) -> Tensor:
    """Same arithmetic as fps_loop as a Python loop (several times faster in eager mode)."""
    rows = _rows(xyz)
    dist, idx = _fps_start(xyz, num)
    last = idx[:, 0]
    for i in range(1, num):
        dist, last = _fps_step(rows, dist, last)
        idx[:, i] = last
    return idx


def farthest_point_sample(xyz: Tensor, num: int) -> Tensor:
    """Indices of farthest points, starting from point 0.

    xyz (N, 3) metres -> (min(N, num),) long (an empty cloud gives an empty index); or a batch
    xyz (B, N, 3) with num <= N -> (B, num).
    """
    if xyz.dim() not in (2, 3) or xyz.shape[-1] != 3:
        raise ValueError(f"farthest_point_sample: xyz must be (N, 3) or (B, N, 3), got {tuple(xyz.shape)}")
    if xyz.dim() == 3 and num > xyz.shape[1]:
        raise ValueError(f"farthest_point_sample: {num} samples from {xyz.shape[1]} points per batch row")
    batch = xyz if xyz.dim() == 3 else xyz[None]
    if tracing():
        idx = fps_loop(batch, num)
    elif _kernel_ready(batch):
        idx = farthest_point_sample_cpu(batch, num)
    else:
        idx = _fps_eager(batch, num)
    return idx if xyz.dim() == 3 else idx[0, : torch.sym_min(xyz.shape[0], num)]


def _kernel_ready(*tensors: Tensor) -> bool:
    """Eager float32 CPU tensors with at least one point each (in every batch row): the numba kernels of
    ``models.point_kernels`` apply (the same indices as the torch forms)."""
    return not tracing() and all(t.device.type == "cpu" and t.dtype == torch.float32 and t.numel() > 0
                                 for t in tensors)


def _direct_d2(xyz: Tensor, centres: Tensor, pad: int) -> Tensor:
    """(..., M, N + pad) float32 squared distances m^2 of centres (..., M, 3) to points (..., N, 3)
    and to ``pad`` padding points _FAR away (so that a TopK of up to ``pad`` entries never needs a
    wider copy of the matrix), summed x, y, z from (M, 1) - (N + pad,) rows like ``((c - x) ** 2).sum(-1)``.

    The direct form, not the GEMM ``|c|^2 + |x|^2 - 2 c x^T``: 70 m out the GEMM's rounding (about
    1e-3 m^2) exceeds a 0.1 m ball's r^2 / 10, and no fixed count of nominated candidates then holds
    the first neighbours of a dense ball."""
    far = xyz.new_full((*xyz.shape[:-2], pad, 3), _FAR)
    rows = torch.cat([xyz, far], -2).transpose(-1, -2)  # (..., 3, N + pad) axis-major
    cols = centres.transpose(-1, -2)  # (..., 3, M)
    d2 = None
    for axis in range(3):
        d = cols[..., axis, :, None] - rows[..., axis, None, :]  # (..., M, N + pad) m
        d2 = d * d if d2 is None else d2 + d * d
    return d2


def ball_queries(xyz: Tensor, centres: Tensor, radii: Sequence[float],
                 nsamples: Sequence[int]) -> list[tuple[Tensor, Tensor]]:
    """For every (radius, nsample): the first ``nsample`` points (in index order) strictly within
    ``radius`` of each centre.

    xyz (N, 3), centres (M, 3) metres, or batches of them (B, N, 3), (B, M, 3) -> [(idx
    (..., M, nsample) long in [0, N], valid (..., M) bool)]. Slots beyond the neighbour count
    repeat the first neighbour; a centre with no neighbour gets index N everywhere (the zero row
    appended by ``group_points``). (One frame stays 2-D: a batch axis of 1 over a dynamic point
    count makes the exporter guard on strides.)
    """
    if _kernel_ready(xyz, centres):
        return ball_queries_cpu(xyz, centres, radii, nsamples)
    return _ball_queries_torch(xyz, centres, radii, nsamples)


def _ball_queries_torch(xyz: Tensor, centres: Tensor, radii: Sequence[float],
                        nsamples: Sequence[int]) -> list[tuple[Tensor, Tensor]]:
    """:func:`ball_queries` in torch ops: the graph's form."""
    n, pad = xyz.shape[-2], max(nsamples)
    d2 = _direct_d2(xyz, centres, pad)  # (..., M, N + pad) m^2, one matrix for every radius
    order = torch.arange(n + pad, device=xyz.device, dtype=d2.dtype)  # (N + pad,) float indices, exact < 2^24
    out = []
    for radius, nsample in zip(radii, nsamples):
        key = torch.where(d2 < radius * radius, order, torch.full_like(d2, n))  # (..., M, N + pad)
        first = torch.topk(key, nsample, dim=-1, largest=False, sorted=True).values.long()  # (..., M, S)
        head = first[..., :1].expand_as(first)  # first neighbour (n if none)
        out.append((torch.where(first < n, first, head), first[..., 0] < n))
    return out


def ball_query(xyz: Tensor, centres: Tensor, radius: float, nsample: int) -> tuple[Tensor, Tensor]:
    """:func:`ball_queries` of one radius: xyz (N, 3), centres (M, 3) -> idx (M, nsample) long in
    [0, N], valid (M,) bool."""
    return ball_queries(xyz, centres, (radius,), (nsample,))[0]


def group_points(features: Tensor, idx: Tensor) -> Tensor:
    """features (N, C), idx (M, S) in [0, N] -> (M, S, C); index N reads a zero row."""
    padded = torch.cat([features, features.new_zeros(1, features.shape[1])], 0)  # (N+1, C)
    flat = torch.index_select(padded, 0, idx.reshape(-1))  # (M*S, C)
    return flat.reshape(idx.shape[0], idx.shape[1], features.shape[1])


def three_nn_interpolate(unknown: Tensor, known: Tensor, known_feats: Tensor) -> Tensor:
    """Inverse-distance weighted mean of the 3 nearest known points' features.

    unknown (N, 3), known (M, 3), known_feats (M, C) -> (N, C). Weights 1 / max(d, 1e-8) with d
    the Euclidean distance, normalised to sum 1 (a floor, not ``d + 1e-8``: coarse points are a
    subset of the fine ones, so zero distances are the rule, and the ONNX optimizer folds
    ``+ 1e-8`` away as ``+ 0``, leaving inf / inf). With fewer than 3 known points the missing
    neighbours are far padding points with zero features (no known point: zero output).
    """
    far = known.new_full((3, 3), _FAR)
    known_p = torch.cat([known, far], 0).T  # (3, M+3) axis-major
    feats_p = torch.cat([known_feats, known_feats.new_zeros(3, known_feats.shape[1])], 0)
    u = unknown.T  # (3, N)
    if _kernel_ready(unknown, known_p.T):  # the same neighbours without the (N, M+3) matrix, their distances as below
        idx = three_nn_cpu(unknown, known_p.T)  # (N, 3)
        dx, dy, dz = (u[i][:, None] - known_p[i][idx] for i in range(3))  # (N, 3) each
        d2_nn = dx * dx + dy * dy + dz * dz  # (N, 3) m^2
    else:
        dx, dy, dz = (u[i][:, None] - known_p[i] for i in range(3))  # (N, M+3) each: rows of (N, 1) - (M+3,)
        d2 = dx * dx + dy * dy + dz * dz  # (N, M+3) m^2 (Mul, not Pow: the same bits, faster in onnxruntime)
        d2_nn, idx = torch.topk(d2, 3, dim=1, largest=False, sorted=True)  # (N, 3)
    weight = 1.0 / torch.sqrt(d2_nn).clamp(min=1e-8)  # (N, 3)
    weight = weight / weight.sum(1, keepdim=True)
    neigh = group_points(feats_p, idx)  # (N, 3, C)
    return (neigh * weight[:, :, None]).sum(1)


def shared_mlp(channels: Sequence[int]) -> nn.Sequential:
    """Per-point Linear -> BatchNorm -> ReLU stack on (..., C) tensors."""
    layers: list[nn.Module] = []
    for c_in, c_out in zip(channels[:-1], channels[1:]):
        layers += [nn.Linear(c_in, c_out, bias=False), PointBatchNorm(c_out), nn.ReLU()]
    return nn.Sequential(*layers)


class PointBatchNorm(RowBatchNorm):
    """:class:`RowBatchNorm` over the last axis of (..., C)."""

    def forward(self, x: Tensor) -> Tensor:
        return super().forward(x.reshape(-1, x.shape[-1])).reshape(x.shape)


class SetAbstraction(nn.Module):
    """Multi-scale-grouping set abstraction: one ball query + shared MLP + max-pool per radius.

    forward(xyz (N, 3), feats (N, C) or None, centres (M, 3)) -> (M, sum of mlp[-1]).
    Grouped coordinates are relative to the centre (metres); empty balls give zero features, or
    with ``zero_empty`` False the MLP's output of an all-zero group (OpenPCDet's stacked
    ``QueryAndGroup`` zeroes an empty ball's coordinates and features, and its max-pool follows).
    """

    def __init__(self, in_channels: int, radii: Sequence[float], nsamples: Sequence[int],
                 mlps: Sequence[Sequence[int]], zero_empty: bool = True):
        super().__init__()
        self.zero_empty = zero_empty
        if not len(radii) == len(nsamples) == len(mlps):
            raise ValueError("SetAbstraction: radii, nsamples and mlps need the same length")
        self.radii = tuple(float(r) for r in radii)
        self.nsamples = tuple(int(s) for s in nsamples)
        self.mlps = nn.ModuleList(shared_mlp([in_channels + 3, *m]) for m in mlps)
        self.out_channels = sum(m[-1] for m in mlps)

    def forward(self, xyz: Tensor, feats: Tensor | None, centres: Tensor) -> Tensor:
        outs = []
        queries = ball_queries(xyz, centres, self.radii, self.nsamples)  # one distance GEMM
        for (idx, valid), mlp in zip(queries, self.mlps):  # (M, S), (M,)
            rel = group_points(xyz, idx) - centres[:, None, :]  # (M, S, 3) metres
            if not self.zero_empty:  # an empty ball groups zeros (its features read the zero row already)
                rel = rel * valid[:, None, None].to(rel.dtype)
            grouped = rel if feats is None else torch.cat([rel, group_points(feats, idx)], -1)
            pooled = mlp(grouped).amax(1)  # (M, C_out)
            outs.append(pooled * valid[:, None].to(pooled.dtype) if self.zero_empty else pooled)
        return torch.cat(outs, -1)


class FeaturePropagation(nn.Module):
    """3-NN interpolation of coarse features onto fine points, skip concat, shared MLP.

    forward(fine_xyz (N, 3), coarse_xyz (M, 3), fine_feats (N, Cf) or None,
    coarse_feats (M, Cc)) -> (N, mlp[-1]).
    """

    def __init__(self, channels: Sequence[int]):
        super().__init__()
        self.mlp = shared_mlp(channels)

    def forward(self, fine_xyz: Tensor, coarse_xyz: Tensor, fine_feats: Tensor | None,
                coarse_feats: Tensor) -> Tensor:
        up = three_nn_interpolate(fine_xyz, coarse_xyz, coarse_feats)  # (N, Cc)
        x = up if fine_feats is None else torch.cat([up, fine_feats], -1)
        return self.mlp(x)
