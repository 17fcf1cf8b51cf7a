"""PointNet++ operators against brute-force numpy references, and ONNX export of FPS/ball query."""
from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch

from models.pointnet2 import (FeaturePropagation, PointBatchNorm, SetAbstraction, ball_queries, ball_query,
                              farthest_point_sample, fps_loop, group_points, three_nn_interpolate)


def fps_reference(xyz: np.ndarray, num: int) -> np.ndarray:
    """Textbook FPS from point 0 in float64 (ties broken by the lowest index)."""
    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    chosen = [0]
    dist = np.full(n, np.inf)
    for _ in range(1, min(n, num)):
        dist = np.minimum(dist, ((xyz - xyz[chosen[-1]]) ** 2).sum(1))
        chosen.append(int(np.argmax(dist)))
    return np.array(chosen, dtype=np.int64)


def ball_query_reference(xyz, centres, radius, nsample):
    idx = np.full((len(centres), nsample), len(xyz), dtype=np.int64)
    valid = np.zeros(len(centres), dtype=bool)
    for m, c in enumerate(centres):
        inside = [i for i in range(len(xyz)) if ((xyz[i] - c) ** 2).sum() < radius ** 2]
        if inside:
            valid[m] = True
            chosen = inside[:nsample]
            idx[m] = chosen + [chosen[0]] * (nsample - len(chosen))
    return idx, valid


@pytest.mark.parametrize("n,num", [(300, 40), (25, 25), (7, 20), (1, 4), (0, 5)])
def test_fps_matches_reference(n, num):
    rng = np.random.default_rng(n + num)
    xyz = rng.uniform(-20, 20, (n, 3)).astype(np.float32)
    expected = fps_reference(xyz.astype(np.float64), num)
    got = farthest_point_sample(torch.from_numpy(xyz), num).numpy()
    np.testing.assert_array_equal(got, expected)
    assert len(set(got.tolist())) == len(got)  # never the same point twice


def test_fps_graph_and_eager_paths_agree():
    xyz = torch.from_numpy(np.random.default_rng(1).normal(0, 5, (200, 3)).astype(np.float32))
    np.testing.assert_array_equal(fps_loop(xyz[None], 30)[0].numpy(),
                                  farthest_point_sample(xyz, 30).numpy())
    batch = xyz.reshape(4, 50, 3)
    np.testing.assert_array_equal(fps_loop(batch, 12).numpy(), farthest_point_sample(batch, 12).numpy())
    for k in range(4):
        np.testing.assert_array_equal(farthest_point_sample(batch, 12)[k].numpy(), fps_reference(batch[k].double().numpy(), 12))


def test_fps_rejects_bad_shape():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        farthest_point_sample(torch.zeros(5, 4), 2)


@pytest.mark.parametrize("n,m,radius,nsample", [(400, 30, 1.5, 8), (50, 10, 3.0, 16),
                                                (0, 6, 1.0, 4), (20, 0, 1.0, 4)])
def test_ball_query_matches_reference(n, m, radius, nsample):
    rng = np.random.default_rng(n * 7 + m)
    xyz = rng.uniform(-4, 4, (n, 3)).astype(np.float32)
    centres = rng.uniform(-4, 4, (m, 3)).astype(np.float32)
    idx, valid = ball_query(torch.from_numpy(xyz), torch.from_numpy(centres), radius, nsample)
    ref_idx, ref_valid = ball_query_reference(xyz, centres, radius, nsample)
    np.testing.assert_array_equal(idx.numpy(), ref_idx)
    np.testing.assert_array_equal(valid.numpy(), ref_valid)


