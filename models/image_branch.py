"""Camera branch of MVX-Net: a small ResNet-like image CNN + FPN, LiDAR-to-image projection,
bilinear sampling of every FPN level at the projected points, and PointFusion.

Pipeline (one frame):

    image (1, 3, H, W) --ImageBackbone--> C2..Ck --FPN--> P2..Pk (each (1, F, H_l, W_l))
    points (N, 3) --project_points(lidar2img)--> uv (N, 2) pixels, depth (N,)
    P_l, uv --bilinear_sample--> (N, F) per level, zero for points behind the camera or
                                 outside the image
    PointFusion(img levels, point features) --> fused point features (N, C_out)

Sampling convention (MMDetection3D's ``point_sample``, ``grid_sample(align_corners=False)``):
the image spans [0, W) x [0, H) in pixel coordinates, so a point at image coordinate ``u``
falls at level coordinate ``u * W_l / W - 0.5`` (level pixel centres at integers); neighbours
beyond the map border are clamped to it. Sampling is written as four gathers and weights so it exports with standard
ONNX ops.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from models.base import no_autocast
from models.vfe import RowBatchNorm

MIN_DEPTH = 0.1  # metres in front of the camera below which a point gets no image feature


@dataclass(frozen=True)
class ImageBranchConfig:
    stem_channels: int = 16  # stride-4 stem output channels
    stage_channels: tuple[int, ...] = (16, 32, 64)  # one stage per entry, strides 4, 8, 16 ...
    blocks_per_stage: int = 1  # residual basic blocks per stage
    fpn_channels: int = 16  # channels of every FPN output level


class BasicBlock(nn.Module):
    """ResNet basic block: two 3x3 convs with a (projected) identity shortcut."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.shortcut = nn.Identity()
        if stride != 1 or cin != cout:
            self.shortcut = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + self.shortcut(x))


class ImageBackbone(nn.Module):
    """ResNet-like: 3x3 stride-2 stem conv + 3x3 stride-2 max pool, then residual stages
    (the first keeps the stem stride, each later one halves the resolution)."""

    def __init__(self, cfg: ImageBranchConfig):
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(3, cfg.stem_channels, 3, 2, 1, bias=False),
            nn.BatchNorm2d(cfg.stem_channels),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1),
        )
        stages, cin = [], cfg.stem_channels
        for i, cout in enumerate(cfg.stage_channels):
            blocks = [BasicBlock(cin, cout, 1 if i == 0 else 2)]
            blocks += [BasicBlock(cout, cout, 1) for _ in range(cfg.blocks_per_stage - 1)]
            stages.append(nn.Sequential(*blocks))
            cin = cout
        self.stages = nn.ModuleList(stages)

    def forward(self, image: Tensor) -> list[Tensor]:
        x = self.stem(image)  # (1, C0, H/4, W/4)
        feats = []
        for stage in self.stages:
            x = stage(x)  # (1, C_i, H/2^(i+2), W/2^(i+2))
            feats.append(x)
        return feats


class FPN(nn.Module):
    """Feature pyramid: lateral 1x1 convs, nearest top-down upsampling + add, 3x3 output convs."""

    def __init__(self, in_channels: tuple[int, ...], out_channels: int):
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_channels, 1) for c in in_channels)
        self.output = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, 1, 1) for _ in in_channels)

    def forward(self, feats: list[Tensor]) -> list[Tensor]:
        lat = [conv(f) for conv, f in zip(self.lateral, feats)]  # each (1, F, H_l, W_l)
        for i in range(len(lat) - 1, 0, -1):
            up = F.interpolate(lat[i], size=lat[i - 1].shape[-2:], mode="nearest")
            lat[i - 1] = lat[i - 1] + up
        return [conv(x) for conv, x in zip(self.output, lat)]  # finest first


class ImageBranch(nn.Module):
    """Image CNN + FPN: (1, 3, H, W) RGB in [0, 1] -> list of (1, F, H_l, W_l), finest first."""

    def __init__(self, cfg: ImageBranchConfig):
        super().__init__()
        self.backbone = ImageBackbone(cfg)
        self.fpn = FPN(cfg.stage_channels, cfg.fpn_channels)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1), persistent=False)

    def forward(self, image: Tensor) -> list[Tensor]:
        return self.fpn(self.backbone((image - self.mean) / self.std))


def project_points(xyz: Tensor, lidar2img: Tensor) -> tuple[Tensor, Tensor]:
    """LiDAR points (N, 3) m -> image pixel coordinates uv (N, 2) and camera depth (N,) m.

    Points with depth < MIN_DEPTH get finite placeholder coordinates; callers mask them by depth.
    """
    homo = torch.cat([xyz, torch.ones_like(xyz[:, :1])], dim=1)  # (N, 4)
    with no_autocast(xyz.device.type):
        cam = homo @ lidar2img.t()  # (N, 4): (u*d, v*d, d, 1)
    depth = cam[:, 2]  # (N,) m along the optical axis
    safe = torch.where(depth >= MIN_DEPTH, depth, torch.ones_like(depth))
    uv = cam[:, :2] / safe[:, None]  # (N, 2) pixels
    return uv, depth


