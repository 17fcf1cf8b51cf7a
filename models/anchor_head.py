"""Anchor head with direction classifier, anchors, rotated-IoU target assignment and loss.

One class (Car), anchors at every BEV cell with the rotations of :class:`HeadConfig`; anchor
order is (y, x, rotation), matching the head's ``(1, R * c, H, W) -> (H * W * R, c)`` flatten.
``detect`` decodes, folds yaw with the direction bin and runs score threshold + rotated NMS in
the graph; ``loss`` assigns targets by rotated BEV IoU (OpenPCDet's matched / unmatched
thresholds; every ground truth also takes its best anchor) and returns the focal + smooth-L1 +
direction losses normalised by the number of positives.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from models import box_coder
from models.iou import ioa_bev_sparse, iou_bev_sparse
from models.losses import box_regression_loss, direction_loss, sigmoid_focal_loss
from models.nms import select_ranked


@dataclass(frozen=True)
class HeadConfig:
    anchor_size: tuple[float, float, float] = (3.9, 1.6, 1.56)  # (l, w, h) metres, Car
    anchor_z: float = -1.0  # anchor centre height, metres (LiDAR frame)
    rotations: tuple[float, ...] = (0.0, math.pi / 2)
    pos_iou: float = 0.6  # BEV IoU >= pos_iou -> positive
    neg_iou: float = 0.45  # BEV IoU < neg_iou -> negative (between: ignored)
    score_thresh: float = 0.1
    nms_pre: int = 256  # top-scoring anchors that enter NMS
    nms_iou: float = 0.1  # rotated BEV IoU above which a lower-scored box is suppressed
    max_out: int = 100
    weight_cls: float = 1.0
    weight_box: float = 2.0
    weight_dir: float = 0.2


def make_anchors(pc_range, feat_hw: tuple[int, int], cfg: HeadConfig) -> Tensor:
    """(H * W * R, 7) anchors at the cell centres of an (H, W) BEV map covering pc_range."""
    x0, y0, _, x1, y1, _ = pc_range
    h, w = feat_hw
    xs = x0 + (torch.arange(w, dtype=torch.float32) + 0.5) * (x1 - x0) / w  # (W,) metres
    ys = y0 + (torch.arange(h, dtype=torch.float32) + 0.5) * (y1 - y0) / h  # (H,) metres
    rots = torch.tensor(cfg.rotations, dtype=torch.float32)  # (R,)
    yy, xx, rr = torch.meshgrid(ys, xs, rots, indexing="ij")  # (H, W, R)
    l, wd, ht = cfg.anchor_size
    n = yy.numel()
    size = torch.tensor([cfg.anchor_z, l, wd, ht], dtype=torch.float32).expand(n, 4)
    return torch.cat([xx.reshape(n, 1), yy.reshape(n, 1), size, rr.reshape(n, 1)], dim=1)


def assign_targets(anchors: Tensor, gt: Tensor, ignore: Tensor, cfg: HeadConfig):
    """Labels (A,) in {1 positive, 0 negative, -1 ignored} and matched gt index (A,).

    Anchors with a share >= neg_iou of their area inside an ``ignore`` box (Van, Truck, DontCare) are
    ignored rather than negatives: by area, not IoU, so that a car-sized anchor on a truck (IoU <= 0.3)
    is not taught that the truck is nothing.
    """
    a = anchors.shape[0]
    labels = torch.zeros(a, dtype=torch.long)
    matched = torch.zeros(a, dtype=torch.long)
    if ignore.shape[0]:
        labels[ioa_bev_sparse(anchors, ignore).max(dim=1).values >= cfg.neg_iou] = -1
    if gt.shape[0] == 0:
        return labels, matched
    iou = iou_bev_sparse(anchors, gt)  # (A, K)
    best_iou, matched = iou.max(dim=1)  # (A,)
    labels[(best_iou >= cfg.neg_iou) & (best_iou < cfg.pos_iou)] = -1
    labels[best_iou >= cfg.pos_iou] = 1
    gt_best = iou.max(dim=0).values  # (K,) best IoU of each gt
    force_a, force_k = torch.nonzero((iou == gt_best[None]) & (gt_best[None] > 0), as_tuple=True)
    labels[force_a] = 1
    matched[force_a] = force_k
    return labels, matched


def head_convs(c_in: int, anchors: int, classes: int = 1) -> tuple[nn.Conv2d, nn.Conv2d, nn.Conv2d]:
    """The 1x1 convs of an anchor head with ``anchors`` anchors per BEV cell: class logits (anchors *
    classes), box residuals (anchors * 7) and direction logits (anchors * 2), each anchor's channels
    together. The class bias starts at the focal loss's 1 % prior, the box conv near zero."""
    conv_cls = nn.Conv2d(c_in, anchors * classes, 1)
    conv_box = nn.Conv2d(c_in, anchors * 7, 1)
    conv_dir = nn.Conv2d(c_in, anchors * 2, 1)
    nn.init.constant_(conv_cls.bias, -math.log((1 - 0.01) / 0.01))
    nn.init.normal_(conv_box.weight, std=0.001)
    nn.init.zeros_(conv_box.bias)
    return conv_cls, conv_box, conv_dir