def test_ball_queries_far_from_the_origin_keep_the_direct_neighbours():
    """The GEMM distances lose precision 80 m out; the exact check of the candidates restores the
    neighbours of the direct (c - x)^2 sum, including points on the sphere to float precision."""
    rng = np.random.default_rng(11)
    xyz = (rng.uniform(-1.5, 1.5, (2, 600, 3)) + [75.0, -30.0, 1.0]).astype(np.float32)
    centres = xyz[:, :40] + rng.normal(0, 0.05, (2, 40, 3)).astype(np.float32)
    direction = rng.normal(size=(40, 3))
    xyz[0, 100:140] = centres[0] + (0.8 * direction / np.linalg.norm(direction, axis=1, keepdims=True))
    out = ball_queries(torch.from_numpy(xyz), torch.from_numpy(centres), (0.8, 1.6), (8, 16))
    for (idx, valid), radius, nsample in zip(out, (0.8, 1.6), (8, 16)):
        for b in range(2):
            d2 = ((torch.from_numpy(centres[b])[:, None] - torch.from_numpy(xyz[b])[None]) ** 2).sum(-1)
            for m in range(40):  # the direct float32 distances decide, as before the GEMM
                inside = torch.nonzero(d2[m] < radius * radius)[:, 0].tolist()
                assert idx[b, m].tolist() == (inside + inside[:1] * nsample)[:nsample]
                assert bool(valid[b, m]) == bool(inside)


def test_group_points_reads_zero_row_for_index_n():
    rng = np.random.default_rng(3)
    feats = rng.normal(size=(9, 5)).astype(np.float32)
    idx = rng.integers(0, 10, (4, 6))
    got = group_points(torch.from_numpy(feats), torch.from_numpy(idx)).numpy()
    padded = np.concatenate([feats, np.zeros((1, 5), np.float32)])
    np.testing.assert_array_equal(got, padded[idx])


@pytest.mark.parametrize("m", [40, 3, 2, 0])
def test_three_nn_interpolate_matches_reference(m):
    rng = np.random.default_rng(m)
    unknown = rng.uniform(-5, 5, (60, 3))
    known = rng.uniform(-5, 5, (m, 3))
    feats = rng.normal(size=(m, 4))
    got = three_nn_interpolate(*(torch.from_numpy(a).float() for a in (unknown, known, feats)))
    expected = np.zeros((60, 4))
    for i, u in enumerate(unknown):
        d = np.sqrt(((known - u) ** 2).sum(1))
        nn3 = np.argsort(d)[:3]
        w = 1.0 / np.maximum(d[nn3], 1e-8)
        # missing neighbours are padding points 1e4 m away with zero features
        w_pad = np.full(3 - len(nn3), 1.0 / np.linalg.norm(u - 1e4))
        expected[i] = (w[:, None] * feats[nn3]).sum(0) / (w.sum() + w_pad.sum())
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-4, atol=1e-5)


