"""The sparse voxel backbone against a dense Conv3d chain (submanifold convs masked to the active
voxels, strided convs to the cells whose receptive field holds one), and ``output_shape``."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from models.sparse import SparseTensor, to_dense
from models.voxel_backbone import StageSpec, VoxelBackbone, VoxelBackboneConfig, output_shape

SHAPE = (10, 12, 14)
CONFIGS = {
    # SECOND's compact layout: the last stage halves z only
    "compact": VoxelBackboneConfig(4, (StageSpec(6, (2, 2, 2), (1, 1, 1), 1), StageSpec(8, (2, 1, 1), (0, 1, 1), 1)),
                                   8, (1, 0, 0)),
    # OpenPCDet's VoxelBackBone8x layout: every stage strided in all axes, no padding in z at the last
    "8x": VoxelBackboneConfig(4, (StageSpec(6, (2, 2, 2), (1, 1, 1), 2), StageSpec(8, (2, 2, 2), (0, 1, 1), 0)),
                              8, (1, 0, 0)),
}


def _dense_conv(x: torch.Tensor, mask: torch.Tensor, conv, stride=1, padding=None):
    """(C, D, H, W) features and (D, H, W) occupancy through one sparse conv, densely."""
    k = conv.kernel
    w = conv.weight.detach().reshape(*k, *conv.weight.shape[1:]).permute(4, 3, 0, 1, 2)
    pad = tuple(n // 2 for n in k) if padding is None else padding
    y = F.conv3d(x[None], w, stride=stride, padding=pad)[0]
    if padding is not None:  # strided: active where the receptive field holds an active cell
        mask = F.conv3d(mask[None, None].float(), torch.ones(1, 1, *k), stride=stride, padding=pad)[0, 0] > 0
    return y * mask, mask


def _dense_block(block, x, mask, stride=1, padding=None):
    conv, bnrelu = block
    y, mask = _dense_conv(x, mask, conv, stride, padding)
    bn = bnrelu.norm
    y = (y - bn.running_mean[:, None, None, None]) / torch.sqrt(bn.running_var[:, None, None, None] + bn.eps)
    y = y * bn.weight[:, None, None, None] + bn.bias[:, None, None, None]
    return torch.relu(y) * mask, mask


@pytest.mark.parametrize("name", CONFIGS)
def test_backbone_matches_dense_conv3d_chain(name):
    cfg = CONFIGS[name]
    torch.manual_seed(0)
    net = VoxelBackbone(3, cfg).eval()
    for m in net.modules():  # non-trivial BatchNorm statistics
        if hasattr(m, "running_var"):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    rng = np.random.default_rng(0)
    lin = rng.choice(int(np.prod(SHAPE)), size=150, replace=False)
    coords = torch.from_numpy(np.stack(np.unravel_index(lin, SHAPE), 1)).long()
    x = SparseTensor(torch.from_numpy(rng.standard_normal((150, 3)).astype(np.float32)), coords, SHAPE)
    with torch.no_grad():
        out, levels = net(x)
        dense, mask = to_dense(x), to_dense(x).abs().sum(0) > 0
        for block in net.stem:
            dense, mask = _dense_block(block, dense, mask)
        ref_levels = [dense]
        for spec, stage in zip(cfg.stages, net.stages):
            dense, mask = _dense_block(stage[0], dense, mask, spec.stride, spec.padding)
            for block in stage[1:]:
                dense, mask = _dense_block(block, dense, mask)
            ref_levels.append(dense)
        dense, mask = _dense_block(net.out, dense, mask, (2, 1, 1), cfg.out_padding)
    assert out.shape == output_shape(SHAPE, cfg) == tuple(dense.shape[1:])
    torch.testing.assert_close(to_dense(out), dense, rtol=1e-4, atol=1e-5)
    for level, ref in zip(levels, ref_levels):
        assert level.shape == tuple(ref.shape[1:])
        torch.testing.assert_close(to_dense(level), ref, rtol=1e-4, atol=1e-5)
