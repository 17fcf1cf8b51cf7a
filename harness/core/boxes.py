"""Box geometry in the LiDAR frame: corners, rotated BEV / 3D IoU, BEV NMS, points in boxes.

Box row: ``[x, y, z, l, w, h, yaw]`` (geometric centre, l along the heading, yaw CCW about +z
from +x). Rotated overlaps clip one rectangle by the other (Sutherland-Hodgman on convex,
counter-clockwise quads) in numba; ``tests/harness/test_boxes.py`` checks them against shapely.
"""
from __future__ import annotations

import numba
import numpy as np

_UNIT = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])  # CCW corner signs (l, w)


def wrap_angle(a):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def box_to_lidar(boxes: np.ndarray, local: np.ndarray) -> np.ndarray:
    """(K, P, D) points given in each box's own frame (metres from its centre, x along its
    heading; D = 2 for BEV, 3 with z) -> the LiDAR frame: turned by the yaw, moved to the centre."""
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = local[..., 0] * c - local[..., 1] * s + boxes[:, None, 0]
    y = local[..., 0] * s + local[..., 1] * c + boxes[:, None, 1]
    return np.stack([x, y, *([local[..., 2] + boxes[:, None, 2]] if local.shape[-1] == 3 else [])], axis=-1)


def corners_bev(boxes: np.ndarray) -> np.ndarray:
    """(K, 4, 2) BEV corners, counter-clockwise."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    return box_to_lidar(boxes, _UNIT[None] * boxes[:, None, 3:5])


def corners_3d(boxes: np.ndarray) -> np.ndarray:
    """(K, 8, 3) corners: the 4 bottom ones (CCW seen from above), then the 4 top ones."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    bev = corners_bev(boxes)
    zlo = (boxes[:, 2] - boxes[:, 5] / 2)[:, None, None]
    zhi = (boxes[:, 2] + boxes[:, 5] / 2)[:, None, None]
    bottom = np.concatenate([bev, np.broadcast_to(zlo, bev.shape[:2] + (1,))], axis=-1)
    top = np.concatenate([bev, np.broadcast_to(zhi, bev.shape[:2] + (1,))], axis=-1)
    return np.concatenate([bottom, top], axis=1)


@numba.njit(cache=True, error_model="numpy")
def _area(poly: np.ndarray) -> float:
    """Signed shoelace area of a polygon (n, 2); positive when counter-clockwise."""
    n = poly.shape[0]
    area = 0.0
    for i in range(n):
        area += poly[i, 0] * poly[(i + 1) % n, 1] - poly[(i + 1) % n, 0] * poly[i, 1]
    return area * 0.5


@numba.njit(cache=True, error_model="numpy")
def _clip_area(subj: np.ndarray, clip: np.ndarray) -> float:
    """Area of the intersection of two convex CCW quads (4, 2)."""
    if _area(subj) <= 0.0 or _area(clip) <= 0.0:
        return 0.0  # a degenerate quad has no inside to clip by
    poly = np.empty((16, 2))
    nxt = np.empty((16, 2))
    n = 4
    poly[:4] = subj
    for e in range(4):
        ax, ay = clip[e, 0], clip[e, 1]
        bx, by = clip[(e + 1) % 4, 0], clip[(e + 1) % 4, 1]
        m = 0
        for i in range(n):
            px, py = poly[i, 0], poly[i, 1]
            qx, qy = poly[(i + 1) % n, 0], poly[(i + 1) % n, 1]
            sp = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
            sq = (bx - ax) * (qy - ay) - (by - ay) * (qx - ax)
            if sp >= 0:
                nxt[m, 0], nxt[m, 1] = px, py
                m += 1
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                nxt[m, 0], nxt[m, 1] = px + t * (qx - px), py + t * (qy - py)
                m += 1
        n = m
        if n == 0:
            return 0.0
        poly[:n] = nxt[:n]
    return max(_area(poly[:n]), 0.0)


@numba.njit(cache=True, error_model="numpy")
def _bev_intersections(ca: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """(Ka, Kb) BEV intersection areas of corner sets (Ka, 4, 2) and (Kb, 4, 2)."""
    out = np.zeros((ca.shape[0], cb.shape[0]))
    for i in range(ca.shape[0]):
        ax0, ax1 = ca[i, :, 0].min(), ca[i, :, 0].max()
        ay0, ay1 = ca[i, :, 1].min(), ca[i, :, 1].max()
        for j in range(cb.shape[0]):
            if cb[j, :, 0].max() <= ax0 or cb[j, :, 0].min() >= ax1:
                continue
            if cb[j, :, 1].max() <= ay0 or cb[j, :, 1].min() >= ay1:
                continue
            out[i, j] = _clip_area(ca[i], cb[j])
    return out


def bev_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Ka, Kb) rotated BEV intersection areas, m^2."""
    return _bev_intersections(corners_bev(a), corners_bev(b))


def _safe_ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def iou_bev(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Ka, Kb) rotated BEV IoU."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 7)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 7)
    inter = bev_intersection(a, b)
    union = (a[:, 3] * a[:, 4])[:, None] + (b[:, 3] * b[:, 4])[None] - inter
    return _safe_ratio(inter, union)


def iou_3d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Ka, Kb) rotated 3D IoU (BEV intersection x height overlap)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 7)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 7)
    inter = bev_intersection(a, b)
    top = np.minimum((a[:, 2] + a[:, 5] / 2)[:, None], (b[:, 2] + b[:, 5] / 2)[None])
    bottom = np.maximum((a[:, 2] - a[:, 5] / 2)[:, None], (b[:, 2] - b[:, 5] / 2)[None])
    inter = inter * np.clip(top - bottom, 0, None)
    vol_a, vol_b = a[:, 3] * a[:, 4] * a[:, 5], b[:, 3] * b[:, 4] * b[:, 5]
    return _safe_ratio(inter, vol_a[:, None] + vol_b[None] - inter)


def nms_bev(boxes: np.ndarray, scores: np.ndarray, thresh: float) -> np.ndarray:
    """Greedy rotated BEV NMS; indices of kept boxes, highest score first."""
    order = np.argsort(-np.asarray(scores), kind="stable")
    iou = iou_bev(boxes, boxes)
    suppressed = np.zeros(len(order), dtype=bool)
    keep = []
    for i in order:
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > thresh
    return np.asarray(keep, dtype=np.int64)


def points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N, K) bool: point n lies inside box k (boundary included)."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    d = pts[:, None, :] - boxes[None, :, :3]  # (N, K, 3)
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    local_x = d[..., 0] * c + d[..., 1] * s
    local_y = -d[..., 0] * s + d[..., 1] * c
    return ((np.abs(local_x) <= boxes[:, 3] / 2) & (np.abs(local_y) <= boxes[:, 4] / 2)
            & (np.abs(d[..., 2]) <= boxes[:, 5] / 2))
