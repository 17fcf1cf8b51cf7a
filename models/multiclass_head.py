"""The published anchor heads of OpenPCDet (``AnchorHeadSingle``) and MMDetection3D
(``Anchor3DHead``): one anchor set per class (3 on KITTI), each anchor scored for every class,
and each reference's own post-processing. Only the Car boxes leave the head (``detect``).

Anchor order is (y, x, class set, rotation) and the conv channels of an anchor are laid out
anchor-major, as in both references: ``(1, S * R * c, H, W) -> (H * W * S * R, c)``, so their
checkpoint tensors load without a permutation.

- OpenPCDet (``post = "openpcdet"``): anchors spread over the range, ends included
  (``align_center: False``; ``anchor_grid = "arange"``), sigmoid, the best class of each anchor,
  score >= ``score_thresh``, top ``nms_pre``, ONE class-agnostic rotated NMS, ``max_out`` boxes;
  the Car ones are returned.
- MMDetection3D (``post = "mmdet3d"``): anchors spread the same way by ``Anchor3DRangeGenerator``
  (``anchor_grid = "linspace"``), the ``nms_pre`` anchors of the best class score, then per
  class: score > ``score_thresh`` and rotated NMS; the ``max_out`` best over all classes; the Car
  ones are returned.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from models import box_coder
from models.anchor_head import AnchorHead, HeadConfig, assign_targets, head_convs, head_outputs
from models.losses import box_regression_loss, direction_loss, sigmoid_focal_loss
from models.nms import nms_in_order, ranked_topk

OPENPCDET_DIR_OFFSET = 0.78539  # pointpillar.yaml / second.yaml DIR_OFFSET (DIR_LIMIT_OFFSET 0.0)
MMDET3D_DIR_OFFSET = -math.pi / 2  # Anchor3DHead's default dir_offset (dir_limit_offset 0)


@dataclass(frozen=True)
class PublishedHeadConfig(HeadConfig):
    """A published head (3 classes on KITTI; MMDetection3D's Car config: 1); ``anchor_size`` /
    ``anchor_z`` of the base are unused (each class has its own), the thresholds and NMS fields are
    the published test config's."""

    rotations: tuple[float, ...] = (0.0, 1.57)  # both references' anchor_rotations
    classes: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")  # the config's class order
    sizes: tuple[tuple[float, float, float], ...] = ((3.9, 1.6, 1.56), (0.8, 0.6, 1.73), (1.76, 0.6, 1.73))  # l, w, h m
    bottoms: tuple[float, ...] = (-1.78, -0.6, -0.6)  # anchor bottom heights, metres (LiDAR frame)
    anchor_grid: str = "arange"  # where the anchors of a row sit along x and y (``axis_positions``)
    dir_offset: float = OPENPCDET_DIR_OFFSET
    post: str = "openpcdet"  # or "mmdet3d": which reference's post-processing
    reported: str = "Car"


# Anchor positions along one axis of n cells over [lo, hi]; the first two spread the anchors from lo to
# hi, ends included (spacing (hi - lo) / (n - 1), not the cell size), and differ only in float32 rounding
# (up to 7.6e-6 m over 70.4 m, which a box inherits).
ANCHOR_GRIDS = {
    # OpenPCDet AnchorGenerator, align_center False
    "arange": lambda lo, hi, n: torch.arange(lo, hi + 1e-5, step=(hi - lo) / (n - 1), dtype=torch.float32)[:n],
    # MMDetection3D Anchor3DRangeGenerator (the anchor range's ends: the KITTI configs' x / y point cloud range)
    "linspace": lambda lo, hi, n: torch.linspace(lo, hi, n, dtype=torch.float32),
    # cell centres: MMDetection3D AlignedAnchor3DRangeGenerator (align_corner False), OpenPCDet align_center True
    "centres": lambda lo, hi, n: _cell_centres(torch.linspace(lo, hi, n + 1, dtype=torch.float32)),
}


def _cell_centres(edges: Tensor) -> Tensor:
    """(n,) centres of the cells between (n + 1,) edges: each left edge plus half the first cell."""
    return edges[:-1] + (edges[1] - edges[0]) / 2


def axis_positions(lo: float, hi: float, n: int, grid: str) -> Tensor:
    """(n,) anchor positions along one axis by the rule ``ANCHOR_GRIDS[grid]``."""
    if grid not in ANCHOR_GRIDS:
        raise ValueError(f"anchor_grid {grid!r}: expected one of {', '.join(ANCHOR_GRIDS)}")
    return ANCHOR_GRIDS[grid](lo, hi, n)


def published_anchors(pc_range, feat_hw: tuple[int, int], cfg: PublishedHeadConfig) -> Tensor:
    """(H * W * S * R, 7) anchors, order (y, x, class set, rotation), centre z = bottom + h / 2."""
    x0, y0, _, x1, y1, _ = pc_range
    h, w = feat_hw
    xs, ys = axis_positions(x0, x1, w, cfg.anchor_grid), axis_positions(y0, y1, h, cfg.anchor_grid)  # (W,), (H,)
    sets = torch.tensor([[b + s[2] / 2, *s] for s, b in zip(cfg.sizes, cfg.bottoms)], dtype=torch.float32)  # (S, 4)
    rots = torch.tensor(cfg.rotations, dtype=torch.float32)  # (R,)
    s, r = sets.shape[0], rots.shape[0]
    shape = (h, w, s, r)
    xx = xs[None, :, None, None].expand(shape)
    yy = ys[:, None, None, None].expand(shape)
    size = sets[None, None, :, None, :].expand(*shape, 4)
    rr = rots[None, None, None, :].expand(shape)
    return torch.cat([xx[..., None], yy[..., None], size, rr[..., None]], dim=-1).reshape(-1, 7)


class MultiClassAnchorHead(AnchorHead):
    """1x1 convs: class logits (A_cell * n), box residuals (A_cell * 7), direction (A_cell * 2)."""

    def __init__(self, c_in: int, feat_hw: tuple[int, int], pc_range, cfg: PublishedHeadConfig):
        nn.Module.__init__(self)
        self.cfg = cfg
        self.dir_offset = cfg.dir_offset
        n, a = len(cfg.classes), len(cfg.classes) * len(cfg.rotations)  # classes, anchors per cell
        self.conv_cls, self.conv_box, self.conv_dir = head_convs(c_in, a, n)
        self.register_buffer("anchors", published_anchors(pc_range, feat_hw, cfg), persistent=False)
        anchor_set = torch.arange(a) // len(cfg.rotations)  # (A_cell,) class set of each anchor of a cell
        self.register_buffer("anchor_set", anchor_set.repeat(feat_hw[0] * feat_hw[1]), persistent=False)  # (A,)
        self.car = cfg.classes.index(cfg.reported)

    def forward(self, feats: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(1, C, H, W) -> class logits (A, n), box residuals (A, 7), direction logits (A, 2)."""
        return head_outputs(feats, (self.conv_cls, self.conv_box, self.conv_dir))

    def detect(self, feats: Tensor) -> tuple[Tensor, Tensor]:
        """Car boxes (M, 7) and scores (M,) after the reference's post-processing."""
        cls, box, dirs = self(feats)
        boxes, scores = self.decode(box, dirs), torch.sigmoid(cls)  # (A, 7), (A, n)
        pick = openpcdet_select if self.cfg.post == "openpcdet" else mmdet3d_select
        boxes, scores, labels = pick(boxes, scores, self.cfg)
        car = torch.nonzero(labels == self.car)[:, 0]
        return boxes[car], scores[car]

    def loss(self, feats: Tensor, gt: Tensor, ignore: Tensor) -> dict[str, Tensor]:
        """Losses for one frame of Car boxes gt (K, 7): the Car anchors are assigned as in
        :class:`AnchorHead`; every other (anchor, class) pair is a negative."""
        cls, box, dirs = self(feats)
        rows = torch.nonzero(self.anchor_set == self.car)[:, 0]  # (A_car,)
        with torch.no_grad():
            labels, matched = assign_targets(self.anchors[rows], gt, ignore, self.cfg)
        pos_rows = rows[labels == 1]  # (P,)
        num_pos = (labels == 1).sum().clamp(min=1).to(cls.dtype)
        targets = torch.zeros_like(cls)
        targets[pos_rows, self.car] = 1.0
        weights = torch.ones_like(cls)
        weights[rows[labels < 0]] = 0.0
        loss_cls = sigmoid_focal_loss(cls, targets, weights) / num_pos
        target_boxes = gt[matched[labels == 1]] if gt.shape[0] else box.new_zeros(0, 7)  # (P, 7)
        loss_box = box_regression_loss(box[pos_rows], box_coder.encode(target_boxes, self.anchors[pos_rows])) / num_pos
        dir_target = box_coder.direction_target(target_boxes[:, 6], self.dir_offset)
        loss_dir = direction_loss(dirs[pos_rows], dir_target) / num_pos
        c = self.cfg
        total = c.weight_cls * loss_cls + c.weight_box * loss_box + c.weight_dir * loss_dir
        return {"loss": total, "loss_cls": loss_cls, "loss_box": loss_box, "loss_dir": loss_dir}


def openpcdet_select(boxes: Tensor, scores: Tensor, cfg: PublishedHeadConfig) -> tuple[Tensor, Tensor, Tensor]:
    """OpenPCDet's class-agnostic post-processing: boxes (A, 7), scores (A, n) -> kept boxes (M, 7),
    best-class scores (M,), labels (M,), best first."""
    best, label = scores.max(dim=1)  # (A,)
    order = ranked_topk(best, cfg.nms_pre)  # (K,) the top ones, then the threshold: the same set
    boxes, best, label = boxes[order], best[order], label[order]
    good = torch.nonzero(best >= cfg.score_thresh)[:, 0]
    boxes, best, label = boxes[good], best[good], label[good]
    keep = nms_in_order(boxes, cfg.nms_iou, cfg.max_out)
    return boxes[keep], best[keep], label[keep]


def mmdet3d_select(boxes: Tensor, scores: Tensor, cfg: PublishedHeadConfig) -> tuple[Tensor, Tensor, Tensor]:
    """MMDetection3D's ``box3d_multiclass_nms`` after its ``nms_pre`` cut: per class, score >
    ``score_thresh`` and rotated NMS; the ``max_out`` best of all classes, best first."""
    order = ranked_topk(scores.max(dim=1).values, cfg.nms_pre)  # (K,)
    boxes, scores = boxes[order], scores[order]
    kept_boxes, kept_scores, kept_labels = [], [], []
    for c in range(scores.shape[1]):
        rank = ranked_topk(scores[:, c], cfg.nms_pre)  # (K,) by this class's score
        rank = rank[scores[rank, c] > cfg.score_thresh]
        keep = rank[nms_in_order(boxes[rank], cfg.nms_iou)]
        kept_boxes.append(boxes[keep])
        kept_scores.append(scores[keep, c])
        kept_labels.append(torch.full_like(keep, c))
    all_scores = torch.cat(kept_scores)
    top = ranked_topk(all_scores, cfg.max_out)
    return torch.cat(kept_boxes)[top], all_scores[top], torch.cat(kept_labels)[top]


def make_head(c_in: int, feat_hw: tuple[int, int], pc_range, cfg: HeadConfig) -> AnchorHead:
    """The head a config asks for: the published multi-class head or the one-class AnchorHead."""
    cls = MultiClassAnchorHead if isinstance(cfg, PublishedHeadConfig) else AnchorHead
    return cls(c_in, feat_hw, pc_range, cfg)
