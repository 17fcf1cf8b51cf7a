"""The one selection path of every detector: ranked top-k -> score threshold -> rotated BEV NMS.

- ``ranked_topk``: the k best of A candidates by score, equal scores ranked by the lower index.
  torch's CPU sort / topk, onnxruntime's TopK and OpenVINO's TopK break ties differently (OpenVINO's
  is not stable), and the runtimes' scores of identical inputs differ by float noise (~1e-7), so
  the k candidates are chosen by value comparisons and ranked by ONE distinct int32 key each: the
  score quantised to 2^-16 above the candidate's index rank. Scores closer than a level rank by
  index. Every key fits int32: OpenVINO's CPU plugin computes int64 in int32.
- ``nms_in_order``: greedy rotated NMS of boxes given best first, as a pair pre-filter
  (``suppression_candidates``), the rotated IoU of the candidate pairs and a fixed-point loop. Eager
  on the CPU it runs the numba kernel of ``models.nms_kernel`` instead (the same kept indices; the
  pairs whose IoU lies within float rounding of the threshold are decided by the torch IoU).
- ``select_ranked``: the two together, with a score threshold and a cap, for the final boxes of
  the one-stage heads and the proposals and final boxes of the two-stage models
  (``ranked_selection``: the indices it keeps).

With boxes sorted by score and S[j, i] = (j < i and IoU(j, i) > t), greedy NMS keeps box i
iff no KEPT box j suppresses it. Iterating ``keep <- not any_j(keep[j] and S[j, i])`` from
all-True reaches that unique fixed point (after t rounds the first t entries are final; in
practice a few rounds), so the result equals greedy NMS exactly. A round is a scatter-add over
the suppressing pairs (j, i), not a pass over the K x K matrix. The loop is a
``torch._higher_order_ops.while_loop``, which the dynamo exporter turns into an ONNX Loop.
The rotated IoU is computed only for the pairs whose axis-aligned BEV bounds could overlap
enough: a few percent of the K^2 pairs of detections.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor
from torch._higher_order_ops.while_loop import while_loop

from models.base import tracing
from models.iou import iou_bev_pairs
from models.nms_kernel import MIN_THRESH, greedy_nms_kernel


def _cond(keep: Tensor, changed: Tensor) -> Tensor:
    return changed.clone()


def fixed_point_round(keep: Tensor, j: Tensor, i: Tensor) -> Tensor:
    """One round: box i is kept iff none of its suppressors j (pairs (P,), (P,)) is kept."""
    hits = keep.new_zeros(keep.shape[0], dtype=torch.float32).index_add(0, i, keep[j].to(torch.float32))
    return hits == 0


def suppress_fixed_point(j: Tensor, i: Tensor, k: int) -> Tensor:
    """(k,) bool keep mask for the suppressing pairs j < i (P,), (P,) of k boxes given best first.

    One round costs O(P), not O(k^2): box i counts the kept boxes among its suppressors by a
    scatter-add over the pairs.
    """
    def body(keep: Tensor, changed: Tensor):
        new = fixed_point_round(keep, j, i)
        return new, (new != keep).sum() > 0  # sum, not any: an empty ReduceMax is not False

    keep = torch.ones(k, dtype=torch.bool)
    if torch.compiler.is_exporting():
        keep, _ = while_loop(_cond, body, (keep, torch.ones((), dtype=torch.bool)))
        return keep
    changed = torch.ones((), dtype=torch.bool)
    while bool(changed):  # eager: the same iteration as a Python loop (while_loop would compile)
        keep, changed = body(keep, changed)
    return keep


_BOUND_SLACK = 0.9  # the AABB bound is tested against 90 % of the IoU limit: float-safe


def suppression_candidates(boxes: Tensor, iou_thresh: float) -> Tensor:
    """(K, K) bool, True where j < i and the rotated BEV IoU of boxes j, i may exceed the limit.

    The intersection of two rotated rectangles lies inside the intersection of their axis-aligned
    BEV bounds, so IoU > t needs bound_area * (1 + t) > t * (area_j + area_i); pairs failing that
    (by a 10 % margin) cannot suppress each other. boxes (K, 7).
    """
    c, s = torch.cos(boxes[:, 6]).abs(), torch.sin(boxes[:, 6]).abs()  # (K,)
    hx = (boxes[:, 3] * c + boxes[:, 4] * s) / 2  # (K,) AABB half sizes, m
    hy = (boxes[:, 3] * s + boxes[:, 4] * c) / 2
    x, y = boxes[:, 0], boxes[:, 1]
    # x and y apart, each (K, K) with K innermost: a trailing axis of 2 broadcasts slowly in a runtime
    ex = (torch.minimum((x + hx)[:, None], (x + hx)[None])
          - torch.maximum((x - hx)[:, None], (x - hx)[None])).clamp(min=0)
    ey = (torch.minimum((y + hy)[:, None], (y + hy)[None])
          - torch.maximum((y - hy)[:, None], (y - hy)[None])).clamp(min=0)
    bound = ex * ey  # (K, K) m^2, >= the rotated intersection
    area = boxes[:, 3] * boxes[:, 4]  # (K,)
    need = iou_thresh / (1 + iou_thresh) * (area[:, None] + area[None]) * _BOUND_SLACK
    return torch.triu(bound > need, diagonal=1)


def nms_in_order(boxes: Tensor, iou_thresh: float, max_keep: int | None = None) -> Tensor:
    """(M,) int64 indices of boxes (K, 7), given best first, kept by greedy rotated BEV NMS: the first
    ``max_keep`` of them if given.

    Box j suppresses box i > j where the pair is a ``suppression_candidates`` one and its rotated IoU
    (``iou_bev_pairs``, float32) exceeds the limit. Eager float32 CPU boxes take the numba kernel
    (:func:`_nms_kernel`), which keeps the same boxes; the graph takes the torch form.
    """
    if _kernel_ready(boxes, iou_thresh):
        return _nms_kernel(boxes, iou_thresh, max_keep)
    return _nms_torch(boxes, iou_thresh, max_keep)


def _nms_torch(boxes: Tensor, iou_thresh: float, max_keep: int | None) -> Tensor:
    """:func:`nms_in_order` in torch ops: the graph's form."""
    k = boxes.shape[0]
    j, i = torch.nonzero(suppression_candidates(boxes, iou_thresh), as_tuple=True)  # (P,), (P,)
    over = torch.nonzero(iou_bev_pairs(boxes[j], boxes[i]) > iou_thresh)[:, 0]  # (S,) suppressing pairs
    keep = suppress_fixed_point(j[over], i[over], k)  # (K,)
    kept = torch.nonzero(keep)[:, 0]
    return kept if max_keep is None else kept[:max_keep]


