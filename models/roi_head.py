"""Shared second-stage pieces of the two-stage detectors (Part-A2, PV-RCNN).

- ``sample_rois``: RoI target assignment by rotated 3D IoU with the ground truth and fg/bg
  sampling, RoIs on an ignored box (``on_ignored``) left out (training only, outside any exported graph).
- ``encode_canonical`` / ``decode_canonical``: residuals of a box in its RoI's canonical frame
  (centre at the origin, heading along +x), normalised like the residual box coder.
- ``RefineHead``: shared MLP, then a confidence branch and a residual branch.
- ``refine_loss``: the confidence (binary cross-entropy against a ramp of the RoI IoU, or a
  car / background label), smooth-L1 residuals and the corner loss on foreground RoIs.
- ``propose``: anchor-RPN proposals (decode + ``models.nms.ranked_selection``) that enter stage 2,
  with their classes.
- ``finalize``: refined boxes of every RoI, then score threshold + NMS for the final output.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from harness.core.boxes import iou_3d
from models.anchor_head import AnchorHead
from models.box_frame import inside_boxes, rotate_to_box_frame
from models.iou import ioa_bev_sparse
from models.nms import ranked_selection
from models.pointnet2 import PointBatchNorm


@dataclass(frozen=True)
class RoITargetConfig:
    """Stage-2 targets as OpenPCDet's ProposalTargetLayer (defaults: PV-RCNN's TARGET_CONFIG)."""
    per_frame: int = 64  # RoIs kept per frame for the stage-2 loss (ROI_PER_IMAGE)
    fg_fraction: float = 0.5  # at most this share of them foreground (FG_RATIO)
    fg_iou: float = 0.55  # IoU >= this: foreground, regressed (REG_FG_THRESH)
    easy_bg_iou: float = 0.1  # background below this is easy, above it hard (CLS_BG_THRESH_LO)
    hard_bg_ratio: float = 0.8  # share of the background drawn from the hard one (HARD_BG_RATIO)
    score_type: str = "roi_iou"  # confidence target: "roi_iou" (IoU-guided) or "cls" (CLS_SCORE_TYPE)
    score_lo: float = 0.25  # roi_iou: 0 below, 1 above score_hi, linear between; cls: 0 below,
    score_hi: float = 0.75  # 1 above score_hi, ignored between (CLS_BG_THRESH, CLS_FG_THRESH)
    gt_jitter: int = 0  # jittered copies of every GT box added to the proposals (OpenPCDet: none)
    jitter_xyz: float = 0.3  # metres, std of the centre jitter
    jitter_size: float = 0.1  # relative std of the size jitter
    jitter_yaw: float = 0.15  # radians

    def __post_init__(self):
        if self.score_type not in ("roi_iou", "cls"):
            raise ValueError(f"score_type must be 'roi_iou' or 'cls', got {self.score_type!r}")


# a RoI with at least this share of its BEV area inside an ignored box (Van, Truck, DontCare) is ignored
# by the confidence loss unless it is foreground: by area, as the anchor head (``assign_targets``), since
# a car-sized RoI on a truck's rear has 3D IoU <= 0.1 with the truck and would never reach an IoU threshold
IGNORE_IOA = 0.5


@dataclass
class RoITargets:
    rois: Tensor  # (S, 7) sampled RoIs, LiDAR frame
    iou: Tensor  # (S,) best 3D IoU with a GT box
    gt: Tensor  # (S, 7) the matched GT box (meaningful where iou >= fg_iou)
    weight: Tensor  # (S,) of the confidence loss: 1, or 0 for a RoI on an ignored box (``on_ignored``)

    def to(self, device) -> "RoITargets":
        return RoITargets(self.rois.to(device), self.iou.to(device), self.gt.to(device), self.weight.to(device))


def jitter_boxes(gt: np.ndarray, copies: int, cfg: RoITargetConfig,
                 rng: np.random.Generator) -> np.ndarray:
    """(G, 7) -> (G * copies, 7) randomly perturbed copies (centre, size, heading)."""
    boxes = np.repeat(gt.astype(np.float64), copies, axis=0)
    boxes[:, 0:3] += rng.normal(0.0, cfg.jitter_xyz, (len(boxes), 3))
    boxes[:, 3:6] *= np.exp(rng.normal(0.0, cfg.jitter_size, (len(boxes), 3)))
    boxes[:, 6] += rng.normal(0.0, cfg.jitter_yaw, len(boxes))
    return boxes.astype(np.float32)


def on_ignored(rois: np.ndarray, ignore: np.ndarray) -> np.ndarray:
    """(K,) bool: at least ``IGNORE_IOA`` of the RoI's (K, 7) BEV area lies inside one ignored box (J, 7)."""
    if not (len(rois) and len(ignore)):
        return np.zeros(len(rois), bool)
    ioa = ioa_bev_sparse(torch.from_numpy(rois.astype(np.float32)), torch.from_numpy(ignore.astype(np.float32)))
    return (ioa.max(dim=1).values >= IGNORE_IOA).numpy()  # (K,)