def test_three_nn_interpolate_floors_coincident_points():
    rng = np.random.default_rng(3)
    known = rng.uniform(-5, 5, (20, 3)).astype(np.float32)
    feats = rng.normal(size=(20, 4)).astype(np.float32)
    unknown = np.concatenate([known[:5], rng.uniform(-5, 5, (40, 3))]).astype(np.float32)
    got = three_nn_interpolate(*(torch.from_numpy(a) for a in (unknown, known, feats))).numpy()
    for i, u in enumerate(unknown.astype(np.float64)):
        d = np.sqrt(((known - u) ** 2).sum(1))
        nn3 = np.argsort(d, kind="stable")[:3]
        w = 1.0 / np.maximum(d[nn3], 1e-8)
        np.testing.assert_allclose(got[i], (feats[nn3] * (w / w.sum())[:, None]).sum(0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(got[:5], feats[:5], atol=1e-5)  # a known point keeps its features
    empty = three_nn_interpolate(torch.from_numpy(unknown), torch.zeros(0, 3), torch.zeros(0, 4))
    assert (empty == 0).all()


def test_set_abstraction_matches_reference():
    torch.manual_seed(0)
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-3, 3, (120, 3)).astype(np.float32)
    feats = rng.normal(size=(120, 2)).astype(np.float32)
    centres = np.concatenate([xyz[:10], [[50.0, 50.0, 50.0]]]).astype(np.float32)  # last: empty
    sa = SetAbstraction(2, radii=[0.8, 1.6], nsamples=[4, 8], mlps=[[8], [6, 5]]).eval()
    got = sa(torch.from_numpy(xyz), torch.from_numpy(feats), torch.from_numpy(centres)).detach()
    assert got.shape == (11, 13)
    outs = []
    for radius, nsample, mlp in zip(sa.radii, sa.nsamples, sa.mlps):
        idx, valid = ball_query_reference(xyz, centres, radius, nsample)
        block = np.zeros((len(centres), mlp[-3].out_features), np.float32)
        for m in np.flatnonzero(valid):
            grouped = np.concatenate([xyz[idx[m]] - centres[m], feats[idx[m]]], 1)
            block[m] = mlp(torch.from_numpy(grouped)).detach().numpy().max(0)
        outs.append(block)
    np.testing.assert_allclose(got.numpy(), np.concatenate(outs, 1), rtol=1e-5, atol=1e-6)
    assert np.all(got.numpy()[-1] == 0)


def test_feature_propagation_shapes_and_train_step():
    torch.manual_seed(0)
    fp = FeaturePropagation([4 + 2, 8, 8])
    out = fp(torch.rand(30, 3), torch.rand(6, 3), torch.rand(30, 2), torch.rand(6, 4))
    assert out.shape == (30, 8)
    out.sum().backward()
    assert fp.mlp[0].weight.grad is not None


class _FpsBall(torch.nn.Module):
    def forward(self, points):
        xyz = points[:, :3]
        keep = farthest_point_sample(xyz, 32)  # (K,)
        centres = torch.index_select(xyz, 0, keep)
        idx, valid = ball_query(xyz, centres, 2.0, 8)
        return keep, idx, valid


def test_fps_and_ball_query_export_to_onnx(tmp_path):
    model = _FpsBall()
    n = torch.export.Dim("n", min=0)
    program = torch.export.export(model, (torch.rand(100, 4),), dynamic_shapes=({0: n},),
                                  strict=False)
    onnx_program = torch.onnx.export(program, dynamo=True, verbose=False)
    path = tmp_path / "fps_ball.onnx"
    onnx_program.save(str(path))
    ops = {node.op_type for node in onnx_program.model_proto.graph.node}
    assert "Loop" in ops and "TopK" in ops
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    for n_points in (500, 40, 1, 0):
        pts = rng.uniform(-10, 10, (n_points, 4)).astype(np.float32)
        got = session.run(None, {session.get_inputs()[0].name: pts})
        want = model(torch.from_numpy(pts))
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w.numpy())


def test_point_batch_norm_matches_batchnorm1d():
    torch.manual_seed(0)
    ours, ref = PointBatchNorm(6), torch.nn.BatchNorm1d(6)
    x = torch.randn(5, 7, 6)
    for _ in range(3):  # training: batch statistics over every row, running stats updated alike
        np.testing.assert_allclose(ours(x).detach().numpy(),
                                   ref(x.reshape(-1, 6)).reshape(5, 7, 6).detach().numpy(), atol=1e-5)
    ours.eval(), ref.eval()
    x = torch.randn(9, 6) * 3 + 1
    np.testing.assert_allclose(ours(x).detach().numpy(), ref(x).detach().numpy(), atol=1e-5)
    ours.train()
    assert ours(torch.randn(1, 6)).shape == (1, 6)  # one row: running statistics, no error


def _profile_balls() -> list[tuple[float, int]]:
    """Every (radius, nsample) a ball query runs with in any profile of PointRCNN and PV-RCNN."""
    from models import zoo
    balls = set()
    for profile in zoo.PROFILES:
        rcnn, pv = zoo.config("point_rcnn", profile), zoo.config("pv_rcnn", profile)
        for radii, nsamples in zip(rcnn.sa_radii, rcnn.sa_nsamples):
            balls.update(zip(radii, nsamples))
        balls.update((radius, nsample) for _, radius, nsample, _ in rcnn.rcnn_sa if nsample)
        balls.update(zip(pv.raw_radii, pv.raw_nsamples))
        balls.update(zip(pv.grid_radii, pv.grid_nsamples))
        for radii in pv.level_radii:
            balls.update(zip(radii, pv.level_nsamples))
    return sorted(balls)


