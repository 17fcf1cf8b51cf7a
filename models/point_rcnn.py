"""PointRCNN (Shi et al., CVPR 2019): point-based two-stage detector on raw points.

    points (N, 4) --range filter, thinning to num_points--> P0 (n0, 3) + intensity
      --PointNet++ (MSG set abstraction x4, feature propagation x4)--> per-point features
      --seg head--> foreground logit per point   --bin head--> one box proposal per point
      --top-k by foreground score + BEV NMS--> rois (K, 7), roi_scores (K,)
      --point RoI pooling, canonical transform--> (K, S, 3 + 2 + C)
      --RoI PointNet++ (set abstraction x3)--> (K, C') --refine head--> car score, residual
      --decode--> rcnn_boxes (K, 7) --score threshold + BEV NMS--> boxes, scores

Stage-1 boxes use PointRCNN's bin-based coding: x and y offsets from the point as a bin in
[-loc_scope, loc_scope) plus a normalised in-bin residual, z as a plain offset, heading as a
bin of 2*pi / heading_bins plus residual, size as a residual to the mean car size.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F

from harness.core.types import Sample
from models.base import Detector, mean_over_frames
from models.box_frame import inside_boxes
from models.nms import nms_in_order, ranked_topk, select_ranked
from models.point_roi_pool import RoISetAbstraction, roi_point_pool
from models.pointnet2 import FeaturePropagation, SetAbstraction, farthest_point_sample, shared_mlp
from models.recipe import Recipe
from models.roi_head import (
    RefineHead,
    RoITargetConfig,
    decode_canonical,
    refine_loss,
    sample_rois,
)
from models.single_stage import frame_targets
from models.voxelize import range_mask


# pointrcnn.yaml's TARGET_CONFIG: a car / background confidence (CLS_SCORE_TYPE cls)
CLS_TARGETS = RoITargetConfig(per_frame=64, fg_iou=0.55, score_type="cls", score_lo=0.45, score_hi=0.6)


@dataclass(frozen=True)
class PointRCNNConfig:
    pc_range: tuple[float, ...] = (0.0, -32.0, -3.0, 80.0, 32.0, 2.0)  # x0 y0 z0 x1 y1 z1, m
    # in-range points sampled to this count for every later stage (OpenPCDet: 16,384). 8,192 keeps
    # a car at 21 m about 41 of its 333 points (4,096: 14) for twice the training step of 4,096
    # (16,384: 3.5x); README "compact profiles"
    num_points: int = 8192
    far_depth: float = 40.0  # m: points this far are all kept by the sampling (OpenPCDet)
    sa_npoints: tuple[int, ...] = (512, 128, 32, 8)
    sa_radii: tuple[tuple[float, ...], ...] = ((0.5, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, 8.0))
    sa_nsamples: tuple[tuple[int, ...], ...] = ((16, 32), (16, 32), (16, 32), (16, 32))
    sa_mlps: tuple = (((16, 16, 32), (16, 16, 32)), ((32, 32, 64), (32, 32, 64)),
                      ((64, 64, 128), (64, 64, 128)), ((128, 128, 128), (128, 128, 128)))
    fp_mlps: tuple[tuple[int, ...], ...] = ((64, 64), (128, 128), (128, 128), (128, 128))  # finest first
    head_channels: int = 64  # hidden width of the segmentation and box heads
    # the last feature propagation also reads each point's own coordinates (scaled over pc_range), beside its
    # intensity: set abstraction sees only offsets from its centres, so without them a point's feature
    # holds its height only through the neighbourhood, and the proposals' z (point z + offset)
    # scattered 0.13 m (sd; anchor models 0.01 m). The references' last propagation reads intensity only.
    skip_xyz: bool = True
    loc_scope: float = 3.0  # m, x/y bins cover [-scope, scope) around each point
    loc_bin_size: float = 0.5  # m
    heading_bins: int = 12
    mean_size: tuple[float, float, float] = (4.5, 1.8, 1.6)  # l, w, h of a car, m
    # top-scoring points decoded before the proposal NMS (OpenPCDet: 9,000 of 16,384). A near car
    # holds hundreds of points that all score high, so 256 went to a few cars: 17 % of the val cars
    # within 45 m got no proposal, and the second stage trained on RoIs of those few cars and
    # ranked boxes badly (val AP40 3D moderate 29.9, where the same boxes ranked by their own 3D
    # IoU give 65.0). 1,024: val 67.8 in the same 12 epochs (docs/results.md)
    pre_nms: int = 1024
    rois: int = 64  # proposals kept after NMS (stage-2 inputs)
    proposal_nms_iou: float = 0.8  # BEV IoU
    pool_samples: int = 128  # points pooled per RoI
    pool_extra_width: float = 1.0  # m added to l, w, h of a RoI for pooling
    rcnn_sa: tuple = ((32, 0.5, 16, (64, 64)), (8, 1.0, 16, (64, 128)), (None, 0.0, 0, (128, 128)))
    refine_hidden: tuple[int, ...] = (128, 128)  # FC layers of the confidence and the residual branch each
    targets: RoITargetConfig = CLS_TARGETS
    score_thresh: float = 0.1
    nms_iou: float = 0.1  # BEV IoU of the final NMS
    max_detections: int = 50
    seg_ignore_margin: float = 0.4  # m: points this close outside a car box are not negatives
    seed: int = 0  # RoI sampling during training


CONFIGS = {
    "tiny": PointRCNNConfig(
        num_points=256, sa_npoints=(64, 16), sa_radii=((2.0,), (6.0,)), sa_nsamples=((16,), (16,)),
        sa_mlps=(((8, 16),), ((16, 32),)), fp_mlps=((16, 16), (32, 32)), head_channels=16,
        pre_nms=64, rois=16, pool_samples=16, rcnn_sa=((8, 0.5, 8, (16, 16)), (None, 0.0, 0, (16, 32))),
        refine_hidden=(32,), max_detections=20,
        targets=replace(CLS_TARGETS, per_frame=16),
    ),
    # far_depth 20 m: our 180-degree scan holds ~51,000 points in range, ~400 of them beyond 40 m and
    # ~4,200 (at most 7,800) beyond 20 m, so at 40 m a car at 30-40 m kept 10 of its 70 points; at 20 m it
    # keeps all (KITTI's camera-view crop leaves ~20,000 points, so OpenPCDet's 16,384 keep most at 40 m)
    "compact": PointRCNNConfig(far_depth=20.0),
    "kitti": PointRCNNConfig(
        pc_range=(0.0, -40.0, -3.0, 70.4, 40.0, 1.0), num_points=16384,
        sa_npoints=(4096, 1024, 256, 64), sa_radii=((0.1, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 4.0)),
        sa_mlps=(((16, 16, 32), (32, 32, 64)), ((64, 64, 128), (64, 96, 128)),
                 ((128, 196, 256), (128, 196, 256)), ((256, 256, 512), (256, 384, 512))),
        fp_mlps=((128, 128), (256, 256), (512, 512), (512, 512)), head_channels=256,
        mean_size=(3.9, 1.6, 1.56), skip_xyz=False, pre_nms=9000, rois=100, proposal_nms_iou=0.85,
        pool_samples=512, rcnn_sa=((128, 0.2, 16, (128, 128, 128)), (32, 0.4, 16, (128, 128, 256)),
                                    (None, 0.0, 0, (256, 256, 512))),
        refine_hidden=(256, 256),
        targets=replace(CLS_TARGETS, per_frame=128),
    ),
}
# compact: 4 epochs over the default run's 1,530 training frames, the steps of 24 over 255 (it took 20 there;
# 3.33 rounded up, since its val AP was still rising: at its 1,024 decoded points, seeds 0 / 1, 67.8 / 46.9
# after 12 and 72.8 / 71.4 after 20); kitti: pointrcnn.yaml's OPTIMIZATION.LR
RECIPE = Recipe(epochs={"compact": 4}, lr={"kitti": 0.01})


# ---- point sampling -------------------------------------------------------------------------

_HASH_MOD = 2 ** 20  # hash_rank's range: distinct ranks for up to 1,048,576 points
_HASH_HI, _HASH_LO = 632, 887  # multiplier 632 * 2**10 + 887 = 648,055: odd, about 2**20 / golden ratio


def hash_rank(n: int, salt: int, device=None) -> Tensor:
    """(n,) int64 Fibonacci hash of the indices 0..n-1: ((i + salt) * 648,055) mod 2**20.

    The multiplier is odd, so indices below 2**20 get distinct ranks, and close to 2**20 over
    the golden ratio, so the indices with the lowest ranks spread evenly over any index range
    (a pseudo-random subset of a LiDAR scan, whose order runs along its rings). Index and
    multiplier are split into 10-bit halves so that every intermediate stays below 2**24:
    OpenVINO computes int64 in int32, and its integer products and remainders above 2**24 came out
    a few units off.
    """
    i = torch.remainder(torch.arange(n, device=device) + salt, _HASH_MOD)  # (n,) < 2**20
    i_hi, i_lo = torch.div(i, 2 ** 10, rounding_mode="floor"), torch.remainder(i, 2 ** 10)  # (n,) < 2**10 each
    cross = torch.remainder(_HASH_HI * i_lo + _HASH_LO * i_hi, 2 ** 10) * 2 ** 10  # (n,) < 2**20
    return torch.remainder(_HASH_LO * i_lo + cross, _HASH_MOD)  # the HI * hi term is a multiple of 2**20


# ---- bin-based box coding ------------------------------------------------------------------


def _bin_counts(cfg: PointRCNNConfig) -> tuple[int, int]:
    return round(2 * cfg.loc_scope / cfg.loc_bin_size), cfg.heading_bins


def bin_channels(cfg: PointRCNNConfig) -> int:
    """x bins + y bins + x res + y res + z + heading bins + heading res + 3 sizes."""
    loc, head = _bin_counts(cfg)
    return 4 * loc + 1 + 2 * head + 3


def encode_bins(boxes: Tensor, xyz: Tensor, cfg: PointRCNNConfig) -> tuple[Tensor, Tensor]:
    """Targets of boxes (P, 7) for points xyz (P, 3) -> bins (P, 3) long (x, y, heading) and
    residuals (P, 7) (x, y normalised by the bin size, z m, heading / half bin, 3 size)."""
    loc, head = _bin_counts(cfg)
    shift = (boxes[:, :2] - xyz[:, :2] + cfg.loc_scope).clamp(0, 2 * cfg.loc_scope - 1e-3)  # (P, 2) m
    loc_bin = torch.floor(shift / cfg.loc_bin_size).long()  # (P, 2)
    loc_res = (shift - (loc_bin + 0.5) * cfg.loc_bin_size) / cfg.loc_bin_size  # (P, 2) in [-0.5, 0.5)
    per = 2 * math.pi / head
    angle = torch.remainder(boxes[:, 6] + per / 2, 2 * math.pi)  # (P,) rad, bin 0 centred on 0
    head_bin = torch.floor(angle / per).long().clamp(max=head - 1)
    head_res = (angle - (head_bin + 0.5) * per) / (per / 2)  # (P,) in [-1, 1)
    mean = boxes.new_tensor(cfg.mean_size)
    size_res = (boxes[:, 3:6] - mean) / mean  # (P, 3)
    bins = torch.cat([loc_bin, head_bin[:, None]], 1)
    res = torch.cat([loc_res, (boxes[:, 2] - xyz[:, 2])[:, None], head_res[:, None], size_res], 1)
    return bins, res


def _split(pred: Tensor, cfg: PointRCNNConfig) -> list[Tensor]:
    loc, head = _bin_counts(cfg)
    return list(torch.split(pred, [loc, loc, loc, loc, 1, head, head, 3], dim=1))


def _at(values: Tensor, index: Tensor) -> Tensor:
    """values (P, B), index (P,) -> (P,)."""
    return torch.gather(values, 1, index[:, None])[:, 0]


def decode_bins(pred: Tensor, xyz: Tensor, cfg: PointRCNNConfig) -> Tensor:
    """Box head output (P, bin_channels) at points xyz (P, 3) -> boxes (P, 7), LiDAR frame."""
    xb, yb, xr, yr, z, hb, hr, size = _split(pred, cfg)
    x_bin, y_bin, h_bin = xb.argmax(1), yb.argmax(1), hb.argmax(1)  # (P,)
    x = (x_bin.float() + 0.5 + _at(xr, x_bin)) * cfg.loc_bin_size - cfg.loc_scope + xyz[:, 0]
    y = (y_bin.float() + 0.5 + _at(yr, y_bin)) * cfg.loc_bin_size - cfg.loc_scope + xyz[:, 1]
    per = 2 * math.pi / cfg.heading_bins
    yaw = (h_bin.float() + 0.5) * per + _at(hr, h_bin) * per / 2 - per / 2
    yaw = torch.remainder(yaw + math.pi, 2 * math.pi) - math.pi
    mean = pred.new_tensor(cfg.mean_size)
    lwh = (size * mean + mean).clamp(min=0.1)  # (P, 3) m
    return torch.cat([torch.stack([x, y, z[:, 0] + xyz[:, 2]], 1), lwh, yaw[:, None]], 1)


def bin_loss(pred: Tensor, bins: Tensor, res: Tensor, cfg: PointRCNNConfig) -> Tensor:
    """Bin classification (cross-entropy) + residual (smooth-L1) loss of foreground points."""
    xb, yb, xr, yr, z, hb, hr, size = _split(pred, cfg)
    cls = F.cross_entropy(xb, bins[:, 0]) + F.cross_entropy(yb, bins[:, 1]) + F.cross_entropy(hb, bins[:, 2])
    reg_pred = torch.stack([_at(xr, bins[:, 0]), _at(yr, bins[:, 1]), z[:, 0], _at(hr, bins[:, 2])], 1)
    reg = F.smooth_l1_loss(torch.cat([reg_pred, size], 1), res, beta=1.0 / 9.0, reduction="sum") / len(res)
    return cls + reg


# ---- network ---------------------------------------------------------------------------------


class PointNet2Backbone(nn.Module):
    """MSG set abstraction down to sa_npoints[-1] centres, feature propagation back to P0."""

    def __init__(self, cfg: PointRCNNConfig):
        super().__init__()
        self.npoints = cfg.sa_npoints
        self.sa = nn.ModuleList()
        channels = [1]  # intensity on P0
        for radii, nsamples, mlps in zip(cfg.sa_radii, cfg.sa_nsamples, cfg.sa_mlps):
            self.sa.append(SetAbstraction(channels[-1], radii, nsamples, mlps))
            channels.append(self.sa[-1].out_channels)
        self.skip_xyz = cfg.skip_xyz
        self.range_lo, self.range_span = cfg.pc_range[:3], tuple(b - a for a, b in zip(cfg.pc_range[:3], cfg.pc_range[3:]))
        skip = [channels[0] + 3 * cfg.skip_xyz, *channels[1:]]  # skip features of each level
        self.fp = nn.ModuleList()
        for level in reversed(range(len(cfg.fp_mlps))):  # coarsest first
            coarse = channels[-1] if level == len(cfg.fp_mlps) - 1 else cfg.fp_mlps[level + 1][-1]
            self.fp.append(FeaturePropagation([coarse + skip[level], *cfg.fp_mlps[level]]))
        self.out_channels = cfg.fp_mlps[0][-1]

    def forward(self, xyz: Tensor, feats: Tensor) -> Tensor:
        """xyz (n0, 3) m, feats (n0, 1) -> (n0, out_channels)."""
        xyzs, featss = [xyz], [feats]
        for npoint, sa in zip(self.npoints, self.sa):
            centres = xyzs[-1][farthest_point_sample(xyzs[-1], npoint)]  # (M, 3)
            featss.append(sa(xyzs[-1], featss[-1], centres))  # (M, C)
            xyzs.append(centres)
        if self.skip_xyz:  # the points' coordinates scaled to [0, 1] over the range: read by the last propagation only
            featss[0] = torch.cat([(xyz - xyz.new_tensor(self.range_lo)) / xyz.new_tensor(self.range_span), feats], 1)
        up = featss[-1]
        for i, fp in enumerate(self.fp):
            level = len(self.fp) - 1 - i
            up = fp(xyzs[level], xyzs[level + 1], featss[level], up)  # (n_level, C)
        return up


def mlp_head(cin: int, hidden: int, cout: int) -> nn.Sequential:
    return nn.Sequential(shared_mlp([cin, hidden]), nn.Linear(hidden, cout))


class RCNNNet(nn.Module):
    """Stage 2: canonical pooled points -> RoI PointNet++ -> confidence logit and residuals."""

    def __init__(self, cfg: PointRCNNConfig, point_channels: int):
        super().__init__()
        self.xyz_up = shared_mlp([5, point_channels, point_channels])  # xyz, seg score, depth
        self.merge = shared_mlp([2 * point_channels, point_channels])
        self.sa = nn.ModuleList()
        cin = point_channels
        for npoint, radius, nsample, mlp in cfg.rcnn_sa:
            self.sa.append(RoISetAbstraction(npoint, radius, nsample, (cin, *mlp)))
            cin = mlp[-1]
        self.head = RefineHead(cin, (), cfg.refine_hidden, dropout=0.0)  # CLS_FC / REG_FC, DP_RATIO 0

    def forward(self, pooled: Tensor, empty: Tensor) -> tuple[Tensor, Tensor]:
        """pooled (K, S, 5 + C) -> logit (K,), canonical residuals (K, 7)."""
        xyz = pooled[..., :3]  # (K, S, 3) canonical, m
        feats = self.merge(torch.cat([self.xyz_up(pooled[..., :5]), pooled[..., 5:]], -1))
        for sa in self.sa:
            xyz, feats = sa(xyz, feats)
        logit, deltas = self.head(feats[:, 0])  # group-all leaves one centre per RoI
        return logit.masked_fill(empty, -10.0), deltas


class PointRCNN(Detector):
    architecture = "point_rcnn"
    two_stage = True
    uses_camera = False

    def __init__(self, cfg: PointRCNNConfig):
        super().__init__()
        self.cfg = cfg
        self.backbone = PointNet2Backbone(cfg)
        c = self.backbone.out_channels
        self.seg_head = mlp_head(c, cfg.head_channels, 1)
        nn.init.constant_(self.seg_head[-1].bias, -math.log(99.0))  # foreground prior 0.01
        self.box_head = mlp_head(c, cfg.head_channels, bin_channels(cfg))
        self.rcnn = RCNNNet(cfg, c)
        self.sampling_rng = np.random.default_rng(cfg.seed)

    def points_of_interest(self, points: Tensor, salt: int = 0) -> tuple[Tensor, Tensor]:
        """(N, 4) -> (num_points, 4) the in-range points sampled to num_points, and a bool
        scalar tensor: some point is in range.

        OpenPCDet's PointRCNN sampling (``sample_points``), deterministic: every point at least
        ``far_depth`` from the sensor is kept and a pseudo-random subset of the nearer ones fills
        the rest, so a near car keeps the same share of its points as the near scan; when the far
        points alone fill the budget, a pseudo-random subset of all in-range points. The
        pseudo-random order is a fixed hash of the point index (:func:`hash_rank`; ``salt``
        shifts it, for fresh draws in training), so torch and every ONNX runtime pick the same
        points. Fewer in-range points than num_points: all of them, then repeats in the same
        order (repeats never win a later farthest point sampling step); none: zero rows.
        """
        total = self.cfg.num_points
        pts = torch.cat([points, points.new_zeros(1, 4)])  # (N + 1, 4): a zero row, read only when nothing is in range
        inside = torch.cat([range_mask(points, self.cfg.pc_range), torch.zeros(1, dtype=torch.bool, device=points.device)])  # (N + 1,)
        depth2 = pts[:, 0] ** 2 + pts[:, 1] ** 2 + pts[:, 2] ** 2  # (N + 1,) m^2
        far = inside & (depth2 >= self.cfg.far_depth ** 2)
        n_in, n_far = inside.sum(), far.sum()  # () int64
        # sort key: the kept far points, then the rest in range in pseudo-random order, then the others
        rank = hash_rank(pts.shape[0], salt, points.device).to(torch.float32)  # (N + 1,) exact below 2**24
        tier = torch.where(inside, 1.0, 2.0) - (far & (n_far < total)).to(torch.float32)  # (N + 1,) 0, 1 or 2
        key = rank + tier * float(_HASH_MOD)  # (N + 1,) distinct keys: no tie to break
        # the first num_points of the order are all that is read: a partial sort (TopK)
        order = torch.topk(key, torch.sym_min(total, key.shape[0]), largest=False, sorted=True).indices
        j = torch.arange(total, device=points.device)  # (num_points,)
        pick = order[torch.remainder(j, n_in.clamp(min=1))]  # (num_points,) cyclic when n_in < num_points
        idx = torch.where(n_in > 0, pick, torch.full_like(j, pts.shape[0] - 1))
        return pts.index_select(0, idx), n_in > 0  # (num_points, 4), ()

    def stage_one(self, pts: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """pts (n0, 4) -> features (n0, C), seg logit (n0,), box head output (n0, B)."""
        feats = self.backbone(pts[:, :3], pts[:, 3:4])
        # the heads' outputs float32 also under autocast: the losses, decoding and proposals' ranking read them
        return feats, self.seg_head(feats)[:, 0].float(), self.box_head(feats).float()

    def decode_top(self, pts: Tensor, seg: Tensor, box: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The points' scores (n0,), the pre_nms best of them (T,) best first, their boxes (T, 7):
        what the proposal NMS takes."""
        scores = torch.sigmoid(seg)  # (n0,)
        top = ranked_topk(scores, self.cfg.pre_nms)  # (T,) best first
        return scores, top, decode_bins(box[top], pts[top, :3], self.cfg)

    def propose(self, pts: Tensor, seg: Tensor, box: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Decode the top pre_nms points, BEV NMS -> rois (R, 7), roi_scores (R,), valid (R,).

        R = cfg.rois always: the K <= R proposals that survive NMS come first, then zero rows.
        """
        scores, top, boxes = self.decode_top(pts, seg, box)
        keep = nms_in_order(boxes, self.cfg.proposal_nms_iou, self.cfg.rois)  # (K,) K <= R
        slot = torch.cat([keep, keep.new_zeros(self.cfg.rois)])[: self.cfg.rois]  # (R,)
        valid = torch.arange(self.cfg.rois, device=seg.device) < keep.shape[0]  # (R,)
        rois = boxes[slot] * valid[:, None].to(boxes.dtype)
        return rois, scores[top][slot] * valid.to(scores.dtype), valid

    def refine(self, pts: Tensor, feats: Tensor, seg: Tensor, rois: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
        """Stage 2 on rois (K, 7) -> confidence logit (K,), canonical residuals (K, 7)."""
        depth = pts[:, :3].norm(dim=1, keepdim=True) / 70.0 - 0.5  # (n0, 1)
        # stage 2 does not train stage 1 through the pooled points (OpenPCDet pools them under no_grad)
        extra = torch.cat([torch.sigmoid(seg)[:, None], depth, feats], 1).detach()  # (n0, 2 + C)
        pooled, empty = roi_point_pool(pts[:, :3], extra, rois, self.cfg.pool_samples, self.cfg.pool_extra_width)
        return self.rcnn(pooled, empty | ~valid)

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        pts, nonempty = self.points_of_interest(points)  # (n0, 4), ()
        feats, seg, box = self.stage_one(pts)
        rois, roi_scores, valid = self.propose(pts, seg, box)  # (R, 7), (R,), (R,)
        valid = valid & nonempty  # no point in range: no RoI (the zero points are padding)
        logit, deltas = self.refine(pts, feats, seg, rois, valid)
        rcnn_boxes = decode_canonical(deltas, rois)  # (R, 7)
        scores = torch.sigmoid(logit) * valid.to(logit.dtype)  # (R,)
        boxes, scores = select_ranked(rcnn_boxes, scores, self.cfg.score_thresh, self.cfg.rois,
                                      self.cfg.nms_iou, self.cfg.max_detections)
        k = valid.sum()
        return boxes, scores, rois[:k], roi_scores[:k], rcnn_boxes[:k]

    # ---- training ----------------------------------------------------------------------------

    def seg_targets(self, xyz: Tensor, cars: Tensor, others: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """fg (n0,) bool, weight (n0,) 0 for ignored points (outside every car box but near one, or inside
        an ignored box ``others``), matched car box per point (n0, 7)."""
        inside = inside_boxes(xyz, cars)  # (G, n0)
        near = inside_boxes(xyz, cars, self.cfg.seg_ignore_margin).any(0) | inside_boxes(xyz, others).any(0)
        fg = inside.any(0)
        weight = (fg | ~near).float()
        match = cars[inside.float().argmax(0)] if len(cars) else xyz.new_zeros(len(xyz), 7)
        return fg, weight, match

    def frame_loss(self, sample: Sample) -> dict[str, Tensor]:
        device = next(self.parameters()).device
        salt = int(self.sampling_rng.integers(_HASH_MOD))  # a fresh draw of the near points per step
        points, cars, others = frame_targets(sample, device)  # others: the ignored boxes (Van, Truck, DontCare)
        pts, _ = self.points_of_interest(points, salt)
        feats, seg, box = self.stage_one(pts)
        fg, weight, match = self.seg_targets(pts[:, :3], cars, others)
        p = torch.sigmoid(seg)
        focal = F.binary_cross_entropy_with_logits(seg, fg.float(), reduction="none")
        focal = focal * torch.where(fg, 0.25 * (1 - p) ** 2, 0.75 * p**2) * weight
        out = {"seg": focal.sum() / fg.sum().clamp(min=1)}
        if bool(fg.any()):
            bins, res = encode_bins(match[fg], pts[fg, :3], self.cfg)
            out["rpn_box"] = bin_loss(box[fg], bins, res, self.cfg)
        else:
            out["rpn_box"] = box.sum() * 0.0
        with torch.no_grad():
            rois, _, valid = self.propose(pts, seg, box)
        targets = sample_rois(rois[valid].cpu().numpy(), cars.cpu().numpy(), self.cfg.targets, self.sampling_rng,
                              others.cpu().numpy()).to(device)
        logit, deltas = self.refine(pts, feats, seg, targets.rois, torch.ones_like(targets.iou, dtype=torch.bool))
        out.update(refine_loss(logit, deltas, targets, self.cfg.targets))
        return out

    def loss(self, samples: list[Sample]) -> dict[str, Tensor]:
        """Mean over frames of the stage-1 (focal seg + bin box) and stage-2 losses."""
        out = mean_over_frames((self.frame_loss(s) for s in samples), len(samples))
        out["loss"] = sum(out.values())
        return out


def build(profile: str = "compact") -> PointRCNN:
    if profile not in CONFIGS:
        raise ValueError(f"point_rcnn: unknown profile {profile!r}; choose from {sorted(CONFIGS)}")
    return PointRCNN(CONFIGS[profile])