def sample_rois(rois: np.ndarray, gt: np.ndarray, cfg: RoITargetConfig,
                rng: np.random.Generator, ignore: np.ndarray | None = None) -> RoITargets:
    """Label proposals by IoU with the GT and draw ``cfg.per_frame`` of them, as OpenPCDet's
    ``ProposalTargetLayer.subsample_rois``.

    rois (K, 7), gt (G, 7) Car boxes, ignore (J, 7) ignored boxes (Van, Truck, DontCare), LiDAR frame.
    Foreground: IoU >= min(fg_iou, score_hi), at most ``fg_fraction`` of the draw, without replacement.
    A RoI on an ignored box (:func:`on_ignored`) that is not foreground is neither foreground nor
    background: it is not drawn. The rest is background (IoU < fg_iou):
    ``hard_bg_ratio`` of it from the hard one (IoU in [easy_bg_iou, fg_iou)), which teaches the
    confidence the IoUs between a miss and a hit, and the remainder from the easy one; both
    drawn with replacement, and from one alone when the other is empty. Without any
    background, the draw is foreground with replacement; with neither, the ignored RoIs with
    replacement, at confidence weight 0 (stage 2 still sees ``per_frame`` RoIs).
    """
    rois = np.concatenate([rois.reshape(-1, 7), jitter_boxes(gt, cfg.gt_jitter, cfg, rng)])
    if len(gt):
        overlaps = iou_3d(rois, gt)  # (K', G)
        best = overlaps.argmax(1)
        iou = overlaps[np.arange(len(rois)), best]
        matched = gt[best]
    else:
        iou = np.zeros(len(rois))
        matched = np.zeros((len(rois), 7), np.float32)
    is_fg = iou >= min(cfg.fg_iou, cfg.score_hi)
    ignored = on_ignored(rois, np.zeros((0, 7)) if ignore is None else ignore) & ~is_fg  # (K',)
    fg = np.flatnonzero(is_fg)
    easy = np.flatnonzero((iou < cfg.easy_bg_iou) & ~ignored)
    hard = np.flatnonzero((iou >= cfg.easy_bg_iou) & (iou < cfg.fg_iou) & ~ignored)
    if len(easy) + len(hard) == 0:  # nothing but foreground or ignored RoIs (or no RoI at all)
        pool = fg if len(fg) else np.flatnonzero(ignored)
        keep = pool[rng.integers(0, len(pool), cfg.per_frame)] if len(pool) else pool
    else:
        n_fg = min(int(round(cfg.per_frame * cfg.fg_fraction)), len(fg))
        n_bg = cfg.per_frame - n_fg
        if not len(hard):
            n_hard = 0
        elif not len(easy):
            n_hard = n_bg
        else:
            n_hard = min(int(n_bg * cfg.hard_bg_ratio), len(hard))
        keep = np.concatenate([rng.permutation(fg)[:n_fg], hard[rng.integers(0, max(len(hard), 1), n_hard)],
                               easy[rng.integers(0, max(len(easy), 1), n_bg - n_hard)]])
    keep = keep.astype(np.int64)
    return RoITargets(rois=torch.from_numpy(rois[keep].astype(np.float32)),
                      iou=torch.from_numpy(iou[keep].astype(np.float32)),
                      gt=torch.from_numpy(matched[keep].astype(np.float32)),
                      weight=torch.from_numpy((~ignored[keep]).astype(np.float32)))


