"""Shared skeleton of the one-stage anchor detectors (PointPillars, SECOND, DV-SECOND).

A subclass defines ``bev(points) -> (1, C, H, W)`` (its voxel encoder and 3D stage) and owns
``backbone2d`` and ``head``; forward and loss then read: BEV map -> 2D backbone -> anchor head.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from harness.types import Sample
from models.base import Detector

IGNORED_CLASSES = ("Van", "DontCare")  # KITTI: not Car, but not background either


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
        """Mean over frames of the head losses (frames run one by one: no batch axis)."""
        device = next(self.parameters()).device
        totals: dict[str, Tensor] = {}
        for sample in samples:
            points, gt, ignore = frame_targets(sample, device)
            losses = self.head.loss(self.backbone2d(self.bev(points)), gt, ignore)
            for k, v in losses.items():
                totals[k] = totals.get(k, 0.0) + v / len(samples)
        return totals
