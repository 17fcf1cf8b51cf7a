"""Eager CPU kernels (numba) of farthest point sampling, ball query and the 3-nearest-neighbour
search: the same float32 arithmetic and the same indices as the torch forms in
``models/pointnet2.py``, which the ONNX graph keeps.

The torch forms pay a dispatch per op and iteration: FPS runs ~10 small ops per picked point
(PointRCNN picks 680 a frame, PV-RCNN 2,048 keypoints out of every voxel mean), and the ball query
builds full (M, N) distance, mask and key matrices for a TopK (the 3-NN search an (N, M) one:
PointRCNN's first feature propagation, 8,192 x 515, was its costliest point op). Here FPS is one pass over the points
per pick, and a ball query scans each centre's points in index order and stops when every radius
has its ``nsample`` neighbours. Distances are summed x, then y, then z in float32 (no fused
multiply-add), as torch sums them, so every comparison and every argmax tie falls the same way.
One exception: of known points at exactly the same distance, the 3-NN search takes the lower
index first, where ``torch.topk`` leaves the order of equal values unspecified.
"""
from __future__ import annotations

from typing import Sequence

import numba
import numpy as np
import torch
from torch import Tensor


_CHUNK = 256  # points whose distances to one centre are computed at once (a vectorised loop)


@numba.njit(cache=True)
def _fps_kernel(xyz: np.ndarray, num: int) -> np.ndarray:
    """(B, num) int64 farthest points of axis-major xyz (B, 3, N) float32, from point 0 (N >= 1)."""
    b, n = xyz.shape[0], xyz.shape[2]
    out = np.zeros((b, num), np.int64)
    dist = np.empty(n, np.float32)
    for r in range(b):
        x, y, z = xyz[r, 0], xyz[r, 1], xyz[r, 2]
        dist[:] = np.inf
        last = 0
        for i in range(1, num):
            lx, ly, lz = x[last], y[last], z[last]
            for j in range(n):  # vectorised: no branch
                dx, dy, dz = x[j] - lx, y[j] - ly, z[j] - lz
                d = dx * dx + dy * dy
                d = d + dz * dz
                dist[j] = min(dist[j], d)
            best, arg = np.float32(-1.0), n  # the padding column (distance -1) of the torch form
            for j in range(n):
                if dist[j] > best:  # strict: the first of equal maxima, as torch.argmax
                    best, arg = dist[j], j
            out[r, i] = arg
            last = arg
    return out


def farthest_point_sample_cpu(batch: Tensor, num: int) -> Tensor:
    """:func:`models.pointnet2._fps_eager` of a (B, N, 3) float32 CPU batch with N >= 1 -> (B, num)."""
    xyz = np.ascontiguousarray(batch.detach().numpy().transpose(0, 2, 1), dtype=np.float32)  # (B, 3, N)
    return torch.from_numpy(_fps_kernel(xyz, num))


@numba.njit(cache=True)
def _ball_kernel(xyz: np.ndarray, centres: np.ndarray, r2: np.ndarray, nsamples: np.ndarray) -> np.ndarray:
    """(R, B, M, S) int64: for each radius, the first nsample point indices (index order) with
    squared distance < r2, then -1. xyz (B, 3, N) axis-major, centres (B, M, 3)."""
    b, n, m = xyz.shape[0], xyz.shape[2], centres.shape[1]
    k, s = r2.shape[0], nsamples.max()
    r2max = r2.max()
    out = np.full((k, b, m, s), -1, np.int64)
    count = np.zeros(k, np.int64)
    d = np.empty(_CHUNK, np.float32)
    for r in range(b):
        x, y, z = xyz[r, 0], xyz[r, 1], xyz[r, 2]
        for c in range(m):
            cx, cy, cz = centres[r, c, 0], centres[r, c, 1], centres[r, c, 2]
            count[:] = 0
            full = 0
            for j0 in range(0, n, _CHUNK):
                j1 = min(n, j0 + _CHUNK)
                for j in range(j0, j1):  # vectorised
                    dx, dy, dz = cx - x[j], cy - y[j], cz - z[j]
                    e = dx * dx + dy * dy
                    d[j - j0] = e + dz * dz
                for j in range(j0, j1):
                    e = d[j - j0]
                    if e < r2max:
                        for q in range(k):
                            if count[q] < nsamples[q] and e < r2[q]:
                                out[q, r, c, count[q]] = j
                                count[q] += 1
                                if count[q] == nsamples[q]:
                                    full += 1
                if full == k:
                    break
    return out


def ball_queries_cpu(xyz: Tensor, centres: Tensor, radii: Sequence[float],
                     nsamples: Sequence[int]) -> list[tuple[Tensor, Tensor]]:
    """:func:`models.pointnet2.ball_queries` of float32 CPU tensors (N, 3) / (M, 3) or batches."""
    n = xyz.shape[-2]
    pts = xyz.detach().reshape(-1, n, 3).numpy()
    pts = np.ascontiguousarray(pts.transpose(0, 2, 1), dtype=np.float32)  # (B, 3, N) axis-major
    ctr = np.ascontiguousarray(centres.detach().reshape(pts.shape[0], -1, 3).numpy(), dtype=np.float32)
    r2 = np.array([r * r for r in radii], np.float32)  # torch compares float32 with the rounded r^2
    found = torch.from_numpy(_ball_kernel(pts, ctr, r2, np.array(nsamples, np.int64)))  # (R, B, M, S)
    out = []
    for q, nsample in enumerate(nsamples):
        first = found[q, ..., :nsample].reshape(*centres.shape[:-1], nsample)  # (..., M, S)
        first = torch.where(first < 0, torch.full_like(first, n), first)  # empty slots: n
        head = first[..., :1].expand_as(first)
        out.append((torch.where(first < n, first, head), first[..., 0] < n))
    return out


@numba.njit(cache=True)
def _three_nn_kernel(unknown: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(N, 3) int64 indices of the 3 nearest known points (M >= 3), nearest first."""
    out = np.zeros((unknown.shape[0], 3), np.int64)
    for i in range(unknown.shape[0]):
        ux, uy, uz = unknown[i, 0], unknown[i, 1], unknown[i, 2]
        best = np.full(3, np.inf, np.float32)
        arg = np.zeros(3, np.int64)
        for j in range(known.shape[0]):
            dx, dy, dz = ux - known[j, 0], uy - known[j, 1], uz - known[j, 2]
            d = dx * dx + dy * dy
            d = d + dz * dz
            if d < best[2]:  # insert, keeping equal distances in index order
                q = 2
                while q > 0 and d < best[q - 1]:
                    best[q], arg[q] = best[q - 1], arg[q - 1]
                    q -= 1
                best[q], arg[q] = d, j
        out[i] = arg
    return out


def three_nn_cpu(unknown: Tensor, known: Tensor) -> Tensor:
    """(N, 3) long: the 3 nearest rows of float32 CPU ``known`` (M >= 3, 3) for each row of
    ``unknown`` (N, 3), nearest first (``torch.topk(d2, 3, largest=False)``'s indices)."""
    u = np.ascontiguousarray(unknown.detach().numpy(), dtype=np.float32)
    k = np.ascontiguousarray(known.detach().numpy(), dtype=np.float32)
    return torch.from_numpy(_three_nn_kernel(u, k))
