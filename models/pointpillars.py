"""PointPillars (Lang et al., CVPR 2019).

    points --hard voxelization (pillars)--> PFN (10-ch decoration, Linear-BN-ReLU, max)
           --scatter--> pseudo-image (1, C, H, W) --3-block 2D backbone--> anchor head --> NMS
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from torch import Tensor

from models.anchor_head import HeadConfig
from models.backbone2d import BEVBackbone, scatter_to_bev
from models.multiclass_head import PublishedHeadConfig, make_head
from models.recipe import Recipe
from models.single_stage import AnchorDetector
from models.vfe import PillarVFE
from models.voxelize import Grid, hard_voxelize


@dataclass(frozen=True)
class PointPillarsConfig:
    # metres, x0 y0 z0 x1 y1 z1: the labelled highway (cars to 80 m ahead, both carriageways)
    pc_range: tuple[float, ...] = (0.0, -32.0, -3.0, 81.92, 32.0, 1.0)
    voxel_size: tuple[float, float, float] = (0.32, 0.32, 4.0)  # pillar size, metres (as Waymo's)
    max_points: int = 32  # per pillar
    max_voxels: int = 16000  # pillars
    pfn_channels: int = 32
    layers: tuple[int, ...] = (2, 3, 3)
    strides: tuple[int, ...] = (2, 2, 2)
    filters: tuple[int, ...] = (32, 64, 128)
    upsample_strides: tuple[float, ...] = (1, 2, 4)
    upsample_filters: tuple[int, ...] = (64, 64, 64)
    head: HeadConfig = HeadConfig(anchor_z=-1.0)
    padded_slots: ClassVar[bool] = False  # see PublishedPointPillarsConfig (not a field)


@dataclass(frozen=True)
class PublishedPointPillarsConfig(PointPillarsConfig):
    """OpenPCDet's network: a pillar with empty slots takes relu(BN(0)) into its max."""

    padded_slots: bool = True


CONFIGS = {
    "tiny": PointPillarsConfig(pc_range=(0.0, -8.0, -3.0, 16.0, 8.0, 1.0), voxel_size=(0.5, 0.5, 4.0),
                               max_points=16, max_voxels=2000, pfn_channels=8, layers=(1, 1),
                               strides=(2, 2), filters=(8, 16), upsample_strides=(1, 2),
                               upsample_filters=(8, 8), head=HeadConfig(anchor_z=-1.0, nms_pre=64)),
    "compact": PointPillarsConfig(),
    "kitti": PublishedPointPillarsConfig(  # OpenPCDet tools/cfgs/kitti_models/pointpillar.yaml
        pc_range=(0.0, -39.68, -3.0, 69.12, 39.68, 1.0), voxel_size=(0.16, 0.16, 4.0), max_points=32,
        max_voxels=40000, pfn_channels=64, layers=(3, 5, 5), strides=(2, 2, 2), filters=(64, 128, 256),
        upsample_strides=(1, 2, 4), upsample_filters=(128, 128, 128),
        head=PublishedHeadConfig(nms_pre=4096, nms_iou=0.01, max_out=500)),
}
# compact: 5 epochs over the default run's 1,530 training frames, the steps of the 30 epochs over 255 it took
# before (there, val AP40 3D moderate on 45 held-out frames of generator-1.4 data, seed 0: 68.8 after 18,
# 74.5 after 30, BEV 82.8 -> 86.3; on earlier data 59.2 after 6, 83.1 after 12, 85.2 after 18; 64 PFN channels
# instead of 32 made a step 40 % slower and gave 83.5 after 12). Over two draws the 1,800 scenes gave val
# 75.8 -> 78.8 and headline 62.1 -> 66.8 (docs/performance.md, "Training levers over draws")
RECIPE = Recipe(epochs={"compact": 5})


class PointPillars(AnchorDetector):
    architecture = "pointpillars"

    def __init__(self, cfg: PointPillarsConfig):
        super().__init__()
        self.cfg = cfg
        self.grid = Grid(cfg.pc_range, cfg.voxel_size)
        self.vfe = PillarVFE(self.grid, cfg.pfn_channels, cfg.padded_slots)
        self.backbone2d = BEVBackbone(cfg.pfn_channels, cfg.layers, cfg.strides, cfg.filters,
                                      cfg.upsample_strides, cfg.upsample_filters)
        _, h, w = self.grid.shape
        stride = round(cfg.strides[0] / cfg.upsample_strides[0])  # output stride of the backbone
        self.head = make_head(self.backbone2d.out_channels, (h // stride, w // stride), cfg.pc_range,
                               cfg.head)

    def bev(self, points: Tensor) -> Tensor:
        """points (N, 4) -> pseudo-image (1, C, H, W), one cell per pillar."""
        pillars = hard_voxelize(points, self.grid, self.cfg.max_points, self.cfg.max_voxels)
        return scatter_to_bev(self.vfe(pillars), pillars.coords, pillars.shape)


def build(profile: str = "compact") -> PointPillars:
    return PointPillars(CONFIGS[profile])
