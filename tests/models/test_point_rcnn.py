import dataclasses
import math

import numpy as np
import pytest
import torch

from harness.core.boxes import points_in_boxes
from harness.core.types import Sample
from models.export import export_onnx, integer_extremes, run_onnx
from models.point_rcnn import (
    CONFIGS,
    PointNet2Backbone,
    PointRCNN,
    bin_channels,
    bin_loss,
    build,
    decode_bins,
    encode_bins,
    hash_rank,
)

CFG = CONFIGS["tiny"]


pytestmark = pytest.mark.usefixtures("one_thread")


def numpy_encode(box, point, cfg):
    """PointRCNN's bin targets for one box and point, written out with Python floats."""
    out_bins, out_res = [], []
    for axis in (0, 1):
        shift = min(max(box[axis] - point[axis] + cfg.loc_scope, 0.0), 2 * cfg.loc_scope - 1e-3)
        b = int(shift // cfg.loc_bin_size)
        out_bins.append(b)
        out_res.append((shift - (b * cfg.loc_bin_size + cfg.loc_bin_size / 2)) / cfg.loc_bin_size)
    per = 2 * math.pi / cfg.heading_bins
    angle = (box[6] + per / 2) % (2 * math.pi)
    hb = min(int(angle // per), cfg.heading_bins - 1)
    out_bins.append(hb)
    res = out_res + [box[2] - point[2], (angle - (hb * per + per / 2)) / (per / 2)]
    res += [(box[3 + i] - cfg.mean_size[i]) / cfg.mean_size[i] for i in range(3)]
    return out_bins, res


def random_boxes(rng, n):
    xyz = rng.uniform(-10, 10, (n, 3))
    boxes = np.concatenate([xyz + rng.uniform(-3.5, 3.5, (n, 3)), rng.uniform([3, 1.5, 1.3], [6, 2.2, 2], (n, 3)),
                            rng.uniform(-math.pi, math.pi, (n, 1))], 1)
    return torch.from_numpy(boxes.astype(np.float32)), torch.from_numpy(xyz.astype(np.float32))


def test_encode_bins_matches_numpy():
    boxes, xyz = random_boxes(np.random.default_rng(0), 300)
    bins, res = encode_bins(boxes, xyz, CFG)
    for i in range(300):
        ref_bins, ref_res = numpy_encode(boxes[i].double().tolist(), xyz[i].double().tolist(), CFG)
        assert bins[i].tolist() == ref_bins
        np.testing.assert_allclose(res[i].numpy(), ref_res, atol=2e-5)


def one_hot_prediction(bins, res, cfg):
    """Box head output whose argmax bins and residuals are the given targets."""
    loc = round(2 * cfg.loc_scope / cfg.loc_bin_size)
    parts = list(torch.split(torch.full((len(bins), bin_channels(cfg)), -5.0), [loc] * 4 + [1] + [cfg.heading_bins] * 2 + [3], 1))
    for j, (b, r) in enumerate([(0, 0), (1, 1)]):
        parts[j].scatter_(1, bins[:, b:b + 1], 5.0)
        parts[2 + j].scatter_(1, bins[:, b:b + 1], res[:, r:r + 1])
    parts[4].copy_(res[:, 2:3])
    parts[5].scatter_(1, bins[:, 2:3], 5.0)
    parts[6].scatter_(1, bins[:, 2:3], res[:, 3:4])
    parts[7].copy_(res[:, 4:])
    return torch.cat(parts, 1)


def test_decode_inverts_encode_within_scope():
    rng = np.random.default_rng(1)
    boxes, xyz = random_boxes(rng, 200)
    boxes[:, :2] = xyz[:, :2] + torch.from_numpy(rng.uniform(-2.9, 2.9, (200, 2)).astype(np.float32))
    bins, res = encode_bins(boxes, xyz, CFG)
    pred = one_hot_prediction(bins, res, CFG)
    dec = decode_bins(pred, xyz, CFG)
    np.testing.assert_allclose(dec[:, :6].numpy(), boxes[:, :6].numpy(), atol=1e-4)
    dyaw = np.remainder(dec[:, 6].numpy() - boxes[:, 6].numpy() + math.pi, 2 * math.pi) - math.pi
    np.testing.assert_allclose(dyaw, 0, atol=1e-4)
    assert float(bin_loss(pred, bins, res, CFG)) < float(bin_loss(torch.zeros_like(pred), bins, res, CFG))


def tiny_scene(rng, n_cars=2, frame_id="000000"):
    """Ground points plus points on the surfaces of a few cars ahead of the sensor."""
    ground = np.stack([rng.uniform(0, 60, 600), rng.uniform(-15, 15, 600), np.full(600, -1.7)], 1)
    boxes = []
    for i in range(n_cars):
        boxes.append([12 + 15 * i + rng.uniform(-2, 2), rng.uniform(-6, 6), -0.9, 4.5, 1.8, 1.6, rng.uniform(-0.3, 0.3)])
    boxes = np.array(boxes, np.float32).reshape(-1, 7)
    car_pts = []
    for b in boxes:
        local = rng.uniform(-0.5, 0.5, (150, 3)) * b[3:6]
        face = rng.integers(0, 3, 150)
        local[np.arange(150), face] = np.sign(local[np.arange(150), face]) * b[3 + face] / 2
        c, s = math.cos(b[6]), math.sin(b[6])
        car_pts.append(local @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + b[:3])
    xyz = np.concatenate([ground, *car_pts]).astype(np.float32)
    points = np.concatenate([xyz, rng.uniform(0, 1, (len(xyz), 1))], 1).astype(np.float32)
    return Sample(frame_id, points, boxes, np.array(["Car"] * len(boxes)))


def numpy_hash_rank(n, salt=0):
    """((i + salt) * 648,055) mod 2**20 in plain int64 arithmetic."""
    return ((np.arange(n, dtype=np.int64) + salt) % 2**20 * 648055) % 2**20


def numpy_points_of_interest(points, cfg, salt=0):
    """OpenPCDet's sampling with the hash order for its random draws: far points first (all of
    them while they fit), then the rest in range by rank, cycled to num_points."""
    n = cfg.num_points
    lo, hi = np.array(cfg.pc_range[:3]), np.array(cfg.pc_range[3:])
    inside = np.flatnonzero(np.all((points[:, :3] >= lo) & (points[:, :3] < hi), axis=1))
    if not len(inside):
        return np.zeros((n, 4), np.float32)
    rank = numpy_hash_rank(len(points) + 1, salt)[inside]
    far = np.linalg.norm(points[inside, :3].astype(np.float64), axis=1) >= cfg.far_depth
    if far.sum() >= n:  # the far points alone fill the budget: no priority
        far[:] = False
    seq = np.concatenate([inside[far][np.argsort(rank[far])], inside[~far][np.argsort(rank[~far])]])
    return points[seq[np.arange(n) % len(seq)]]


def test_hash_rank_matches_int64_and_is_a_permutation():
    for n, salt in [(0, 0), (1000, 0), (5000, 123_456), (2**20, 0), (300, 2**20 - 7)]:
        got = hash_rank(n, salt).numpy()
        np.testing.assert_array_equal(got, numpy_hash_rank(n, salt))
        assert len(np.unique(got)) == n  # distinct below 2**20 points
    assert len(np.unique(hash_rank(2**20, 99).numpy())) == 2**20


@pytest.mark.parametrize("salt", [0, 777])
@pytest.mark.parametrize("n_near, n_far", [(900, 100), (50, 30), (0, 70), (20, 600), (0, 0), (300, 0), (10, 256)])
def test_points_of_interest_matches_numpy(n_near, n_far, salt):
    rng = np.random.default_rng(n_near + 7 * n_far)
    cfg = CONFIGS["tiny"]  # 256 points
    near = rng.uniform([0, -25, -2.5], [30, 25, 1.5], (n_near, 3))
    far = rng.uniform([45, -30, -2.5], [79, 30, 1.5], (n_far, 3))
    outside = rng.uniform([-50, 40, -2], [-1, 60, 1], (40, 3))
    xyz = rng.permutation(np.concatenate([near, far, outside]))
    points = np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32)
    got, nonempty = PointRCNN(cfg).points_of_interest(torch.from_numpy(points), salt)
    np.testing.assert_array_equal(got.numpy(), numpy_points_of_interest(points, cfg, salt))
    assert bool(nonempty) == (n_near + n_far > 0)


def test_points_of_interest_keeps_near_density():
    """A near car keeps about the share of its points that the near scan keeps, far points all."""
    rng = np.random.default_rng(5)
    cfg = dataclasses.replace(CONFIGS["tiny"], num_points=2000)
    scan = rng.uniform([0, -30, -2], [39, 30, 1], (20000, 3))  # near ground, 40 m circle not crossed
    scan = scan[np.linalg.norm(scan, axis=1) < 39]
    car = rng.uniform([5, -1, -1], [9, 1, 0.5], (3000, 3))  # 3,000 points at 7 m
    far = rng.uniform([50, -10, -2], [70, 10, 1], (400, 3))
    xyz = rng.permutation(np.concatenate([scan, car, far]))
    got, _ = PointRCNN(cfg).points_of_interest(torch.from_numpy(np.c_[xyz, np.zeros(len(xyz))].astype(np.float32)))
    kept = got.numpy()[:, :3]
    assert len(np.unique(kept, axis=0)) == 2000
    assert (kept[:, 0] >= 50).sum() == 400  # every far point
    in_car = ((kept >= [5, -1, -1]) & (kept < [9, 1, 0.5])).all(1).sum()
    share = (2000 - 400) / (len(scan) + len(car))
    assert abs(in_car - 3000 * share) < 0.15 * 3000 * share


def test_build_rejects_unknown_profile():
    with pytest.raises(ValueError, match="unknown profile"):
        build("huge")
    assert isinstance(build("tiny"), PointRCNN)


def test_seg_targets_leave_points_on_an_ignored_box_out():
    """A point inside a truck box (or near a car) is neither foreground nor background (weight 0); a
    point inside a car inside an ignored box is the car's; the rest is background."""
    rng = np.random.default_rng(3)
    cars = np.array([[2.0, 1.0, -0.9, 4.0, 1.8, 1.5, 0.4], [-12.0, 3.0, -0.9, 4.2, 1.7, 1.5, 0.1]], np.float32)
    others = np.array([[-4.0, -3.0, 0.0, 11.5, 2.55, 3.8, -0.3], [-12.0, 3.0, -0.5, 8.0, 4.0, 3.0, 0.0]], np.float32)
    xyz = np.c_[rng.uniform(-18, 8, (6000, 2)), rng.uniform(-2, 1.5, 6000)].astype(np.float32)
    fg, weight, _ = PointRCNN(CFG).seg_targets(*(torch.from_numpy(a) for a in (xyz, cars, others)))
    in_car = points_in_boxes(xyz, cars).any(1)
    m = CFG.seg_ignore_margin  # added to l, w and h
    near_car = points_in_boxes(xyz, cars + np.float32([0, 0, 0, m, m, m, 0])).any(1)
    on_truck = points_in_boxes(xyz, others[:1])[:, 0]
    np.testing.assert_array_equal(fg.numpy(), in_car)
    np.testing.assert_array_equal(weight.numpy() == 0, (near_car | points_in_boxes(xyz, others).any(1)) & ~in_car)
    assert on_truck.sum() > 100 and (weight.numpy()[on_truck] == 0).all()


def test_frame_loss_takes_the_ignored_classes(monkeypatch):
    """The segmentation's and the RoI sampling's ignored boxes are the anchor heads' (Van, Truck, DontCare:
    ``frame_targets``); a Pedestrian is background for the Car detector, as in every other model."""
    import models.point_rcnn as point_rcnn
    seen = {}
    seg_targets, sample_rois = PointRCNN.seg_targets, point_rcnn.sample_rois
    monkeypatch.setattr(PointRCNN, "seg_targets", lambda self, xyz, cars, others: (
        seen.setdefault("seg", others.clone()), seg_targets(self, xyz, cars, others))[1])
    monkeypatch.setattr(point_rcnn, "sample_rois", lambda rois, gt, cfg, rng, ignore: (
        seen.setdefault("rois", ignore.copy()), sample_rois(rois, gt, cfg, rng, ignore))[1])
    scene = tiny_scene(np.random.default_rng(4), n_cars=1)
    boxes = np.concatenate([scene.gt_boxes, [[30.0, 5.0 * i, -0.9, 4.0, 1.8, 1.5, 0.0] for i in range(5)]])
    names = np.array(["Car", "Van", "Truck", "DontCare", "Pedestrian", "Cyclist"])
    torch.manual_seed(0)
    PointRCNN(CFG).loss([Sample("000000", scene.points, boxes.astype(np.float32), names)])
    for key in ("seg", "rois"):
        np.testing.assert_array_equal(np.asarray(seen[key]), boxes[1:4].astype(np.float32))


def test_forward_shapes_and_loss_falls():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = PointRCNN(CFG)
    scenes = [tiny_scene(rng, frame_id=str(i)) for i in range(2)]
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(25):
        out = model.loss(scenes)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(float(out["loss"].detach()))
    assert set(out) >= {"loss", "seg", "rpn_box", "rcnn_score", "rcnn_reg"}
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])
    model.eval()
    with torch.no_grad():
        boxes, scores, rois, roi_scores, rcnn_boxes = model(torch.from_numpy(scenes[0].points))
    k = rois.shape[0]
    assert boxes.shape[1] == 7 and scores.shape == boxes.shape[:1] and boxes.shape[0] <= CFG.max_detections
    assert rois.shape == (k, 7) and roi_scores.shape == (k,) and rcnn_boxes.shape == (k, 7) and 0 < k <= CFG.rois


