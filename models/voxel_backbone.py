"""Sparse 3D voxel backbone (SECOND / OpenPCDet ``VoxelBackBone8x`` layout, configurable).

stem: SubM(c_in -> c_stem) + SubM(c_stem)        at the input resolution
stage i: SparseConv(stride_i) + n_i x SubM        one strided conv per stage
out: SparseConv(kernel (3, 1, 1), stride (2, 1, 1)) -> the z-collapse before height compression
Each conv is followed by BatchNorm + ReLU. ``forward`` returns the output tensor and the
stage outputs (finest first) so that two-stage models can pool from them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from torch import nn

from models.sparse import SparseConv3d, SparseTensor, SubMConv3d, conv_block, out_shape


@dataclass(frozen=True)
class StageSpec:
    channels: int
    stride: tuple[int, int, int]  # (z, y, x)
    padding: tuple[int, int, int]
    subm: int  # submanifold convs after the strided one


@dataclass(frozen=True)
class VoxelBackboneConfig:
    stem_channels: int = 16
    stages: tuple[StageSpec, ...] = (StageSpec(32, (2, 2, 2), (1, 1, 1), 1),
                                     StageSpec(64, (2, 2, 2), (1, 1, 1), 1),
                                     StageSpec(64, (2, 1, 1), (0, 1, 1), 1))
    out_channels: int = 64
    out_padding: tuple[int, int, int] = (0, 0, 0)  # of the (3, 1, 1) / (2, 1, 1) z-collapse
    depth_pad: ClassVar[int] = 0  # empty cells above the voxel grid in the sparse input (not a field)

    def input_shape(self, grid_shape) -> tuple[int, int, int]:
        """(D, H, W) of the sparse input: the voxel grid with ``depth_pad`` more z cells."""
        d, h, w = grid_shape
        return d + self.depth_pad, h, w


@dataclass(frozen=True)
class Backbone8xConfig(VoxelBackboneConfig):
    """OpenPCDet's ``VoxelBackBone8x`` / MMDetection3D's ``SparseEncoder``: the sparse input is one
    z cell deeper than the voxel grid (``sparse_shape = grid_size[::-1] + [1, 0, 0]``: 41 cells
    for 40), which moves the strided convs' windows over the real voxels."""

    depth_pad: int = 1


class VoxelBackbone(nn.Module):
    def __init__(self, c_in: int, cfg: VoxelBackboneConfig):
        super().__init__()
        c = cfg.stem_channels
        self.stem = nn.Sequential(conv_block(SubMConv3d(c_in, c), c), conv_block(SubMConv3d(c, c), c))
        self.stages = nn.ModuleList()
        for spec in cfg.stages:
            mods = [conv_block(SparseConv3d(c, spec.channels, 3, spec.stride, spec.padding), spec.channels)]
            mods += [conv_block(SubMConv3d(spec.channels, spec.channels), spec.channels)
                     for _ in range(spec.subm)]
            self.stages.append(nn.Sequential(*mods))
            c = spec.channels
        self.out = conv_block(SparseConv3d(c, cfg.out_channels, (3, 1, 1), (2, 1, 1), cfg.out_padding),
                              cfg.out_channels)
        self.out_channels = cfg.out_channels
        self.input_shape = cfg.input_shape

    def forward(self, x: SparseTensor) -> tuple[SparseTensor, list[SparseTensor]]:
        """x on the voxel grid -> (output, [stem, stage outputs]) on the sparse input's grid."""
        x = self.stem(SparseTensor(x.features, x.coords, self.input_shape(x.shape)))
        levels = [x]
        for stage in self.stages:
            x = stage(x)
            levels.append(x)
        return self.out(x), levels


def output_shape(grid_shape, cfg: VoxelBackboneConfig) -> tuple[int, int, int]:
    """(D, H, W) after the stages and the z-collapse."""
    shape = cfg.input_shape(grid_shape)
    for spec in cfg.stages:
        shape = out_shape(shape, 3, spec.stride, spec.padding)
    return out_shape(shape, (3, 1, 1), (2, 1, 1), cfg.out_padding)
