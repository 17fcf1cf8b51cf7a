"""KITTI labels of a frame: 3D boxes from the vehicle meshes, 2D boxes, truncation, occlusion.

- 2D box: the box's projected corners (near-clipped), clipped to the image.
- truncation: share of the object's volume (a lattice of points in its 3D box) that the camera
  does not see in its image: outside the image or behind the camera.
- occlusion: share v of the object's camera rays (a grid over its 2D box, cast against the
  object alone) whose first hit in the full scene is the object: 0 if v >= 0.75,
  1 if v >= 0.4, 2 if v >= 0.05, else 3.
- DontCare (as KITTI): objects in the image but beyond `max_label_distance`, or not visible.
  Their rows come after every object row, as in KITTI's files (OpenPCDet's and MMDetection3D's
  loaders take the first rows as the objects); unlike KITTI's placeholders they keep the
  vehicle's 3D box, which training uses as a region whose anchors are neither car nor background.
- Objects outside the camera's image are not labelled. Rows are ordered by distance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from harness.core.boxes import box_to_lidar, corners_3d, wrap_angle
from harness.core.kitti import Calib, Labels
from simulator.lidar import Pose
from simulator.raycast import RayScene, rays_hit_triangles
from simulator.vehicles import Vehicle

OCCLUSION_LEVELS = (0.75, 0.4, 0.05)  # visible share thresholds for levels 0, 1, 2
TRUNCATION_GRID = 8  # lattice points per box side for the truncation share


@dataclass(frozen=True)
class LabelConfig:
    width: int = 1242
    height: int = 375
    max_label_distance: float = 80.0  # m
    occlusion_grid: int = 12  # rays per side of the 2D box


def lidar_boxes(vehicles: list[Vehicle], pose: Pose, mount_height: float) -> np.ndarray:
    """(K, 7) boxes of the vehicles in the LiDAR frame."""
    if not vehicles:
        return np.zeros((0, 7))
    centres = np.array([[v.x, v.y, v.z] for v in vehicles])
    local = pose.to_lidar(centres, mount_height)
    dims = np.array([v.dims for v in vehicles])
    yaw = wrap_angle(np.array([v.heading for v in vehicles]) - pose.yaw)
    return np.concatenate([local, dims, yaw[:, None]], 1)


def projected_boxes(boxes: np.ndarray, calib: Calib) -> tuple[np.ndarray, np.ndarray]:
    """Unclipped (K, 4) 2D boxes (corners near-clipped at depth 0.1) and a mask of boxes in front."""
    corners = corners_3d(boxes)
    rect = calib.lidar_to_rect(corners.reshape(-1, 3)).reshape(-1, 8, 3)
    front = (rect[..., 2] > 0.1).any(1)
    rect[..., 2] = np.maximum(rect[..., 2], 0.1)
    uv, _ = calib.project_rect(rect.reshape(-1, 3))
    uv = uv.reshape(-1, 8, 2)
    return np.concatenate([uv.min(1), uv.max(1)], 1), front


def clip_boxes(raw: np.ndarray, width: int, height: int) -> np.ndarray:
    """2D boxes (K, 4) clipped to the image."""
    return np.stack([np.clip(raw[:, 0], 0, width - 1), np.clip(raw[:, 1], 0, height - 1),
                     np.clip(raw[:, 2], 0, width - 1), np.clip(raw[:, 3], 0, height - 1)], 1)


def box_lattice(boxes: np.ndarray, grid: int = TRUNCATION_GRID) -> np.ndarray:
    """(K, grid**3, 3) LiDAR-frame points at the cell centres of a grid x grid x grid split of each box."""
    f = (np.arange(grid) + 0.5) / grid - 0.5
    unit = np.stack(np.meshgrid(f, f, f, indexing="ij"), -1).reshape(-1, 3)
    return box_to_lidar(boxes, unit[None] * boxes[:, None, 3:6])


def truncation(boxes: np.ndarray, calib: Calib, width: int, height: int, grid: int = TRUNCATION_GRID) -> np.ndarray:
    """(K,) share of each box's volume outside the camera image (or behind the camera), from a
    lattice of grid**3 points: KITTI's truncation, "the object leaving image boundaries". The
    area of the unclipped 2D box would overstate it for an object beside the camera, whose
    corners behind the image plane project far out."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    pts = box_lattice(boxes, grid)
    uv, depth = calib.project_rect(calib.lidar_to_rect(pts.reshape(-1, 3)))
    uv, depth = uv.reshape(pts.shape[:2] + (2,)), depth.reshape(pts.shape[:2])
    with np.errstate(invalid="ignore"):
        seen = ((depth > 0.1) & (uv[..., 0] >= 0) & (uv[..., 0] <= width - 1)
                & (uv[..., 1] >= 0) & (uv[..., 1] <= height - 1))
    return 1.0 - seen.mean(1)