def test_training_takes_the_rois_of_the_torch_nms(monkeypatch):
    """In training the proposal NMS runs the numba kernel: the same RoIs, scores and losses as with the
    torch (graph) form, on a crowd of overlapping proposals."""
    import models.nms as nms
    torch.manual_seed(0)
    model = PointRCNN(dataclasses.replace(CFG, pre_nms=256, rois=256)).train()
    with torch.no_grad():  # spread the untrained foreground scores; boxes of like size and heading, which overlap
        model.seg_head[-1].weight.mul_(30.0)
        model.box_head[-1].weight.mul_(0.05)
    scene = tiny_scene(np.random.default_rng(5), n_cars=3)
    seen, propose, kernel = [], PointRCNN.propose, nms._nms_kernel
    monkeypatch.setattr(PointRCNN, "propose", lambda self, *a: seen.append(propose(self, *a)) or seen[-1])
    monkeypatch.setattr(nms, "_nms_kernel", lambda *a: seen.append("kernel") or kernel(*a))

    def step():
        model.sampling_rng = np.random.default_rng(0)
        return model.loss([scene])

    fast = step()
    monkeypatch.setattr(nms, "_kernel_ready", lambda *a: False)
    slow = step()
    assert seen[0] == "kernel" and "kernel" not in seen[2:]
    (rois, scores, valid), (ref_rois, ref_scores, ref_valid) = seen[1], seen[2]
    assert 10 < int(valid.sum()) < 240  # the NMS suppressed some of the 256 boxes and kept many
    assert torch.equal(rois, ref_rois) and torch.equal(scores, ref_scores) and torch.equal(valid, ref_valid)
    assert fast.keys() == slow.keys() and all(torch.equal(fast[k], slow[k]) for k in fast)