def _dense_cloud_70m(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """(n, 3) float32 points 70 m out: a car's surface sampled at ~1 cm (hundreds of points within
    0.4 m), ground and scattered returns, in shuffled index order (balls mix near and far points)."""
    surface = rng.uniform([-2.0, -0.9, 0.0], [2.0, 0.9, 1.5], (n // 2, 3)) * [1.0, 1.0, 1.0]
    surface[: n // 4, 1] = 0.9  # a side face: a dense plane
    ground = np.column_stack([rng.uniform(-8, 8, (n // 4, 2)), np.full(n // 4, -0.3)])
    scatter = rng.normal(0, 2.0, (n - n // 2 - n // 4, 3))
    cloud = np.concatenate([surface, ground, scatter]) + [70.0, 12.0, -1.4]
    return cloud[rng.permutation(n)].astype(np.float32)


def _ball_reference_all(xyz: np.ndarray, centres: np.ndarray, radius: float, nsample: int):
    """Vectorised :func:`ball_query_reference`: direct float32 (c - x)^2 sums."""
    inside = ((centres[:, None, :] - xyz[None, :, :]) ** 2).sum(-1) < np.float32(radius * radius)  # (M, N)
    idx = np.full((len(centres), nsample), len(xyz), dtype=np.int64)
    for m in range(len(centres)):
        chosen = np.flatnonzero(inside[m])[:nsample].tolist()
        if chosen:
            idx[m] = chosen + [chosen[0]] * (nsample - len(chosen))
    return idx, inside.any(1)


def test_ball_queries_at_every_profile_radius_70m_out_match_brute_force():
    """A dense ball far out gets its first neighbours, not points just outside the radius (a
    candidate band sized from 70 m coordinates once gave 8 of 402 neighbours)."""
    rng = np.random.default_rng(47)
    xyz = _dense_cloud_70m(rng)
    centres = xyz[rng.choice(len(xyz), 300, replace=False)] + rng.normal(0, 0.02, (300, 3)).astype(np.float32)
    balls = _profile_balls()
    assert {0.1, 0.4} <= {r for r, _ in balls}  # the kitti radii are among them
    out = ball_queries(torch.from_numpy(xyz), torch.from_numpy(centres), *zip(*balls))
    full = 0
    for (idx, valid), (radius, nsample) in zip(out, balls):
        ref_idx, ref_valid = _ball_reference_all(xyz, centres, radius, nsample)
        np.testing.assert_array_equal(idx.numpy(), ref_idx, err_msg=f"radius {radius} nsample {nsample}")
        np.testing.assert_array_equal(valid.numpy(), ref_valid)
        full += int((ref_idx[:, -1] != ref_idx[:, 0]).sum())
    assert full > 0  # the test holds balls with more neighbours than slots


class _Balls(torch.nn.Module):
    def __init__(self, balls):
        super().__init__()
        self.radii, self.nsamples = zip(*balls)

    def forward(self, xyz, centres):
        return [t for pair in ball_queries(xyz, centres, self.radii, self.nsamples) for t in pair]


def test_ball_queries_70m_out_export_to_onnx_like_brute_force(tmp_path):
    rng = np.random.default_rng(48)
    xyz = _dense_cloud_70m(rng, 3000)
    centres = xyz[:200] + rng.normal(0, 0.02, (200, 3)).astype(np.float32)
    balls = _profile_balls()
    model = _Balls(balls)
    shapes = ({0: torch.export.Dim("n", min=0)}, {0: torch.export.Dim("m", min=0)})
    program = torch.export.export(model, (torch.rand(100, 3), torch.rand(10, 3)), dynamic_shapes=shapes,
                                  strict=False)
    path = tmp_path / "balls.onnx"
    torch.onnx.export(program, dynamo=True, verbose=False).save(str(path))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {session.get_inputs()[0].name: xyz, session.get_inputs()[1].name: centres})
    for k, (radius, nsample) in enumerate(balls):
        ref_idx, ref_valid = _ball_reference_all(xyz, centres, radius, nsample)
        np.testing.assert_array_equal(got[2 * k], ref_idx, err_msg=f"radius {radius} nsample {nsample}")
        np.testing.assert_array_equal(got[2 * k + 1], ref_valid)
