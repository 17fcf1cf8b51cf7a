import math

import numpy as np
import pytest
import torch

from harness.core.types import Sample
from models.base import reset_norm_statistics
from models.export import export_onnx, integer_extremes, run_onnx
from models.mvx_net import CONFIGS, MVXNet, build
from models.voxelize import dynamic_voxelize

CFG = CONFIGS["tiny"]
H, W = CFG.image_hw


pytestmark = pytest.mark.usefixtures("one_thread")


def camera_matrix():
    """Camera 0.5 m above the LiDAR looking along +x; image H x W."""
    k = np.array([[60.0, 0, W / 2, 0], [0, 60.0, H / 2, 0], [0, 0, 1, 0]])
    lidar_to_cam = np.array([[0, -1, 0, 0], [0, 0, -1, 0.5], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=float)
    m = np.eye(4)
    m[:3] = k @ lidar_to_cam
    return m.astype(np.float32)


def tiny_scene(rng, n_cars=1, frame_id="000000"):
    """Ground plus points on the surfaces of cars inside the tiny range; a matching image."""
    ground = np.stack([rng.uniform(0, 16, 400), rng.uniform(-8, 8, 400), np.full(400, -1.7)], 1)
    boxes = np.array([[6 + 5 * i + rng.uniform(-1, 1), rng.uniform(-3, 3), -0.9, 4.5, 1.8, 1.6,
                       rng.uniform(-0.3, 0.3)] for i in range(n_cars)], np.float32).reshape(-1, 7)
    car_pts = []
    for b in boxes:
        local = rng.uniform(-0.5, 0.5, (200, 3)) * b[3:6]
        face = rng.integers(0, 3, 200)
        local[np.arange(200), face] = np.sign(local[np.arange(200), face]) * b[3 + face] / 2
        c, s = math.cos(b[6]), math.sin(b[6])
        car_pts.append(local @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + b[:3])
    xyz = np.concatenate([ground, *car_pts]).astype(np.float32)
    points = np.concatenate([xyz, rng.uniform(0, 1, (len(xyz), 1))], 1).astype(np.float32)
    image = rng.uniform(0, 1, (3, H, W)).astype(np.float32)
    return Sample(frame_id, points, boxes, np.array(["Car"] * len(boxes)), image, camera_matrix())


def test_build_and_missing_camera():
    with pytest.raises(ValueError, match="unknown profile"):
        build("huge")
    model = build("tiny")
    assert isinstance(model, MVXNet) and model.uses_camera and model.input_names == ("points", "image", "lidar2img")
    sample = tiny_scene(np.random.default_rng(0))
    sample.image = None
    with pytest.raises(ValueError, match="no camera image"):
        model.loss([sample])


def test_image_reaches_only_points_in_view():
    """Voxel features depend on the image for points in view and not for points behind it."""
    torch.manual_seed(0)
    model = build("tiny").eval()
    rng = np.random.default_rng(1)
    m = torch.from_numpy(camera_matrix())
    front = torch.tensor([[8.0, 0.0, -0.5, 0.5], [8.1, 0.2, -0.4, 0.3]])
    behind = front.clone()
    behind[:, 0] = torch.tensor([0.02, 0.05])  # in range, but closer to the camera plane than MIN_DEPTH
    img_a, img_b = (torch.from_numpy(rng.uniform(0, 1, (1, 3, H, W)).astype(np.float32)) for _ in range(2))

    def voxel_feats(points, image):
        with torch.no_grad():
            feats = model.image_branch(image)
            return model.vfe(dynamic_voxelize(points, model.grid), feats, m, (H, W))

    assert not torch.allclose(voxel_feats(front, img_a), voxel_feats(front, img_b))
    torch.testing.assert_close(voxel_feats(behind, img_a), voxel_feats(behind, img_b))


def test_forward_shapes_and_loss_falls():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = build("tiny")
    scenes = [tiny_scene(rng, 2, str(i)) for i in range(2)]
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(10):
        out = model.loss(scenes)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(float(out["loss"].detach()))
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])
    model.eval()
    s = scenes[0]
    with torch.no_grad():
        boxes, scores = model(torch.from_numpy(s.points), torch.from_numpy(s.image)[None], torch.from_numpy(s.lidar2img))
    assert boxes.shape[1] == 7 and scores.shape == boxes.shape[:1]


