import numpy as np
import torch

from models.vfe import MeanVFE, PillarVFE, scatter_max_nonneg, scatter_mean
from models.voxelize import Grid, dynamic_voxelize

GRID = Grid((0.0, -4.0, -3.0, 8.0, 4.0, 1.0), (0.5, 0.5, 4.0))


def test_scatter_mean_and_max_match_loops():
    rng = np.random.default_rng(0)
    vals = rng.random((200, 3)).astype(np.float32)
    idx = rng.integers(0, 30, 200)
    mean = scatter_mean(torch.from_numpy(vals), torch.from_numpy(idx), 32).numpy()
    mx = scatter_max_nonneg(torch.from_numpy(vals), torch.from_numpy(idx), 32).numpy()
    for g in range(32):
        rows = vals[idx == g]
        ref_mean = rows.mean(0) if len(rows) else np.zeros(3)
        ref_max = rows.max(0) if len(rows) else np.zeros(3)
        np.testing.assert_allclose(mean[g], ref_mean, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(mx[g], ref_max)


def test_mean_vfe_and_pillar_decoration():
    rng = np.random.default_rng(1)
    pts = torch.from_numpy((rng.random((400, 4)) * [8, 8, 4, 1] + [0, -4, -3, 0]).astype(np.float32))
    vox = dynamic_voxelize(pts, GRID)
    feats = MeanVFE()(vox).numpy()
    pillar = PillarVFE(GRID, 8)
    dec = pillar.decorate(vox).numpy()
    for i, (z, y, x) in enumerate(vox.coords.tolist()):
        rows = vox.points[vox.point2voxel == i].numpy()
        np.testing.assert_allclose(feats[i], rows.mean(0), rtol=1e-5, atol=1e-6)
        sel = (vox.point2voxel == i).numpy()
        centre = np.array([x + 0.5, y + 0.5, z + 0.5]) * GRID.voxel_size + np.array(GRID.pc_range[:3])
        np.testing.assert_allclose(dec[sel, 4:7], rows[:, :3] - rows[:, :3].mean(0), atol=1e-5)
        np.testing.assert_allclose(dec[sel, 7:10], rows[:, :3] - centre, atol=1e-5)
    pillar.eval()
    out = pillar(vox).detach().numpy()
    per_point = torch.relu(pillar.norm(pillar.linear(torch.from_numpy(dec)))).detach().numpy()
    for i in range(vox.num_voxels):
        np.testing.assert_allclose(out[i], per_point[(vox.point2voxel == i).numpy()].max(0), rtol=1e-6)


def test_voxel_max_uses_slots_of_hard_voxels():
    from models.vfe import voxel_max_nonneg
    from models.voxelize import hard_voxelize

    rng = np.random.default_rng(2)
    pts = torch.from_numpy((rng.random((3000, 4)) * [8, 8, 4, 1] + [0, -4, -3, 0]).astype(np.float32))
    for cap in (1, 3, 40):
        vox = hard_voxelize(pts, GRID, cap, 10000)
        vals = torch.from_numpy(rng.random((vox.points.shape[0], 5)).astype(np.float32))
        with torch.no_grad():
            got = voxel_max_nonneg(vals, vox).numpy()  # inference: the dense slot form
        for i in range(vox.num_voxels):
            np.testing.assert_array_equal(got[i], vals[(vox.point2voxel == i).numpy()].numpy().max(0))


def test_voxel_max_of_dynamic_voxels_matches_loop():
    """Dynamic voxels: chunks of DENSE_SLOTS points densely, the points past CHUNKS chunks scattered."""
    from models.vfe import CHUNKS, DENSE_SLOTS, voxel_max_nonneg
    from models.voxelize import dynamic_voxelize

    rng = np.random.default_rng(3)
    # 3000 points in 256 voxels: several chunks per voxel; in a 1 m cube: past the dense chunks
    for n, extent in ((0, 8), (40, 8), (3000, 8), (3000, 1)):
        pts = torch.from_numpy((rng.random((n, 4)) * [extent, extent, extent / 2, 1] + [0, -4, -3, 0]).astype(np.float32))
        vox = dynamic_voxelize(pts, GRID)
        slot = vox.slot
        vals = torch.from_numpy(rng.random((vox.points.shape[0], 5)).astype(np.float32))
        with torch.no_grad():
            got = voxel_max_nonneg(vals, vox).numpy()
        assert n < 3000 or (slot >= (DENSE_SLOTS if extent == 8 else DENSE_SLOTS * CHUNKS)).any()
        for i in range(vox.num_voxels):
            members = (vox.point2voxel == i).numpy()
            np.testing.assert_array_equal(got[i], vals[members].numpy().max(0))
            assert slot[members].tolist() == list(range(members.sum()))  # input order


def test_voxel_max_training_form_matches_slot_form_with_gradients():
    from models.vfe import slot_max, voxel_max_nonneg
    from models.voxelize import hard_voxelize

    rng = np.random.default_rng(5)
    pts = torch.from_numpy((rng.random((3000, 4)) * [8, 8, 4, 1] + [0, -4, -3, 0]).astype(np.float32))
    for cap in (1, 3, 40):
        vox = hard_voxelize(pts, GRID, cap, 10000)
        upstream = torch.from_numpy(rng.standard_normal((vox.num_voxels, 5)).astype(np.float32))
        base = torch.from_numpy(rng.random((vox.points.shape[0], 5)).astype(np.float32))
        outs, grads = [], []
        def dense(v, vox):
            t = vox.max_points
            return slot_max(v, vox.point2voxel * t + vox.slot, torch.arange(len(v)), vox.num_voxels, t)

        for form in (voxel_max_nonneg, dense):  # under autograd voxel_max_nonneg scatters
            vals = base.clone().requires_grad_(True)
            out = form(vals, vox)
            (out * upstream).sum().backward()
            outs.append(out.detach())
            grads.append(vals.grad)
        torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0)
        torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=0)


def test_row_batch_norm_trains_on_one_or_no_row():
    """Fewer than two rows in training (a RoI grid with one occupied cell): the running statistics
    normalise, as in inference, and stay as they were; two or more rows train as BatchNorm1d."""
    from models.vfe import RowBatchNorm
    bn = RowBatchNorm(3)
    bn.running_mean.copy_(torch.tensor([1.0, -2.0, 0.5]))
    bn.running_var.copy_(torch.tensor([4.0, 1.0, 0.25]))
    bn.train()
    x = torch.tensor([[3.0, -1.0, 1.0]])
    want = (x - bn.running_mean) / torch.sqrt(bn.running_var + bn.eps)
    torch.testing.assert_close(bn(x), want)
    assert bn(torch.zeros(0, 3)).shape == (0, 3)
    torch.testing.assert_close(bn.running_mean, torch.tensor([1.0, -2.0, 0.5]))
    rows = torch.randn(16, 3)
    ref = torch.nn.BatchNorm1d(3)
    ref.load_state_dict(bn.state_dict())
    ref.train()
    torch.testing.assert_close(bn(rows), ref(rows))
