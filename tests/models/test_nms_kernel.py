"""The numba NMS kernel against the torch form the ONNX graph keeps: the same kept indices on random box
sets (empty, one box, crowded, rotated, slim, duplicated, capped), on pairs whose IoU lies within float
rounding of the limit, and its float64 IoU within its margin of the torch IoU."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from models import nms
from models.iou import iou_bev_pairs
from models.nms import _nms_torch, nms_in_order
from models.nms_kernel import iou_bev_pairs_f64, pair_margin

pytestmark = pytest.mark.usefixtures("one_thread")


def _box_set(rng: np.random.Generator, k: int, spread: float, slim: bool, square_yaw: bool, duplicates: bool,
             x0: float = 40.0) -> torch.Tensor:
    """(k, 7) float32 car boxes around (x0, 0), centres within ``spread`` m; slim ones, yaws at multiples of
    pi / 2 (parallel edges) and the second half a copy of the first on request."""
    centre = rng.uniform(-spread, spread, (k, 3)) + [x0, 0.0, 0.0]
    size = rng.uniform([3.0, 1.5, 1.3], [5.0, 2.2, 1.9], (k, 3))
    if slim:
        size[:, :2] *= rng.uniform(0.1, 2.0, (k, 2))
    yaw = rng.uniform(-np.pi, np.pi, (k, 1))
    if square_yaw:
        yaw = np.round(yaw / (np.pi / 2)) * (np.pi / 2)
    boxes = np.concatenate([centre, size, yaw], 1).astype(np.float32)
    if duplicates:
        boxes[k // 2:] = boxes[: k - k // 2]
    return torch.from_numpy(boxes)


@pytest.mark.parametrize("k,spread,slim,square_yaw,duplicates", [
    (0, 5.0, False, False, False), (1, 5.0, False, False, False), (2, 0.3, False, True, False),
    (300, 2.0, False, False, False), (300, 6.0, True, False, False), (200, 3.0, False, True, False),
    (200, 3.0, False, False, True), (120, 60.0, True, True, True)])
def test_kernel_keeps_the_torch_boxes(k, spread, slim, square_yaw, duplicates):
    boxes = _box_set(np.random.default_rng(k + int(spread)), k, spread, slim, square_yaw, duplicates)
    for thresh in (0.01, 0.1, 0.55, 0.8):
        want = _nms_torch(boxes, thresh, None).numpy()
        for cap in (None, 1, 16, 64):
            got = nms_in_order(boxes, thresh, cap)
            assert got.dtype == torch.int64
            np.testing.assert_array_equal(got.numpy(), want[:cap])


def _pairs_at_the_limit(rng: np.random.Generator, n: int, thresh: float) -> torch.Tensor:
    """(2n, 7) float32 pairs: a box and its copy shifted along its heading so that their IoU is
    ``thresh`` up to a few float32 ulps of the shift, rotated and placed 10-70 m out."""
    boxes = []
    for _ in range(n):
        length, width, yaw = rng.uniform(3.0, 5.0), rng.uniform(1.5, 2.2), rng.choice([0.0, rng.uniform(-3, 3)])
        shift = np.float32(length * (1 - thresh) / (1 + thresh))  # IoU (l - d) / (l + d) = thresh
        shift = np.nextafter(shift, np.float32(np.inf) * rng.choice([-1, 1]), dtype=np.float32)
        x, y = rng.uniform(10, 70), rng.uniform(-20, 20)
        for d in (0.0, float(shift)):
            boxes.append([x + d * np.cos(yaw), y + d * np.sin(yaw), -1.0, length, width, 1.6, yaw])
    return torch.tensor(boxes, dtype=torch.float32)


def test_pairs_at_the_limit_take_the_torch_decision(monkeypatch):
    """Pairs whose IoU is the limit within float rounding: the torch IoU decides them, and the kept
    indices are the torch form's on both sides of the limit."""
    decided = []
    suppresses = nms._suppresses
    monkeypatch.setattr(nms, "_suppresses", lambda *a: decided.append(suppresses(*a)) or decided[-1])
    rng = np.random.default_rng(5)
    for thresh in (0.1, 0.7, 0.8):
        boxes = _pairs_at_the_limit(rng, 40, thresh)
        for start in range(0, len(boxes), 2):
            pair = boxes[start:start + 2]
            np.testing.assert_array_equal(nms_in_order(pair, thresh).numpy(), _nms_torch(pair, thresh, None).numpy())
        np.testing.assert_array_equal(nms_in_order(boxes, thresh).numpy(), _nms_torch(boxes, thresh, None).numpy())
    assert len(decided) >= 120 and any(decided) and not all(decided)


def test_float64_iou_stays_within_the_margin_of_the_torch_iou():
    """The kernel trusts its float64 IoU only beyond ``pair_margin`` of the limit: the float32 torch
    IoU of near, far, slim and parallel pairs stays within a quarter of it."""
    rng = np.random.default_rng(6)
    a = _box_set(rng, 3000, 70.0, True, False, False).numpy()
    a[1000:2000, 6] = 0.0  # parallel edges
    b = a.copy()
    b[:, :2] += rng.normal(0, 0.3, (3000, 2))
    b[:, 3:5] *= rng.uniform(0.9, 1.1, (3000, 2))
    b[:1000, 6] += rng.normal(0, 0.2, 1000)
    got = iou_bev_pairs_f64(a.astype(np.float64), b.astype(np.float64))
    ref = iou_bev_pairs(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    margin = np.array([pair_margin(p.astype(np.float64), q.astype(np.float64)) for p, q in zip(a, b)])
    assert (ref > 0.5).sum() > 500  # overlapping pairs, not only disjoint ones
    assert (np.abs(got - ref) <= margin / 4).all()


def test_tiny_limits_and_graphs_take_the_torch_form(monkeypatch):
    calls = []
    monkeypatch.setattr(nms, "_nms_kernel", lambda *a: calls.append(a))
    boxes = _box_set(np.random.default_rng(7), 50, 3.0, False, False, False)
    nms_in_order(boxes, 0.0)
    nms_in_order(boxes.double(), 0.5)
    monkeypatch.setattr(nms, "tracing", lambda: True)
    nms_in_order(boxes, 0.5)
    assert calls == []


def test_degenerate_boxes_hand_the_call_to_the_torch_form(monkeypatch):
    """Boxes of zero width leave every pair undecided (no rounding bound): past ``_MAX_UNDECIDED`` of
    them the torch form takes the call."""
    calls = []
    torch_form = nms._nms_torch
    monkeypatch.setattr(nms, "_nms_torch", lambda *a: calls.append(a) or torch_form(*a))
    boxes = _box_set(np.random.default_rng(8), 100, 1.0, False, False, False)
    boxes[:, 4] = 0.0
    np.testing.assert_array_equal(nms_in_order(boxes, 0.5).numpy(), torch_form(boxes, 0.5, None).numpy())
    assert len(calls) == 1