def occlusion_level(visible: np.ndarray) -> np.ndarray:
    """KITTI occlusion level 0..3 from the visible share."""
    visible = np.asarray(visible, dtype=np.float64)
    return (visible[..., None] < np.asarray(OCCLUSION_LEVELS)).sum(-1)


def visible_share(scene: RayScene, k: int, bbox: np.ndarray, calib: Calib, pose: Pose,
                  mount_height: float, grid: int) -> float:
    """Share of vehicle k's camera rays (over its 2D box) that reach it first in the full scene."""
    m = calib.lidar2img().astype(np.float64)[:3]
    inv = np.linalg.inv(m[:, :3])
    cam = -inv @ m[:, 3]
    u = np.linspace(bbox[0], bbox[2], grid)
    v = np.linspace(bbox[1], bbox[3], grid)
    uu, vv = np.meshgrid(u, v)
    d = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], 1) @ inv.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rot = pose.rotation()
    dw = d @ rot.T
    cw = rot @ cam + np.array([pose.x, pose.y, mount_height])
    own = rays_hit_triangles(cw, dw, scene.vehicle_triangles[k])
    if not own.any():
        return 0.0
    hits = scene.cast(cw, dw)
    return float((own & (hits.actor == k)).sum() / own.sum())


def frame_labels(scene: RayScene, vehicles: list[Vehicle], pose: Pose, mount_height: float, calib: Calib,
                 cfg: LabelConfig = LabelConfig()) -> tuple[Labels, np.ndarray]:
    """Labels of the frame and, per vehicle, its row in them (-1 if not labelled)."""
    boxes = lidar_boxes(vehicles, pose, mount_height)
    rows = np.full(len(vehicles), -1)
    if not vehicles:
        return Labels.empty(), rows
    raw, front = projected_boxes(boxes, calib)
    clipped = clip_boxes(raw, cfg.width, cfg.height)
    trunc = truncation(boxes, calib, cfg.width, cfg.height)
    in_image = front & (clipped[:, 2] - clipped[:, 0] >= 1) & (clipped[:, 3] - clipped[:, 1] >= 1)
    order = np.argsort(np.linalg.norm(boxes[:, :2], axis=1), kind="stable")
    keep, names, occ = [], [], []
    for k in order:
        if not in_image[k]:
            continue
        vis = visible_share(scene, int(k), clipped[k], calib, pose, mount_height, cfg.occlusion_grid)
        far = np.linalg.norm(boxes[k, :2]) > cfg.max_label_distance
        keep.append(k)
        names.append("DontCare" if far or vis <= 0 else vehicles[k].label)
        occ.append(int(occlusion_level(np.array([vis]))[0]))
    last = np.argsort([n == "DontCare" for n in names], kind="stable")  # objects by distance, then DontCare
    keep, names, occ = np.array(keep, dtype=int)[last], [names[i] for i in last], np.array(occ, dtype=int)[last]
    rows[keep] = np.arange(len(keep))
    labels = Labels.from_lidar(boxes[keep], calib, names, bbox=clipped[keep], truncated=trunc[keep], occluded=occ)
    return labels, rows
