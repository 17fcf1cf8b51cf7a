"""Rotated BEV / 3D IoU in plain torch (no custom ops), usable inside an exported graph.

The intersection of two rotated rectangles is a convex polygon whose vertices are among
24 candidates: the 4 corners of each rectangle inside the other and the 16 edge-edge crossings.
Valid candidates are sorted by angle around their mean and the shoelace formula gives the
area; invalid slots are replaced by the first sorted vertex, which adds zero area. Everything
is batched over pairs, so the cost is O(pairs) with 24 points each. x and y are separate
tensors with the pair axis innermost: broadcasting over a trailing axis of 2 (or 4) is slow in
onnxruntime, and this layout runs the graph's IoU about three times faster.
"""
from __future__ import annotations

import torch
from torch import Tensor

_UNIT_X = (0.5, -0.5, -0.5, 0.5)  # CCW corner signs along l
_UNIT_Y = (0.5, 0.5, -0.5, -0.5)  # and along w
_EPS = 1e-6


def corners_xy(boxes: Tensor) -> tuple[Tensor, Tensor]:
    """x, y (4, M) of the counter-clockwise BEV corners of boxes (M, 7): the pair axis innermost."""
    ux = torch.tensor(_UNIT_X, dtype=boxes.dtype)[:, None] * boxes[None, :, 3]  # (4, M) box frame
    uy = torch.tensor(_UNIT_Y, dtype=boxes.dtype)[:, None] * boxes[None, :, 4]
    c, s = torch.cos(boxes[None, :, 6]), torch.sin(boxes[None, :, 6])  # (1, M)
    return ux * c - uy * s + boxes[None, :, 0], ux * s + uy * c + boxes[None, :, 1]


def corners_bev(boxes: Tensor) -> Tensor:
    """(..., 4, 2) counter-clockwise BEV corners of boxes (..., 7)."""
    x, y = corners_xy(boxes.reshape(-1, 7))
    return torch.stack([x.t(), y.t()], dim=-1).reshape(*boxes.shape[:-1], 4, 2)


def _next(x: Tensor) -> Tensor:
    """x shifted by one along dim 0 (cyclic): row i holds x[i + 1] (torch.roll guards on the size
    of data-dependent shapes during export; index_select does not)."""
    n = x.shape[0]
    return x.index_select(0, torch.tensor(list(range(1, n)) + [0]))


def _inside(px: Tensor, py: Tensor, qx: Tensor, qy: Tensor) -> Tensor:
    """(P, M) bool: points (P, M) inside (or on) the CCW quads (4, M)."""
    ex, ey = _next(qx) - qx, _next(qy) - qy  # (4, M)
    rx, ry = px[:, None] - qx[None], py[:, None] - qy[None]  # (P, 4, M)
    return (ex[None] * ry - ey[None] * rx >= -_EPS).all(dim=1)


