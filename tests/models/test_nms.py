"""The one selection path: ranked top-k (int32 keys, ties by index), greedy rotated NMS."""
import numpy as np
import pytest
import torch

from harness.core.boxes import iou_bev
from models.nms import (INT32_MAX, MAX_K, SCORE_LEVELS, index_bits, nms_in_order, ranked_topk, select_ranked,
                        suppression_candidates)


def test_ranked_topk_keys_fit_int32():
    assert (SCORE_LEVELS + 1) * 2 ** index_bits(MAX_K) <= INT32_MAX + 1  # top level, index 0
    scores = torch.rand(70400)
    scores[:10] = 1.0
    assert ranked_topk(scores, 50).tolist()[:10] == list(range(10))  # the largest keys, no wrap-around
    with pytest.raises(ValueError, match="int32"):
        ranked_topk(scores, MAX_K + 1)


def test_ranked_topk_takes_the_lower_indices_at_the_cut():
    scores = torch.tensor([0.2, 0.5, 0.5, 0.9, 0.5, 0.5, 0.1])
    assert ranked_topk(scores, 3).tolist() == [3, 1, 2]  # 0.5 x 4 at the cut: indices 1, 2
    assert ranked_topk(scores, 10).tolist() == [3, 1, 2, 4, 5, 0, 6]
    assert ranked_topk(scores, 0).tolist() == []
    near = torch.tensor([0.3, 0.5 + 2e-6, 0.5, 0.7])  # within one 2^-16 level: by index
    assert ranked_topk(near, 4).tolist() == [3, 1, 2, 0]
    assert ranked_topk(near.flip(0), 4).tolist() == [0, 1, 2, 3]


def test_ranked_topk_breaks_ties_by_index():
    rng = np.random.default_rng(7)
    scores = rng.integers(0, 6, 3000) / 7.0  # many exact ties
    got = ranked_topk(torch.from_numpy(scores).float(), 500).numpy()
    want = sorted(range(3000), key=lambda i: (-np.float32(scores[i]), i))[:500]
    np.testing.assert_array_equal(got, want)
    assert len(ranked_topk(torch.zeros(0), 5)) == 0


def test_select_ranked_is_greedy_nms_in_rank_order(random_boxes):
    rng = np.random.default_rng(8)
    boxes = random_boxes(rng, 120, 12.0)
    boxes[:, 3:6] *= 1.5  # more overlaps
    scores = (rng.integers(0, 20, 120) / 20.0).astype(np.float32)  # ties
    got_boxes, got_scores = select_ranked(torch.from_numpy(boxes), torch.from_numpy(scores),
                                          0.1, 100, 0.2, 30)
    order = sorted(range(120), key=lambda i: (-scores[i], i))[:100]
    order = [i for i in order if scores[i] > 0.1]
    overlaps = iou_bev(boxes, boxes)
    kept: list[int] = []
    for i in order:  # greedy NMS, reference
        if all(overlaps[i, j] <= 0.2 for j in kept):
            kept.append(i)
    kept = kept[:30]
    np.testing.assert_allclose(got_boxes.numpy(), boxes[kept], atol=1e-6)
    np.testing.assert_array_equal(got_scores.numpy(), scores[kept])


def greedy_nms(boxes: np.ndarray, thresh: float) -> list[int]:
    """Reference: greedy NMS of boxes given best first, with the reference rotated BEV IoU."""
    overlaps = iou_bev(boxes, boxes) if len(boxes) else np.zeros((0, 0))
    kept: list[int] = []
    for i in range(len(boxes)):
        if all(overlaps[i, j] <= thresh for j in kept):
            kept.append(i)
    return kept


def test_nms_in_order_is_greedy_nms(random_boxes):
    rng = np.random.default_rng(9)
    for k, spread, thresh in [(150, 10.0, 0.7), (150, 10.0, 0.1), (80, 4.0, 0.3), (40, 200.0, 0.1),
                              (1, 5.0, 0.5), (0, 5.0, 0.5)]:
        boxes = random_boxes(rng, k, spread)
        boxes[:, 3:5] *= rng.uniform(0.3, 2.0, (k, 2))  # slim and wide boxes too
        got = nms_in_order(torch.from_numpy(boxes), thresh).numpy()
        np.testing.assert_array_equal(got, greedy_nms(boxes, thresh))


def test_suppression_candidates_hold_every_overlapping_pair(random_boxes):
    rng = np.random.default_rng(10)
    boxes = random_boxes(rng, 200, 8.0)
    boxes[:, 3:5] *= rng.uniform(0.3, 2.0, (200, 2))
    overlaps = np.triu(iou_bev(boxes, boxes), 1)  # (K, K) j < i
    for thresh in (0.05, 0.3, 0.7):
        cand = suppression_candidates(torch.from_numpy(boxes), thresh).numpy()
        assert not (np.tril(cand).any())
        assert cand[overlaps > thresh].all()
        if thresh >= 0.3:  # the bound prunes even pairs that overlap a little
            assert cand.sum() < (overlaps > 0).sum()