def calibrate_norms(model, scenes):
    """BatchNorm running statistics = averages over train-mode passes on the scenes."""
    reset_norm_statistics(model)  # cumulative average of the passes below
    model.train()
    with torch.no_grad():
        for s in scenes:
            model.backbone2d(model.bev(torch.from_numpy(s.points), torch.from_numpy(s.image)[None], torch.from_numpy(s.lidar2img)))
    model.eval()


def spread_scores(model, image, lidar2img, gen):
    """Large random class-layer weights and a bias that puts every anchor of an empty cloud at
    logit <= -3, like a trained head: empty cells stay below the score threshold and cells
    near points get scores spread over (0, 1) (a fresh head scores every anchor ~0.01, where
    float noise alone reorders near-ties)."""
    cls = model.head.conv_cls
    with torch.no_grad():
        cls.weight.copy_(torch.randn(cls.weight.shape, generator=gen) * 3 / cls.weight.shape[1] ** 0.5)
        empty = model.head(model.backbone2d(model.bev(torch.zeros(0, 4), image, lidar2img)))[0]  # (A,)
        cls.bias -= empty.reshape(-1, cls.bias.shape[0]).max(dim=0).values + 3.0


def test_onnx_matches_torch(tmp_path):
    torch.manual_seed(0)
    rng = np.random.default_rng(2)
    model = build("tiny")
    s = tiny_scene(rng, 2)
    calibrate_norms(model, [s, tiny_scene(rng, 1)])
    spread_scores(model, torch.from_numpy(s.image)[None], torch.from_numpy(s.lidar2img), torch.Generator().manual_seed(4))
    path = tmp_path / "mvx_net.onnx"
    export_onnx(model, path, {"sotif.profile": "tiny"})
    outside = np.concatenate([rng.uniform([0, -8, -3], [1, 8, 1], (50, 3)), rng.uniform(0, 1, (50, 1))], 1)
    side = np.concatenate([rng.uniform([2, 6, -3], [4, 8, 1], (50, 3)), rng.uniform(0, 1, (50, 1))], 1)
    clouds = [s.points, s.points[::5], np.concatenate([rng.uniform([0, -8, -3], [16, 8, 1], (300, 3)),
              rng.uniform(0, 1, (300, 1))], 1), outside, side, np.zeros((0, 4))]
    counts = []
    for cloud in clouds:
        cloud = cloud.astype(np.float32)
        inputs = (cloud, s.image[None], s.lidar2img)
        got = run_onnx(path, *inputs)
        with torch.no_grad():
            ref = [t.numpy() for t in model(*(torch.from_numpy(x) for x in inputs))]
        assert got[0].shape == ref[0].shape
        counts.append(len(ref[0]))
        np.testing.assert_allclose(got[1], ref[1], atol=1e-4)
        np.testing.assert_allclose(rows(got[0]), rows(ref[0]), atol=1e-3, rtol=1e-4)
    assert counts[0] > 0 and counts[-1] == 0  # boxes reach the outputs; none from an empty cloud
    inputs = (clouds[0].astype(np.float32), s.image[None], s.lidar2img)
    assert max(integer_extremes(path, *inputs).values()) < 2 ** 31  # OpenVINO computes int64 in int32


def rows(boxes):
    """Boxes in lexicographic order: equal scores may come out in either order."""
    return boxes[np.lexsort(boxes.T[::-1])]


def test_cached_export_equals_its_fresh_export(tmp_path):
    """The cached graph filled with other weights gives a fresh export's bytes (tests/models/test_export.py):
    test_onnx_matches_torch's export filled the cache, so only the fresh export traces."""
    from tests.models.test_export import cached_export_equals_fresh
    cached_export_equals_fresh(tmp_path, "mvx_net")
