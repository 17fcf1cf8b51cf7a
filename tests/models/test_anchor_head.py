import math

import numpy as np
import torch

from harness.core.boxes import bev_intersection, iou_bev
from models.anchor_head import AnchorHead, HeadConfig, assign_targets, make_anchors

RANGE = (0.0, -8.0, -3.0, 16.0, 8.0, 1.0)
CFG = HeadConfig(anchor_z=-1.0)


def test_anchor_layout_matches_head_flatten():
    anchors = make_anchors(RANGE, (4, 8), CFG)
    assert anchors.shape == (4 * 8 * 2, 7)
    grid = anchors.reshape(4, 8, 2, 7)
    np.testing.assert_allclose(grid[2, 5, 1].numpy(), [11.0, 2.0, -1.0, 3.9, 1.6, 1.56, math.pi / 2],
                               rtol=1e-6)
    head = AnchorHead(3, (4, 8), RANGE, CFG)
    feats = torch.zeros(1, 3, 4, 8)
    feats[0, :, 2, 5] = torch.tensor([1.0, 2.0, 3.0])
    cls, box, dirs = head(feats)
    ref = head.conv_cls.weight[:, :, 0, 0] @ feats[0, :, 2, 5] + head.conv_cls.bias  # (R,)
    torch.testing.assert_close(cls.reshape(4, 8, 2)[2, 5], ref)
    assert box.shape == (64, 7) and dirs.shape == (64, 2)


def test_head_gemm_matches_the_three_convs():
    torch.manual_seed(3)
    head = AnchorHead(16, (6, 10), RANGE, CFG)
    feats = torch.randn(1, 16, 6, 10, requires_grad=True)
    cls, box, dirs = head(feats)
    loss = (cls.square().sum() + box.sin().sum() + dirs.cos().sum())
    grads = torch.autograd.grad(loss, [feats, *head.parameters()])

    def flat(x, c):  # the conv layout: (1, R * c, H, W) -> (H * W * R, c)
        return x[0].permute(1, 2, 0).reshape(-1, c)
    ref = (flat(head.conv_cls(feats), 1)[:, 0], flat(head.conv_box(feats), 7), flat(head.conv_dir(feats), 2))
    for got, want in zip((cls, box, dirs), ref):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    ref_loss = ref[0].square().sum() + ref[1].sin().sum() + ref[2].cos().sum()
    for got, want in zip(grads, torch.autograd.grad(ref_loss, [feats, *head.parameters()])):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


def test_assign_targets_matches_numpy_rules():
    anchors = make_anchors(RANGE, (8, 16), CFG)
    gt = np.array([[5.1, 1.2, -1.0, 4.0, 1.7, 1.5, 0.1], [11.0, -3.0, -1.0, 4.2, 1.8, 1.5, 1.4]], np.float32)
    ignore = np.array([[3.0, -5.0, -1.0, 5.0, 2.0, 2.0, 0.0]], np.float32)
    labels, matched = assign_targets(anchors, torch.from_numpy(gt), torch.from_numpy(ignore), CFG)
    iou = iou_bev(anchors.numpy(), gt)
    a = anchors.numpy()
    ign = (bev_intersection(a, ignore) / (a[:, 3] * a[:, 4])[:, None]).max(1) >= CFG.neg_iou  # share inside
    ref = np.where(iou.max(1) >= CFG.pos_iou, 1, np.where(iou.max(1) >= CFG.neg_iou, -1, 0))
    ref[ign & (ref == 0)] = -1
    ref[((iou >= iou.max(0) - 1e-5) & (iou > 0)).any(1)] = 1  # each gt's best anchors (float32 ties)
    np.testing.assert_array_equal(labels.numpy(), ref)
    pos = ref == 1
    np.testing.assert_array_equal(matched.numpy()[pos], iou.argmax(1)[pos])


def test_anchors_on_a_truck_are_ignored():
    """Car-sized anchors on an ignored truck (IoU <= 0.3 with it) are ignored, not negatives."""
    anchors = make_anchors(RANGE, (8, 16), CFG)
    truck = torch.tensor([[8.0, 0.0, -1.0, 11.5, 2.55, 3.8, 0.0]])
    labels, _ = assign_targets(anchors, torch.zeros(0, 7), truck, CFG)
    a = anchors.numpy()
    inside = (np.abs(a[:, 0] - 8.0) <= 3.5) & (np.abs(a[:, 1]) <= 1.0) & (np.abs(np.sin(a[:, 6])) < 1e-6)  # 2/3 or more on it
    assert inside.sum() > 0 and (labels.numpy()[inside] == -1).all()
    assert iou_bev(a[inside], truck.numpy()).max() < 0.3
    assert (labels.numpy()[np.abs(a[:, 1]) > 4] == 0).all()  # far from it: negatives


def test_head_loss_decreases_and_detect_runs():
    torch.manual_seed(0)
    head = AnchorHead(16, (8, 16), RANGE, CFG)
    feats = torch.randn(1, 16, 8, 16)
    gt = torch.tensor([[5.1, 1.2, -1.0, 4.0, 1.7, 1.5, 2.5]])
    opt = torch.optim.Adam(head.parameters(), lr=0.05)
    first = None
    for _ in range(60):
        loss = head.loss(feats, gt, torch.zeros(0, 7))["loss"]
        first = first if first is not None else float(loss.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.3 * first
    boxes, scores = head.detect(feats)
    assert boxes.shape[0] >= 1 and float(scores[0]) > 0.3
    np.testing.assert_allclose(boxes[0, :2].detach().numpy(), [5.1, 1.2], atol=0.3)
    assert abs(math.remainder(float(boxes[0, 6]) - 2.5, 2 * math.pi)) < 0.2
