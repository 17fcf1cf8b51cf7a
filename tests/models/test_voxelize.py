import numpy as np
import torch

import models.voxelize as voxelize
from models.voxelize import (Grid, dynamic_voxelize, filter_range, group_cells, hard_voxelize, range_mask,
                             unique_cells)

GRID = Grid((0.0, -4.0, -2.0, 8.0, 4.0, 1.0), (0.5, 0.5, 0.75))


def _cloud(rng, n):
    lo, hi = np.array([-1, -5, -3, 0]), np.array([9, 5, 2, 1])
    return torch.from_numpy((rng.random((n, 4)) * (hi - lo) + lo).astype(np.float32))


def _reference(points, grid, max_points=None, max_voxels=None):
    """Plain loop: voxels in order of first appearance, points in input order."""
    pts = points.numpy()
    x0, y0, z0, x1, y1, z1 = grid.pc_range
    groups = {}
    for p in pts:
        if not (x0 <= p[0] < x1 and y0 <= p[1] < y1 and z0 <= p[2] < z1):
            continue
        key = tuple(int(np.floor((p[a] - grid.pc_range[a]) / grid.voxel_size[a])) for a in (2, 1, 0))
        groups.setdefault(key, []).append(p)
    keys = list(groups)[:max_voxels] if max_voxels else list(groups)
    return {k: np.stack(groups[k][:max_points] if max_points else groups[k]) for k in keys}


def _as_dict(vox):
    out = {}
    for i, c in enumerate(vox.coords.tolist()):
        out[tuple(c)] = vox.points[vox.point2voxel == i].numpy()
    return out


def test_range_mask_matches_numpy():
    rng = np.random.default_rng(0)
    pts = _cloud(rng, 500)
    lo, hi = np.array(GRID.pc_range[:3]), np.array(GRID.pc_range[3:])
    ref = ((pts.numpy()[:, :3] >= lo) & (pts.numpy()[:, :3] < hi)).all(1)
    assert np.array_equal(range_mask(pts, GRID.pc_range).numpy(), ref)
    assert filter_range(pts, GRID.pc_range).shape[0] == ref.sum()


def test_unique_cells_matches_torch_unique(monkeypatch):
    rng = np.random.default_rng(3)
    for table_cells in (voxelize.TABLE_CELLS, 0):  # the occupancy table, then the Unique fallback
        monkeypatch.setattr(voxelize, "TABLE_CELLS", table_cells)
        for n, cells in ((0, 10), (1, 10), (500, 64), (3000, 100_000)):
            linear = torch.from_numpy(rng.integers(0, cells, n))
            assert np.array_equal(unique_cells(linear, cells).numpy(), np.unique(linear.numpy()))


def _rank_in_group(group):
    """Rank of every entry among the equal entries before it (a plain loop)."""
    seen, rank = {}, []
    for g in group.tolist():
        rank.append(seen.get(g, 0))
        seen[g] = rank[-1] + 1
    return np.array(rank, dtype=np.int64)


def test_group_cells_matches_numpy_unique(monkeypatch):
    rng = np.random.default_rng(3)
    for graph in (False, True):  # eager stable sort, then the graph's radix passes
        monkeypatch.setattr(voxelize, "tracing", lambda: graph)
        for n, cells in ((0, 10), (1, 10), (500, 64), (3000, 100_000), (4000, 90_000_000)):
            linear = torch.from_numpy(rng.integers(0, cells, n))
            ref_cells, ref_inverse = np.unique(linear.numpy(), return_inverse=True)
            got = group_cells(linear, cells)
            assert np.array_equal(got.cells.numpy(), ref_cells)
            assert np.array_equal(got.inverse.numpy(), ref_inverse.reshape(-1))
            assert np.array_equal(got.rank.numpy(), _rank_in_group(linear.numpy()))


def test_grid_centres_match_numpy():
    rng = np.random.default_rng(7)
    d, h, w = GRID.shape
    coords = np.c_[rng.integers(0, d, 50), rng.integers(0, h, 50), rng.integers(0, w, 50)]  # (z, y, x)
    lo, size = np.array(GRID.pc_range[:3]), np.array(GRID.voxel_size)
    for stride in (1.0, 2.0, np.array([2.0, 4.0, 1.0])):
        ref = (coords[:, ::-1] + 0.5) * size * stride + lo
        got = GRID.centres(torch.from_numpy(coords), torch.as_tensor(stride, dtype=torch.float32))
        assert got.shape == (50, 3)
        np.testing.assert_allclose(got.numpy(), ref, rtol=1e-6, atol=1e-5)
    assert GRID.centres(torch.zeros((0, 3), dtype=torch.long)).shape == (0, 3)


def test_dynamic_voxelize_matches_loop():
    rng = np.random.default_rng(1)
    for n in (0, 1, 300, 2000):
        pts = _cloud(rng, n)
        vox = dynamic_voxelize(pts, GRID)
        ref, got = _reference(pts, GRID), _as_dict(vox)
        assert set(ref) == set(got)
        for k in ref:
            assert np.array_equal(np.sort(ref[k], 0), np.sort(got[k], 0))
        assert vox.shape == (4, 16, 16)


def test_hard_voxelize_caps_like_loop():
    rng = np.random.default_rng(2)
    for n, t, v in ((0, 3, 10), (500, 2, 40), (3000, 5, 100000), (3000, 1, 7)):
        pts = _cloud(rng, n)
        vox = hard_voxelize(pts, GRID, t, v)
        ref, got = _reference(pts, GRID, t, v), _as_dict(vox)
        assert list(ref) == list(got)  # same voxels, same order
        for k in ref:
            assert np.array_equal(ref[k], got[k])  # same points, input order


def test_group_order_radix_passes_equal_a_stable_sort(monkeypatch):
    monkeypatch.setattr(voxelize, "tracing", lambda: True)  # the graph form: int32-sized radix passes
    rng = np.random.default_rng(4)
    for n, groups in ((0, 5), (1, 5), (3000, 7), (5000, 2 ** 11 + 5), (20000, 3_000_000)):
        group = torch.from_numpy(rng.integers(0, groups, n))
        got = voxelize.group_order(group, groups).numpy()
        assert np.array_equal(got, np.argsort(group.numpy(), kind="stable"))
    pts = _cloud(rng, 3000)
    ref, got = _reference(pts, GRID, 2, 40), _as_dict(hard_voxelize(pts, GRID, 2, 40))
    assert list(ref) == list(got) and all(np.array_equal(ref[k], got[k]) for k in ref)