def head_outputs(feats: Tensor, convs: tuple[nn.Conv2d, nn.Conv2d, nn.Conv2d]) -> tuple[Tensor, Tensor, Tensor]:
    """(1, C, H, W) -> class logits (A, n), box residuals (A, 7), direction logits (A, 2) of the
    ``head_convs`` ``convs``, A = H * W * anchors per cell, in the conv layout (cell, anchor); float32.

    The three 1x1 convs run as one conv with their stacked weights (the same products): torch's
    convolution of a large map into 2 or 4 channels is several times slower than into their sum
    (in SECOND's training step the three separate convs took ~9 %).
    """
    # float32 also under autocast (``train --amp``): the losses, the decoding and the proposals' ranking read it
    out = F.conv2d(feats, torch.cat([c.weight for c in convs]), torch.cat([c.bias for c in convs])).float()
    out = out[0].permute(1, 2, 0).reshape(-1, out.shape[1])  # (H * W, anchors * (n + 9))
    k, b = convs[0].out_channels, convs[1].out_channels  # anchors * n, anchors * 7
    return out[:, :k].reshape(-1, 7 * k // b), out[:, k:k + b].reshape(-1, 7), out[:, k + b:].reshape(-1, 2)


class AnchorHead(nn.Module):
    """1x1 convs for class logits (R), box residuals (R * 7) and direction logits (R * 2)."""

    dir_offset = math.pi / 4  # the yaw offset of the direction bins (``box_coder.apply_direction``)

    def __init__(self, c_in: int, feat_hw: tuple[int, int], pc_range, cfg: HeadConfig):
        super().__init__()
        self.cfg = cfg
        self.conv_cls, self.conv_box, self.conv_dir = head_convs(c_in, len(cfg.rotations))
        self.register_buffer("anchors", make_anchors(pc_range, feat_hw, cfg), persistent=False)

    def forward(self, feats: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(1, C, H, W) -> cls logits (A,), box residuals (A, 7), direction logits (A, 2)."""
        cls, box, dirs = head_outputs(feats, (self.conv_cls, self.conv_box, self.conv_dir))
        return cls.reshape(-1), box, dirs

    def decode(self, box: Tensor, dir_logits: Tensor) -> Tensor:
        """(A, 7) boxes with yaw folded by the direction bin."""
        boxes = box_coder.decode(box, self.anchors)
        yaw = box_coder.apply_direction(boxes[:, 6], torch.argmax(dir_logits, dim=1), self.dir_offset)
        return torch.cat([boxes[:, :6], yaw[:, None]], dim=1)

    def detect(self, feats: Tensor) -> tuple[Tensor, Tensor]:
        """Final boxes (M, 7) and scores (M,) after score threshold and rotated NMS."""
        cls, box, dirs = self(feats)
        c = self.cfg
        return select_ranked(self.decode(box, dirs), torch.sigmoid(cls), c.score_thresh,
                             c.nms_pre, c.nms_iou, c.max_out)

    def loss(self, feats: Tensor, gt: Tensor, ignore: Tensor) -> dict[str, Tensor]:
        """Losses for one frame: gt (K, 7) Car boxes, ignore (J, 7) boxes not to penalise."""
        cls, box, dirs = self(feats)
        with torch.no_grad():
            labels, matched = assign_targets(self.anchors, gt, ignore, self.cfg)
        pos = labels == 1
        num_pos = pos.sum().clamp(min=1).to(cls.dtype)
        weights = (labels >= 0).to(cls.dtype)
        loss_cls = sigmoid_focal_loss(cls, pos.to(cls.dtype), weights) / num_pos
        target_boxes = gt[matched[pos]] if gt.shape[0] else box.new_zeros(0, 7)  # (P, 7)
        anchors = self.anchors[pos]
        loss_box = box_regression_loss(box[pos], box_coder.encode(target_boxes, anchors)) / num_pos
        dir_target = box_coder.direction_target(target_boxes[:, 6], self.dir_offset)
        loss_dir = direction_loss(dirs[pos], dir_target) / num_pos
        c = self.cfg
        total = c.weight_cls * loss_cls + c.weight_box * loss_box + c.weight_dir * loss_dir
        return {"loss": total, "loss_cls": loss_cls, "loss_box": loss_box, "loss_dir": loss_dir}
