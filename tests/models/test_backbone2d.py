import numpy as np
import torch

from models.backbone2d import BEVBackbone, scatter_to_bev


def test_scatter_to_bev_places_each_pillar():
    rng = np.random.default_rng(0)
    lin = rng.choice(6 * 9, 20, replace=False)
    coords = torch.from_numpy(np.stack([np.zeros(20, int), lin // 9, lin % 9], 1))
    feats = torch.from_numpy(rng.standard_normal((20, 3)).astype(np.float32))
    img = scatter_to_bev(feats, coords, (1, 6, 9))
    ref = np.zeros((3, 6, 9), np.float32)
    ref[:, lin // 9, lin % 9] = feats.numpy().T
    np.testing.assert_array_equal(img[0].numpy(), ref)


def test_backbone_shapes_and_strides():
    net = BEVBackbone(8, (1, 2), (2, 2), (16, 32), (1, 2), (8, 8)).eval()
    out = net(torch.randn(1, 8, 32, 48))
    assert out.shape == (1, 16, 16, 24) and net.out_channels == 16
    down = BEVBackbone(8, (0,), (1,), (4,), (0.5,), (6,)).eval()
    assert down(torch.randn(1, 8, 8, 8)).shape == (1, 6, 4, 4)
