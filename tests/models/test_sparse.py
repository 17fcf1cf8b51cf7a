import contextlib

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from models.sparse import (SparseConv3d, SparseInverseConv3d, SparseTensor, SubMConv3d, gather_gemm, height_compress,
                           out_shape, pair_gemm, table_gemm, to_dense)

# the convs run the one-GEMM form without autograd and the pair form with it: both against the references
MODES = pytest.mark.parametrize("mode", [torch.no_grad, contextlib.nullcontext], ids=["inference", "autograd"])

SHAPE = (6, 9, 11)


def _sparse(rng, n, c, shape=SHAPE):
    lin = rng.choice(int(np.prod(shape)), size=n, replace=False)
    coords = np.stack(np.unravel_index(lin, shape), 1)
    return SparseTensor(torch.from_numpy(rng.standard_normal((n, c)).astype(np.float32)),
                        torch.from_numpy(coords).long(), shape)


def _dense_weight(conv):
    k = conv.kernel
    w = conv.weight.detach()  # (K, Cin, Cout)
    return w.reshape(*k, w.shape[1], w.shape[2]).permute(4, 3, 0, 1, 2)  # (Cout, Cin, kz, ky, kx)


def _at(dense, coords):
    return dense[:, coords[:, 0], coords[:, 1], coords[:, 2]].T  # (V, C)


@MODES
def test_subm_conv_matches_dense_conv3d(mode):
    rng = np.random.default_rng(0)
    for n in (0, 1, 40, 300):
        x = _sparse(rng, n, 3)
        conv = SubMConv3d(3, 5)
        with mode():
            y = conv(x)
        ref = F.conv3d(to_dense(x)[None], _dense_weight(conv), padding=1)[0]
        assert torch.equal(y.coords, x.coords)
        torch.testing.assert_close(y.features, _at(ref, x.coords), rtol=1e-4, atol=1e-5)


