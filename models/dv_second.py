"""DV-SECOND: SECOND with dynamic voxelization (Zhou et al., CoRL 2019; MMDetection3D's
``dv_second``): no point or voxel caps, the voxel feature is the scatter-mean over ALL points
of a voxel. Everything after the VFE is SECOND's network, so the two form a clean A/B.

    points --dynamic voxelization--> scatter-mean VFE --SECOND's sparse 3D backbone, height
           compression, 2D backbone, anchor head--> NMS
"""
from __future__ import annotations

from dataclasses import dataclass, replace

from torch import Tensor

from models.multiclass_head import MMDET3D_DIR_OFFSET, PublishedHeadConfig
from models.recipe import Recipe
from models.second import PUBLISHED, SECOND, TINY, SECONDConfig, SECONDNetwork, network_fields
from models.voxelize import Voxels, dynamic_voxelize


@dataclass(frozen=True)
class DVSECONDConfig(SECONDNetwork):
    """SECOND's network without its voxel caps (``max_points``, ``max_voxels``)."""


def _from_second(cfg: SECONDConfig) -> DVSECONDConfig:
    """The same network with the voxel caps dropped."""
    return DVSECONDConfig(**network_fields(cfg))


# MMDetection3D configs/_base_/models/second_hv_secfpn_kitti.py: classes in the data set config's
# order, Anchor3DRangeGenerator over [0, 70.4] x [-40, 40] m (176 x 200 anchors per row, ends
# included: 0.402 / 0.402 m apart, not the 0.4 m cell), its test_cfg (nms_pre 100, score_thr 0.1,
# nms_thr 0.01, max_num 50)
MMDET3D_HEAD = PublishedHeadConfig(
    classes=("Pedestrian", "Cyclist", "Car"), sizes=((0.8, 0.6, 1.73), (1.76, 0.6, 1.73), (3.9, 1.6, 1.56)),
    bottoms=(-0.6, -0.6, -1.78), anchor_grid="linspace", dir_offset=MMDET3D_DIR_OFFSET, post="mmdet3d",
    nms_pre=100, nms_iou=0.01, max_out=50)
CONFIGS = {"tiny": _from_second(TINY), "compact": DVSECONDConfig(),
           "kitti": replace(_from_second(PUBLISHED), head=MMDET3D_HEAD)}
RECIPE = Recipe(epochs={"compact": 2})  # SECOND's schedule: the two stay a clean A/B


class DVSECOND(SECOND):
    architecture = "dv_second"

    def voxelize(self, points: Tensor) -> Voxels:
        return dynamic_voxelize(points, self.grid)  # every in-range point, no caps


def build(profile: str = "compact") -> DVSECOND:
    return DVSECOND(CONFIGS[profile])
