import numpy as np
import onnxruntime as ort
import pytest
import torch

from models.box_frame import inside_boxes
from models.point_roi_pool import RoISetAbstraction, roi_point_pool
from models.pointnet2 import ball_queries, farthest_point_sample


pytestmark = pytest.mark.usefixtures("one_thread")


def brute_force_pool(xyz, feats, rois, num_samples, extra_width):
    """Per RoI, per point loops in float64: enlarged-box test, cyclic sampling, canonical frame."""
    k, c = len(rois), feats.shape[1]
    pooled, empty = np.zeros((k, num_samples, 3 + c)), np.zeros(k, bool)
    for r, (cx, cy, cz, l, w, h, yaw) in enumerate(rois):
        members = []
        for i, (px, py, pz) in enumerate(xyz):
            dx, dy, dz = px - cx, py - cy, pz - cz
            lx = dx * np.cos(yaw) + dy * np.sin(yaw)
            ly = -dx * np.sin(yaw) + dy * np.cos(yaw)
            if abs(lx) < (l + extra_width) / 2 and abs(ly) < (w + extra_width) / 2 and abs(dz) < (h + extra_width) / 2:
                members.append((i, lx, ly, dz))
        if not members:
            empty[r] = True
            continue
        for j in range(num_samples):
            i, lx, ly, dz = members[j % len(members)]
            pooled[r, j] = np.concatenate([[lx, ly, dz], feats[i]])
    return pooled, empty


def random_case(rng, n, k):
    xyz = rng.uniform([-10, -10, -2], [10, 10, 2], (n, 3))
    feats = rng.normal(size=(n, 2))
    centres = xyz[rng.integers(0, max(n, 1), k)] if n else rng.uniform(-5, 5, (k, 3))
    rois = np.concatenate(
        [centres + rng.normal(0, 0.5, (k, 3)), rng.uniform([1, 0.5, 0.5], [5, 3, 2], (k, 3)), rng.uniform(-np.pi, np.pi, (k, 1))], 1
    )
    return xyz.astype(np.float32), feats.astype(np.float32), rois.astype(np.float32)


@pytest.mark.parametrize("seed,n,k,s", [(0, 300, 12, 16), (1, 40, 5, 8), (2, 0, 3, 4), (3, 200, 0, 8), (4, 2000, 20, 64)])
def test_roi_point_pool_matches_brute_force(seed, n, k, s):
    rng = np.random.default_rng(seed)
    xyz, feats, rois = random_case(rng, n, k)
    got, empty = roi_point_pool(torch.from_numpy(xyz), torch.from_numpy(feats), torch.from_numpy(rois), s, 1.0)
    ref, ref_empty = brute_force_pool(xyz.astype(np.float64), feats, rois.astype(np.float64), s, 1.0)
    assert got.shape == (k, s, 5)
    np.testing.assert_array_equal(empty.numpy(), ref_empty)
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-4, atol=1e-4)
    if k and n:
        assert (~ref_empty).any()  # the case exercises real pooling, not only empty RoIs


def test_canonical_frame_of_a_rotated_box():
    """A point 1 m ahead of a box heading +y sits at canonical x = +1."""
    rois = torch.tensor([[5.0, 5.0, 0.0, 4.0, 2.0, 1.5, np.pi / 2]])
    xyz = torch.tensor([[5.0, 6.0, 0.2], [7.5, 5.0, 0.0]])
    pooled, empty = roi_point_pool(xyz, torch.zeros(2, 0), rois, 2, 0.0)
    assert not empty[0]
    np.testing.assert_allclose(pooled[0, 0].numpy(), [1.0, 0.0, 0.2], atol=1e-6)
    np.testing.assert_allclose(pooled[0, 1].numpy(), [1.0, 0.0, 0.2], atol=1e-6)  # cyclic repeat
    assert inside_boxes(xyz, rois).tolist() == [[True, False]]


class Pool(torch.nn.Module):
    def forward(self, points, rois):
        return roi_point_pool(points[:, :3], points[:, 3:], rois, 16, 0.5)


