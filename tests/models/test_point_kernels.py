"""The numba FPS, ball-query and 3-NN kernels against the torch forms the ONNX graph keeps: the
same indices on random clouds, on clouds with exact distance ties and on points exactly on a radius
(FPS, ball query), and the same interpolated values and gradients."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from models import pointnet2
from models.point_kernels import ball_queries_cpu, farthest_point_sample_cpu, three_nn_cpu
from models.pointnet2 import _ball_queries_torch, _fps_eager, ball_queries, farthest_point_sample, three_nn_interpolate


def _cloud(rng: np.random.Generator, shape, grid: bool) -> torch.Tensor:
    """Random float32 points; on a 0.5 m lattice (exact distance ties) when ``grid``, else 70 m out."""
    if grid:
        return torch.from_numpy((rng.integers(-6, 7, (*shape, 3)) * 0.5).astype(np.float32))
    return torch.from_numpy((rng.normal(0, 3, (*shape, 3)) + [70.0, -5.0, 0.0]).astype(np.float32))


@pytest.mark.parametrize("b,n,num,grid", [(1, 500, 64, False), (3, 200, 50, True), (2, 7, 7, True),
                                          (1, 1, 4, False), (4, 128, 32, False)])
def test_fps_kernel_picks_the_torch_points(b, n, num, grid):
    xyz = _cloud(np.random.default_rng(n + num), (b, n), grid)
    np.testing.assert_array_equal(farthest_point_sample_cpu(xyz, num).numpy(), _fps_eager(xyz, num).numpy())


@pytest.mark.parametrize("batch,grid", [((), False), ((), True), ((5,), False), ((3,), True)])
def test_ball_query_kernel_finds_the_torch_neighbours(batch, grid):
    rng = np.random.default_rng(len(batch) + grid)
    xyz = _cloud(rng, (*batch, 400), grid)
    centres = torch.cat([xyz[..., :30, :], _cloud(rng, (*batch, 20), grid)], -2)  # points and free centres
    radii, nsamples = (0.5, 1.0, 2.5), (8, 16, 32)
    got, want = ball_queries_cpu(xyz, centres, radii, nsamples), _ball_queries_torch(xyz, centres, radii, nsamples)
    for (idx, valid), (ref_idx, ref_valid) in zip(got, want):
        np.testing.assert_array_equal(idx.numpy(), ref_idx.numpy())
        np.testing.assert_array_equal(valid.numpy(), ref_valid.numpy())  # on a lattice, points lie on the radii


def test_eager_operators_use_the_kernels_and_keep_empty_inputs():
    xyz = _cloud(np.random.default_rng(0), (300,), False)
    np.testing.assert_array_equal(farthest_point_sample(xyz, 20).numpy(), _fps_eager(xyz[None], 20)[0].numpy())
    assert farthest_point_sample(xyz[:0], 5).shape == (0,)
    idx, valid = ball_queries(xyz[:0], xyz[:4], (1.0,), (8,))[0]  # no points: index 0 (the zero row)
    assert idx.shape == (4, 8) and not valid.any() and (idx == 0).all()
    idx, valid = ball_queries(xyz, xyz[:0], (1.0,), (8,))[0]
    assert idx.shape == (0, 8) and valid.shape == (0,)


@pytest.mark.parametrize("n,m", [(2000, 130), (50, 3), (7, 1), (300, 0)])
def test_three_nn_kernel_takes_the_torch_neighbours_and_values(n, m, monkeypatch):
    rng = np.random.default_rng(n + m)
    unknown = _cloud(rng, (n,), False)
    known = unknown[rng.permutation(n)[:m]] if m <= n else _cloud(rng, (m,), False)  # coarse points among the fine
    feats = torch.randn(m, 5, generator=torch.Generator().manual_seed(m), requires_grad=True)
    padded = torch.cat([known, known.new_full((3, 3), 1.0e4)])
    d2 = sum((unknown[:, None, a] - padded[None, :, a]) ** 2 for a in range(3))
    want_idx = torch.topk(d2, 3, dim=1, largest=False, sorted=True).indices
    got_idx = three_nn_cpu(unknown, padded)  # the padding points tie: compare distances, not indices
    np.testing.assert_array_equal(d2.gather(1, got_idx).numpy(), d2.gather(1, want_idx).numpy())
    if m >= 3:
        np.testing.assert_array_equal(got_idx.numpy(), want_idx.numpy())
    got = three_nn_interpolate(unknown, known, feats)
    grad = torch.autograd.grad(got.sum(), feats, allow_unused=True)[0] if m else None
    monkeypatch.setattr(pointnet2, "_kernel_ready", lambda *t: False)  # the torch (graph) form
    want = three_nn_interpolate(unknown, known, feats)
    assert torch.equal(got, want)
    if m:
        assert torch.equal(grad, torch.autograd.grad(want.sum(), feats)[0])


def test_empty_batches_take_the_torch_forms():
    assert farthest_point_sample(torch.zeros(0, 6, 3), 2).shape == (0, 2)
    idx, valid = ball_queries(torch.zeros(0, 6, 3), torch.zeros(0, 2, 3), (1.0,), (4,))[0]
    assert idx.shape == (0, 2, 4) and valid.shape == (0, 2)
