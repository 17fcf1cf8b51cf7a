"""SECOND-style 2D BEV backbone: strided conv blocks, each deconvolved to a common stride and
concatenated (OpenPCDet ``BaseBEVBackbone``), and the pillar scatter to a pseudo-image."""
from __future__ import annotations

import torch
from torch import Tensor, nn


def scatter_to_bev(features: Tensor, coords: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """(1, C, H, W) pseudo-image from pillar features (V, C) at coords (V, 3) (z, y, x), D = 1."""
    _, h, w = shape
    c = features.shape[1]
    lin = coords[:, 1] * w + coords[:, 2]  # (V,)
    # written channel-major, so the map needs no transposed copy (forward and backward)
    dense = features.new_zeros(c, h * w).index_copy(1, lin, features.T)  # (C, H*W)
    return dense.reshape(1, c, h, w)


def _conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
            nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.01), nn.ReLU()]


def _upsample(c_in: int, c_out: int, stride: float) -> nn.Sequential:
    if stride >= 1:
        s = int(stride)
        conv = nn.ConvTranspose2d(c_in, c_out, s, stride=s, bias=False)
    else:
        s = int(round(1 / stride))
        conv = nn.Conv2d(c_in, c_out, s, stride=s, bias=False)
    return nn.Sequential(conv, nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.01), nn.ReLU())


class BEVBackbone(nn.Module):
    """Blocks i = 0..n-1: a conv with stride ``strides[i]`` then ``layers[i]`` 3x3 convs
    (``filters[i]`` channels); each block's output is brought to a common resolution by
    ``upsample_strides[i]`` (deconv, or conv when < 1) with ``upsample_filters[i]`` channels,
    and the results are concatenated: out channels = sum(upsample_filters)."""

    def __init__(self, c_in: int, layers, strides, filters, upsample_strides, upsample_filters):
        super().__init__()
        self.blocks = nn.ModuleList()
        self.ups = nn.ModuleList()
        c = c_in
        for n, s, f, us, uf in zip(layers, strides, filters, upsample_strides, upsample_filters):
            mods = _conv_bn_relu(c, f, s)
            for _ in range(n):
                mods += _conv_bn_relu(f, f)
            self.blocks.append(nn.Sequential(*mods))
            self.ups.append(_upsample(f, uf, us))
            c = f
        self.out_channels = sum(upsample_filters)

    def forward(self, x: Tensor) -> Tensor:
        """(1, C_in, H, W) -> (1, sum(upsample_filters), H / s, W / s)."""
        outs = []
        for block, up in zip(self.blocks, self.ups):
            x = block(x)
            outs.append(up(x))
        return torch.cat(outs, dim=1) if len(outs) > 1 else outs[0]
