"""PV-RCNN (Shi et al., CVPR 2020), OpenPCDet layout.

    points (N, 4) --hard voxelization, mean VFE--> sparse voxels
      --SECOND sparse 3D backbone--> levels (strides 1, 2, 4, ...) --z-collapse--> BEV
      --2D backbone--> anchor RPN --rotated NMS--> rois (K, 7), roi_scores (K,)
    voxel-mean points (V, 4) --farthest point sampling--> keypoints (P, 3)
      --voxel set abstraction: ball-query PointNets over the voxel-mean points and 3D conv
        levels, bilinear BEV features--> keypoint features --predicted keypoint weighting-->
      --RoI-grid pooling (g^3 grid points per RoI, ball query over keypoints)-->
      --shared FC --refine head--> IoU-guided score, residuals
      --decode--> rcnn_boxes (K, 7) --score threshold + BEV NMS--> boxes, scores

On a CPU the keypoints are sampled from, and the point branch of the VSA groups, the mean
points of the non-empty voxels (the mean VFE's output, one per voxel) rather than every raw
point: a highway frame holds ~50k points in range but a few thousand voxels, and FPS plus ball
query cost O(points x keypoints).

The ``kitti`` profile is OpenPCDet's pv_rcnn.yaml network (``sotif-bench import``; docs/models.md):
keypoints from the raw points, its VSA and keypoint weighting, its RoI grid (``models.pv_rcnn_published``),
the 3-class RPN whose proposals keep their best class, and the Car boxes of one class-agnostic NMS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from harness.core.types import Sample
from models.anchor_head import HeadConfig
from models.base import Detector, mean_over_frames
from models.box_frame import inside_boxes
from models.image_branch import bilinear_sample
from models.losses import sigmoid_focal_loss
from models.multiclass_head import PublishedHeadConfig
from models.pointnet2 import PointBatchNorm, SetAbstraction, farthest_point_sample
from models.pv_rcnn_published import PublishedRoIGridPool, PublishedVSA, in_range_points, sample_keypoints
from models.recipe import Recipe
from models.roi_head import (OutputConfig, ProposalConfig, RefineHead, RoITargetConfig,
                             finalize, propose, refine_loss, roi_support, sample_rois)
from models.roi_pool import RoIGridPool
from models.second import BACKBONE_8X, SECONDConfig
from models.single_stage import bev_stages, frame_targets
from models.sparse import SparseTensor, height_compress
from models.vfe import MeanVFE
from models.voxel_backbone import StageSpec, VoxelBackbone, VoxelBackboneConfig, output_shape
from models.voxelize import Grid, hard_voxelize


@dataclass(frozen=True)
class PVRCNNConfig(SECONDConfig):
    # SECOND's first stage (SECONDConfig: range, voxels, 3D and 2D backbones, anchor head), which the run
    # starts from the run's SECOND
    # (0.4 m voxels: val 68.1, SOTIF headline 46.6; 0.2 m from SECOND, 6 epochs: 93.2 and 67.7)
    proposals_train: ProposalConfig = ProposalConfig(nms_pre=256, nms_iou=0.7, rois=64)
    proposals_test: ProposalConfig = ProposalConfig(nms_pre=256, nms_iou=0.7, rois=32)
    keypoints: int = 512  # farthest-point-sampled keypoints
    raw_radii: tuple[float, ...] = (0.8, 1.6)  # m, ball queries over the voxel-mean points
    raw_nsamples: tuple[int, ...] = (16, 16)
    raw_mlps: tuple[tuple[int, ...], ...] = ((16, 16), (16, 16))
    levels: tuple[int, ...] = (2, 3)  # which backbone levels (0 = stem) feed the VSA
    level_radii: tuple[tuple[float, ...], ...] = ((1.2, 2.4), (2.4, 4.8))  # m, per level
    level_nsamples: tuple[int, ...] = (16, 16)
    kp_channels: int = 64  # fused keypoint features
    kp_margin: float = 0.2  # m: keypoints this close to a box count as foreground
    grid: int = 4  # RoI grid points per axis
    grid_radii: tuple[float, ...] = (0.8, 1.6)
    grid_nsamples: tuple[int, ...] = (16, 16)
    grid_mlps: tuple[tuple[int, ...], ...] = ((32, 32), (32, 32))
    fc: tuple[int, ...] = (128, 128)
    branch_fc: tuple[int, ...] = (128,)  # per confidence / residual branch after the shared fc
    dropout: float = 0.3
    targets: RoITargetConfig = RoITargetConfig(per_frame=32)
    output: OutputConfig = OutputConfig()
    weight_kp: float = 1.0
    weight_rcnn: float = 1.0
    seed: int = 0  # RoI sampling draws

    @property
    def grid_of_voxels(self) -> Grid:
        return Grid(self.pc_range, self.voxel_size)


@dataclass(frozen=True)
class PublishedPVRCNNConfig(PVRCNNConfig):
    """OpenPCDet's pv_rcnn.yaml network (``models.pv_rcnn_published``): keypoints from the raw points,
    per-level ball-query sample counts and PointHeadSimple's layers (a class of its own, so that the other
    profiles' configs keep their fields). ``level_nsamples`` is unused."""

    level_nsample_sets: tuple[tuple[int, ...], ...] = ((16, 16), (16, 32), (16, 32), (16, 32))  # per level
    kp_fc: tuple[int, ...] = (256, 256)  # POINT_HEAD.CLS_FC


