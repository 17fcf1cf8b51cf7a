"""PV-RCNN tiny profile: keypoint targets (keypoints on ignored boxes left out), level centres and BEV
sampling against references,
output shapes, loss falls, onnxruntime == torch on random, tiny and empty clouds."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from harness.core.boxes import points_in_boxes
from models.export import export_onnx, integer_extremes, run_onnx
from models.pv_rcnn import CONFIGS, PVRCNN, build, keypoint_targets, level_centres
from models.sparse import SparseTensor

def test_keypoint_targets_match_reference():
    rng = np.random.default_rng(0)
    gt = np.array([[2.0, 1.0, 0.0, 4.0, 2.0, 1.5, 0.4], [-3.0, -2.0, 0.2, 3.0, 1.5, 1.2, -1.2]],
                  np.float32)
    kp = np.c_[rng.uniform(-6, 6, (2000, 2)), rng.uniform(-1.5, 1.5, 2000)].astype(np.float32)
    got, weight = keypoint_targets(torch.from_numpy(kp), torch.from_numpy(gt), torch.zeros(0, 7), 0.2)
    grown = gt.copy()
    grown[:, 3:6] += 0.4
    want = points_in_boxes(kp, grown).any(1)
    np.testing.assert_array_equal(got.numpy() > 0, want)
    assert 50 < want.sum() < 1900 and (weight.numpy() == 1).all()
    fg, weight = keypoint_targets(torch.from_numpy(kp), torch.zeros(0, 7), torch.zeros(0, 7), 0.2)
    assert not fg.any() and (weight.numpy() == 1).all()


def test_keypoints_on_an_ignored_box_have_weight_zero():
    """The predicted keypoint weighting: a keypoint inside a truck box (enlarged by the margin, as the
    cars') is neither foreground nor background; the cars' keypoints keep their targets."""
    rng = np.random.default_rng(1)
    gt = np.array([[2.0, 1.0, 0.0, 4.0, 2.0, 1.5, 0.4]], np.float32)
    truck = np.array([[-3.0, -1.0, 0.5, 11.5, 2.55, 3.8, 0.2]], np.float32)  # overlaps the car: the car first
    kp = np.c_[rng.uniform(-10, 6, (3000, 2)), rng.uniform(-1.5, 2.0, 3000)].astype(np.float32)
    fg, weight = keypoint_targets(*(torch.from_numpy(a) for a in (kp, gt, truck)), 0.2)
    grow = lambda b: b + [0, 0, 0, 0.4, 0.4, 0.4, 0]  # noqa: E731
    in_car, in_truck = points_in_boxes(kp, grow(gt))[:, 0], points_in_boxes(kp, grow(truck))[:, 0]
    np.testing.assert_array_equal(fg.numpy() > 0, in_car)
    np.testing.assert_array_equal(weight.numpy() == 0, in_truck & ~in_car)
    assert (in_truck & ~in_car).sum() > 100 and (in_truck & in_car).sum() > 20
    old, _ = keypoint_targets(torch.from_numpy(kp), torch.from_numpy(gt), torch.zeros(0, 7), 0.2)
    assert torch.equal(old, fg)


def test_level_centres_match_reference():
    cfg = CONFIGS["tiny"]
    d, h, w = cfg.grid_of_voxels.shape
    coarse = (d // 4, h // 4, w // 4)  # a level at stride 4
    coords = torch.tensor([[0, 0, 0], [1, 2, 3]])
    got = level_centres(SparseTensor(torch.zeros(2, 1), coords, coarse), cfg.grid_of_voxels).numpy()
    x0, y0, z0 = cfg.pc_range[:3]
    dx, dy, dz = (4 * v for v in cfg.voxel_size)
    want = [[x0 + dx / 2, y0 + dy / 2, z0 + dz / 2], [x0 + 3.5 * dx, y0 + 2.5 * dy, z0 + 1.5 * dz]]
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_bev_sampling_matches_bilinear_reference():
    model = build("tiny")
    x0, y0, _, x1, y1, _ = model.cfg.pc_range
    rng = np.random.default_rng(2)
    bev = rng.normal(size=(3, 8, 10)).astype(np.float32)  # (C, H, W)
    kp = np.c_[rng.uniform(x0, x1, 50), rng.uniform(y0, y1, 50), np.zeros(50)].astype(np.float32)
    got = model.vsa.sample_bev(torch.from_numpy(bev), torch.from_numpy(kp)).numpy()
    for i, (x, y, _) in enumerate(kp.astype(np.float64)):
        u = (x - x0) / (x1 - x0) * 10 - 0.5  # continuous column, cell centres at integers
        v = (y - y0) / (y1 - y0) * 8 - 0.5
        u, v = np.clip(u, 0, 9), np.clip(v, 0, 7)
        c0, r0 = int(np.floor(u)), int(np.floor(v))
        c1, r1 = min(c0 + 1, 9), min(r0 + 1, 7)
        a, b = u - c0, v - r0
        want = (bev[:, r0, c0] * (1 - a) * (1 - b) + bev[:, r0, c1] * a * (1 - b)
                + bev[:, r1, c0] * (1 - a) * b + bev[:, r1, c1] * a * b)
        np.testing.assert_allclose(got[i], want, rtol=1e-4, atol=1e-5)


def test_outputs_and_loss_falls(two_car_scene, train_steps):
    torch.manual_seed(0)
    model = build("tiny")
    assert isinstance(model, PVRCNN) and model.two_stage
    sample = two_car_scene(np.random.default_rng(1))
    first, last = train_steps(model, sample, steps=8)
    assert last < 0.8 * first
    model.eval()
    with torch.no_grad():
        boxes, scores, rois, roi_scores, rcnn_boxes = model(torch.from_numpy(sample.points))
    k = CONFIGS["tiny"].proposals_test.rois
    assert rois.shape == (k, 7) and roi_scores.shape == (k,) and rcnn_boxes.shape == (k, 7)
    assert boxes.shape[1] == 7 and boxes.shape[0] == scores.shape[0] <= k


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A random tiny model whose RPN and refinement outputs get large random weights, so that
    scores spread over (0, 1) instead of sitting at the initial prior (near-ties)."""
    torch.manual_seed(0)
    model = build("tiny").eval()
    gen = torch.Generator().manual_seed(1)
    layers = ((model.rpn.conv_cls, 1.0), (model.rpn.conv_box, 0.1), (model.refine.cls, 1.0),
              (model.refine.reg, 0.1))
    with torch.no_grad():
        for layer, std in layers:
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen) * std)
            layer.bias.copy_(torch.randn(layer.bias.shape, generator=gen) * std)
    path = tmp_path_factory.mktemp("pv_rcnn") / "pv_rcnn.onnx"
    hist = export_onnx(model, path, {"sotif.profile": "tiny"})
    return model, path, hist


