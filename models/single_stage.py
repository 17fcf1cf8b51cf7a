"""Shared skeleton of the one-stage anchor detectors (PointPillars, SECOND, DV-SECOND), and the
BEV first stage that every sparse-backbone detector builds the same way (``bev_stages``).

A subclass defines ``bev(points) -> (1, C, H, W)`` (its voxel encoder and 3D stage) and owns
``backbone2d`` and ``head``; forward and loss then read: BEV map -> 2D backbone -> anchor head.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from harness.core.types import Sample
from models.anchor_head import AnchorHead, HeadConfig
from models.backbone2d import BEVBackbone
from models.base import Detector, mean_over_frames
from models.multiclass_head import make_head
from models.voxel_backbone import VoxelBackboneConfig, output_shape
from models.voxelize import Grid

# not Car, but not background either: KITTI's Van and DontCare, and Truck (a car-sized box on a truck's rear is
# what a braking system needs, so the Car head is not taught that trucks are nothing)
IGNORED_CLASSES = ("Van", "Truck", "DontCare")


def frame_targets(sample: Sample, device) -> tuple[Tensor, Tensor, Tensor]:
    """points (N, 4), Car boxes (K, 7) and ignored boxes (J, 7) of a sample, as tensors."""
    ignore = np.isin(sample.gt_names, IGNORED_CLASSES)
    return (torch.as_tensor(np.asarray(sample.points, np.float32), device=device),
            torch.as_tensor(sample.boxes_of("Car"), device=device),
            torch.as_tensor(np.asarray(sample.gt_boxes, np.float32)[ignore].reshape(-1, 7),
                            device=device))


class AnchorDetector(Detector):
    """points -> bev() -> backbone2d -> head (detect / loss)."""

    def bev(self, points: Tensor) -> Tensor:
        raise NotImplementedError

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """points (N, 4) -> boxes (M, 7), scores (M,)."""
        return self.head.detect(self.backbone2d(self.bev(points)))

    def loss(self, samples: list[Sample]) -> dict[str, Tensor]:
        """Mean over frames of the head losses."""
        device = next(self.parameters()).device
        return mean_over_frames((self.head.loss(self.backbone2d(self.bev(points)), gt, ignore)
                                 for points, gt, ignore in (frame_targets(s, device) for s in samples)), len(samples))


def bev_stages(grid: Grid, backbone3d: VoxelBackboneConfig, pc_range, head: HeadConfig, layers, strides,
               filters, upsample_strides, upsample_filters) -> tuple[BEVBackbone, AnchorHead]:
    """The first stage after a sparse 3D backbone (SECOND, DV-SECOND, MVX-Net, Part-A2, PV-RCNN):
    its z-collapsed BEV map (C * D channels) -> 2D backbone -> anchor head on the backbone's
    output map (``upsample_strides[0] / strides[0]`` cells per BEV cell)."""
    d, h, w = output_shape(grid.shape, backbone3d)
    backbone2d = BEVBackbone(backbone3d.out_channels * d, layers, strides, filters, upsample_strides,
                             upsample_filters)
    up = upsample_strides[0] / strides[0]
    return backbone2d, make_head(backbone2d.out_channels, (round(h * up), round(w * up)), pc_range, head)
