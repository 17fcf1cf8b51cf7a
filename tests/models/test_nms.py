import numpy as np
import torch

from harness.boxes import nms_bev
from models.nms import nms_rotated, select_detections


def _scene(rng, n):
    b = np.zeros((n, 7), np.float32)
    b[:, :2] = rng.random((n, 2)) * 12
    b[:, 3:6] = [3.9, 1.6, 1.5]
    b[:, 6] = rng.random(n) * 6.28 - 3.14
    return b, rng.random(n).astype(np.float32)


def _greedy(boxes, scores, thresh):
    """Brute-force greedy NMS on shapely-checked IoU (harness.boxes)."""
    return nms_bev(boxes, scores, thresh)


def test_nms_equals_greedy_reference():
    rng = np.random.default_rng(0)
    for n, t in ((0, 0.1), (1, 0.1), (40, 0.1), (120, 0.3), (120, 0.01)):
        b, s = _scene(rng, n)
        got = nms_rotated(torch.from_numpy(b), torch.from_numpy(s), t).numpy()
        ref = _greedy(b, s, t) if n else np.zeros(0, np.int64)
        assert np.array_equal(got, ref)


def test_select_detections_threshold_topk_and_cap():
    rng = np.random.default_rng(1)
    b, s = _scene(rng, 200)
    boxes, scores = select_detections(torch.from_numpy(b), torch.from_numpy(s), 0.5, 64, 0.2, 5)
    top = np.argsort(-s)[:64]
    top = top[s[top] > 0.5]
    ref = top[_greedy(b[top], s[top], 0.2)][:5]
    np.testing.assert_array_equal(scores.numpy(), s[ref])
    np.testing.assert_array_equal(boxes.numpy(), b[ref])