def _kernel_ready(boxes: Tensor, iou_thresh: float) -> bool:
    """Eager float32 CPU boxes and a limit the kernel's bound test serves (``MIN_THRESH``)."""
    return (not tracing() and boxes.device.type == "cpu" and boxes.dtype == torch.float32
            and iou_thresh >= MIN_THRESH)


def _suppresses(boxes: Tensor, j: int, i: int, iou_thresh: float) -> bool:
    """Box j suppresses box i in the torch form: a candidate pair whose float32 IoU exceeds the limit
    (both element-wise in the pair, so a pair alone gets the bits it gets among all of them)."""
    pair = boxes[[j, i]]  # (2, 7)
    return bool(suppression_candidates(pair, iou_thresh)[0, 1]) and bool(
        iou_bev_pairs(pair[:1], pair[1:])[0] > iou_thresh)


_MAX_UNDECIDED = 64  # pairs the torch IoU decides for the kernel before the torch form takes the call


def _nms_kernel(boxes: Tensor, iou_thresh: float, max_keep: int | None) -> Tensor:
    """:func:`nms_in_order` by ``models.nms_kernel.greedy_nms_kernel``. Each pair it leaves undecided
    (float64 IoU within float rounding of the limit: rare) is decided here by the torch IoU, and the
    kernel resumes after it; past ``_MAX_UNDECIDED`` such pairs (degenerate boxes) the torch form runs."""
    k = boxes.shape[0]
    cap = k if max_keep is None else max(0, min(k, max_keep))
    b = boxes.detach()
    arr = b.numpy().astype(np.float64)  # (K, 7)
    suppressed, kept = np.zeros(k, np.bool_), np.empty(cap, np.int64)
    count, j, i = greedy_nms_kernel(arr, float(iou_thresh), cap, suppressed, kept, 0, 0, -1)
    undecided = 0
    while j >= 0:
        if undecided == _MAX_UNDECIDED:
            return _nms_torch(b, iou_thresh, max_keep)
        suppressed[i] = _suppresses(b, j, i, iou_thresh)
        undecided += 1
        count, j, i = greedy_nms_kernel(arr, float(iou_thresh), cap, suppressed, kept, count, j, i + 1)
    return torch.from_numpy(kept[:count])