def assert_same_rows(got, ref, atol=1e-4):
    """Same rows up to order: near-equal scores may be ranked differently by two runtimes."""
    assert got.shape == ref.shape
    if len(ref):
        dist = np.abs(got.reshape(len(got), 1, -1) - ref.reshape(1, len(ref), -1)).max(-1)  # (G, R)
        assert dist.min(0).max() < atol and dist.min(1).max() < atol


def test_onnx_matches_torch(tmp_path):
    torch.manual_seed(0)
    model = PointRCNN(CFG)
    rng = np.random.default_rng(1)
    model.loss([tiny_scene(rng)])  # move the batch-norm statistics off their defaults
    model.eval()
    with torch.no_grad():  # spread the untrained foreground scores (all near 0.01): ranks not decided by rounding
        model.seg_head[-1].weight.mul_(30.0)
    path = tmp_path / "point_rcnn.onnx"
    export_onnx(model, path, {"sotif.profile": "tiny"})
    clouds = [tiny_scene(rng).points, tiny_scene(rng, 1).points[::7],
              np.concatenate([rng.uniform([0, -20, -3], [80, 20, 2], (500, 3)), rng.uniform(0, 1, (500, 1))], 1),
              np.c_[rng.uniform([45, -20, -2], [79, 20, 1], (90, 3)), rng.uniform(0, 1, (90, 1))],  # far only
              np.zeros((3, 4)), np.zeros((0, 4))]
    for cloud in clouds:
        cloud = cloud.astype(np.float32)
        got = run_onnx(path, cloud)
        with torch.no_grad():
            ref = [t.numpy() for t in model(torch.from_numpy(cloud))]
        assert_same_rows(np.concatenate([got[0], got[1][:, None]], 1), np.concatenate([ref[0], ref[1][:, None]], 1))
        assert_same_rows(np.concatenate([got[2], got[3][:, None], got[4]], 1),
                         np.concatenate([ref[2], ref[3][:, None], ref[4]], 1))
        assert (len(ref[2]) > 0) == (len(cloud) > 0)  # RoIs from any cloud with points in range
    assert max(integer_extremes(path, clouds[0].astype(np.float32)).values()) < 2 ** 31  # OpenVINO: int32