@MODES
def test_subm_conv_of_other_kernels_matches_dense_conv3d(mode):
    """The padded index grid's margin follows the kernel (5: two cells, (1, 3, 3): none in z)."""
    rng = np.random.default_rng(6)
    for kernel in (5, (1, 3, 3), (3, 1, 5)):
        x = _sparse(rng, 200, 2)
        conv = SubMConv3d(2, 3, kernel)
        with mode():
            y = conv(x)
        ref = F.conv3d(to_dense(x)[None], _dense_weight(conv), padding=tuple(k // 2 for k in conv.kernel))[0]
        torch.testing.assert_close(y.features, _at(ref, x.coords), rtol=1e-4, atol=1e-5)


@MODES
def test_strided_conv_matches_dense_conv3d(mode):
    rng = np.random.default_rng(1)
    for kernel, stride, pad in ((3, 2, 1), ((3, 1, 1), (2, 1, 1), 0), (3, 2, (0, 1, 1)), (5, 3, 2), (2, 2, 0)):
        x = _sparse(rng, 120, 4)
        conv = SparseConv3d(4, 6, kernel, stride, pad)
        with mode():
            y = conv(x)
        occ = F.conv3d((to_dense(x).abs().sum(0, keepdim=True) > 0).float()[None],
                       torch.ones(1, 1, *conv.kernel), stride=stride, padding=pad)[0, 0]
        assert y.shape == out_shape(SHAPE, kernel, stride, pad) == tuple(occ.shape)
        ref_coords = torch.nonzero(occ > 0)
        assert torch.equal(y.coords, ref_coords)  # both sorted by linear index
        ref = F.conv3d(to_dense(x)[None], _dense_weight(conv), stride=stride, padding=pad)[0]
        torch.testing.assert_close(y.features, _at(ref, y.coords), rtol=1e-4, atol=1e-5)


@MODES
def test_inverse_conv_matches_conv_transpose3d(mode):
    rng = np.random.default_rng(2)
    fine = _sparse(rng, 150, 2)
    down = SparseConv3d(2, 4, 3, 2, 1)(fine)
    up = SparseInverseConv3d(4, 3, 3, 2, 1)
    with mode():
        y = up(down, fine)
    assert torch.equal(y.coords, fine.coords)
    w = up.weight.detach().reshape(3, 3, 3, 4, 3).permute(3, 4, 0, 1, 2)  # (Cin, Cout, k, k, k)
    natural = [(n - 1) * 2 - 2 + 3 for n in down.shape]  # conv_transpose3d's output size
    extra = tuple(f - n for f, n in zip(SHAPE, natural))  # output_padding back to the fine grid
    dense = F.conv_transpose3d(to_dense(down)[None], w, stride=2, padding=1, output_padding=extra)[0]
    torch.testing.assert_close(y.features, _at(dense, fine.coords), rtol=1e-4, atol=1e-5)


def test_pair_gemm_matches_table_gemm_and_its_gradients():
    rng = np.random.default_rng(4)
    for v_in, v_out, k in ((0, 5, 27), (30, 0, 27), (200, 150, 27), (80, 60, 3)):
        table = torch.from_numpy(np.where(rng.uniform(size=(v_out, k)) < 0.3, rng.integers(0, max(v_in, 1), (v_out, k)),
                                          v_in))  # ~30 % occupied, V_in = empty
        feats = torch.from_numpy(rng.standard_normal((v_in, 6)).astype(np.float32)).requires_grad_()
        weight = torch.from_numpy(rng.standard_normal((k, 6, 4)).astype(np.float32)).requires_grad_()
        grad_out = torch.from_numpy(rng.standard_normal((v_out, 4)).astype(np.float32))
        results = []
        for fn in (pair_gemm, table_gemm):
            out = fn(feats, table, weight)
            gf, gw = torch.autograd.grad(out, (feats, weight), grad_out, allow_unused=True)
            results.append((out.detach(), gf, gw))
        for got, ref in zip(*results):
            torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-5)


def test_gather_gemm_agrees_with_and_without_autograd():
    rng = np.random.default_rng(5)
    table = torch.from_numpy(rng.integers(0, 21, (15, 27)))
    feats, weight = torch.randn(20, 3), torch.randn(27, 3, 2)
    with torch.no_grad():
        torch.testing.assert_close(gather_gemm(feats, table, weight), table_gemm(feats, table, weight))
    torch.testing.assert_close(gather_gemm(feats, table, weight), pair_gemm(feats, table, weight))


def test_height_compress_stacks_channels_per_height():
    rng = np.random.default_rng(3)
    x = _sparse(rng, 50, 3)
    bev = height_compress(x)
    assert bev.shape == (1, 3 * SHAPE[0], SHAPE[1], SHAPE[2])
    for (z, yy, xx), f in zip(x.coords.tolist(), x.features):
        torch.testing.assert_close(bev[0, torch.arange(3) * SHAPE[0] + z, yy, xx], f)
    assert int((bev != 0).sum()) == int((x.features != 0).sum())


def test_submanifold_convs_of_one_resolution_share_their_pairs(monkeypatch):
    """The stem's two SubM convs build the pairs of their table once, and compute what they
    computed with the pairs built for each conv: the same bits, forward and backward."""
    import models.sparse as sparse
    rng = np.random.default_rng(6)
    coords = torch.from_numpy(np.unique(rng.integers(0, 12, (300, 3)), axis=0))
    feats = torch.randn(coords.shape[0], 4, requires_grad=True)
    torch.manual_seed(0)
    convs = torch.nn.Sequential(SubMConv3d(4, 8), torch.nn.Identity())
    second = SubMConv3d(8, 8)

    def run():
        x = SparseTensor(feats, coords, (12, 12, 12))
        out = second(convs[0](x)).features
        return out, torch.autograd.grad(out.square().sum(), (feats, second.weight))

    built = []
    real = sparse.table_pairs
    monkeypatch.setattr(sparse, "table_pairs", lambda t, v: built.append(v) or real(t, v))
    shared = run()
    assert len(built) == 1
    monkeypatch.setattr(sparse, "subm_pairs", lambda x, k: real(sparse.subm_table(x, k), x.coords.shape[0]))
    fresh = run()
    assert torch.equal(shared[0], fresh[0]) and all(torch.equal(a, b) for a, b in zip(shared[1], fresh[1]))
