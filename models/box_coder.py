"""SECOND's residual box coder and the direction-bin helpers (OpenPCDet ``ResidualCoder``).

Boxes are ``[x, y, z, l, w, h, yaw]`` with the geometric centre (the project's one box convention), so no
bottom-centre shift is needed. With d = sqrt(l_a^2 + w_a^2):
``dx = (x_g - x_a) / d, dy = (y_g - y_a) / d, dz = (z_g - z_a) / h_a,
dl = log(l_g / l_a), dw = log(w_g / w_a), dh = log(h_g / h_a), dyaw = yaw_g - yaw_a``.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor


def encode(boxes: Tensor, anchors: Tensor) -> Tensor:
    """(..., 7) residuals of boxes (..., 7) w.r.t. anchors (..., 7)."""
    xa, ya, za, la, wa, ha, ra = anchors.unbind(-1)
    xg, yg, zg, lg, wg, hg, rg = boxes.unbind(-1)
    diag = torch.sqrt(la ** 2 + wa ** 2)
    return torch.stack([(xg - xa) / diag, (yg - ya) / diag, (zg - za) / ha,
                        torch.log(lg / la), torch.log(wg / wa), torch.log(hg / ha), rg - ra], -1)


def decode(deltas: Tensor, anchors: Tensor) -> Tensor:
    """(..., 7) boxes from residuals (..., 7) and anchors (..., 7); inverse of :func:`encode`."""
    xa, ya, za, la, wa, ha, ra = anchors.unbind(-1)
    dx, dy, dz, dl, dw, dh, dr = deltas.unbind(-1)
    diag = torch.sqrt(la ** 2 + wa ** 2)
    return torch.stack([dx * diag + xa, dy * diag + ya, dz * ha + za, torch.exp(dl) * la,
                        torch.exp(dw) * wa, torch.exp(dh) * ha, dr + ra], -1)


def limit_period(val: Tensor, offset: float = 0.5, period: float = math.pi) -> Tensor:
    """val - floor(val / period + offset) * period (OpenPCDet's limit_period)."""
    return val - torch.floor(val / period + offset) * period


def wrap_angle(a: Tensor) -> Tensor:
    """Angles wrapped to [-pi, pi)."""
    return limit_period(a, 0.5, 2 * math.pi)


def direction_target(yaw: Tensor, offset: float = math.pi / 4) -> Tensor:
    """(...,) int64 direction bin in {0, 1}: which half-turn (yaw - offset) lies in."""
    rot = limit_period(yaw - offset, 0.0, 2 * math.pi)
    return torch.floor(rot / math.pi).long().clamp(0, 1)


def apply_direction(yaw: Tensor, dir_bin: Tensor, offset: float = math.pi / 4) -> Tensor:
    """Yaw folded to the half-turn given by the direction bin, wrapped to [-pi, pi)."""
    rot = limit_period(yaw - offset, 0.0, math.pi)
    return wrap_angle(rot + offset + math.pi * dir_bin.to(yaw.dtype))
