"""RoI-aware and RoI-grid pooling against brute-force loops; ONNX export of RoI-aware pooling."""
from __future__ import annotations

import numpy as np
import onnxruntime as ort
import torch

from models.pointnet2 import ball_query
from models.roi_pool import RoIGridPool, roi_grid_points, roiaware_pool


def random_rois(rng, k):
    centre = rng.uniform(-3, 3, (k, 3))
    size = rng.uniform(1.0, 4.0, (k, 3))
    yaw = rng.uniform(-np.pi, np.pi, (k, 1))
    return np.concatenate([centre, size, yaw], 1).astype(np.float32)


def roiaware_reference(rois, xyz, fmax, favg, out):
    k_n = len(rois)
    pmax = np.zeros((k_n, *out, fmax.shape[1]))
    pavg = np.zeros((k_n, *out, favg.shape[1]))
    for k, (cx, cy, cz, l, w, h, yaw) in enumerate(rois.astype(np.float64)):
        cells: dict[tuple, list[int]] = {}
        for i, (x, y, z) in enumerate(xyz.astype(np.float64)):
            dx, dy = x - cx, y - cy
            lx = dx * np.cos(yaw) + dy * np.sin(yaw)
            ly = -dx * np.sin(yaw) + dy * np.cos(yaw)
            lz = z - cz
            if abs(lx) < l / 2 and abs(ly) < w / 2 and abs(lz) < h / 2:
                cell = tuple(min(int((v + s / 2) / s * o), o - 1)
                             for v, s, o in zip((lx, ly, lz), (l, w, h), out))
                cells.setdefault(cell, []).append(i)
        for cell, members in cells.items():
            pmax[(k, *cell)] = fmax[members].max(0)
            pavg[(k, *cell)] = favg[members].mean(0)
    return pmax, pavg


def test_roiaware_pool_matches_reference():
    rng = np.random.default_rng(0)
    rois = random_rois(rng, 6)
    rois[-1, :3] = 100.0  # an RoI far from every point
    xyz = rng.uniform(-5, 5, (800, 3)).astype(np.float32)
    fmax = rng.normal(size=(800, 4)).astype(np.float32)
    favg = rng.uniform(size=(800, 3)).astype(np.float32)
    out = (3, 4, 2)
    got_max, got_avg = roiaware_pool(*(torch.from_numpy(a) for a in (rois, xyz, fmax, favg)), out)
    ref_max, ref_avg = roiaware_reference(rois, xyz, fmax, favg, out)
    assert got_max.shape == (6, 3, 4, 2, 4) and got_avg.shape == (6, 3, 4, 2, 3)
    assert ref_max[:-1].any() and not ref_max[-1].any()
    np.testing.assert_allclose(got_max.numpy(), ref_max, atol=1e-6)
    np.testing.assert_allclose(got_avg.numpy(), ref_avg, atol=1e-6)


def test_roiaware_pool_empty_inputs():
    rois = torch.from_numpy(random_rois(np.random.default_rng(1), 3))
    got_max, got_avg = roiaware_pool(rois, torch.zeros(0, 3), torch.zeros(0, 5), torch.zeros(0, 2),
                                     (2, 2, 2))
    assert got_max.shape == (3, 2, 2, 2, 5) and not got_max.any() and not got_avg.any()
    got_max, _ = roiaware_pool(torch.zeros(0, 7), torch.rand(10, 3), torch.rand(10, 5),
                               torch.rand(10, 2), (2, 2, 2))
    assert got_max.shape == (0, 2, 2, 2, 5)


def test_roiaware_pool_gradient_reaches_max_features():
    rng = np.random.default_rng(2)
    rois = torch.from_numpy(random_rois(rng, 3))
    xyz = torch.from_numpy(rng.uniform(-3, 3, (300, 3)).astype(np.float32))
    fmax = torch.rand(300, 2, requires_grad=True)
    pmax, _ = roiaware_pool(rois, xyz, fmax, torch.rand(300, 1), (2, 2, 2))
    pmax.sum().backward()
    assert fmax.grad.sum() == (pmax != 0).sum()  # one winner per non-empty cell and channel


def test_roi_grid_points_match_reference():
    rng = np.random.default_rng(3)
    rois = random_rois(rng, 4)
    got = roi_grid_points(torch.from_numpy(rois), 3).numpy()
    for k, (cx, cy, cz, l, w, h, yaw) in enumerate(rois.astype(np.float64)):
        rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        g = 0
        for i in range(3):
            for j in range(3):
                for m in range(3):
                    local = (np.array([i, j, m]) + 0.5) / 3 - 0.5
                    local = local * [l, w, h]
                    xy = rot @ local[:2] + [cx, cy]
                    np.testing.assert_allclose(got[k, g], [*xy, local[2] + cz], atol=1e-5)
                    g += 1


def test_roi_grid_pool_matches_reference():
    torch.manual_seed(0)
    rng = np.random.default_rng(4)
    rois = random_rois(rng, 3)
    kp = rng.uniform(-4, 4, (200, 3)).astype(np.float32)
    feats = rng.normal(size=(200, 5)).astype(np.float32)
    pool = RoIGridPool(5, grid=2, radii=[0.8, 1.6], nsamples=[4, 8], mlps=[[6], [7]]).eval()
    got = pool(*(torch.from_numpy(a) for a in (rois, kp, feats))).detach().numpy()
    assert got.shape == (3, 8, 13)
    centres = roi_grid_points(torch.from_numpy(rois), 2).reshape(-1, 3).numpy()
    ref = np.zeros((len(centres), 13), np.float32)
    col = 0
    for radius, nsample, mlp in zip(pool.sa.radii, pool.sa.nsamples, pool.sa.mlps):
        width = mlp[-3].out_features
        for c, centre in enumerate(centres):
            inside = np.flatnonzero(((kp - centre) ** 2).sum(1) < radius ** 2)[:nsample]
            if len(inside) == 0:
                continue
            idx = np.concatenate([inside, np.repeat(inside[:1], nsample - len(inside))])
            grouped = np.concatenate([kp[idx] - centre, feats[idx]], 1)
            ref[c, col:col + width] = mlp(torch.from_numpy(grouped)).detach().numpy().max(0)
        col += width
    np.testing.assert_allclose(got.reshape(-1, 13), ref, rtol=1e-5, atol=1e-5)
    # the brute-force neighbour lists agree with ball_query's
    idx, valid = ball_query(torch.from_numpy(kp), torch.from_numpy(centres), 0.8, 4)
    assert valid.sum() == sum(((kp - c) ** 2).sum(1).min() < 0.64 for c in centres)


class _Pool(torch.nn.Module):
    def forward(self, points, rois):
        return roiaware_pool(rois, points[:, :3], points[:, 3:], points[:, :3], (2, 3, 2))


def test_roiaware_pool_exports_to_onnx(tmp_path):
    model = _Pool()
    rng = np.random.default_rng(5)
    rois = random_rois(rng, 4)
    dims = ({0: torch.export.Dim("n", min=0)}, {0: torch.export.Dim("k", min=0)})
    program = torch.export.export(model, (torch.rand(50, 4), torch.from_numpy(rois)),
                                  dynamic_shapes=dims, strict=False)
    path = tmp_path / "roiaware.onnx"
    torch.onnx.export(program, dynamo=True, verbose=False).save(str(path))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    for n in (600, 3, 0):
        pts = rng.uniform(-5, 5, (n, 4)).astype(np.float32)
        got = session.run(None, dict(zip(names, (pts, rois))))
        want = model(torch.from_numpy(pts), torch.from_numpy(rois))
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w.numpy(), atol=1e-6)
