import numpy as np
import onnxruntime as ort
import pytest
import torch

from models.image_branch import (
    MIN_DEPTH,
    ImageBranch,
    ImageBranchConfig,
    PointFusion,
    PointFusionConfig,
    bilinear_sample,
    project_points,
    visible_mask,
)


pytestmark = pytest.mark.usefixtures("one_thread")


def numpy_project(xyz, lidar2img):
    out = np.zeros((len(xyz), 2)), np.zeros(len(xyz))
    for i, p in enumerate(xyz):
        q = lidar2img @ np.append(p, 1.0)
        out[1][i] = q[2]
        if q[2] >= MIN_DEPTH:
            out[0][i] = q[:2] / q[2]
    return out


def numpy_bilinear(feat, uv, depth, image_hw):
    """Per-point loop: level coordinate, border clamp, 4 neighbours; zero outside / behind."""
    c, hl, wl = feat.shape
    out = np.zeros((len(uv), c))
    for i, (u, v) in enumerate(uv):
        if depth[i] < MIN_DEPTH or not (0 <= u < image_hw[1] and 0 <= v < image_hw[0]):
            continue
        x = min(max(u * wl / image_hw[1] - 0.5, 0.0), wl - 1)
        y = min(max(v * hl / image_hw[0] - 0.5, 0.0), hl - 1)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        for xx, wx in ((x0, 1 - (x - x0)), (min(x0 + 1, wl - 1), x - x0)):
            for yy, wy in ((y0, 1 - (y - y0)), (min(y0 + 1, hl - 1), y - y0)):
                out[i] += wx * wy * feat[:, yy, xx]
    return out


