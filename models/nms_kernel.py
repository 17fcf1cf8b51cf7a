"""Eager CPU kernel (numba) of the greedy rotated BEV NMS of ``models.nms.nms_in_order``.

The torch form computes the float32 rotated IoU of every candidate pair and iterates a fixed point
over the suppressing pairs: ~30 small ops a call, each over thousands of pairs. Here greedy NMS
runs box by box, best first: a kept box tests the boxes after it that are not yet suppressed, an
axis-aligned bound rejects most pairs, and it stops once ``max_keep`` boxes are kept (the two-stage
models use only the first ``rois`` proposals).

The IoU is that of ``models.iou.iou_bev_pairs`` (the same corners, the same ``_EPS`` tolerances of
the inside and crossing tests, the same polygon), computed in float64 from the float32 boxes. It
decides a pair alone only when it is more than ``pair_margin`` from the threshold: a bound of the
float32 rounding of the torch IoU, scaled to the pair's distance from the sensor and its shortest
side, with a wide reserve (measured: at most ~10 of its 64 ulps; ``tests/models/test_nms_kernel.py``
holds the rounding under a quarter of the margin). A pair within the margin is handed back
undecided, and the caller decides it with the torch IoU itself (``models.nms``). So the kept indices
are the torch form's, ties at the threshold included.
"""
from __future__ import annotations

import math

import numba
import numpy as np

MIN_THRESH = 1e-3  # IoU limits below this take the torch form (the bound test needs pair_margin < limit / 2)
MARGIN_ULPS = 64.0  # pair_margin's multiple of the float32 rounding scale
_EPS = 1e-6  # models.iou._EPS: the inside and crossing tolerances
_UNIT_X = (0.5, -0.5, -0.5, 0.5)  # models.iou: CCW corner signs along l
_UNIT_Y = (0.5, 0.5, -0.5, -0.5)  # and along w


@numba.njit(cache=True)
def _corners(boxes: np.ndarray) -> np.ndarray:
    """(K, 2, 4) float64 CCW BEV corners (x row, y row) of boxes (K, 7), as ``models.iou.corners_xy``."""
    out = np.empty((boxes.shape[0], 2, 4))
    for k in range(boxes.shape[0]):
        c, s = math.cos(boxes[k, 6]), math.sin(boxes[k, 6])
        for q in range(4):
            ux, uy = _UNIT_X[q] * boxes[k, 3], _UNIT_Y[q] * boxes[k, 4]
            out[k, 0, q] = ux * c - uy * s + boxes[k, 0]
            out[k, 1, q] = ux * s + uy * c + boxes[k, 1]
    return out


