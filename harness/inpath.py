"""In-path obstacles in a detector's boxes: hits on the slow vehicle and phantom boxes in the ego's lane.

What a braking system asks of a box is whether something stands in the ego's path and where its near face is,
not how well the box fits (BEV IoU stays a separate box-quality figure, ``harness.boxes.iou_bev``).

- A box lies *on* an object when their BEV footprints overlap or their centres are within ``CENTRE_M`` (2 m,
  nuScenes' centre-distance matching).
- Its *rear face* is the face nearest the ego along the lane: the least projection of its footprint on the
  lane direction (the slow vehicle's heading), metres from the sensor.
- An *in-path hit*: a box with score >= the operating threshold, of any class but DontCare, that lies on the
  slow vehicle with its rear face within max(``REAR_ABS_M``, ``REAR_REL`` x range) of the true rear face (the
  distance the ego brakes for), range being the true rear face's distance.
- A *phantom*: a box with score >= the threshold whose centre lies in the ego's lane corridor (half a lane
  width either side of the lane's centre line, from the ego's front to ``RANGE_X_M`` ahead) and that lies on
  no object of the frame (its label rows, DontCare included: every row is a vehicle with its 3D box).

The lane's centre line, in the LiDAR frame, is the arc that leaves the sensor along +x (the ego drives on its
lane's centre line, heading along it) and passes through the lane's centre at the slow vehicle (its centre
less its lateral offset in the lane): ``lane_curvature``. Pure numpy; the loaders live in ``harness.verdict``.
"""
from __future__ import annotations

import numpy as np

from harness.core.boxes import bev_intersection
from harness.core.visibility import RANGE_X_M

CENTRE_M = 2.0  # m, centre-distance matching (nuScenes)
REAR_ABS_M = 1.0  # m, rear-face tolerance ...
REAR_REL = 0.03  # ... or this share of the range, whichever is larger
LANE_HALF_WIDTH_M = 1.75  # m, half the simulated highway's 3.5 m lane (simulator.road.RoadConfig)
LIDAR_TO_FRONT_M = 4.7 / 2  # m, the ego's front bumper ahead of its roof LiDAR (simulator.scenario.EGO_DIMS)


def _boxes(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64).reshape(-1, 7)


def rear_face(boxes, lane_yaw: float) -> np.ndarray:
    """(K,) metres from the sensor to each box's face nearest the ego along the lane direction ``lane_yaw``:
    the least projection of its BEV footprint on (cos lane_yaw, sin lane_yaw)."""
    b = _boxes(boxes)
    c, s = np.cos(lane_yaw), np.sin(lane_yaw)
    rel = b[:, 6] - lane_yaw
    half_extent = b[:, 3] / 2 * np.abs(np.cos(rel)) + b[:, 4] / 2 * np.abs(np.sin(rel))
    return b[:, 0] * c + b[:, 1] * s - half_extent


def rear_tolerance(true_rear_m: float) -> float:
    """Metres a box's rear face may miss the true one by: max(1 m, 3 % of its range)."""
    return max(REAR_ABS_M, REAR_REL * float(true_rear_m))


def on_objects(boxes, objects) -> np.ndarray:
    """(D, G) bool: box d lies on object g (BEV footprints overlap, or centres within ``CENTRE_M``)."""
    b, o = _boxes(boxes), _boxes(objects)
    if len(b) == 0 or len(o) == 0:
        return np.zeros((len(b), len(o)), dtype=bool)
    near = np.hypot(b[:, None, 0] - o[None, :, 0], b[:, None, 1] - o[None, :, 1]) <= CENTRE_M
    return near | (bev_intersection(b, o) > 0.0)


def inpath_hits(boxes, slow_box) -> np.ndarray:
    """(D,) bool: box d is an in-path hit on ``slow_box`` (7,) (module docstring; scores not looked at)."""
    b, slow = _boxes(boxes), _boxes(slow_box)
    if len(b) == 0:
        return np.zeros(0, dtype=bool)
    yaw = float(slow[0, 6])
    true_rear = float(rear_face(slow, yaw)[0])
    close = np.abs(rear_face(b, yaw) - true_rear) <= rear_tolerance(true_rear)
    return on_objects(b, slow)[:, 0] & close


def lane_curvature(slow_box, lateral_offset_m: float = 0.0) -> float:
    """1/m, positive to the left: the arc from the sensor along +x through the lane's centre at the slow
    vehicle (its centre moved by ``lateral_offset_m``, its offset to the left of the lane centre, to its right)."""
    x, y, yaw = float(slow_box[0]), float(slow_box[1]), float(slow_box[6])
    x, y = x + lateral_offset_m * np.sin(yaw), y - lateral_offset_m * np.cos(yaw)
    r2 = x * x + y * y
    return 2.0 * y / r2 if r2 > 0 else 0.0


def lane_offset(points, curvature: float) -> np.ndarray:
    """(P,) metres to the left of the lane's centre line (the arc of ``curvature``) of BEV points (P, 2)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if abs(curvature) < 1e-12:
        return p[:, 1].copy()
    r = 1.0 / curvature  # signed radius: the arc's centre is (0, r)
    return r - np.sign(r) * np.hypot(p[:, 0], p[:, 1] - r)


def in_corridor(boxes, curvature: float) -> np.ndarray:
    """(D,) bool: the box centre lies in the ego's lane corridor (within ``LANE_HALF_WIDTH_M`` of the centre
    line, from the ego's front bumper to ``RANGE_X_M`` ahead)."""
    b = _boxes(boxes)
    ahead = (b[:, 0] >= LIDAR_TO_FRONT_M) & (b[:, 0] <= RANGE_X_M)
    return ahead & (np.abs(lane_offset(b[:, :2], curvature)) <= LANE_HALF_WIDTH_M)


def phantoms(boxes, objects, curvature: float) -> np.ndarray:
    """(D,) bool: box d is a phantom in-path detection (in the corridor, on no object; scores not looked at)."""
    b = _boxes(boxes)
    if len(b) == 0:
        return np.zeros(0, dtype=bool)
    return in_corridor(b, curvature) & ~on_objects(b, objects).any(axis=1)
