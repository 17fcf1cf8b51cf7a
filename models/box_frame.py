"""Points in the canonical frame of boxes, and point-in-box tests: the one implementation that
targets, RoI pooling and RoI support share.

Boxes are LiDAR-frame rows [x, y, z, l, w, h, yaw] with the geometric centre; a box's canonical
frame has its origin at the centre, x along the heading, y to its left and z up.
"""
from __future__ import annotations

import torch
from torch import Tensor


def rotate_to_box_frame(local: Tensor, boxes: Tensor) -> Tensor:
    """(K, S, 3) points relative to the centres of boxes (K, 7), rotated by -yaw of their box."""
    cos, sin = torch.cos(boxes[:, 6])[:, None], torch.sin(boxes[:, 6])[:, None]  # (K, 1)
    x = local[..., 0] * cos + local[..., 1] * sin  # rotation by -yaw
    y = -local[..., 0] * sin + local[..., 1] * cos
    return torch.stack([x, y, local[..., 2]], dim=-1)


def to_box_frame(xyz: Tensor, boxes: Tensor) -> Tensor:
    """Points (N, 3) in the canonical frame of every box (K, 7) -> (K, N, 3) metres."""
    return rotate_to_box_frame(xyz[None, :, :] - boxes[:, None, :3], boxes)


def inside_local(local: Tensor, boxes: Tensor, extra_width: float = 0.0) -> Tensor:
    """(K, N) bool: canonical points ``local`` (K, N, 3) strictly inside their box (K, 7) enlarged
    by ``extra_width`` metres in length, width and height (half on each side)."""
    half = (boxes[:, 3:6] + extra_width) / 2  # (K, 3) half extents, m
    inside = local.abs() < half[:, None, :]  # (K, N, 3)
    return inside[..., 0] & inside[..., 1] & inside[..., 2]


def inside_boxes(xyz: Tensor, boxes: Tensor, extra_width: float = 0.0) -> Tensor:
    """(K, N) bool: point (N, 3) strictly inside the box (K, 7) enlarged by extra_width metres."""
    return inside_local(to_box_frame(xyz, boxes), boxes, extra_width)
