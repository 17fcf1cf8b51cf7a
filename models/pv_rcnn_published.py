"""OpenPCDet's PV-RCNN pieces (``tools/cfgs/kitti_models/pv_rcnn.yaml``) where they differ from ours: the
``kitti`` profile of ``models/pv_rcnn.py`` is built from them (docs/models.md lists the differences).

- ``in_range_points``: the raw points the network sees (``mask_points_by_range``: x and y within the
  range, ends included, z not filtered), from which the keypoints are sampled and the raw-point set
  abstraction groups.
- ``sample_keypoints``: farthest point sampling from point 0, the picks repeated in order when the cloud
  holds fewer points than keypoints (``VoxelSetAbstraction.get_sampled_points``).
- ``bev_features``: ``bilinear_interpolate_torch`` of the height-compressed map at the keypoints, pixel i
  at x0 + i * stride * voxel (its corner, not its centre), with its index clamps.
- ``PublishedVSA``: [BEV, raw points, x_conv1..x_conv4] concatenated in that order (640 channels), fused
  by Linear-BN-ReLU to 128; ``PointHeadSimple`` (CLS_FC 256-256, class-agnostic) reads the features
  before the fusion (``USE_POINT_FEATURES_BEFORE_FUSION``) and its sigmoid weights the fused ones (the
  weighting of ``PVRCNNHead.roi_grid_pool``). Every set abstraction pools the MLP of an all-zero group
  for an empty ball, as the stacked ``QueryAndGroup``, and squares its radius as the CUDA kernel does.
- ``grid_points`` / ``PublishedRoIGridPool``: the 6 x 6 x 6 RoI grid points as ``PVRCNNHead`` computes
  them (a ``matmul`` by the rotation matrix: the same float32 bits, which the ball query's radius test
  needs), pooled features laid out channel-major as its flatten reads them.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor, nn

from models.base import no_autocast
from models.pointnet2 import PointBatchNorm, SetAbstraction, farthest_point_sample


def in_range_points(points: Tensor, pc_range: Sequence[float]) -> Tensor:
    """(N', 4) the points (N, 4) whose x and y lie within the range, ends included (any z)."""
    x0, y0, _, x1, y1, _ = pc_range
    keep = (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)
    return points[keep]


def sample_keypoints(points: Tensor, num: int) -> Tensor:
    """(num, 3) farthest-point-sampled keypoints of points (N, >= 3), from point 0; with N < num the N
    picks repeat in order (an empty cloud: keypoints at the origin)."""
    idx = farthest_point_sample(points[:, :3], num)  # (min(N, num),)
    picked = torch.ones_like(idx).sum().clamp(min=1)  # (,) the count as a tensor (dynamic in the graph)
    pick = torch.cat([idx, idx.new_zeros(1)])[torch.arange(num, device=idx.device) % picked]  # (num,)
    return torch.cat([points[:, :3], points.new_zeros(1, 3)])[pick]


def bev_features(bev: Tensor, xyz: Tensor, pc_range: Sequence[float], voxel_size: Sequence[float],
                 stride: int) -> Tensor:
    """bev (C, H, W) map at the keypoints xyz (P, 3) -> (P, C): OpenPCDet's bilinear_interpolate_torch."""
    c, h, w = bev.shape
    x = (xyz[:, 0] - pc_range[0]) / voxel_size[0] / stride  # (P,) map pixels, pixel i at its corner
    y = (xyz[:, 1] - pc_range[1]) / voxel_size[1] / stride
    x0, y0 = torch.floor(x).long(), torch.floor(y).long()
    x1, y1 = (x0 + 1).clamp(0, w - 1), (y0 + 1).clamp(0, h - 1)
    x0, y0 = x0.clamp(0, w - 1), y0.clamp(0, h - 1)
    rows = bev.reshape(c, h * w).t()  # (H*W, C): whole rows gathered on axis 0

    def at(yy: Tensor, xx: Tensor) -> Tensor:
        return rows.index_select(0, yy * w + xx)  # (P, C)

    fx0, fx1, fy0, fy1 = x0.to(x.dtype), x1.to(x.dtype), y0.to(y.dtype), y1.to(y.dtype)
    wa, wb = (fx1 - x) * (fy1 - y), (fx1 - x) * (y - fy0)  # (P,) the clamped corners' weights, as OpenPCDet
    wc, wd = (x - fx0) * (fy1 - y), (x - fx0) * (y - fy0)
    return (at(y0, x0) * wa[:, None] + at(y1, x0) * wb[:, None] + at(y0, x1) * wc[:, None]
            + at(y1, x1) * wd[:, None])


def cuda_radii(radii: Sequence[float]) -> tuple[float, ...]:
    """The radii rounded to float32: the stacked ball query squares ``float radius`` in float32, whose
    square is the float32 rounding of the rounded radius's exact square (1 ulp above ours for 0.4, 0.8 and
    1.6 m)."""
    return tuple(torch.tensor(radii, dtype=torch.float32).tolist())


def point_head(c_in: int, widths: Sequence[int]) -> nn.Sequential:
    """OpenPCDet's PointHeadTemplate.make_fc_layers: [Linear (no bias), BN, ReLU] per width, Linear(., 1)."""
    layers: list[nn.Module] = []
    for c_out in widths:
        layers += [nn.Linear(c_in, c_out, bias=False), PointBatchNorm(c_out), nn.ReLU()]
        c_in = c_out
    layers.append(nn.Linear(c_in, 1))
    nn.init.constant_(layers[-1].bias, -math.log((1 - 0.01) / 0.01))  # focal-loss prior
    return nn.Sequential(*layers)


class PublishedVSA(nn.Module):
    """OpenPCDet's VoxelSetAbstraction with PointHeadSimple's keypoint weighting (module docstring).

    forward(keypoints (P, 3), points (N, 4) raw x y z intensity, levels [(xyz (V_i, 3), feats (V_i, C_i))]
    for x_conv1..4, bev (1, C, H, W)) -> (weighted features (P, kp_channels), foreground logit (P,)).
    ``cfg``: a ``models.pv_rcnn.PublishedPVRCNNConfig``.
    """

    def __init__(self, cfg, level_channels: list[int], bev_channels: int, bev_stride: int):
        super().__init__()
        self.cfg, self.bev_stride = cfg, bev_stride
        self.raw = SetAbstraction(1, cuda_radii(cfg.raw_radii), cfg.raw_nsamples, cfg.raw_mlps, zero_empty=False)
        self.levels = nn.ModuleList(
            SetAbstraction(c, cuda_radii(radii), nsamples, [(c, c)] * len(radii), zero_empty=False)
            for c, radii, nsamples in zip(level_channels, cfg.level_radii, cfg.level_nsample_sets))
        total = bev_channels + self.raw.out_channels + sum(s.out_channels for s in self.levels)
        self.fuse = nn.Sequential(nn.Linear(total, cfg.kp_channels, bias=False),
                                  PointBatchNorm(cfg.kp_channels), nn.ReLU())
        self.weight = point_head(total, cfg.kp_fc)

    def forward(self, keypoints: Tensor, points: Tensor, levels: list[tuple[Tensor, Tensor]],
                bev: Tensor) -> tuple[Tensor, Tensor]:
        c = self.cfg
        parts = [bev_features(bev[0], keypoints, c.pc_range, c.voxel_size, self.bev_stride),  # (P, C_bev)
                 self.raw(points[:, :3], points[:, 3:4], keypoints)]  # (P, C_raw)
        parts += [sa(xyz, feats, keypoints) for sa, (xyz, feats) in zip(self.levels, levels)]  # (P, C_level)
        before = torch.cat(parts, 1)  # (P, 640) point_features_before_fusion
        logit = self.weight(before).squeeze(1).float()  # (P,) float32 also under autocast (its loss)
        return self.fuse(before) * torch.sigmoid(logit)[:, None], logit


def grid_points(rois: Tensor, grid: int) -> Tensor:
    """(K, grid**3, 3) RoI grid points of rois (K, 7), cells ordered (x, y, z) along (l, w, h): PVRCNNHead's
    get_global_grid_points_of_roi, the same ops (the rotation a matmul) so that the same RoIs give the same bits."""
    steps = torch.arange(grid, device=rois.device)
    idx = torch.stack(torch.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(1, -1, 3).float()  # (1, G, 3)
    size = rois[:, None, 3:6]  # (K, 1, 3)
    local = (idx + 0.5) / grid * size - size / 2  # (K, G, 3) metres
    c, s = torch.cos(rois[:, 6]), torch.sin(rois[:, 6])
    zeros, ones = torch.zeros_like(c), torch.ones_like(c)
    rot = torch.stack((c, s, zeros, -s, c, zeros, zeros, zeros, ones), 1).view(-1, 3, 3)  # (K, 3, 3)
    with no_autocast(rois.device.type):
        return torch.matmul(local, rot) + rois[:, None, 0:3]


class PublishedRoIGridPool(nn.Module):
    """PVRCNNHead's RoI-grid pooling: forward(rois (K, 7), kp_xyz (P, 3), kp_feats (P, C)) ->
    (K, out_channels, grid**3), channel-major as its flatten reads it."""

    def __init__(self, in_channels: int, grid: int, radii: Sequence[float], nsamples: Sequence[int],
                 mlps: Sequence[Sequence[int]]):
        super().__init__()
        self.grid = grid
        self.sa = SetAbstraction(in_channels, cuda_radii(radii), nsamples, mlps, zero_empty=False)
        self.out_channels = self.sa.out_channels

    def forward(self, rois: Tensor, kp_xyz: Tensor, kp_feats: Tensor) -> Tensor:
        points = grid_points(rois, self.grid)  # (K, G, 3)
        pooled = self.sa(kp_xyz, kp_feats, points.reshape(-1, 3))  # (K*G, C)
        return pooled.reshape(rois.shape[0], self.grid ** 3, self.out_channels).transpose(1, 2)
