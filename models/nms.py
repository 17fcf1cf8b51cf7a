"""Rotated BEV NMS inside the graph: IoU matrix + a fixed-point loop (exact greedy NMS).

With boxes sorted by score and S[j, i] = (j < i and IoU(j, i) > t), greedy NMS keeps box i
iff no KEPT box j suppresses it. Iterating ``keep <- not any_j(keep[j] and S[j, i])`` from
all-True reaches that unique fixed point (after t rounds the first t entries are final; in
practice a few rounds), so the result equals greedy NMS exactly. The loop is a
``torch._higher_order_ops.while_loop``, which the dynamo exporter turns into an ONNX Loop.
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch._higher_order_ops.while_loop import while_loop

from models.iou import iou_bev


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
    sorted_boxes = boxes[order]
    over = iou_bev(sorted_boxes, sorted_boxes) > iou_thresh  # (K, K)
    keep = suppress_fixed_point(torch.triu(over, diagonal=1))
    return order[keep]


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
