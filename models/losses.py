"""Losses of the anchor heads: sigmoid focal, smooth-L1 with the sin-difference yaw encoding,
direction cross-entropy (SECOND / OpenPCDet defaults)."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def sigmoid_focal_loss(logits: Tensor, targets: Tensor, weights: Tensor, alpha: float = 0.25,
                       gamma: float = 2.0) -> Tensor:
    """Sum over elements of w * alpha_t * (1 - p_t)^gamma * BCE(logits, targets)."""
    p = torch.sigmoid(logits)
    p_t = targets * p + (1 - targets) * (1 - p)
    alpha_t = targets * alpha + (1 - targets) * (1 - alpha)
    bce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    return (weights * alpha_t * (1 - p_t) ** gamma * bce).sum()


def smooth_l1(diff: Tensor, beta: float = 1.0 / 9.0) -> Tensor:
    """Elementwise smooth-L1 (Huber / beta) of a difference."""
    ad = diff.abs()
    return torch.where(ad < beta, 0.5 * ad ** 2 / beta, ad - 0.5 * beta)


def sin_difference(pred: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Replace the yaw residual (last column) so that pred - target = sin(pred_yaw - tgt_yaw)."""
    a, b = pred[..., 6:7], target[..., 6:7]
    pred = torch.cat([pred[..., :6], torch.sin(a) * torch.cos(b)], dim=-1)
    target = torch.cat([target[..., :6], torch.cos(a) * torch.sin(b)], dim=-1)
    return pred, target


def box_regression_loss(pred: Tensor, target: Tensor) -> Tensor:
    """Sum of smooth-L1 over residuals (P, 7) with the sin-difference yaw."""
    p, t = sin_difference(pred, target)
    return smooth_l1(p - t).sum()


def direction_loss(logits: Tensor, target: Tensor) -> Tensor:
    """Sum of cross-entropy over direction logits (P, 2) and bins (P,)."""
    return F.cross_entropy(logits, target, reduction="sum")