def visible_mask(uv: Tensor, depth: Tensor, height: int | Tensor, width: int | Tensor) -> Tensor:
    """(N,) bool: in front of the camera and inside the image [0, W) x [0, H)."""
    u, v = uv[:, 0], uv[:, 1]
    return (depth >= MIN_DEPTH) & (u >= 0) & (u < width) & (v >= 0) & (v < height)


def bilinear_sample(feat: Tensor, uv: Tensor, visible: Tensor, image_hw: tuple) -> Tensor:
    """Sample a feature map at image pixel coordinates.

    feat (C, H_l, W_l) features of one level; uv (N, 2) pixels of the full image of size
    image_hw = (H, W); visible (N,) bool. Returns (N, C), zero where not visible.
    """
    c, hl, wl = feat.shape
    x = uv[:, 0] * (wl / image_hw[1]) - 0.5  # (N,) level pixel coordinate
    y = uv[:, 1] * (hl / image_hw[0]) - 0.5
    x = x.clamp(0, wl - 1)  # border clamp: all visible points map into the map
    y = y.clamp(0, hl - 1)
    x0f, y0f = torch.floor(x), torch.floor(y)
    wx, wy = x - x0f, y - y0f  # (N,) weights of the right / lower neighbour
    x0, y0 = x0f.long(), y0f.long()
    x1 = (x0 + 1).clamp(max=wl - 1)
    y1 = (y0 + 1).clamp(max=hl - 1)
    rows = feat.reshape(c, hl * wl).t().contiguous()  # (H_l*W_l, C): one row per pixel

    def gather(yy: Tensor, xx: Tensor) -> Tensor:
        # whole rows on axis 0: onnxruntime gathers columns of (C, H_l*W_l) element by element
        return rows.index_select(0, yy * wl + xx)  # (N, C)

    out = (
        gather(y0, x0) * ((1 - wx) * (1 - wy))[:, None]
        + gather(y0, x1) * (wx * (1 - wy))[:, None]
        + gather(y1, x0) * ((1 - wx) * wy)[:, None]
        + gather(y1, x1) * (wx * wy)[:, None]
    )
    return out * visible[:, None].to(out.dtype)


@dataclass(frozen=True)
class PointFusionConfig:
    img_channels: int = 16  # channels of every FPN level
    num_levels: int = 3  # FPN levels sampled
    pts_channels: int = 32  # incoming point feature channels
    mid_channels: int = 32  # channels of the lateral convs and of the fused features
    out_channels: int = 32  # fused point feature channels


class PointFusion(nn.Module):
    """MMDetection3D's PointFusion: lateral 1x1 conv per FPN level, bilinear sampling at the
    projected points, concatenation over levels, linear+BN transforms of the image and point
    features, sum and ReLU."""

    def __init__(self, cfg: PointFusionConfig):
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(cfg.img_channels, cfg.mid_channels, 3, 1, 1) for _ in range(cfg.num_levels))
        self.img_transform = nn.Sequential(
            nn.Linear(cfg.mid_channels * cfg.num_levels, cfg.out_channels), RowBatchNorm(cfg.out_channels, eps=1e-3)
        )
        self.pts_transform = nn.Sequential(
            nn.Linear(cfg.pts_channels, cfg.out_channels), RowBatchNorm(cfg.out_channels, eps=1e-3)
        )
        self.num_levels = cfg.num_levels

    def sample_levels(self, img_feats: list[Tensor], xyz: Tensor, lidar2img: Tensor, image_hw: tuple) -> Tensor:
        """(N, mid * levels) image features of every point, zero where not visible."""
        uv, depth = project_points(xyz, lidar2img)  # (N, 2) px, (N,) m
        visible = visible_mask(uv, depth, image_hw[0], image_hw[1])  # (N,)
        sampled = [
            bilinear_sample(conv(feat)[0], uv, visible, image_hw)  # (N, mid)
            for conv, feat in zip(self.lateral, img_feats[: self.num_levels])
        ]
        return torch.cat(sampled, dim=1)

    def forward(
        self, img_feats: list[Tensor], xyz: Tensor, pts_feats: Tensor, lidar2img: Tensor, image_hw: tuple
    ) -> Tensor:
        """img_feats list of (1, C_img, H_l, W_l); xyz (N, 3) m; pts_feats (N, C_pts) -> (N, C_out)."""
        img_pts = self.sample_levels(img_feats, xyz, lidar2img, image_hw)  # (N, mid * L)
        fused = self.img_transform(img_pts) + self.pts_transform(pts_feats)  # (N, C_out)
        return F.relu(fused)
