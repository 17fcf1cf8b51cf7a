"""DV-SECOND: SECOND with dynamic voxelization (Zhou et al., CoRL 2019; MMDetection3D's
``dv_second``): no point or voxel caps, the voxel feature is the scatter-mean over ALL points
of a voxel. Everything after the VFE is SECOND's network, so the two form a clean A/B.

    points --dynamic voxelization--> scatter-mean VFE --SECOND's sparse 3D backbone, height
           compression, 2D backbone, anchor head--> NMS
"""
from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from models.anchor_head import HeadConfig
from models.second import KITTI, SECOND, TINY, SECONDConfig
from models.voxel_backbone import VoxelBackboneConfig
from models.voxelize import Voxels, dynamic_voxelize

_BASE = SECONDConfig()


@dataclass(frozen=True)
class DVSECONDConfig:
    pc_range: tuple[float, ...] = _BASE.pc_range
    voxel_size: tuple[float, float, float] = _BASE.voxel_size
    backbone3d: VoxelBackboneConfig = _BASE.backbone3d
    layers: tuple[int, ...] = _BASE.layers
    strides: tuple[int, ...] = _BASE.strides
    filters: tuple[int, ...] = _BASE.filters
    upsample_strides: tuple[float, ...] = _BASE.upsample_strides
    upsample_filters: tuple[int, ...] = _BASE.upsample_filters
    head: HeadConfig = _BASE.head


def _from_second(cfg: SECONDConfig) -> DVSECONDConfig:
    """The same network with the voxel caps dropped."""
    return DVSECONDConfig(cfg.pc_range, cfg.voxel_size, cfg.backbone3d, cfg.layers, cfg.strides, cfg.filters,
                          cfg.upsample_strides, cfg.upsample_filters, cfg.head)


CONFIGS = {"tiny": _from_second(TINY), "compact": DVSECONDConfig(), "kitti": _from_second(KITTI)}


class DVSECOND(SECOND):
    architecture = "dv_second"

    def voxelize(self, points: Tensor) -> Voxels:
        return dynamic_voxelize(points, self.grid)  # every in-range point, no caps


def build(profile: str = "compact") -> DVSECOND:
    return DVSECOND(CONFIGS[profile])