def camera_matrix():
    """KITTI-like camera looking along +x of the LiDAR, 1.0 m up, image 40 x 64."""
    k = np.array([[50.0, 0, 32, 0], [0, 50.0, 20, 0], [0, 0, 1, 0]])
    lidar_to_cam = np.array([[0, -1, 0, 0], [0, 0, -1, 1.0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=float)
    m = np.eye(4)
    m[:3] = k @ lidar_to_cam
    return m.astype(np.float32)


def random_points(rng, n):
    """Mix of points in front (many inside the image, some outside) and behind the camera."""
    xyz = np.stack([rng.uniform(-10, 40, n), rng.uniform(-30, 30, n), rng.uniform(-3, 3, n)], 1)
    return xyz.astype(np.float32)


def test_project_points_matches_numpy():
    rng = np.random.default_rng(0)
    xyz, m = random_points(rng, 300), camera_matrix()
    uv, depth = project_points(torch.from_numpy(xyz), torch.from_numpy(m))
    ref_uv, ref_depth = numpy_project(xyz.astype(np.float64), m.astype(np.float64))
    np.testing.assert_allclose(depth.numpy(), ref_depth, rtol=1e-5, atol=1e-4)
    front = ref_depth >= MIN_DEPTH
    np.testing.assert_allclose(uv.numpy()[front], ref_uv[front], rtol=1e-4, atol=1e-3)
    assert np.isfinite(uv.numpy()).all()


@pytest.mark.parametrize("seed,hl,wl", [(0, 10, 16), (1, 5, 8), (2, 3, 3), (3, 1, 1)])
def test_bilinear_sample_matches_numpy(seed, hl, wl):
    rng = np.random.default_rng(seed)
    feat = rng.normal(size=(5, hl, wl)).astype(np.float32)
    image_hw = (40, 64)
    uv = np.stack([rng.uniform(-10, 74, 400), rng.uniform(-10, 50, 400)], 1).astype(np.float32)
    uv[:8] = [[0, 0], [63.99, 39.99], [0, 39.5], [63.5, 0], [-0.01, 5], [64, 5], [5, 40], [5, -0.01]]
    depth = rng.uniform(-5, 30, 400).astype(np.float32)
    depth[:8] = 10.0
    vis = visible_mask(torch.from_numpy(uv), torch.from_numpy(depth), *image_hw)
    got = bilinear_sample(torch.from_numpy(feat), torch.from_numpy(uv), vis, image_hw).numpy()
    ref = numpy_bilinear(feat.astype(np.float64), uv.astype(np.float64), depth, image_hw)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    assert (got[4:8] == 0).all() and (got[depth < MIN_DEPTH] == 0).all()
    assert np.abs(got[:4]).sum() > 0


def test_bilinear_matches_grid_sample_inside_the_map():
    """Away from the borders the sampling equals torch's grid_sample(align_corners=False)."""
    rng = np.random.default_rng(4)
    feat = torch.from_numpy(rng.normal(size=(3, 10, 16)).astype(np.float32))
    image_hw = (40, 64)
    uv = torch.from_numpy(np.stack([rng.uniform(4, 60, 200), rng.uniform(4, 36, 200)], 1).astype(np.float32))
    vis = torch.ones(200, dtype=torch.bool)
    got = bilinear_sample(feat, uv, vis, image_hw)
    grid = torch.stack([uv[:, 0] / image_hw[1] * 2 - 1, uv[:, 1] / image_hw[0] * 2 - 1], 1).view(1, 1, -1, 2)
    ref = torch.nn.functional.grid_sample(feat[None], grid, align_corners=False)[0, :, 0].t()
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)


def test_image_branch_shapes_and_fpn_top_down():
    torch.manual_seed(0)
    cfg = ImageBranchConfig(stem_channels=8, stage_channels=(8, 16, 32), fpn_channels=8)
    branch = ImageBranch(cfg).eval()
    feats = branch(torch.rand(1, 3, 48, 80))
    assert [tuple(f.shape) for f in feats] == [(1, 8, 12, 20), (1, 8, 6, 10), (1, 8, 3, 5)]
    # the top-down path carries the coarsest level into the finest one
    x = torch.rand(1, 3, 48, 80)
    c = branch.backbone((x - branch.mean) / branch.std)
    c_alt = [c[0], c[1], c[2] + 1.0]
    assert not torch.allclose(branch.fpn(c)[0], branch.fpn(c_alt)[0])


class FusionModule(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.branch = ImageBranch(ImageBranchConfig(stem_channels=8, stage_channels=(8, 16), fpn_channels=8))
        self.fusion = PointFusion(PointFusionConfig(img_channels=8, num_levels=2, pts_channels=4, mid_channels=8, out_channels=8))

    def forward(self, points, image, lidar2img):
        feats = self.branch(image)
        return self.fusion(feats, points[:, :3], points, lidar2img, tuple(image.shape[-2:]))


def test_point_fusion_zero_image_features_outside_and_behind():
    torch.manual_seed(0)
    model = FusionModule().eval()
    m = torch.from_numpy(camera_matrix())
    pts = torch.tensor([[20.0, 0.0, 0.0, 0.5], [-20.0, 0.0, 0.0, 0.5], [5.0, 30.0, 0.0, 0.5]])
    img_pts = model.fusion.sample_levels(model.branch(torch.rand(1, 3, 40, 64)), pts[:, :3], m, (40, 64))
    assert img_pts[0].abs().sum() > 0
    assert (img_pts[1:] == 0).all()


def test_point_fusion_onnx_matches_torch(tmp_path):
    torch.manual_seed(0)
    model = FusionModule().eval()
    image, m = torch.rand(1, 3, 40, 64), torch.from_numpy(camera_matrix())
    path = tmp_path / "fusion.onnx"
    example = (torch.rand(50, 4) * 20, image, m)
    torch.onnx.export(
        model, example, str(path), dynamo=True, input_names=["points", "image", "lidar2img"],
        dynamic_shapes={"points": {0: torch.export.Dim("n", min=0)}, "image": None, "lidar2img": None},
    )
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for n in (0, 1, 300):
        rng = np.random.default_rng(n)
        xyz = random_points(rng, n)
        points = torch.from_numpy(np.concatenate([xyz, rng.uniform(0, 1, (n, 1))], 1).astype(np.float32))
        (got,) = sess.run(None, {"points": points.numpy(), "image": image.numpy(), "lidar2img": m.numpy()})
        with torch.no_grad():
            ref = model(points, image, m).numpy()
        assert got.shape == (n, 8)
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