def test_roi_point_pool_onnx_matches_torch(tmp_path):
    path = tmp_path / "pool.onnx"
    dims = {"points": {0: torch.export.Dim("n", min=0)}, "rois": {0: torch.export.Dim("k", min=0)}}
    torch.onnx.export(Pool().eval(), (torch.rand(50, 5), torch.rand(4, 7) + 1), str(path), dynamo=True,
                      input_names=["points", "rois"], dynamic_shapes=dims)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for seed, n, k in [(0, 500, 10), (1, 0, 3), (2, 30, 0), (3, 1, 2)]:
        xyz, feats, rois = random_case(np.random.default_rng(seed), n, k)
        points = np.concatenate([xyz, feats], 1)
        got = sess.run(None, {"points": points, "rois": rois})
        ref = Pool()(torch.from_numpy(points), torch.from_numpy(rois))
        np.testing.assert_allclose(got[0], ref[0].numpy(), rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(got[1], ref[1].numpy())


def numpy_fps(xyz, num):
    idx, dist = [0], np.full(len(xyz), np.inf)
    for _ in range(1, num):
        dist = np.minimum(dist, ((xyz - xyz[idx[-1]]) ** 2).sum(1))
        idx.append(int(np.argmax(dist)))
    return idx


def numpy_ball_query(xyz, centre, radius, nsample):
    inside = [i for i in range(len(xyz)) if ((xyz[i] - centre) ** 2).sum() < radius**2]
    return (inside + [inside[0]] * nsample)[:nsample]


def test_batched_fps_and_ball_query_match_numpy():
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-2, 2, (6, 40, 3)).astype(np.float32)
    idx = farthest_point_sample(torch.from_numpy(xyz), 10).numpy()
    for k in range(6):
        assert idx[k].tolist() == numpy_fps(xyz[k].astype(np.float64), 10)
    centres = xyz[np.arange(6)[:, None], idx]  # (6, 10, 3)
    ball = ball_queries(torch.from_numpy(xyz), torch.from_numpy(centres), (1.2,), (8,))[0][0].numpy()
    for k in range(6):
        for m in range(10):
            assert ball[k, m].tolist() == numpy_ball_query(xyz[k], centres[k, m], 1.2, 8)


def test_roi_set_abstraction_matches_per_roi_loop():
    torch.manual_seed(0)
    rng = np.random.default_rng(6)
    xyz = torch.from_numpy(rng.uniform(-2, 2, (4, 32, 3)).astype(np.float32))
    feats = torch.from_numpy(rng.normal(size=(4, 32, 5)).astype(np.float32))
    sa = RoISetAbstraction(8, 1.0, 6, [5, 16, 12]).eval()
    centres, out = sa(xyz, feats)
    for k in range(4):
        idx = numpy_fps(xyz[k].double().numpy(), 8)
        np.testing.assert_allclose(centres[k].numpy(), xyz[k, idx].numpy())
        for m, c in enumerate(idx):
            ball = numpy_ball_query(xyz[k].numpy(), xyz[k, c].numpy(), 1.0, 6)
            grouped = torch.cat([xyz[k, ball] - xyz[k, c], feats[k, ball]], 1)  # (6, 8)
            ref = sa.mlp(grouped).amax(0)
            torch.testing.assert_close(out[k, m], ref, rtol=1e-5, atol=1e-5)
    group_all = RoISetAbstraction(None, 0.0, 0, [5, 8]).eval()
    _, pooled = group_all(xyz, feats)
    torch.testing.assert_close(pooled[:, 0], group_all.mlp(torch.cat([xyz, feats], -1)).amax(1))


class RoISA(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.sa = RoISetAbstraction(8, 1.0, 6, [2, 8])

    def forward(self, xyz, feats):
        return self.sa(xyz, feats)


def test_roi_set_abstraction_onnx_matches_torch(tmp_path):
    torch.manual_seed(0)
    model, path = RoISA().eval(), tmp_path / "sa.onnx"
    k = torch.export.Dim("k", min=0)
    torch.onnx.export(model, (torch.rand(3, 16, 3), torch.rand(3, 16, 2)), str(path), dynamo=True,
                      input_names=["xyz", "feats"], dynamic_shapes=({0: k}, {0: k}))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(7)
    for k in (5, 1, 0):
        xyz, feats = rng.uniform(-2, 2, (k, 16, 3)).astype(np.float32), rng.normal(size=(k, 16, 2)).astype(np.float32)
        got = sess.run(None, {"xyz": xyz, "feats": feats})
        with torch.no_grad():
            ref = model(torch.from_numpy(xyz), torch.from_numpy(feats))
        np.testing.assert_allclose(got[0], ref[0].numpy(), atol=1e-6)
        np.testing.assert_allclose(got[1], ref[1].numpy(), rtol=1e-5, atol=1e-5)