CONFIGS = {
    "tiny": PVRCNNConfig(
        pc_range=(0.0, -12.8, -3.0, 25.6, 12.8, 1.8), voxel_size=(0.8, 0.8, 0.4), max_voxels=4000,
        backbone3d=VoxelBackboneConfig(8, (StageSpec(8, (2, 2, 2), (1, 1, 1), 0),
                                           StageSpec(16, (2, 2, 2), (1, 1, 1), 0),
                                           StageSpec(16, (2, 1, 1), (0, 1, 1), 0)), 16, (1, 0, 0)),
        layers=(1,), strides=(1,), filters=(16,), upsample_strides=(2,),
        upsample_filters=(16,), head=HeadConfig(anchor_z=-1.0, nms_pre=64),
        proposals_train=ProposalConfig(64, 0.7, 16), proposals_test=ProposalConfig(64, 0.7, 8),
        keypoints=64, raw_mlps=((8,), (8,)), level_nsamples=(8, 8), kp_channels=16, grid=3,
        grid_nsamples=(8, 8), grid_mlps=((8,), (8,)), fc=(32,), branch_fc=(32,),
        targets=RoITargetConfig(per_frame=16)),
    "compact": PVRCNNConfig(),
    "kitti": PublishedPVRCNNConfig(  # OpenPCDet tools/cfgs/kitti_models/pv_rcnn.yaml (docs/models.md)
        pc_range=(0.0, -40.0, -3.0, 70.4, 40.0, 1.0), voxel_size=(0.05, 0.05, 0.1),
        max_voxels=40000,  # OpenPCDet's test-time cap (16000 in training)
        backbone3d=BACKBONE_8X,  # VoxelBackBone8x: 41 cells deep, 256 BEV channels
        layers=(5, 5), strides=(1, 2), filters=(128, 256), upsample_strides=(1, 2),
        upsample_filters=(256, 256), head=PublishedHeadConfig(nms_pre=4096, nms_iou=0.1, max_out=500),
        proposals_train=ProposalConfig(9000, 0.8, 512), proposals_test=ProposalConfig(1024, 0.7, 100),
        keypoints=2048, raw_radii=(0.4, 0.8), raw_mlps=((16, 16), (16, 16)), levels=(0, 1, 2, 3),
        level_radii=((0.4, 0.8), (0.8, 1.2), (1.2, 2.4), (2.4, 4.8)), level_nsamples=(16, 32),
        kp_channels=128, grid=6, grid_mlps=((64, 64), (64, 64)), fc=(256, 256), branch_fc=(256, 256),
        targets=RoITargetConfig(per_frame=128),
        # the stage-2 confidence alone, boxes of every RoI, sizes uncapped, as OpenPCDet
        output=OutputConfig(score="rcnn", nms_pre=4096, max_out=500, max_log_size=None, drop_empty=False)),
}
# compact: 1 epoch over the default run's 1,530 training frames from the run's SECOND, the steps of the 6
# over 255 it took before (there, at SECOND's 0.2 m voxels from a 6-epoch SECOND val 93.2; cold at 0.4 m 68.1
# after 8 epochs and 78.8 after 16); kitti: OpenPCDet's pv_rcnn.yaml, OPTIMIZATION.LR 0.01. The RPN
# is SECOND's anchor head (``head.`` in SECOND's checkpoint).
RECIPE = Recipe(epochs={"compact": 1}, lr={"kitti": 0.01}, warm_from="second", warm_aliases=(("rpn.", "head."),))


def level_centres(x: SparseTensor, grid: Grid) -> Tensor:
    """(V, 3) x, y, z centres in metres of the voxels of a backbone level (any stride)."""
    d, h, w = grid.shape
    stride = torch.tensor([w / x.shape[2], h / x.shape[1], d / x.shape[0]])  # (3,) x, y, z
    return grid.centres(x.coords, stride)