class _Sampling(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, points):
        return self.model.points_of_interest(points)[0]


def test_points_of_interest_exports_exactly_for_large_clouds(tmp_path):
    """onnxruntime and OpenVINO (int64 computed in int32, integer arithmetic inexact above 2**24) pick
    the points torch picks from 300,000 (the hash's products would exceed 2**24 unsplit)."""
    import onnxruntime as ort
    module = _Sampling(PointRCNN(CFG)).eval()
    rng = np.random.default_rng(4)
    small = np.c_[rng.uniform([0, -30, -2.5], [79, 30, 1.5], (500, 3)), rng.uniform(0, 1, 500)].astype(np.float32)
    path = tmp_path / "sampling.onnx"
    dim = torch.export.Dim("n", min=0, max=2**20 - 1)
    torch.onnx.export(module, (torch.from_numpy(small),), dynamo=True, dynamic_shapes=({0: dim},)).save(path)
    large = np.c_[rng.uniform([0, -30, -2.5], [79, 30, 1.5], (300_000, 3)), rng.uniform(0, 1, 300_000)]
    large = large.astype(np.float32)
    runners = [lambda x: ort.InferenceSession(str(path)).run(None, {"points": x})[0]]
    try:
        import openvino
        compiled = openvino.Core().compile_model(str(path), "CPU", {"INFERENCE_PRECISION_HINT": "f32"})
        runners.append(lambda x: compiled(x)[0])
    except ImportError:
        pass
    for cloud in (small, large):
        ref = module(torch.from_numpy(cloud)).numpy()
        for run in runners:
            np.testing.assert_array_equal(run(cloud), ref)


@pytest.mark.parametrize("skip_xyz", [False, True])
def test_point_features_know_their_height_only_with_skip_xyz(skip_xyz):
    """Set abstraction and feature propagation see offsets between points only, so lifting the
    whole cloud by 0.5 m leaves every point's feature unchanged: the network cannot tell a point's
    height (and a proposal's z is that height plus a predicted offset). With ``skip_xyz`` the last
    propagation reads the coordinates, and the features change."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(CFG, skip_xyz=skip_xyz)
    net = PointNet2Backbone(cfg).eval()
    rng = np.random.default_rng(3)
    xyz = torch.from_numpy(rng.uniform([2, -6, -2], [14, 6, 0], (256, 3)).astype(np.float32))
    feats = torch.from_numpy(rng.uniform(0, 1, (256, 1)).astype(np.float32))
    with torch.no_grad():
        low, high = net(xyz, feats), net(xyz + torch.tensor([0.0, 0.0, 0.5]), feats)
    diff = float((low - high).abs().max())
    if skip_xyz:
        assert diff > 1e-3
    else:
        assert diff < 1e-4