INT32_MAX = 2 ** 31 - 1
SCORE_LEVELS = 2 ** 16  # score quantisation of the ranking key: coarser than float noise (~1e-7)
MAX_K = 2 ** 14  # candidates a ranking holds: SCORE_LEVELS * 2 * MAX_K = 2^31


def index_bits(bound: int) -> int:
    """Bits that hold every index below ``bound`` (at least 1)."""
    return max(1, (bound - 1).bit_length())


def ranked_topk(scores: Tensor, k: int) -> Tensor:
    """(min(k, A),) indices of scores (A,) in [0, 1], best first: ranked by the score quantised to
    2^-16, equal levels by the lower index (also at the cut: the k best are the first k so ranked).

    The candidates are every score level above the k-th largest level and the first ones equal to
    it, found by comparisons and NonZero (ascending), so no TopK tie rule enters; they are then
    ranked by one distinct int32 key, ``level * 2^b + (2^b - 1 - position)``.
    """
    if k > MAX_K:
        raise ValueError(f"ranked_topk: k = {k} > {MAX_K} would overflow the int32 ranking key")
    kk = torch.sym_min(k, scores.shape[0])
    level = torch.floor(scores.clamp(0.0, 1.0) * SCORE_LEVELS).to(torch.int32)  # (A,) in [0, 2^16]
    top = torch.topk(level, kk).values  # (kk,) descending: values, not indices, so tie-free
    cut = torch.cat([level.new_full((1,), SCORE_LEVELS + 1), top])[-1]  # k-th largest (none: above all)
    above, at = level > cut, level == cut  # (A,)
    room = kk - above.sum()
    take = above | (at & (torch.cumsum(at.to(torch.int32), 0) <= room))
    cand = torch.nonzero(take)[:, 0]  # (kk,) ascending index
    bits = index_bits(k)
    position = torch.arange(cand.shape[0], dtype=torch.int32, device=scores.device)
    key = torch.index_select(level, 0, cand) * (2 ** bits) + ((2 ** bits - 1) - position)  # (kk,) distinct
    return torch.index_select(cand, 0, torch.sort(key, descending=True).indices)


def select_ranked(boxes: Tensor, scores: Tensor, score_thresh: float, nms_pre: int,
                  nms_iou: float, max_out: int) -> tuple[Tensor, Tensor]:
    """Top ``nms_pre`` by score -> score threshold -> rotated NMS -> at most ``max_out``.

    boxes (A, 7), scores (A,) in [0, 1] -> (M, 7), (M,) best first.
    """
    kept = ranked_selection(boxes, scores, score_thresh, nms_pre, nms_iou, max_out)
    return boxes[kept], scores[kept]


def ranked_selection(boxes: Tensor, scores: Tensor, score_thresh: float, nms_pre: int,
                     nms_iou: float, max_out: int) -> Tensor:
    """(M,) int64 indices into boxes (A, 7) / scores (A,) that :func:`select_ranked` keeps, best first."""
    order = ranked_topk(scores, nms_pre)  # (K,)
    order = order[scores[order] > score_thresh]
    return order[nms_in_order(boxes[order], nms_iou, max_out)]
