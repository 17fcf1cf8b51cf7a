"""Training under bfloat16 autocast (``train --amp bf16``, harness.amp): every detector's tiny profile takes a step
whose loss is finite and near the float32 one, and whose weights and optimizer state stay float32; the sparse
convolutions and the coordinates computed by a matmul stay float32."""
import copy

import numpy as np
import pytest
import torch

from harness.amp import autocast, native_bf16
from harness.dataset import synthetic_sample
from models import zoo
from models.image_branch import project_points
from models.sparse import SparseTensor, SubMConv3d

pytestmark = [pytest.mark.usefixtures("one_thread"),
              pytest.mark.skipif(not native_bf16(), reason="this CPU has no native bfloat16 (avx512_bf16 / "
                                 "amx_bf16): autocast would be emulated there, and train --amp is refused")]


def _camera(h: int, w: int) -> np.ndarray:
    """(4, 4) lidar2img of a camera 0.5 m above the LiDAR looking along +x, image H x W."""
    k = np.array([[60.0, 0, w / 2, 0], [0, 60.0, h / 2, 0], [0, 0, 1, 0]])
    lidar_to_cam = np.array([[0, -1, 0, 0], [0, 0, -1, 0.5], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=float)
    m = np.eye(4)
    m[:3] = k @ lidar_to_cam
    return m.astype(np.float32)


def _step(net, sample, amp: str) -> float:
    """One training step (forward and loss under ``amp``'s autocast, backward, AdamW) from the draws of seed 0."""
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        net.sampling_rng = np.random.default_rng(0)
        with autocast(amp):
            loss = net.loss([sample])["loss"]
        loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
    optimizer.step()
    assert all(v.dtype == torch.float32 for s in optimizer.state.values() for v in s.values() if v.is_floating_point())
    return float(loss.detach())


@pytest.mark.parametrize("name", zoo.MODEL_NAMES)
def test_a_bf16_step_gives_the_float32_loss_and_keeps_float32_weights(name):
    """Within 2 %: the two-stage models' proposals are ranked on rounded scores, so a few RoIs differ."""
    torch.manual_seed(0)
    net = zoo.build(name, "tiny").train()
    sample = synthetic_sample(np.random.default_rng(1))
    if net.uses_camera:
        h, w = net.image_hw
        sample.image = np.random.default_rng(2).uniform(0, 1, (3, h, w)).astype(np.float32)
        sample.lidar2img = _camera(h, w)
    twin = copy.deepcopy(net)
    full, mixed = _step(net, sample, ""), _step(twin, sample, "bf16")
    assert np.isfinite(mixed) and mixed == pytest.approx(full, rel=2e-2)
    floats = [v for v in twin.state_dict().values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float32 for v in floats)


@pytest.mark.parametrize("grad", [False, True], ids=["inference", "autograd"])
def test_sparse_convs_compute_in_float32_under_autocast(grad):
    """Autocast leaves the sparse convolutions alone: the float32 result bit for bit, also from bfloat16 rows (the
    point encoders' under autocast, cast to float32), and float32 gradients."""
    rng = np.random.default_rng(3)
    coords = torch.from_numpy(np.stack(np.unravel_index(rng.choice(6 * 9 * 11, 120, replace=False), (6, 9, 11)), 1))
    feats = torch.from_numpy(rng.standard_normal((120, 8)).astype(np.float32)).bfloat16().float()
    conv = SubMConv3d(8, 6)
    with torch.set_grad_enabled(grad):
        want = conv(SparseTensor(feats, coords, (6, 9, 11))).features
        with autocast("bf16"):
            got = conv(SparseTensor(feats.bfloat16().requires_grad_(grad), coords, (6, 9, 11))).features
    assert got.dtype == torch.float32 and torch.equal(got, want)
    if grad:
        got.sum().backward()
        assert conv.weight.grad.dtype == torch.float32


def test_projection_stays_float32_under_autocast():
    """Image coordinates of far points: a bfloat16 matmul would be off by pixels; no_autocast keeps them."""
    xyz = torch.tensor([[60.3, 1.7, -0.4], [41.1, -3.3, 0.2], [75.9, 7.1, 1.4]])
    lidar2img = torch.from_numpy(_camera(375, 1242))
    uv, depth = project_points(xyz, lidar2img)
    with autocast("bf16"):
        uv_amp, depth_amp = project_points(xyz, lidar2img)
    assert uv_amp.dtype == torch.float32 and torch.equal(uv_amp, uv) and torch.equal(depth_amp, depth)