def _crossings(ax: Tensor, ay: Tensor, bx: Tensor, by: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """x, y (16, M) of the edge-edge crossings of quads a, b (4, M) and their validity (16, M)."""
    px, py = ax[:, None], ay[:, None]  # (4, 1, M): edge starts of a
    rx, ry = (_next(ax) - ax)[:, None], (_next(ay) - ay)[:, None]
    qx, qy = bx[None], by[None]  # (1, 4, M): of b
    sx, sy = (_next(bx) - bx)[None], (_next(by) - by)[None]
    denom = rx * sy - ry * sx  # (4, 4, M)
    ok = denom.abs() > _EPS
    safe = torch.where(ok, denom, torch.ones_like(denom))
    dx, dy = qx - px, qy - py
    t = (dx * sy - dy * sx) / safe
    u = (dx * ry - dy * rx) / safe
    ok = ok & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    m = ax.shape[1]
    return (px + t * rx).reshape(16, m), (py + t * ry).reshape(16, m), ok.reshape(16, m)


def _polygon_area(x: Tensor, y: Tensor, valid: Tensor) -> Tensor:
    """(M,) area of the convex polygons of the valid points x, y (P, M), ordered by angle.

    The two sums run over the points of a pair laid out as (M, P[, 2]): those are the float
    sums the area has always had, so every IoU (and so every training target) is unchanged.
    """
    w = valid.to(x.dtype)  # (P, M)
    count = w.sum(dim=0)  # (M,)
    pts = torch.stack([x, y], dim=-1).permute(1, 0, 2).contiguous()  # (M, P, 2)
    centre = (pts * w.t().contiguous()[..., None]).sum(dim=1) / count.clamp(min=1.0)[:, None]  # (M, 2)
    rx, ry = x - centre[None, :, 0], y - centre[None, :, 1]  # (P, M)
    angle = torch.atan2(ry, rx)  # (P, M) in [-pi, pi]
    angle = torch.where(valid, angle, torch.full_like(angle, 10.0))  # invalid slots last
    order = torch.argsort(angle, dim=0)  # (P, M)
    ox, oy, ok = torch.gather(rx, 0, order), torch.gather(ry, 0, order), torch.gather(valid, 0, order)
    ox, oy = torch.where(ok, ox, ox[:1]), torch.where(ok, oy, oy[:1])  # valid first, then the first again
    area = 0.5 * (ox * _next(oy) - oy * _next(ox)).t().contiguous().sum(dim=1)  # (M,)
    return torch.where(count >= 3, area.abs(), torch.zeros_like(area))


def intersection_bev_pairs(a: Tensor, b: Tensor) -> Tensor:
    """(M,) BEV intersection areas of paired boxes a[m], b[m] (M, 7), m^2."""
    ax, ay = corners_xy(a)
    bx, by = corners_xy(b)
    cx, cy, cross_ok = _crossings(ax, ay, bx, by)
    x, y = torch.cat([ax, bx, cx]), torch.cat([ay, by, cy])  # (24, M)
    ok = torch.cat([_inside(ax, ay, bx, by), _inside(bx, by, ax, ay), cross_ok])  # (24, M)
    return _polygon_area(x, y, ok)


def _ratio(num: Tensor, den: Tensor) -> Tensor:
    return torch.where(den > 0, num / den.clamp(min=1e-12), torch.zeros_like(num))


def iou_bev_pairs(a: Tensor, b: Tensor) -> Tensor:
    """(M,) rotated BEV IoU of paired boxes (M, 7)."""
    inter = intersection_bev_pairs(a, b)
    return _ratio(inter, a[:, 3] * a[:, 4] + b[:, 3] * b[:, 4] - inter)


def iou_3d_pairs(a: Tensor, b: Tensor) -> Tensor:
    """(M,) rotated 3D IoU of paired boxes (M, 7): BEV intersection x height overlap."""
    top = torch.minimum(a[:, 2] + a[:, 5] / 2, b[:, 2] + b[:, 5] / 2)
    bottom = torch.maximum(a[:, 2] - a[:, 5] / 2, b[:, 2] - b[:, 5] / 2)
    inter = intersection_bev_pairs(a, b) * (top - bottom).clamp(min=0)
    vol_a, vol_b = a[:, 3] * a[:, 4] * a[:, 5], b[:, 3] * b[:, 4] * b[:, 5]
    return _ratio(inter, vol_a + vol_b - inter)


def _all_pairs(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    ka, kb = a.shape[0], b.shape[0]
    return (a[:, None, :].expand(ka, kb, 7).reshape(-1, 7),
            b[None, :, :].expand(ka, kb, 7).reshape(-1, 7))


def iou_bev(a: Tensor, b: Tensor) -> Tensor:
    """(Ka, Kb) rotated BEV IoU of every box of a (Ka, 7) with every box of b (Kb, 7)."""
    pa, pb = _all_pairs(a, b)
    return iou_bev_pairs(pa, pb).reshape(a.shape[0], b.shape[0])


def iou_3d(a: Tensor, b: Tensor) -> Tensor:
    """(Ka, Kb) rotated 3D IoU."""
    pa, pb = _all_pairs(a, b)
    return iou_3d_pairs(pa, pb).reshape(a.shape[0], b.shape[0])


_APART = 0.1  # m: boxes whose BEV bounds are this far apart get IoU exactly 0 from iou_bev_pairs too
_PAIR_CHUNK = 2048  # pairs per iou_bev_pairs call: its (24, M) temporaries stay in the cache


def bounds_apart(a: Tensor, b: Tensor, gap: float = _APART) -> Tensor:
    """(M,) bool: the axis-aligned BEV bounds of paired boxes a, b (M, 7) are more than ``gap`` apart
    along x or y. Then no corner of one lies within ``_EPS`` of the other's edges and no edges cross
    (float rounding of their arithmetic at 100 m is ~1e-5 m), so ``iou_bev_pairs`` gives them 0."""
    def half(boxes: Tensor) -> tuple[Tensor, Tensor]:
        c, s = torch.cos(boxes[:, 6]).abs(), torch.sin(boxes[:, 6]).abs()
        return (boxes[:, 3] * c + boxes[:, 4] * s) / 2, (boxes[:, 3] * s + boxes[:, 4] * c) / 2
    (hxa, hya), (hxb, hyb) = half(a), half(b)
    return (((a[:, 0] - b[:, 0]).abs() > hxa + hxb + gap) | ((a[:, 1] - b[:, 1]).abs() > hya + hyb + gap))


def _sparse(a: Tensor, b: Tensor, pairs) -> Tensor:
    """(Ka, Kb) ``pairs(a[i], b[j])`` for the pairs whose circumcircles overlap and whose bounds are not
    apart (:func:`bounds_apart`), in chunks of pairs; 0 for the others (they do not intersect)."""
    ra = 0.5 * torch.sqrt(a[:, 3] ** 2 + a[:, 4] ** 2)  # (Ka,) circumradius
    rb = 0.5 * torch.sqrt(b[:, 3] ** 2 + b[:, 4] ** 2)
    dist = torch.cdist(a[:, :2], b[:, :2])  # (Ka, Kb)
    ia, ib = torch.nonzero(dist < ra[:, None] + rb[None, :], as_tuple=True)
    near = ~bounds_apart(a[ia], b[ib])
    ia, ib = ia[near], ib[near]
    out = a.new_zeros(a.shape[0], b.shape[0])
    for start in range(0, ia.numel(), _PAIR_CHUNK):
        ca, cb = ia[start:start + _PAIR_CHUNK], ib[start:start + _PAIR_CHUNK]
        out[ca, cb] = pairs(a[ca], b[cb])
    return out


def iou_bev_sparse(a: Tensor, b: Tensor) -> Tensor:
    """(Ka, Kb) rotated BEV IoU computed only for pairs whose circumcircles overlap and whose
    bounds are not apart (:func:`bounds_apart`), in chunks of pairs.

    For eager use with many boxes (anchors x ground truth): equal to :func:`iou_bev`, bit for bit.
    """
    return _sparse(a, b, iou_bev_pairs)


def ioa_bev_sparse(a: Tensor, b: Tensor) -> Tensor:
    """(Ka, Kb) share of each a box's BEV area inside each b box (intersection over a's area), sparse as
    :func:`iou_bev_sparse`: how much of an anchor lies in an ignored region, whatever the region's size."""
    return _sparse(a, b, lambda pa, pb: _ratio(intersection_bev_pairs(pa, pb), pa[:, 3] * pa[:, 4]))
