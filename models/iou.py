"""Rotated BEV / 3D IoU in plain torch (no custom ops), usable inside an exported graph.

The intersection of two rotated rectangles is a convex polygon whose vertices are among
24 candidates: the 4 corners of each rectangle inside the other and the 16 edge-edge crossings.
Valid candidates are sorted by angle around their mean and the shoelace formula gives the
area; invalid slots are replaced by the first sorted vertex, which adds zero area. Everything
is batched over pairs, so the cost is O(pairs) with 24 points each.
"""
from __future__ import annotations

import torch
from torch import Tensor

_UNIT = ((0.5, 0.5), (-0.5, 0.5), (-0.5, -0.5), (0.5, -0.5))  # CCW corner signs (l, w)
_EPS = 1e-6


def corners_bev(boxes: Tensor) -> Tensor:
    """(..., 4, 2) counter-clockwise BEV corners of boxes (..., 7)."""
    unit = torch.tensor(_UNIT, dtype=boxes.dtype)  # (4, 2)
    local = unit * boxes[..., None, 3:5]  # (..., 4, 2) box frame
    c, s = torch.cos(boxes[..., 6:7]), torch.sin(boxes[..., 6:7])  # (..., 1)
    x = local[..., 0] * c - local[..., 1] * s + boxes[..., 0:1]
    y = local[..., 0] * s + local[..., 1] * c + boxes[..., 1:2]
    return torch.stack([x, y], dim=-1)


def _next(x: Tensor) -> Tensor:
    """x shifted by one along dim 1 (cyclic): row i holds x[:, i + 1] (torch.roll guards on
    the size of data-dependent shapes during export; index_select does not)."""
    n = x.shape[1]
    return x.index_select(1, torch.tensor(list(range(1, n)) + [0]))


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _inside(points: Tensor, quad: Tensor) -> Tensor:
    """(M, P) bool: points (M, P, 2) inside (or on) the CCW quads (M, 4, 2)."""
    edge = _next(quad) - quad  # (M, 4, 2)
    rel = points[:, :, None, :] - quad[:, None, :, :]  # (M, P, 4, 2)
    return (_cross(edge[:, None], rel) >= -_EPS).all(dim=-1)


def _crossings(qa: Tensor, qb: Tensor) -> tuple[Tensor, Tensor]:
    """Edge-edge crossing points (M, 16, 2) and validity (M, 16) of quads (M, 4, 2)."""
    p, r = qa[:, :, None, :], (_next(qa) - qa)[:, :, None, :]  # (M, 4, 1, 2)
    q, s = qb[:, None, :, :], (_next(qb) - qb)[:, None, :, :]  # (M, 1, 4, 2)
    denom = _cross(r, s)  # (M, 4, 4)
    ok = denom.abs() > _EPS
    safe = torch.where(ok, denom, torch.ones_like(denom))
    t = _cross(q - p, s) / safe
    u = _cross(q - p, r) / safe
    ok = ok & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    pts = p + t[..., None] * r  # (M, 4, 4, 2)
    return pts.reshape(-1, 16, 2), ok.reshape(-1, 16)


def _polygon_area(points: Tensor, valid: Tensor) -> Tensor:
    """(M,) area of the convex hull-ordered valid points (M, P, 2)."""
    w = valid.to(points.dtype)  # (M, P)
    count = w.sum(dim=1)  # (M,)
    centre = (points * w[..., None]).sum(dim=1) / count.clamp(min=1.0)[:, None]  # (M, 2)
    rel = points - centre[:, None, :]
    angle = torch.atan2(rel[..., 1], rel[..., 0])  # (M, P) in [-pi, pi]
    angle = torch.where(valid, angle, torch.full_like(angle, 10.0))  # invalid slots last
    order = torch.argsort(angle, dim=1)  # (M, P)
    ordered = torch.gather(rel, 1, order[..., None].expand(-1, -1, 2))  # (M, P, 2)
    ok = torch.gather(valid, 1, order)  # (M, P) valid first
    ordered = torch.where(ok[..., None], ordered, ordered[:, :1, :])
    area = 0.5 * _cross(ordered, _next(ordered)).sum(dim=1)
    return torch.where(count >= 3, area.abs(), torch.zeros_like(area))


def intersection_bev_pairs(a: Tensor, b: Tensor) -> Tensor:
    """(M,) BEV intersection areas of paired boxes a[m], b[m] (M, 7), m^2."""
    qa, qb = corners_bev(a), corners_bev(b)  # (M, 4, 2)
    cross_pts, cross_ok = _crossings(qa, qb)
    pts = torch.cat([qa, qb, cross_pts], dim=1)  # (M, 24, 2)
    ok = torch.cat([_inside(qa, qb), _inside(qb, qa), cross_ok], dim=1)  # (M, 24)
    return _polygon_area(pts, ok)


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


def iou_bev_sparse(a: Tensor, b: Tensor) -> Tensor:
    """(Ka, Kb) rotated BEV IoU computed only for pairs whose circumcircles overlap.

    For eager use with many boxes (anchors x ground truth): equal to :func:`iou_bev`.
    """
    ra = 0.5 * torch.sqrt(a[:, 3] ** 2 + a[:, 4] ** 2)  # (Ka,) circumradius
    rb = 0.5 * torch.sqrt(b[:, 3] ** 2 + b[:, 4] ** 2)
    dist = torch.cdist(a[:, :2], b[:, :2])  # (Ka, Kb)
    ia, ib = torch.nonzero(dist < ra[:, None] + rb[None, :], as_tuple=True)
    out = a.new_zeros(a.shape[0], b.shape[0])
    if ia.numel():
        out[ia, ib] = iou_bev_pairs(a[ia], b[ib])
    return out
