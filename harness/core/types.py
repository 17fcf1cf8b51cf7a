"""Plain data classes shared by the simulator, the models and the harness.

Conventions (README, docs/simulator.md): LiDAR frame x forward, y left, z up, metres. Points are float32
(N, 4) = x, y, z, intensity in [0, 1]. A box row is [x, y, z, l, w, h, yaw] with (x, y, z)
the geometric centre and yaw counter-clockwise about +z from +x, wrapped to [-pi, pi).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CLASSES = ("Car",)  # the benchmarked class; Van is "ignored" and DontCare is "don't care" as in KITTI (training
# ignores Truck too: models.single_stage.IGNORED_CLASSES)


@dataclass
class Sample:
    """One frame as the models see it (training and evaluation)."""

    frame_id: str
    points: np.ndarray  # (N, 4) float32, LiDAR frame
    gt_boxes: np.ndarray  # (K, 7) float32, LiDAR frame, every labelled object
    gt_names: np.ndarray  # (K,) str, KITTI class names ("Car", "Van", "Truck", "DontCare", ...)
    image: np.ndarray | None = None  # (3, H, W) float32 RGB in [0, 1]
    lidar2img: np.ndarray | None = None  # (4, 4) float32, P2 @ R0_rect @ Tr_velo_to_cam

    def boxes_of(self, name: str = "Car") -> np.ndarray:
        """(k, 7) float32 boxes of one class."""
        return self.gt_boxes[self.gt_names == name].astype(np.float32)