def test_empty_cloud_gives_no_box(exported, no_box_on_empty_cloud):
    model, path, _ = exported
    no_box_on_empty_cloud(model, path)


def test_export_keeps_every_step_in_the_graph(exported):
    _, _, hist = exported
    for op in ("Loop", "TopK", "ScatterElements", "Gather"):
        assert op in hist, op


def test_integer_intermediates_fit_int32(exported, random_cloud):
    """OpenVINO computes int64 in int32: no integer tensor of the graph may leave that range."""
    _, path, _ = exported
    points = random_cloud(np.random.default_rng(5), CONFIGS["tiny"].pc_range, 3000)
    assert max(integer_extremes(path, points).values()) < 2 ** 31


@pytest.mark.parametrize("n", [3000, 7, 0])
def test_onnx_matches_torch(exported, n, random_cloud):
    model, path, _ = exported
    points = random_cloud(np.random.default_rng(n), CONFIGS["tiny"].pc_range, n)
    got = run_onnx(path, points)
    with torch.no_grad():
        want = model(torch.from_numpy(points))
    assert len(got) == 5
    for g, w in zip(got, want):
        assert g.shape == tuple(w.shape)
        np.testing.assert_allclose(g, w.numpy(), rtol=1e-4, atol=1e-4)


def test_cached_export_equals_its_fresh_export(exported, tmp_path):
    """After the module's export (``exported``), whose trace the graph cache holds: filled with other
    weights it gives a fresh export's bytes (tests/models/test_export.py)."""
    from tests.models.test_export import cached_export_equals_fresh
    cached_export_equals_fresh(tmp_path, "pv_rcnn")
