import numpy as np
import pytest

from harness.augment import AugmentConfig, augment, flip_y, rotate_z, scale
from harness.core.boxes import points_in_boxes
from harness.dataset import synthetic_sample


def _membership(sample):
    grown = sample.gt_boxes.copy()
    grown[:, 3:6] += 0.02
    return points_in_boxes(sample.points, grown)


def test_augment_keeps_points_inside_their_boxes():
    s = synthetic_sample(np.random.default_rng(0))
    before = _membership(s)
    for seed in range(5):
        a = augment(s, np.random.default_rng(seed), AugmentConfig(rotation=np.pi, scale=(0.8, 1.2)))
        assert np.array_equal(_membership(a), before)
        assert a.gt_boxes[:, 6].min() >= -np.pi and a.gt_boxes[:, 6].max() < np.pi


def test_transforms_match_matrices():
    rng = np.random.default_rng(1)
    pts = rng.standard_normal((50, 4)).astype(np.float32)
    boxes = np.array([[5.0, 2.0, -1.0, 4.0, 1.7, 1.5, 0.3]], np.float32)
    p, b = rotate_z(pts, boxes, 0.5)
    rot = np.array([[np.cos(0.5), -np.sin(0.5)], [np.sin(0.5), np.cos(0.5)]])
    np.testing.assert_allclose(p[:, :2], pts[:, :2] @ rot.T, atol=1e-5)
    np.testing.assert_allclose(b[0, 6], 0.8, atol=1e-6)
    p, b = flip_y(pts, boxes)
    assert np.array_equal(p[:, 1], -pts[:, 1]) and np.isclose(b[0, 6], -0.3)
    p, b = scale(pts, boxes, 1.1)
    np.testing.assert_allclose(b[0, :6], boxes[0, :6] * 1.1, rtol=1e-6)
    np.testing.assert_array_equal(p[:, 3], pts[:, 3])


def test_lidar2img_follows_the_points():
    s = synthetic_sample(np.random.default_rng(2))
    l2i = np.array([[700, -600, 0, 10], [0, 0, -700, 5], [1, 0, 0, 0.3], [0, 0, 0, 1]], np.float32)
    s.lidar2img = l2i
    a = augment(s, np.random.default_rng(3))
    hom = lambda p: np.c_[p[:, :3], np.ones(len(p))]
    before, after = hom(s.points) @ l2i.T, hom(a.points) @ a.lidar2img.T
    np.testing.assert_allclose(after[:, :2] / after[:, 2:3], before[:, :2] / before[:, 2:3], rtol=1e-3, atol=1e-2)


def _car_database(seed):
    from harness.gt_database import GtDatabase
    s = synthetic_sample(np.random.default_rng(seed), num_cars=4, extent=30.0, frame_id="db")
    inside = _membership(s)
    parts = [s.points[inside[:, k]] for k in range(len(s.gt_boxes))]
    counts = np.array([len(p) for p in parts])
    return GtDatabase(np.concatenate(parts), np.r_[0, np.cumsum(counts)], s.gt_boxes, s.gt_names,
                      np.array(["db"] * len(counts)), counts, np.zeros(len(counts), int))


def test_gt_sampling_runs_before_the_global_transforms():
    from harness.gt_database import GtSamplingConfig, sample_objects
    db = _car_database(5)
    s = synthetic_sample(np.random.default_rng(6), num_cars=1, extent=30.0)
    a = augment(s, np.random.default_rng(7), AugmentConfig(rotation=np.pi), db)
    assert len(a.gt_boxes) > 1 and len(a.gt_names) == len(a.gt_boxes)
    rng = np.random.default_rng(7)
    pasted = sample_objects(s, db, rng, GtSamplingConfig())
    np.testing.assert_array_equal(augment(pasted, rng, AugmentConfig(rotation=np.pi)).points, a.points)
    assert np.array_equal(_membership(a), _membership(pasted))
    off = AugmentConfig(gt_sampling=GtSamplingConfig(enabled=False))
    np.testing.assert_array_equal(augment(s, np.random.default_rng(8), off, db).points,
                                  augment(s, np.random.default_rng(8), off).points)


def test_gt_sampling_refuses_frames_with_an_image():
    s = synthetic_sample(np.random.default_rng(9))
    s.lidar2img = np.eye(4, dtype=np.float32)
    with pytest.raises(ValueError, match="image"):
        augment(s, np.random.default_rng(0), AugmentConfig(), _car_database(1))
