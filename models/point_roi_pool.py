"""PointRCNN's point RoI pooling with canonical transformation (OpenPCDet ``RoIPointPool3d``).

For every RoI (box row [x, y, z, l, w, h, yaw], LiDAR frame, geometric centre):

1. enlarge the box by ``extra_width`` metres in length, width and height (half on each side);
2. take the points inside the enlarged box, the first ``num_samples`` in point order; when
   fewer are inside, repeat them cyclically (slot j holds inside point j mod count), as the
   CUDA op does; a RoI with no point inside is flagged empty and gets zero rows;
3. express their coordinates in the RoI's canonical frame: centre subtracted, rotated by
   -yaw about +z (x along the RoI heading, y to its left, z up).

Everything is dense tensor algebra (broadcast transform, TopK, gather) so it exports to
standard ONNX ops and handles zero points or zero RoIs.
"""
from __future__ import annotations

import torch
from torch import Tensor


def to_canonical(xyz: Tensor, rois: Tensor) -> Tensor:
    """Points (N, 3) expressed in the frame of every RoI (K, 7) -> (K, N, 3) metres."""
    return rotate_to_canonical(xyz[None, :, :] - rois[:, None, :3], rois)  # (K, N, 3)


def rotate_to_canonical(local: Tensor, rois: Tensor) -> Tensor:
    """(K, S, 3) points relative to RoI centres, rotated by -yaw of their RoI (K, 7)."""
    cos, sin = torch.cos(rois[:, 6])[:, None], torch.sin(rois[:, 6])[:, None]  # (K, 1)
    x = local[..., 0] * cos + local[..., 1] * sin  # rotation by -yaw
    y = -local[..., 0] * sin + local[..., 1] * cos
    return torch.stack([x, y, local[..., 2]], dim=-1)


def inside_rois(xyz: Tensor, rois: Tensor, extra_width: float = 0.0) -> Tensor:
    """(K, N) bool: point strictly inside the RoI enlarged by extra_width metres per dimension."""
    local = to_canonical(xyz, rois)  # (K, N, 3)
    half = (rois[:, 3:6] + extra_width) / 2  # (K, 3) half extents, m
    return (local.abs() < half[:, None, :]).all(dim=-1)


def sample_indices(inside: Tensor, num_samples: int) -> tuple[Tensor, Tensor]:
    """First ``num_samples`` inside points per RoI, repeated cyclically when fewer.

    inside (K, N) bool -> idx (K, num_samples) long in [0, N] (N for empty RoIs) and
    empty (K,) bool.
    """
    k, n = inside.shape
    order = torch.arange(n, device=inside.device).expand(k, n)  # (K, N)
    key = torch.where(inside, order, torch.full_like(order, n))
    key = torch.cat([key, key.new_full((k, num_samples), n)], dim=1)  # (K, N + S)
    first, _ = torch.topk(key, num_samples, dim=1, largest=False, sorted=True)  # (K, S)
    count = inside.sum(dim=1, keepdim=True)  # (K, 1)
    slot = torch.arange(num_samples, device=inside.device)[None, :]  # (1, S)
    cyclic = torch.remainder(slot, count.clamp(min=1))  # (K, S)
    idx = torch.gather(first, 1, cyclic)  # (K, S); all N for an empty RoI
    return idx, count[:, 0] == 0


def roi_point_pool(
    xyz: Tensor, feats: Tensor, rois: Tensor, num_samples: int, extra_width: float
) -> tuple[Tensor, Tensor]:
    """Pool the points of every RoI into its canonical frame.

    xyz (N, 3) m; feats (N, C); rois (K, 7). Returns pooled (K, S, 3 + C) = canonical xyz
    followed by the point features, and empty (K,) bool (pooled rows are zero for empty RoIs).
    """
    inside = inside_rois(xyz, rois, extra_width)  # (K, N)
    idx, empty = sample_indices(inside, num_samples)  # (K, S), (K,)
    table = torch.cat([xyz, feats], dim=1)  # (N, 3 + C)
    table = torch.cat([table, table.new_zeros(1, table.shape[1])], dim=0)  # (N + 1, 3 + C)
    rows = torch.index_select(table, 0, idx.reshape(-1)).reshape(idx.shape[0], num_samples, table.shape[1])
    local = rotate_to_canonical(rows[..., :3] - rois[:, None, :3], rois)  # (K, S, 3)
    keep = (~empty)[:, None, None].to(rows.dtype)  # (K, 1, 1)
    return torch.cat([local, rows[..., 3:]], dim=-1) * keep, empty
