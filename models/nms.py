"""Rotated BEV NMS inside the graph: pair pre-filter + IoU + a fixed-point loop (exact greedy NMS).

With boxes sorted by score and S[j, i] = (j < i and IoU(j, i) > t), greedy NMS keeps box i
iff no KEPT box j suppresses it. Iterating ``keep <- not any_j(keep[j] and S[j, i])`` from
all-True reaches that unique fixed point (after t rounds the first t entries are final; in
practice a few rounds), so the result equals greedy NMS exactly. The loop is a
``torch._higher_order_ops.while_loop``, which the dynamo exporter turns into an ONNX Loop.
The rotated IoU is computed only for the pairs whose axis-aligned BEV bounds could overlap
enough (``suppression_candidates``): a few percent of the K^2 pairs of detections.
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch._higher_order_ops.while_loop import while_loop

from models.iou import iou_bev_pairs


def _cond(keep: Tensor, changed: Tensor) -> Tensor:
    return changed.clone()


def suppress_fixed_point(suppress: Tensor) -> Tensor:
    """(K,) bool keep mask for a strictly upper-triangular suppression matrix (K, K)."""
    def body(keep: Tensor, changed: Tensor):
        new = ~((keep[:, None] & suppress).sum(dim=0) > 0)
        return new, (new != keep).sum() > 0  # sum, not any: an empty ReduceMax is not False

    keep = torch.ones(suppress.shape[0], dtype=torch.bool)
    if torch.compiler.is_exporting():
        keep, _ = while_loop(_cond, body, (keep, torch.ones((), dtype=torch.bool)))
        return keep
    changed = torch.ones((), dtype=torch.bool)
    while bool(changed):  # eager: the same iteration as a Python loop (while_loop would compile)
        keep, changed = body(keep, changed)
    return keep


def nms_rotated(boxes: Tensor, scores: Tensor, iou_thresh: float) -> Tensor:
    """(M,) int64 indices of the boxes (K, 7) kept by greedy rotated BEV NMS, best first."""
    order = topk_indices(scores, scores.shape[0])  # (K,) best first, ties by lower index
    return order[nms_in_order(boxes[order], iou_thresh)]


_BOUND_SLACK = 0.9  # the AABB bound is tested against 90 % of the IoU limit: float-safe


def suppression_candidates(boxes: Tensor, iou_thresh: float) -> Tensor:
    """(K, K) bool, True where j < i and the rotated BEV IoU of boxes j, i may exceed the limit.

    The intersection of two rotated rectangles lies inside the intersection of their axis-aligned
    BEV bounds, so IoU > t needs bound_area * (1 + t) > t * (area_j + area_i); pairs failing that
    (by a 10 % margin) cannot suppress each other. boxes (K, 7).
    """
    c, s = torch.cos(boxes[:, 6]).abs(), torch.sin(boxes[:, 6]).abs()  # (K,)
    half = torch.stack([boxes[:, 3] * c + boxes[:, 4] * s, boxes[:, 3] * s + boxes[:, 4] * c], 1) / 2
    lo, hi = boxes[:, 0:2] - half, boxes[:, 0:2] + half  # (K, 2) AABB corners, m
    ext = (torch.minimum(hi[:, None], hi[None]) - torch.maximum(lo[:, None], lo[None])).clamp(min=0)
    bound = ext[..., 0] * ext[..., 1]  # (K, K) m^2, >= the rotated intersection
    area = boxes[:, 3] * boxes[:, 4]  # (K,)
    need = iou_thresh / (1 + iou_thresh) * (area[:, None] + area[None]) * _BOUND_SLACK
    return torch.triu(bound > need, diagonal=1)


def nms_in_order(boxes: Tensor, iou_thresh: float) -> Tensor:
    """(M,) int64 indices of boxes (K, 7), given best first, kept by greedy rotated BEV NMS.

    The rotated IoU is computed only for the pairs of ``suppression_candidates``.
    """
    k = boxes.shape[0]
    j, i = torch.nonzero(suppression_candidates(boxes, iou_thresh), as_tuple=True)  # (P,), (P,)
    over = iou_bev_pairs(boxes[j], boxes[i]) > iou_thresh  # (P,)
    flat = boxes.new_zeros(k * k).scatter(0, j * k + i, over.to(boxes.dtype))  # (K*K,)
    keep = suppress_fixed_point(flat.reshape(k, k) > 0)  # (K,)
    return torch.nonzero(keep)[:, 0]


def topk_indices(scores: Tensor, k: int) -> Tensor:
    """(min(k, N),) indices of the largest scores, best first; ties by lower index, as ONNX
    TopK does (torch.topk leaves tie order unspecified)."""
    if torch.compiler.is_exporting():
        return torch.topk(scores, min(k, scores.shape[0])).indices  # ONNX TopK: ties by index
    return torch.sort(scores, descending=True, stable=True).indices[:k]


def select_detections(boxes: Tensor, scores: Tensor, score_thresh: float, nms_pre: int,
                      nms_thresh: float, max_out: int) -> tuple[Tensor, Tensor]:
    """Top ``nms_pre`` by score -> score threshold -> rotated NMS -> at most ``max_out``."""
    top = topk_indices(scores, nms_pre)  # (K,)
    boxes, scores = boxes[top], scores[top]
    good = scores > score_thresh
    boxes, scores = boxes[good], scores[good]
    keep = nms_rotated(boxes, scores, nms_thresh)[:max_out]
    return boxes[keep], scores[keep]
