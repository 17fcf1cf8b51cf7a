"""Training augmentation of one frame (points and boxes together, LiDAR frame).

Ground-truth database sampling (``harness.gt_database``, when a database is passed), then global
flip about the x axis (y -> -y), global rotation about z, global scaling, as in SECOND / OpenPCDet;
the random draws come from the ``numpy.random.Generator`` passed in.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from harness.core.boxes import wrap_angle
from harness.core.types import Sample
from harness.gt_database import GtDatabase, GtSamplingConfig, sample_objects


@dataclass(frozen=True)
class AugmentConfig:
    flip_y: bool = True  # mirror left/right with probability 0.5
    rotation: float = np.pi / 4  # max |global yaw rotation|, rad
    scale: tuple[float, float] = (0.95, 1.05)  # global scale range
    gt_sampling: GtSamplingConfig = field(default_factory=GtSamplingConfig)  # LiDAR-only models


def flip_y(points: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror about the x axis: y -> -y, yaw -> -yaw."""
    points, boxes = points.copy(), boxes.copy()
    points[:, 1] *= -1
    boxes[:, 1] *= -1
    boxes[:, 6] = wrap_angle(-boxes[:, 6])
    return points, boxes


def rotate_z(points: np.ndarray, boxes: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotate the scene by ``angle`` (rad, counter-clockwise) about the sensor's z axis."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]], dtype=np.float64)
    points, boxes = points.copy(), boxes.copy()
    points[:, :2] = (points[:, :2].astype(np.float64) @ rot.T).astype(points.dtype)
    boxes[:, :2] = (boxes[:, :2].astype(np.float64) @ rot.T).astype(boxes.dtype)
    boxes[:, 6] = wrap_angle(boxes[:, 6] + angle)
    return points, boxes


def scale(points: np.ndarray, boxes: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale positions and box sizes by ``factor`` (intensity and yaw unchanged)."""
    points, boxes = points.copy(), boxes.copy()
    points[:, :3] *= factor
    boxes[:, :6] *= factor
    return points, boxes


def _transform(flipped: bool, angle: float, factor: float) -> np.ndarray:
    """(4, 4) homogeneous map applied to the points: scale @ rotation @ flip."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    flip = np.diag([1.0, -1.0 if flipped else 1.0, 1.0, 1.0])
    return np.diag([factor, factor, factor, 1.0]) @ rot @ flip


def augment(sample: Sample, rng: np.random.Generator, cfg: AugmentConfig = AugmentConfig(),
            database: GtDatabase | None = None) -> Sample:
    """A randomly flipped, rotated and scaled copy of a sample, with objects of ``database``
    pasted in first when one is given and ``cfg.gt_sampling.enabled``.

    ``lidar2img`` (camera models) is composed with the inverse map, so the image still
    matches the moved points. Pasted objects would not be in the image: a sample with an
    image gets no ground-truth sampling (``ValueError``).
    """
    if database is not None and cfg.gt_sampling.enabled:
        if sample.image is not None or sample.lidar2img is not None:
            raise ValueError(f"frame {sample.frame_id}: ground-truth sampling of a frame with an image "
                             "would paste objects the image does not show")
        sample = sample_objects(sample, database, rng, cfg.gt_sampling)
    points, boxes = sample.points, sample.gt_boxes.reshape(-1, 7)
    flipped = bool(cfg.flip_y and rng.random() < 0.5)
    angle = float(rng.uniform(-cfg.rotation, cfg.rotation)) if cfg.rotation > 0 else 0.0
    factor = float(rng.uniform(*cfg.scale))
    if flipped:
        points, boxes = flip_y(points, boxes)
    points, boxes = rotate_z(points, boxes, angle)
    points, boxes = scale(points, boxes, factor)
    lidar2img = sample.lidar2img
    if lidar2img is not None:
        lidar2img = (lidar2img @ np.linalg.inv(_transform(flipped, angle, factor))).astype(np.float32)
    return replace(sample, points=points.astype(np.float32), gt_boxes=boxes.astype(np.float32),
                   lidar2img=lidar2img)
