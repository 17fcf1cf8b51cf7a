"""PointNet++ point operators in plain torch, exportable to standard ONNX ops.

One frame, no batch axis. Every operator accepts empty inputs:

- ``farthest_point_sample``: iterative FPS, a ``while_loop`` (ONNX ``Loop``) when exported and
  a Python loop in eager mode (same arithmetic, same result).
- ``ball_query``: squared distances + ``TopK`` of the first ``nsample`` in-radius indices, padded
  with the first neighbour like the CUDA op; a ball with no neighbour points at the zero row
  that ``group_points`` appends.
- ``three_nn_interpolate``: 3-NN inverse-distance interpolation for feature propagation.
- ``SetAbstraction``: multi-scale grouping (several radii), shared MLP, max-pool.
- ``FeaturePropagation``: interpolation + skip concatenation + shared MLP.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn
from torch._higher_order_ops.while_loop import while_loop

from models.base import tracing
from models.vfe import RowBatchNorm

_FAR = 1.0e4  # metres; position of the padding points used by three_nn_interpolate


def _fps_graph(xyz: Tensor, num: int) -> Tensor:
    """FPS as a while_loop (exports to an ONNX Loop). xyz (N, 3) -> (num,) long."""
    n = xyz.shape[0]
    padded = torch.cat([xyz, xyz.new_zeros(1, 3)], 0)  # (N+1, 3); row N never wins unless N == 0
    dist = torch.cat([xyz.new_full((n,), float("inf")), xyz.new_full((1,), -1.0)])  # (N+1,)
    idx = torch.zeros(num, dtype=torch.long, device=xyz.device)  # (num,) first pick: point 0
    step = torch.ones(1, dtype=torch.long, device=xyz.device)
    last = torch.zeros(1, dtype=torch.long, device=xyz.device)

    def cond(i: Tensor, last: Tensor, idx: Tensor, dist: Tensor) -> Tensor:
        return (i < num).squeeze(0)

    def body(i: Tensor, last: Tensor, idx: Tensor, dist: Tensor):
        centre = torch.index_select(padded, 0, last)  # (1, 3)
        dist = torch.minimum(dist, ((padded - centre) ** 2).sum(-1))  # (N+1,) m^2
        nxt = torch.argmax(dist).reshape(1)
        return i + 1, nxt, idx.scatter(0, i, nxt), dist

    _, _, idx, _ = while_loop(cond, body, (step, last, idx, dist))
    return idx


def _fps_eager(xyz: Tensor, num: int) -> Tensor:
    """Same algorithm as _fps_graph as a Python loop (several times faster in eager mode)."""
    n = xyz.shape[0]
    padded = torch.cat([xyz, xyz.new_zeros(1, 3)], 0)
    dist = torch.cat([xyz.new_full((n,), float("inf")), xyz.new_full((1,), -1.0)])
    idx = torch.zeros(num, dtype=torch.long, device=xyz.device)
    last = 0
    for i in range(1, num):
        dist = torch.minimum(dist, ((padded - padded[last]) ** 2).sum(-1))
        last = int(torch.argmax(dist))
        idx[i] = last
    return idx


def farthest_point_sample(xyz: Tensor, num: int) -> Tensor:
    """Indices of ``min(N, num)`` farthest points, starting from point 0.

    xyz: (N, 3) metres. Returns (min(N, num),) long; an empty cloud gives an empty index.
    """
    if xyz.dim() != 2 or xyz.shape[1] != 3:
        raise ValueError(f"farthest_point_sample: xyz must be (N, 3), got {tuple(xyz.shape)}")
    idx = _fps_graph(xyz, num) if tracing() else _fps_eager(xyz, num)
    return idx[: torch.sym_min(xyz.shape[0], num)]


def ball_query(xyz: Tensor, centres: Tensor, radius: float, nsample: int) -> tuple[Tensor, Tensor]:
    """First ``nsample`` points (in index order) within ``radius`` of each centre.

    xyz: (N, 3), centres: (M, 3), metres. Returns idx (M, nsample) long in [0, N] and
    valid (M,) bool. Slots beyond the neighbour count repeat the first neighbour; a centre with
    no neighbour gets index N everywhere (the zero row appended by ``group_points``).
    """
    n = xyz.shape[0]
    d2 = ((centres[:, None, :] - xyz[None, :, :]) ** 2).sum(-1)  # (M, N) m^2
    order = torch.arange(n, device=xyz.device).expand_as(d2)  # (M, N)
    key = torch.where(d2 < radius * radius, order, torch.full_like(order, n))  # (M, N)
    key = torch.cat([key, key.new_full((key.shape[0], nsample), n)], 1)  # (M, N+nsample)
    first, _ = torch.topk(key, nsample, dim=1, largest=False, sorted=True)  # (M, nsample)
    valid = first[:, 0] < n  # (M,)
    head = first[:, :1].expand_as(first)  # (M, nsample) first neighbour (n if none)
    idx = torch.where(first < n, first, head)
    return idx, valid


def group_points(features: Tensor, idx: Tensor) -> Tensor:
    """features (N, C), idx (M, S) in [0, N] -> (M, S, C); index N reads a zero row."""
    padded = torch.cat([features, features.new_zeros(1, features.shape[1])], 0)  # (N+1, C)
    flat = torch.index_select(padded, 0, idx.reshape(-1))  # (M*S, C)
    return flat.reshape(idx.shape[0], idx.shape[1], features.shape[1])


def three_nn_interpolate(unknown: Tensor, known: Tensor, known_feats: Tensor) -> Tensor:
    """Inverse-distance weighted mean of the 3 nearest known points' features.

    unknown (N, 3), known (M, 3), known_feats (M, C) -> (N, C). Weights 1 / (d + 1e-8) with d
    the Euclidean distance, normalised to sum 1. With fewer than 3 known points the missing
    neighbours are far padding points with zero features (no known point: zero output).
    """
    far = known.new_full((3, 3), _FAR)
    known_p = torch.cat([known, far], 0)  # (M+3, 3)
    feats_p = torch.cat([known_feats, known_feats.new_zeros(3, known_feats.shape[1])], 0)
    d2 = ((unknown[:, None, :] - known_p[None, :, :]) ** 2).sum(-1)  # (N, M+3) m^2
    d2_nn, idx = torch.topk(d2, 3, dim=1, largest=False, sorted=True)  # (N, 3)
    weight = 1.0 / (torch.sqrt(d2_nn) + 1e-8)  # (N, 3)
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
    Grouped coordinates are relative to the centre (metres); empty balls give zero features.
    """

    def __init__(self, in_channels: int, radii: Sequence[float], nsamples: Sequence[int],
                 mlps: Sequence[Sequence[int]]):
        super().__init__()
        if not len(radii) == len(nsamples) == len(mlps):
            raise ValueError("SetAbstraction: radii, nsamples and mlps need the same length")
        self.radii = tuple(float(r) for r in radii)
        self.nsamples = tuple(int(s) for s in nsamples)
        self.mlps = nn.ModuleList(shared_mlp([in_channels + 3, *m]) for m in mlps)
        self.out_channels = sum(m[-1] for m in mlps)

    def forward(self, xyz: Tensor, feats: Tensor | None, centres: Tensor) -> Tensor:
        outs = []
        for radius, nsample, mlp in zip(self.radii, self.nsamples, self.mlps):
            idx, valid = ball_query(xyz, centres, radius, nsample)  # (M, S), (M,)
            rel = group_points(xyz, idx) - centres[:, None, :]  # (M, S, 3) metres
            grouped = rel if feats is None else torch.cat([rel, group_points(feats, idx)], -1)
            pooled = mlp(grouped).amax(1)  # (M, C_out)
            outs.append(pooled * valid[:, None].to(pooled.dtype))
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