def wrap(angle: Tensor) -> Tensor:
    """Angles to [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def encode_canonical(gt: Tensor, rois: Tensor) -> Tensor:
    """Residuals of gt (S, 7) in the canonical frame of rois (S, 7) -> (S, 7).

    (dx, dy) / RoI BEV diagonal, dz / RoI height, log size ratios, heading difference. The GT
    heading is flipped by pi when it points against the RoI, so the heading residual lies in
    [-pi/2, pi/2] (a box is the same box either way).
    """
    d = rotate_to_box_frame((gt[:, 0:3] - rois[:, 0:3])[:, None], rois)[:, 0]  # (S, 3) metres
    lx, ly = d[:, 0], d[:, 1]
    diag = torch.sqrt(rois[:, 3] ** 2 + rois[:, 4] ** 2)
    dyaw = wrap(gt[:, 6] - rois[:, 6])
    dyaw = torch.where(dyaw.abs() > math.pi / 2, wrap(dyaw + math.pi), dyaw)
    size = torch.log(gt[:, 3:6] / rois[:, 3:6])  # (S, 3)
    return torch.stack([lx / diag, ly / diag, d[:, 2] / rois[:, 5], size[:, 0], size[:, 1],
                        size[:, 2], dyaw], 1)


def decode_canonical(deltas: Tensor, rois: Tensor, max_log_size: float | None = 4.0) -> Tensor:
    """Inverse of encode_canonical: deltas (S, 7), rois (S, 7) -> boxes (S, 7), LiDAR frame.
    The log size ratios are capped at ``max_log_size`` (None: not capped, as OpenPCDet's decoder)."""
    diag = torch.sqrt(rois[:, 3] ** 2 + rois[:, 4] ** 2)
    lx, ly = deltas[:, 0] * diag, deltas[:, 1] * diag
    c, s = torch.cos(rois[:, 6]), torch.sin(rois[:, 6])
    x = rois[:, 0] + lx * c - ly * s
    y = rois[:, 1] + lx * s + ly * c
    z = rois[:, 2] + deltas[:, 2] * rois[:, 5]
    log_size = deltas[:, 3:6] if max_log_size is None else deltas[:, 3:6].clamp(max=max_log_size)
    size = rois[:, 3:6] * torch.exp(log_size)  # (S, 3)
    yaw = wrap(rois[:, 6] + deltas[:, 6])
    return torch.cat([torch.stack([x, y, z], 1), size, yaw[:, None]], 1)


def box_corners(boxes: Tensor) -> Tensor:
    """(S, 7) -> (S, 8, 3) corners (same order as harness.core.boxes.corners_3d)."""
    unit = boxes.new_tensor([[0.5, 0.5, -0.5], [-0.5, 0.5, -0.5], [-0.5, -0.5, -0.5],
                             [0.5, -0.5, -0.5], [0.5, 0.5, 0.5], [-0.5, 0.5, 0.5],
                             [-0.5, -0.5, 0.5], [0.5, -0.5, 0.5]])  # (8, 3)
    local = unit[None] * boxes[:, None, 3:6]  # (S, 8, 3)
    c, s = torch.cos(boxes[:, 6])[:, None], torch.sin(boxes[:, 6])[:, None]
    x = local[..., 0] * c - local[..., 1] * s
    y = local[..., 0] * s + local[..., 1] * c
    return torch.stack([x, y, local[..., 2]], -1) + boxes[:, None, 0:3]


def corner_loss(pred: Tensor, gt: Tensor, delta: float = 1.0) -> Tensor:
    """Huber loss of corner distances, the smaller of gt and gt flipped by pi. -> (S,)."""
    flipped = torch.cat([gt[:, :6], (gt[:, 6:] + math.pi)], 1)
    pc = box_corners(pred)
    dist = torch.minimum((pc - box_corners(gt)).norm(dim=2), (pc - box_corners(flipped)).norm(dim=2))
    return F.huber_loss(dist, torch.zeros_like(dist), delta=delta, reduction="none").mean(1)


def _fc_stack(c_in: int, widths: Sequence[int], dropout: float) -> tuple[nn.Sequential, int]:
    """Linear-BN-ReLU layers (dropout after the first), as OpenPCDet's make_fc_layers."""
    layers: list[nn.Module] = []
    for i, c_out in enumerate(widths):
        layers += [nn.Linear(c_in, c_out, bias=False), PointBatchNorm(c_out), nn.ReLU()]
        if i == 0 and dropout > 0:
            layers.append(nn.Dropout(dropout))
        c_in = c_out
    return nn.Sequential(*layers), c_in


class RefineHead(nn.Module):
    """Shared FC layers on pooled RoI features, then a confidence branch and a residual branch
    (SHARED_FC, CLS_FC and REG_FC of OpenPCDet's RoI heads).

    forward(x (K, C)) -> (logit (K,), deltas (K, 7)), float32 also under autocast (the losses and decoding read them).
    """

    def __init__(self, in_channels: int, hidden: Sequence[int], branch: Sequence[int] = (),
                 dropout: float = 0.3):
        super().__init__()
        layers: list[nn.Module] = []
        for c_in, c_out in zip([in_channels, *hidden[:-1]], hidden):
            layers += [nn.Linear(c_in, c_out, bias=False), PointBatchNorm(c_out), nn.ReLU(),
                       nn.Dropout(dropout)]
        self.shared = nn.Sequential(*layers)
        width = hidden[-1] if hidden else in_channels  # without shared layers the branches take x
        self.cls_fc, c_cls = _fc_stack(width, branch, dropout)
        self.reg_fc, c_reg = _fc_stack(width, branch, dropout)
        self.cls = nn.Linear(c_cls, 1)
        self.reg = nn.Linear(c_reg, 7)
        nn.init.normal_(self.reg.weight, std=0.001)
        nn.init.zeros_(self.reg.bias)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        h = self.shared(x)  # (K, hidden[-1] or C)
        return self.cls(self.cls_fc(h)).squeeze(1).float(), self.reg(self.reg_fc(h)).float()


def iou_score_target(iou: Tensor, cfg: RoITargetConfig) -> Tensor:
    """Linear ramp of the RoI IoU: 0 at score_lo, 1 at score_hi. (S,) -> (S,)."""
    return ((iou - cfg.score_lo) / (cfg.score_hi - cfg.score_lo)).clamp(0.0, 1.0)


def score_loss(logit: Tensor, iou: Tensor, cfg: RoITargetConfig, weight: Tensor | None = None) -> Tensor:
    """Binary cross-entropy of the confidence logits (S,) against the RoIs' IoU (S,): the
    IoU-guided ramp (``roi_iou``), or car (IoU > score_hi) / background (IoU < score_lo) with
    the RoIs between ignored (``cls``); the mean over the RoIs that count. ``weight`` (S,) 0 / 1
    (:class:`RoITargets`; None: all 1) leaves the RoIs on an ignored box out."""
    weight = torch.ones_like(logit) if weight is None else weight
    if cfg.score_type == "roi_iou":
        target = iou_score_target(iou, cfg)
    else:
        target = (iou > cfg.score_hi).to(logit.dtype)
        weight = weight * ((iou > cfg.score_hi) | (iou < cfg.score_lo)).to(logit.dtype)
    loss = F.binary_cross_entropy_with_logits(logit, target, reduction="none")  # (S,)
    return (loss * weight).sum() / weight.sum().clamp(min=1)


def refine_loss(logit: Tensor, deltas: Tensor, targets: RoITargets,
                cfg: RoITargetConfig) -> dict[str, Tensor]:
    """Stage-2 losses on S sampled RoIs: logit (S,), deltas (S, 7)."""
    score = score_loss(logit, targets.iou, cfg, targets.weight)
    fg = targets.iou >= cfg.fg_iou  # (S,)
    if bool(fg.any()):
        rois, gt = targets.rois[fg], targets.gt[fg]
        reg = F.smooth_l1_loss(deltas[fg], encode_canonical(gt, rois), beta=1.0 / 9.0,
                               reduction="none").sum(1).mean()
        corner = corner_loss(decode_canonical(deltas[fg], rois), gt).mean()
    else:
        reg = corner = deltas.sum() * 0.0
    return {"rcnn_score": score, "rcnn_reg": reg, "rcnn_corner": corner}


@dataclass(frozen=True)
class ProposalConfig:
    nms_pre: int = 256  # top anchors by RPN score that enter the proposal NMS
    nms_iou: float = 0.7  # rotated BEV IoU of the proposal NMS
    rois: int = 32  # proposals kept (stage-2 inputs)


def propose(head: AnchorHead, feats: Tensor, cfg: ProposalConfig) -> tuple[Tensor, Tensor, Tensor]:
    """Stage-1 proposals from an anchor head: feats (1, C, H, W) -> rois (K, 7), scores (K,), labels (K,)
    int64. A multi-class head's anchor is scored by its best class, whose index is its label, and one
    class-agnostic NMS selects (OpenPCDet's proposal_layer); a one-class head's labels are 0."""
    cls, box, dirs = head(feats)  # (A,) or (A, n) logits
    boxes = head.decode(box, dirs)  # (A, 7)
    scores = torch.sigmoid(cls)
    if scores.dim() == 2:
        scores, labels = scores.max(dim=1)  # (A,), (A,)
    else:
        labels = torch.zeros_like(scores, dtype=torch.long)
    kept = ranked_selection(boxes, scores, -1.0, cfg.nms_pre, cfg.nms_iou, cfg.rois)  # (K,)
    return boxes[kept], scores[kept], labels[kept]


SCORE_RULES = ("rcnn", "geometric")


@dataclass(frozen=True)
class OutputConfig:
    score_thresh: float = 0.1  # on the final score
    nms_iou: float = 0.1  # rotated BEV IoU of the final NMS
    max_out: int = 100
    nms_pre: int = 512  # at least the number of RoIs: every refined box may enter the NMS
    # the final score: "rcnn", the stage-2 confidence alone (OpenPCDet, MMDetection3D), or
    # "geometric", sqrt(stage-1 RoI score * stage-2 confidence) (CenterPoint's two-stage rule):
    # a short schedule leaves the IoU-guided confidence noisy, and the RPN score vetoes its outliers
    score: str = "geometric"
    max_log_size: float | None = 4.0  # cap of the refined boxes' log size ratios (None: OpenPCDet's uncapped)
    drop_empty: bool = True  # a RoI with no LiDAR data inside gives no box (``roi_support``; OpenPCDet keeps it)

    def __post_init__(self):
        if self.score not in SCORE_RULES:
            raise ValueError(f"score must be one of {', '.join(SCORE_RULES)}, got {self.score!r}")


def roi_support(xyz: Tensor, rois: Tensor) -> Tensor:
    """(K,) bool: at least one of the points / voxel centres xyz (N, 3) lies inside the RoI (K, 7)."""
    # a count, not .any(): ONNX ReduceMax over an empty axis is not False in onnxruntime
    return inside_boxes(xyz, rois).to(torch.int32).sum(dim=1) > 0


def final_scores(roi_scores: Tensor, logit: Tensor, rule: str) -> Tensor:
    """The final score of every refined box (K,) from the RoI scores (K,) and the stage-2
    confidence logits (K,), by ``OutputConfig.score``."""
    confidence = torch.sigmoid(logit)
    if rule == "rcnn":
        return confidence
    return torch.sqrt(roi_scores.clamp(min=0.0) * confidence)


def finalize(rois: Tensor, roi_scores: Tensor, logit: Tensor, deltas: Tensor, cfg: OutputConfig,
             support: Tensor | None = None, roi_labels: Tensor | None = None,
             reported: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """rois (K, 7), roi_scores (K,), logit (K,), deltas (K, 7) -> boxes (M, 7), scores (M,),
    rcnn_boxes (K, 7).

    ``support`` (K,) bool (``roi_support``): a RoI with no LiDAR data inside pooled nothing, so its
    score is only the head's bias; such RoIs give no box (else an empty cloud gives boxes) when
    ``cfg.drop_empty``. ``roi_labels`` (K,): the RoIs' classes (``propose``); the NMS is class-agnostic
    and only the boxes of RoIs labelled ``reported`` are returned (OpenPCDet's labels of RCNN boxes)."""
    rcnn_boxes = decode_canonical(deltas, rois, cfg.max_log_size)  # (K, 7)
    scores = final_scores(roi_scores, logit, cfg.score)
    if support is not None and cfg.drop_empty:
        scores = scores * support.to(scores.dtype)
    kept = ranked_selection(rcnn_boxes, scores, cfg.score_thresh, cfg.nms_pre, cfg.nms_iou, cfg.max_out)
    if roi_labels is not None:
        kept = kept[roi_labels[kept] == reported]
    return rcnn_boxes[kept], scores[kept], rcnn_boxes