class VoxelSetAbstraction(nn.Module):
    """Keypoints gather raw-point, 3D-conv-level and BEV features; predicted keypoint weighting.

    forward(keypoints (P, 3), points (N, 4) x y z intensity, levels [(xyz (V_i, 3), feats (V_i, C_i))],
    bev (1, C, H, W)) -> (weighted features (P, kp_channels), foreground logit (P,)).
    """

    def __init__(self, cfg: PVRCNNConfig, level_channels: list[int], bev_channels: int):
        super().__init__()
        self.cfg = cfg
        self.raw = SetAbstraction(1, cfg.raw_radii, cfg.raw_nsamples, cfg.raw_mlps)
        self.levels = nn.ModuleList(
            SetAbstraction(c, radii, cfg.level_nsamples, [(c, c)] * len(radii))
            for c, radii in zip(level_channels, cfg.level_radii))
        total = self.raw.out_channels + sum(s.out_channels for s in self.levels) + bev_channels
        self.fuse = nn.Sequential(nn.Linear(total, cfg.kp_channels, bias=False),
                                  PointBatchNorm(cfg.kp_channels), nn.ReLU())
        self.weight = nn.Sequential(nn.Linear(cfg.kp_channels, 32, bias=False), PointBatchNorm(32),
                                    nn.ReLU(), nn.Linear(32, 1))
        nn.init.constant_(self.weight[-1].bias, -math.log((1 - 0.01) / 0.01))  # focal-loss prior

    def forward(self, keypoints: Tensor, points: Tensor, levels: list[tuple[Tensor, Tensor]],
                bev: Tensor) -> tuple[Tensor, Tensor]:
        parts = [self.raw(points[:, :3], points[:, 3:4], keypoints)]  # (P, C_raw)
        for sa, (xyz, feats) in zip(self.levels, levels):
            parts.append(sa(xyz, feats, keypoints))  # (P, C_level)
        parts.append(self.sample_bev(bev[0], keypoints))  # (P, C_bev)
        feats = self.fuse(torch.cat(parts, 1))  # (P, kp_channels)
        logit = self.weight(feats).squeeze(1).float()  # (P,) float32 also under autocast (its loss)
        return feats * torch.sigmoid(logit)[:, None], logit

    def sample_bev(self, bev: Tensor, xyz: Tensor) -> Tensor:
        """Bilinear BEV features at the keypoints' (x, y): bev (C, H, W) -> (P, C)."""
        x0, y0, _, x1, y1, _ = self.cfg.pc_range
        h, w = bev.shape[1], bev.shape[2]
        u = (xyz[:, 0] - x0) / (x1 - x0) * w  # (P,) BEV pixels, cell centres at i + 0.5
        v = (xyz[:, 1] - y0) / (y1 - y0) * h
        inside = (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
        return bilinear_sample(bev, torch.stack([u, v], 1), inside, (h, w))


def keypoint_targets(keypoints: Tensor, gt: Tensor, others: Tensor, margin: float) -> tuple[Tensor, Tensor]:
    """Foreground (P,) float 1 where the keypoint lies inside a Car box gt (G, 7) enlarged by ``margin``
    metres, and weight (P,) float 0 where it lies, not foreground, inside an ignored box others (J, 7)
    (Van, Truck, DontCare) enlarged alike: a truck's keypoints are not background."""
    fg = inside_boxes(keypoints, gt, 2 * margin).any(0)  # (P,)
    ignored = inside_boxes(keypoints, others, 2 * margin).any(0) & ~fg
    return fg.float(), (~ignored).float()


class PVRCNN(Detector):
    architecture = "pv_rcnn"
    two_stage = True

    def __init__(self, cfg: PVRCNNConfig):
        super().__init__()
        self.cfg = cfg
        self.grid = cfg.grid_of_voxels
        self.vfe = MeanVFE()
        self.backbone3d = VoxelBackbone(MeanVFE.out_channels, cfg.backbone3d)
        self.backbone2d, self.rpn = bev_stages(self.grid, cfg.backbone3d, cfg.pc_range, cfg.head, cfg.layers,
                                               cfg.strides, cfg.filters, cfg.upsample_strides, cfg.upsample_filters)
        bev_channels = cfg.backbone3d.out_channels * output_shape(self.grid.shape, cfg.backbone3d)[0]
        channels = [cfg.backbone3d.stem_channels] + [s.channels for s in cfg.backbone3d.stages]
        self.published = isinstance(cfg, PublishedPVRCNNConfig)
        if self.published:
            bev_stride = self.grid.shape[2] // output_shape(self.grid.shape, cfg.backbone3d)[2]
            self.vsa = PublishedVSA(cfg, [channels[i] for i in cfg.levels], bev_channels, bev_stride)
        else:
            self.vsa = VoxelSetAbstraction(cfg, [channels[i] for i in cfg.levels], bev_channels)
        pool = PublishedRoIGridPool if self.published else RoIGridPool
        self.roi_grid = pool(cfg.kp_channels, cfg.grid, cfg.grid_radii, cfg.grid_nsamples, cfg.grid_mlps)
        # the Car RoIs' label (published 3-class RPN), or None: every RoI is reported
        self.reported = self.rpn.car if isinstance(cfg.head, PublishedHeadConfig) else None
        self.refine = RefineHead(self.roi_grid.out_channels * cfg.grid ** 3, cfg.fc, cfg.branch_fc, cfg.dropout)
        self.sampling_rng = np.random.default_rng(cfg.seed)

    def stage1(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """points (N, 4) -> keypoints (P, 3), keypoint features (P, C), keypoint logit (P,),
        RPN features (1, C', H, W), voxel means (V, 3)."""
        voxels = hard_voxelize(points, self.grid, self.cfg.max_points, self.cfg.max_voxels)
        means = self.vfe(voxels)  # (V, 4) mean x, y, z, intensity of each voxel's points
        out, levels = self.backbone3d(SparseTensor(means, voxels.coords, voxels.shape))
        bev = height_compress(out)  # (1, C*D, H, W)
        if self.published:  # OpenPCDet: keypoints from the raw points, which the raw-point SA groups
            src = in_range_points(points, self.cfg.pc_range)  # (N', 4)
            keypoints = sample_keypoints(src, self.cfg.keypoints)  # (P, 3)
            sources = [(self.grid.centres(levels[i].coords, 2 ** i), levels[i].features) for i in self.cfg.levels]
        else:
            src = means
            keypoints = means[farthest_point_sample(means[:, :3], self.cfg.keypoints), :3]  # (P, 3)
            sources = [(level_centres(levels[i], self.grid), levels[i].features) for i in self.cfg.levels]
        kp_feats, kp_logit = self.vsa(keypoints, src, sources, bev)
        return keypoints, kp_feats, kp_logit, self.backbone2d(bev), means[:, :3]

    def stage2(self, rois: Tensor, keypoints: Tensor, kp_feats: Tensor) -> tuple[Tensor, Tensor]:
        """rois (K, 7) -> IoU-guided logit (K,), residuals (K, 7)."""
        pooled = self.roi_grid(rois, keypoints, kp_feats)  # (K, g^3, C); kitti (K, C, g^3)
        return self.refine(pooled.flatten(1))

    def forward(self, points: Tensor):
        """points (N, 4) -> boxes (M, 7), scores (M,), rois (K, 7), roi_scores (K,), rcnn_boxes (K, 7)."""
        keypoints, kp_feats, _, bev, voxel_xyz = self.stage1(points)
        rois, roi_scores, roi_labels = propose(self.rpn, bev, self.cfg.proposals_test)
        logit, deltas = self.stage2(rois, keypoints, kp_feats)
        labels = None if self.reported is None else roi_labels
        boxes, scores, rcnn_boxes = finalize(rois, roi_scores, logit, deltas, self.cfg.output,
                                             roi_support(voxel_xyz, rois), labels, self.reported or 0)
        return boxes, scores, rois, roi_scores, rcnn_boxes

    def frame_loss(self, sample: Sample, device) -> dict[str, Tensor]:
        points, gt, ignore = frame_targets(sample, device)
        keypoints, kp_feats, kp_logit, bev, _ = self.stage1(points)
        losses = dict(self.rpn.loss(bev, gt, ignore))
        kp_fg, kp_weight = keypoint_targets(keypoints, gt, ignore, self.cfg.kp_margin)
        losses["keypoint"] = sigmoid_focal_loss(kp_logit, kp_fg, kp_weight) / kp_fg.sum().clamp(min=1.0)
        with torch.no_grad():
            rois, _, _ = propose(self.rpn, bev, self.cfg.proposals_train)
        targets = sample_rois(rois.cpu().numpy(), gt.cpu().numpy(), self.cfg.targets, self.sampling_rng,
                              ignore.cpu().numpy()).to(device)
        losses.update(refine_loss(*self.stage2(targets.rois, keypoints, kp_feats), targets, self.cfg.targets))
        c = self.cfg
        losses["loss"] = (losses["loss"] + c.weight_kp * losses["keypoint"]
                          + c.weight_rcnn * (losses["rcnn_score"] + losses["rcnn_reg"] + losses["rcnn_corner"]))
        return losses

    def loss(self, samples: list[Sample]) -> dict[str, Tensor]:
        """Mean over frames (frames run one by one: no batch axis)."""
        device = next(self.parameters()).device
        return mean_over_frames((self.frame_loss(s, device) for s in samples), len(samples))


def build(profile: str = "compact") -> PVRCNN:
    return PVRCNN(CONFIGS[profile])
