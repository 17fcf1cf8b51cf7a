"""Second-stage pooling: RoI-aware point pooling (Part-A2) and RoI-grid pooling (PV-RCNN).

Boxes are LiDAR-frame rows [x, y, z, l, w, h, yaw] with the geometric centre. Both poolers are
plain tensor ops (nonzero, gather, ScatterElements with max / add reduction) so they export to
ONNX; an RoI that holds no point yields zeros.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from models.box_frame import inside_local, to_box_frame
from models.pointnet2 import SetAbstraction


def roi_voxel_pairs(rois: Tensor, xyz: Tensor, out_size: Sequence[int]) -> tuple[Tensor, Tensor]:
    """Which point falls in which cell of which RoI grid.

    rois (K, 7), xyz (N, 3), out_size (ox, oy, oz) cells along (l, w, h). Returns cell (P,) long,
    the flat cell index k * ox*oy*oz + (ix*oy + iy)*oz + iz, and point (P,) long, for the P
    (RoI, point) pairs with the point strictly inside the RoI.
    """
    local = to_box_frame(xyz, rois)  # (K, N, 3)
    half = rois[:, None, 3:6] / 2  # (K, 1, 3)
    inside = inside_local(local, rois)  # (K, N)
    pair = torch.nonzero(inside)  # (P, 2): roi, point
    k, p = pair[:, 0], pair[:, 1]
    size = torch.tensor(list(out_size), dtype=xyz.dtype, device=xyz.device)  # (3,)
    lp = local[k, p]  # (P, 3)
    frac = (lp + half[k, 0]) / rois[k, 3:6]  # (P, 3) in (0, 1)
    cell3 = torch.minimum(torch.floor(frac * size), size - 1).clamp(min=0).long()  # (P, 3)
    ox, oy, oz = out_size
    cell = k * (ox * oy * oz) + (cell3[:, 0] * oy + cell3[:, 1]) * oz + cell3[:, 2]
    return cell, p


def roiaware_pool(rois: Tensor, xyz: Tensor, max_feats: Tensor, avg_feats: Tensor,
                  out_size: Sequence[int]) -> tuple[Tensor, Tensor]:
    """RoI-aware point cloud pooling: per RoI cell, max of ``max_feats``, mean of ``avg_feats``.

    rois (K, 7), xyz (N, 3), max_feats (N, Cm), avg_feats (N, Ca).
    Returns (K, ox, oy, oz, Cm) and (K, ox, oy, oz, Ca); empty cells are zero.
    """
    cell, p = roi_voxel_pairs(rois, xyz, out_size)  # (P,), (P,)
    n_cells = rois.shape[0] * out_size[0] * out_size[1] * out_size[2]
    shape = (rois.shape[0], *out_size)
    fm = max_feats.index_select(0, p)  # (P, Cm)
    pooled_max = fm.new_full((n_cells, fm.shape[1]), float("-inf"))
    pooled_max = pooled_max.scatter_reduce(0, cell[:, None].expand_as(fm), fm, "amax")
    pooled_max = torch.where(torch.isinf(pooled_max), torch.zeros_like(pooled_max), pooled_max)
    fa = avg_feats.index_select(0, p)  # (P, Ca)
    total = fa.new_zeros(n_cells, fa.shape[1]).index_add(0, cell, fa)
    count = fa.new_zeros(n_cells).index_add(0, cell, torch.ones_like(cell, dtype=fa.dtype))
    pooled_avg = total / count.clamp(min=1.0)[:, None]
    return (pooled_max.reshape(*shape, max_feats.shape[1]),
            pooled_avg.reshape(*shape, avg_feats.shape[1]))


def roi_grid_points(rois: Tensor, grid: int) -> Tensor:
    """Cell centres of a grid x grid x grid lattice in every RoI, LiDAR frame.

    rois (K, 7) -> (K, grid**3, 3) metres, ordered (i along l, j along w, k along h).
    """
    steps = (torch.arange(grid, dtype=rois.dtype, device=rois.device) + 0.5) / grid - 0.5
    gi, gj, gk = torch.meshgrid(steps, steps, steps, indexing="ij")
    unit = torch.stack([gi, gj, gk], -1).reshape(-1, 3)  # (G, 3) in [-0.5, 0.5]
    local = unit[None] * rois[:, None, 3:6]  # (K, G, 3)
    c, s = torch.cos(rois[:, 6])[:, None], torch.sin(rois[:, 6])[:, None]
    x = local[..., 0] * c - local[..., 1] * s
    y = local[..., 0] * s + local[..., 1] * c
    return torch.stack([x, y, local[..., 2]], -1) + rois[:, None, 0:3]


class RoIGridPool(nn.Module):
    """RoI-grid pooling: each grid point aggregates keypoint features by multi-radius ball query.

    forward(rois (K, 7), kp_xyz (P, 3), kp_feats (P, C)) -> (K, grid**3, out_channels).
    """

    def __init__(self, in_channels: int, grid: int, radii: Sequence[float],
                 nsamples: Sequence[int], mlps: Sequence[Sequence[int]]):
        super().__init__()
        self.grid = grid
        self.sa = SetAbstraction(in_channels, radii, nsamples, mlps)
        self.out_channels = self.sa.out_channels

    def forward(self, rois: Tensor, kp_xyz: Tensor, kp_feats: Tensor) -> Tensor:
        points = roi_grid_points(rois, self.grid)  # (K, G, 3)
        pooled = self.sa(kp_xyz, kp_feats, points.reshape(-1, 3))  # (K*G, C)
        return pooled.reshape(rois.shape[0], self.grid ** 3, self.out_channels)