@numba.njit(cache=True)
def _bounds(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """lo_x, hi_x, lo_y, hi_y (K,) float64: the axis-aligned BEV bounds of the corners (K, 2, 4)."""
    k = corners.shape[0]
    lo_x, hi_x, lo_y, hi_y = np.empty(k), np.empty(k), np.empty(k), np.empty(k)
    for n in range(k):
        lo_x[n], hi_x[n] = corners[n, 0].min(), corners[n, 0].max()
        lo_y[n], hi_y[n] = corners[n, 1].min(), corners[n, 1].max()
    return lo_x, hi_x, lo_y, hi_y


@numba.njit(cache=True)
def _inside(px: float, py: float, quad: np.ndarray) -> bool:
    """Point inside (or within ``_EPS`` of) the CCW quad (2, 4)."""
    for q in range(4):
        n = (q + 1) % 4
        ex, ey = quad[0, n] - quad[0, q], quad[1, n] - quad[1, q]
        if ex * (py - quad[1, q]) - ey * (px - quad[0, q]) < -_EPS:
            return False
    return True


@numba.njit(cache=True)
def _intersection(a: np.ndarray, b: np.ndarray, xs: np.ndarray, ys: np.ndarray, ang: np.ndarray) -> float:
    """BEV intersection area of the CCW quads a, b (2, 4), m^2: the convex polygon of the corners
    inside the other quad and the edge crossings (``models.iou.intersection_bev_pairs``).
    xs, ys, ang (24,): scratch."""
    n = 0
    for q in range(4):
        if _inside(a[0, q], a[1, q], b):
            xs[n], ys[n] = a[0, q], a[1, q]
            n += 1
    for q in range(4):
        if _inside(b[0, q], b[1, q], a):
            xs[n], ys[n] = b[0, q], b[1, q]
            n += 1
    for q in range(4):
        px, py = a[0, q], a[1, q]
        rx, ry = a[0, (q + 1) % 4] - px, a[1, (q + 1) % 4] - py
        for m in range(4):
            sx, sy = b[0, (m + 1) % 4] - b[0, m], b[1, (m + 1) % 4] - b[1, m]
            denom = rx * sy - ry * sx
            if abs(denom) <= _EPS:
                continue
            dx, dy = b[0, m] - px, b[1, m] - py
            t = (dx * sy - dy * sx) / denom
            u = (dx * ry - dy * rx) / denom
            if 0.0 <= t <= 1.0 and 0.0 <= u <= 1.0:
                xs[n], ys[n] = px + t * rx, py + t * ry
                n += 1
    if n < 3:
        return 0.0
    cx, cy = xs[:n].mean(), ys[:n].mean()
    for p in range(n):
        xs[p], ys[p] = xs[p] - cx, ys[p] - cy
        ang[p] = math.atan2(ys[p], xs[p])
    for p in range(1, n):  # insertion sort by angle
        q = p
        while q > 0 and ang[q - 1] > ang[q]:
            ang[q - 1], ang[q] = ang[q], ang[q - 1]
            xs[q - 1], xs[q] = xs[q], xs[q - 1]
            ys[q - 1], ys[q] = ys[q], ys[q - 1]
            q -= 1
    area = 0.0
    for p in range(n):
        nxt = (p + 1) % n
        area += xs[p] * ys[nxt] - ys[p] * xs[nxt]
    return 0.5 * abs(area)


@numba.njit(cache=True)
def _iou(a: np.ndarray, b: np.ndarray, area_a: float, area_b: float, xs: np.ndarray, ys: np.ndarray,
         ang: np.ndarray) -> float:
    """Rotated BEV IoU of the quads a, b (2, 4) of areas area_a, area_b (``models.iou._ratio``)."""
    inter = _intersection(a, b, xs, ys, ang)
    union = area_a + area_b - inter
    return inter / max(union, 1e-12) if union > 0 else 0.0


@numba.njit(cache=True)
def iou_bev_pairs_f64(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M,) float64 rotated BEV IoU of paired boxes a, b (M, 7): ``models.iou.iou_bev_pairs`` in float64."""
    ca, cb = _corners(a), _corners(b)
    xs, ys, ang = np.empty(24), np.empty(24), np.empty(24)
    out = np.empty(a.shape[0])
    for m in range(a.shape[0]):
        out[m] = _iou(ca[m], cb[m], a[m, 3] * a[m, 4], b[m, 3] * b[m, 4], xs, ys, ang)
    return out


@numba.njit(cache=True)
def pair_margin(a: np.ndarray, b: np.ndarray) -> float:
    """Bound of the float32 rounding of the torch IoU of boxes a, b (7,): ``MARGIN_ULPS`` float32 ulps
    of the farthest coordinate over the shortest side (a corner's rounding over the box's width),
    plus the area a point within ``_EPS`` of an edge can add over the smaller area."""
    reach = max(abs(a[0]), abs(a[1]), abs(b[0]), abs(b[1])) + 0.5 * max(math.hypot(a[3], a[4]),
                                                                         math.hypot(b[3], b[4]))
    side = max(min(a[3], a[4], b[3], b[4]), 1e-30)
    area = max(min(a[3] * a[4], b[3] * b[4]), 1e-30)
    return MARGIN_ULPS * 2.0 ** -24 * reach / side + 4 * _EPS / area


@numba.njit(cache=True)
def greedy_nms_kernel(boxes: np.ndarray, thresh: float, max_keep: int, suppressed: np.ndarray,
                      kept: np.ndarray, count: int, j0: int, i0: int) -> tuple[int, int, int]:
    """Greedy rotated BEV NMS of boxes (K, 7) float64 given best first, into ``kept`` (at most
    ``max_keep``) and ``suppressed`` (K,) bool; -> (count kept, -1, -1).

    It stops at the first pair (j kept, i after it) whose float64 IoU lies within ``pair_margin`` of
    ``thresh`` and returns (count, j, i): the caller sets ``suppressed[i]`` to the torch form's
    decision and resumes with (count, j, i + 1). A first call passes (0, 0, -1)."""
    k = boxes.shape[0]
    corners = _corners(boxes)  # (K, 2, 4)
    lo_x, hi_x, lo_y, hi_y = _bounds(corners)  # (K,) each: BEV bounds, m
    area = boxes[:, 3] * boxes[:, 4]  # (K,) m^2
    half = 0.5 * thresh / (1.0 + thresh)  # bound <= half * (area_j + area_i): IoU <= thresh / 2
    xs, ys, ang = np.empty(24), np.empty(24), np.empty(24)
    j, start = j0, i0
    while j < k:
        if start < 0:  # box j is next: kept unless suppressed
            if count == max_keep:
                break
            if suppressed[j]:
                j += 1
                continue
            kept[count] = j
            count += 1
            if count == max_keep:  # the boxes after j can no longer be kept
                break
            start = j + 1
        for i in range(start, k):
            if suppressed[i]:
                continue
            ex = min(hi_x[j], hi_x[i]) - max(lo_x[j], lo_x[i])
            ey = min(hi_y[j], hi_y[i]) - max(lo_y[j], lo_y[i])
            margin = pair_margin(boxes[j], boxes[i])
            if (ex <= 0.0 or ey <= 0.0 or ex * ey <= half * (area[j] + area[i])) and margin < 0.5 * thresh:
                continue  # float64 IoU <= thresh / 2: more than the margin below the limit
            iou = _iou(corners[j], corners[i], area[j], area[i], xs, ys, ang)
            if iou > thresh + margin:
                suppressed[i] = True
            elif iou >= thresh - margin:
                return count, j, i
        j += 1
        start = -1
    return count, -1, -1
