"""Part-A2 tiny profile: part targets against a brute-force reference (voxels on ignored boxes left out),
output shapes, loss falls, onnxruntime == torch on random, tiny and empty clouds."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from harness.core.boxes import points_in_boxes
from models.export import export_onnx, integer_extremes, run_onnx
from models.parta2 import CONFIGS, PartA2, build, part_targets, roi_dense_grid, roi_sparse_grid, voxel_centres
from models.sparse import SparseTensor, SubMConv3d

def test_part_targets_match_reference():
    rng = np.random.default_rng(0)
    gt = np.array([[2.0, 1.0, 0.0, 4.0, 2.0, 1.5, 0.4], [-3.0, -2.0, 0.2, 3.0, 1.5, 1.2, -1.2]],
                  np.float32)
    xyz = rng.uniform(-6, 6, (3000, 3)).astype(np.float32)
    xyz[:, 2] = rng.uniform(-1.5, 1.5, 3000)
    fg, ignore, part = part_targets(torch.from_numpy(xyz), torch.from_numpy(gt), torch.zeros(0, 7), 0.3)
    inside = points_in_boxes(xyz, gt)  # (V, G)
    grown = gt.copy()
    grown[:, 3:6] += 0.6
    near = points_in_boxes(xyz, grown)
    np.testing.assert_array_equal(fg.numpy() > 0, inside.any(1))
    np.testing.assert_array_equal(ignore.numpy(), near.any(1) & ~inside.any(1))
    assert 50 < inside.sum() and ignore.numpy().sum() > 10
    for v in np.flatnonzero(inside.any(1)):
        b = gt[np.argmax(inside[v])].astype(np.float64)
        d = xyz[v] - b[:3]
        c, s = np.cos(b[6]), np.sin(b[6])
        local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
        np.testing.assert_allclose(part[v].numpy(), local / b[3:6] + 0.5, atol=1e-5)
    assert not part.numpy()[~inside.any(1)].any()


def test_voxels_on_an_ignored_box_have_no_seg_or_part_loss():
    """A voxel inside a truck or van box (or within the margin of one) is neither foreground nor
    background: seg weight 0, no part target; one inside a car inside a DontCare region stays a car's;
    the cars' targets are those without ignored boxes."""
    rng = np.random.default_rng(1)
    gt = np.array([[2.0, 1.0, -0.9, 4.0, 1.8, 1.5, 0.4], [-12.0, 3.0, -0.9, 4.2, 1.7, 1.5, 0.1]], np.float32)
    others = np.array([[-4.0, -3.0, 0.0, 11.5, 2.55, 3.8, -0.3],  # truck
                       [-12.0, 3.0, -0.5, 8.0, 4.0, 3.0, 0.0]], np.float32)  # DontCare around the second car
    xyz = np.c_[rng.uniform(-18, 8, (6000, 2)), rng.uniform(-2, 1.5, 6000)].astype(np.float32)
    fg, ignore, part = part_targets(*(torch.from_numpy(a) for a in (xyz, gt, others)), 0.3)
    grow = lambda b: b + [0, 0, 0, 0.6, 0.6, 0.6, 0]  # noqa: E731
    in_car = points_in_boxes(xyz, gt).any(1)
    near = points_in_boxes(xyz, grow(gt)).any(1) | points_in_boxes(xyz, grow(others)).any(1)
    np.testing.assert_array_equal(fg.numpy() > 0, in_car)
    np.testing.assert_array_equal(ignore.numpy(), near & ~in_car)
    on_truck = points_in_boxes(xyz, others[:1])[:, 0]
    assert on_truck.sum() > 100 and ignore.numpy()[on_truck].all() and not part.numpy()[on_truck].any()
    assert points_in_boxes(xyz, gt[1:])[:, 0].sum() > 10  # the car inside the DontCare region is foreground
    old = part_targets(torch.from_numpy(xyz), torch.from_numpy(gt), torch.zeros(0, 7), 0.3)
    assert torch.equal(old[0], fg) and torch.equal(old[2], part)  # the cars' targets unchanged
    assert not part_targets(torch.from_numpy(xyz), torch.zeros(0, 7), torch.from_numpy(others), 0.3)[0].any()
    np.testing.assert_array_equal(
        part_targets(torch.from_numpy(xyz), torch.zeros(0, 7), torch.from_numpy(others), 0.3)[1].numpy(),
        points_in_boxes(xyz, grow(others)).any(1))


def test_voxel_centres_match_reference():
    cfg = CONFIGS["tiny"]
    coords = torch.tensor([[0, 0, 0], [3, 5, 7]])
    x = SparseTensor(torch.zeros(2, 1), coords, cfg.grid.shape)
    got = voxel_centres(x, cfg.grid).numpy()
    x0, y0, z0 = cfg.pc_range[:3]
    dx, dy, dz = cfg.voxel_size
    want = [[x0 + dx / 2, y0 + dy / 2, z0 + dz / 2], [x0 + 7.5 * dx, y0 + 5.5 * dy, z0 + 3.5 * dz]]
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_submanifold_conv_over_stacked_rois_is_a_conv_per_roi():
    """One SubMConv3d over the stacked pooled grids equals, per RoI, a dense 3x3x3 conv of the
    zero-filled grid read at the occupied cells (and zero elsewhere): no tap reaches another RoI."""
    rng = np.random.default_rng(3)
    k, g, c = 5, 4, 3
    pooled = torch.from_numpy(rng.normal(size=(k, g, g, g, c)).astype(np.float32))
    occupied = torch.from_numpy(rng.uniform(size=(k, g, g, g)) < 0.4)
    conv = SubMConv3d(c, 2, 3)
    with torch.no_grad():
        got = roi_dense_grid(conv(roi_sparse_grid(pooled, occupied)), k, g)  # (K, 2, g, g, g)
        dense_in = (pooled * occupied[..., None]).permute(0, 4, 1, 2, 3)  # (K, C, g, g, g)
        weight = conv.weight.reshape(3, 3, 3, c, 2).permute(4, 3, 0, 1, 2)  # (2, C, 3, 3, 3)
        want = torch.nn.functional.conv3d(dense_in, weight, padding=1) * occupied[:, None]
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-5)


def test_outputs_and_loss_falls(two_car_scene, train_steps):
    torch.manual_seed(0)
    model = build("tiny")
    assert isinstance(model, PartA2) and model.two_stage
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
    layers = ((model.rpn.conv_cls, 1.0), (model.rpn.conv_box, 0.1), (model.rcnn.refine.cls, 1.0),
              (model.rcnn.refine.reg, 0.1))
    with torch.no_grad():
        for layer, std in layers:
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen) * std)
            layer.bias.copy_(torch.randn(layer.bias.shape, generator=gen) * std)
    path = tmp_path_factory.mktemp("parta2") / "parta2.onnx"
    hist = export_onnx(model, path, {"sotif.profile": "tiny"})
    return model, path, hist


def test_empty_cloud_gives_no_box(exported, no_box_on_empty_cloud):
    model, path, _ = exported
    no_box_on_empty_cloud(model, path)


def test_export_keeps_every_step_in_the_graph(exported):
    _, _, hist = exported
    for op in ("Loop", "TopK", "ScatterElements", "Conv", "Gather"):
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
