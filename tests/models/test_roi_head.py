"""Second-stage target assignment (RoIs on ignored boxes left out), canonical box coding, corner and
IoU-guided losses."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from shapely.geometry import Polygon

from harness.core.boxes import corners_3d, corners_bev, iou_3d, points_in_boxes, wrap_angle
from models.roi_head import (IGNORE_IOA, SCORE_RULES, OutputConfig, RefineHead, RoITargetConfig, box_corners,
                             corner_loss, decode_canonical, encode_canonical, final_scores, finalize,
                             iou_score_target, on_ignored, refine_loss, roi_support, sample_rois, score_loss)


def test_encode_canonical_matches_reference(random_boxes):
    rng = np.random.default_rng(0)
    gt, rois = random_boxes(rng, 50), random_boxes(rng, 50)
    got = encode_canonical(torch.from_numpy(gt), torch.from_numpy(rois)).numpy()
    for i, (g, r) in enumerate(zip(gt.astype(np.float64), rois.astype(np.float64))):
        dx, dy = g[0] - r[0], g[1] - r[1]
        lx = np.cos(r[6]) * dx + np.sin(r[6]) * dy
        ly = -np.sin(r[6]) * dx + np.cos(r[6]) * dy
        diag = np.hypot(r[3], r[4])
        dyaw = wrap_angle(g[6] - r[6])
        if abs(dyaw) > np.pi / 2:
            dyaw = wrap_angle(dyaw + np.pi)
        want = [lx / diag, ly / diag, (g[2] - r[2]) / r[5], *np.log(g[3:6] / r[3:6]), dyaw]
        np.testing.assert_allclose(got[i], want, rtol=1e-4, atol=1e-4)


def test_decode_inverts_encode_up_to_heading_flip(random_boxes):
    rng = np.random.default_rng(1)
    gt, rois = random_boxes(rng, 100), random_boxes(rng, 100)
    gt_t, rois_t = torch.from_numpy(gt), torch.from_numpy(rois)
    back = decode_canonical(encode_canonical(gt_t, rois_t), rois_t).numpy()
    np.testing.assert_allclose(back[:, :6], gt[:, :6], rtol=1e-4, atol=1e-3)
    dyaw = np.abs(wrap_angle(back[:, 6] - gt[:, 6]))
    assert np.all((dyaw < 1e-4) | (np.abs(dyaw - np.pi) < 1e-4))
    assert np.all(np.abs(iou_3d(back, gt).diagonal() - 1.0) < 1e-3)


def test_box_corners_match_harness(random_boxes):
    boxes = random_boxes(np.random.default_rng(2), 30)
    np.testing.assert_allclose(box_corners(torch.from_numpy(boxes)).numpy(), corners_3d(boxes),
                               atol=1e-4)


def test_corner_loss_matches_reference_and_ignores_flip(random_boxes):
    rng = np.random.default_rng(3)
    gt, pred = random_boxes(rng, 20, 2.0), random_boxes(rng, 20, 2.0)
    got = corner_loss(torch.from_numpy(pred), torch.from_numpy(gt)).numpy()
    flipped = gt.copy()
    flipped[:, 6] += np.pi
    d = np.minimum(np.linalg.norm(corners_3d(pred) - corners_3d(gt), axis=2),
                   np.linalg.norm(corners_3d(pred) - corners_3d(flipped), axis=2))
    huber = np.where(d < 1.0, 0.5 * d ** 2, d - 0.5).mean(1)
    np.testing.assert_allclose(got, huber, rtol=1e-4, atol=1e-5)
    same = corner_loss(torch.from_numpy(flipped), torch.from_numpy(gt))
    assert float(same.abs().max()) < 1e-4


def test_sample_rois_labels_and_balances(random_boxes):
    rng = np.random.default_rng(4)
    gt = random_boxes(rng, 3, 15.0)
    proposals = np.concatenate([random_boxes(rng, 80, 20.0), gt + [0.2, 0, 0, 0, 0, 0, 0.05]])
    cfg = RoITargetConfig(per_frame=32, fg_fraction=0.25, gt_jitter=5)
    t = sample_rois(proposals, gt, cfg, np.random.default_rng(0))
    assert len(t.rois) == 32
    overlaps = iou_3d(t.rois.numpy(), gt)
    np.testing.assert_allclose(t.iou.numpy(), overlaps.max(1), atol=1e-5)
    fg = t.iou.numpy() >= cfg.fg_iou
    assert 0 < fg.sum() <= 8
    np.testing.assert_array_equal(t.gt.numpy()[fg], gt[overlaps.argmax(1)][fg])
    again = sample_rois(proposals, gt, cfg, np.random.default_rng(0))
    assert torch.equal(again.rois, t.rois)  # same seed, same draw


def test_sample_rois_without_gt_or_proposals(random_boxes):
    cfg = RoITargetConfig(per_frame=8)
    rng = np.random.default_rng(5)
    t = sample_rois(random_boxes(rng, 20), np.zeros((0, 7), np.float32), cfg, rng)
    assert len(t.rois) == 8 and float(t.iou.max()) == 0.0
    t = sample_rois(np.zeros((0, 7), np.float32), random_boxes(rng, 2), cfg, rng)
    assert len(t.rois) == 0  # nothing to draw from
    t = sample_rois(np.zeros((0, 7), np.float32), random_boxes(rng, 2), replace(cfg, gt_jitter=3), rng)
    assert len(t.rois) == 8 and (t.iou.numpy() > 0).any()  # drawn from the jittered copies


def test_sample_rois_draws_only_proposals_by_default(random_boxes):
    """No ground-truth copies join the proposals unless a config asks for them (OpenPCDet adds
    none); the draw then holds only rows of the proposals, whatever the foreground share."""
    rng = np.random.default_rng(8)
    gt = random_boxes(rng, 4, 15.0)
    proposals = np.concatenate([random_boxes(rng, 30, 20.0), gt[:1] + [0.1, 0, 0, 0, 0, 0, 0.02]]).astype(np.float32)
    t = sample_rois(proposals, gt, RoITargetConfig(per_frame=32), np.random.default_rng(0))
    rows = t.rois.numpy()
    assert np.abs(rows[:, None, :] - proposals[None, :, :]).max(-1).min(1).max() == 0.0
    assert (t.iou.numpy() >= 0.55).sum() == 1  # the one good proposal, no copy of the other cars
    jittered = sample_rois(proposals, gt, RoITargetConfig(per_frame=32, gt_jitter=4), np.random.default_rng(0))
    assert (jittered.iou.numpy() >= 0.55).sum() > 1


@pytest.mark.parametrize("name", ["parta2", "pv_rcnn", "point_rcnn"])
@pytest.mark.parametrize("profile", ["tiny", "compact", "kitti"])
def test_no_profile_adds_ground_truth_copies(name, profile):
    from models.zoo import config
    assert config(name, profile).targets.gt_jitter == 0


def _shifted(ious) -> np.ndarray:
    """Copies of a 4 x 2 x 1.5 m box at the origin, moved along x to the given 3D IoUs with it."""
    ious = np.asarray(ious, np.float64)
    boxes = np.zeros((len(ious), 7), np.float32)
    boxes[:, 0] = 4.0 * (1 - ious) / (1 + ious)
    boxes[:, 3:6] = (4.0, 2.0, 1.5)
    return boxes


@pytest.mark.parametrize("n_fg, n_hard, n_easy", [(30, 40, 40), (3, 40, 40), (3, 2, 40), (3, 40, 0),
                                                   (3, 0, 40), (30, 0, 0), (0, 40, 40), (0, 0, 5)])
def test_sample_rois_draws_as_openpcdet(n_fg, n_hard, n_easy):
    """Counts per pool as OpenPCDet's subsample_rois / sample_bg_inds: foreground (IoU >= 0.55)
    at most half, without replacement; of the background, 80 % hard (IoU in [0.1, 0.55)), the
    rest easy, with replacement; one pool alone when the other is empty."""
    rng = np.random.default_rng(n_fg + 7 * n_hard + 13 * n_easy)
    gt = _shifted([1.0])
    ious = np.concatenate([rng.uniform(0.56, 0.99, n_fg), rng.uniform(0.11, 0.54, n_hard),
                           rng.uniform(0.0, 0.09, n_easy)])
    cfg = RoITargetConfig(per_frame=32, gt_jitter=0)
    t = sample_rois(_shifted(ious), gt, cfg, np.random.default_rng(0))
    got = t.iou.numpy()
    np.testing.assert_allclose(np.sort(got), np.sort(iou_3d(t.rois.numpy(), gt).max(1)), atol=1e-5)
    want_fg = min(16, n_fg) if n_hard + n_easy else 32
    n_bg = 32 - want_fg if n_hard + n_easy else 0
    want_hard = (n_bg if not n_easy else min(int(n_bg * 0.8), n_hard)) if n_hard else 0
    assert len(got) == 32
    assert (got >= 0.55).sum() == want_fg
    assert ((got >= 0.1) & (got < 0.55)).sum() == want_hard
    assert (got < 0.1).sum() == n_bg - want_hard
    fg_rows = t.rois.numpy()[got >= 0.55]
    if n_hard + n_easy:  # foreground without replacement
        assert len(np.unique(fg_rows[:, 0])) == len(fg_rows)


TRUCK = np.array([[20.0, 0.0, -0.1, 11.5, 2.55, 3.8, 0.0]], np.float32)  # rear face at x = 14.25 m
ON_REAR = np.array([[15.7, 0.3, -0.9, 3.9, 1.6, 1.56, 0.05]], np.float32)  # a car-sized RoI on it, 0.5 m out
ON_NOTHING = np.array([[40.0, 10.0, -0.9, 3.9, 1.6, 1.56, 0.3]], np.float32)


def _shapely_ioa(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Ka, Kb) share of each a box's BEV rectangle inside each b box's, by shapely."""
    pa, pb = [Polygon(c) for c in corners_bev(a)], [Polygon(c) for c in corners_bev(b)]
    return np.array([[x.intersection(y).area / x.area for y in pb] for x in pa]).reshape(len(a), len(b))


def test_on_ignored_matches_shapely(random_boxes):
    rng = np.random.default_rng(11)
    rois = random_boxes(rng, 300, 12.0)
    ignore = random_boxes(rng, 6, 10.0) * [1, 1, 1, 2.5, 1.3, 2.0, 1]  # truck- and van-sized
    want = _shapely_ioa(rois, ignore).max(1)
    clear = np.abs(want - IGNORE_IOA) > 1e-3  # float32 against float64 at the threshold
    np.testing.assert_array_equal(on_ignored(rois, ignore)[clear], (want >= IGNORE_IOA)[clear])
    assert 10 < (want >= IGNORE_IOA).sum() < 290
    assert not on_ignored(rois, np.zeros((0, 7), np.float32)).any()
    assert on_ignored(np.zeros((0, 7), np.float32), ignore).shape == (0,)


def test_a_roi_on_a_truck_is_not_background_and_one_on_nothing_is(random_boxes):
    """A car-sized RoI on a truck's rear face (3D IoU < 0.1 with the truck) is not drawn as background;
    one on nothing is; a RoI on a car inside an ignored box stays foreground."""
    assert float(_shapely_ioa(ON_REAR, TRUCK)[0, 0]) > 0.85 and iou_3d(ON_REAR, TRUCK)[0, 0] < 0.1
    car = np.array([[5.0, -6.0, -0.9, 4.2, 1.8, 1.5, 0.2]], np.float32)
    dontcare = np.array([[5.0, -6.0, -0.5, 9.0, 5.0, 3.0, 0.0]], np.float32)  # a car inside a DontCare region
    proposals = np.concatenate([ON_REAR, ON_NOTHING, car + [0.1, 0, 0, 0, 0, 0, 0.02]])
    cfg = RoITargetConfig(per_frame=16)
    t = sample_rois(proposals, car, cfg, np.random.default_rng(0), np.concatenate([TRUCK, dontcare]))
    rows = t.rois.numpy()
    assert not np.isclose(rows[:, 0], ON_REAR[0, 0]).any()  # never drawn
    nothing = np.isclose(rows[:, 0], ON_NOTHING[0, 0])
    assert nothing.any() and (t.iou.numpy()[nothing] == 0).all()  # background
    assert (t.iou.numpy()[~nothing] >= cfg.fg_iou).all()  # the rest: the car, foreground on the DontCare
    assert (t.weight.numpy() == 1).all()
    old = sample_rois(proposals, car, cfg, np.random.default_rng(0))  # without ignored boxes: background
    assert np.isclose(old.rois.numpy()[:, 0], ON_REAR[0, 0]).any()


def test_rois_only_on_a_truck_have_no_confidence_loss():
    """With nothing else to draw, the RoIs on the truck fill the draw at weight 0: the confidence loss
    neither rewards nor penalises them (0, no gradient), in both score types."""
    for cfg in (RoITargetConfig(per_frame=8), RoITargetConfig(per_frame=8, score_type="cls", score_lo=0.45,
                                                                score_hi=0.6)):
        t = sample_rois(ON_REAR, np.zeros((0, 7), np.float32), cfg, np.random.default_rng(0), TRUCK)
        assert len(t.rois) == 8 and (t.weight.numpy() == 0).all()
        logit = torch.randn(8, requires_grad=True)
        losses = refine_loss(logit, torch.zeros(8, 7), t, cfg)
        losses["rcnn_score"].backward()
        assert float(losses["rcnn_score"].detach()) == 0.0 and float(logit.grad.abs().max()) == 0.0
        assert float(losses["rcnn_reg"].detach()) == 0.0


def test_sample_rois_without_ignored_boxes_is_unchanged(random_boxes):
    """Car behaviour: no ignored box, or ignored boxes far from every RoI, give the draw of no ``ignore``
    argument (the function before ignored boxes) with every weight 1."""
    rng = np.random.default_rng(12)
    gt = random_boxes(rng, 3, 15.0)
    proposals = np.concatenate([random_boxes(rng, 80, 20.0), gt + [0.2, 0, 0, 0, 0, 0, 0.05]]).astype(np.float32)
    far = TRUCK + [200.0, 0, 0, 0, 0, 0, 0]
    cfg = RoITargetConfig(per_frame=32)
    want = sample_rois(proposals, gt, cfg, np.random.default_rng(0))
    for ignore in (np.zeros((0, 7), np.float32), far):
        got = sample_rois(proposals, gt, cfg, np.random.default_rng(0), ignore)
        for name in ("rois", "iou", "gt", "weight"):
            assert torch.equal(getattr(got, name), getattr(want, name))
    assert (want.weight.numpy() == 1).all()


def test_score_loss_leaves_weight_zero_rois_out():
    rng = np.random.default_rng(13)
    iou = torch.from_numpy(rng.uniform(0, 1, 200).astype(np.float32))
    logit = torch.from_numpy(rng.normal(0, 2, 200).astype(np.float32))
    weight = torch.from_numpy((rng.uniform(0, 1, 200) > 0.3).astype(np.float32))
    kept = weight.numpy() > 0
    for cfg in (RoITargetConfig(), RoITargetConfig(score_type="cls", score_lo=0.45, score_hi=0.6)):
        want = score_loss(logit[kept], iou[kept], cfg)
        np.testing.assert_allclose(float(score_loss(logit, iou, cfg, weight)), float(want), rtol=1e-6)
        assert float(score_loss(logit, iou, cfg, torch.ones(200))) == float(score_loss(logit, iou, cfg))


def test_score_loss_of_both_score_types_matches_reference():
    rng = np.random.default_rng(6)
    iou = torch.from_numpy(rng.uniform(0, 1, 300).astype(np.float32))
    logit = torch.from_numpy(rng.normal(0, 2, 300).astype(np.float32))
    p = 1 / (1 + np.exp(-logit.numpy().astype(np.float64)))
    bce = lambda y: -(y * np.log(p) + (1 - y) * np.log(1 - p))  # noqa: E731
    ramp = np.clip((iou.numpy() - 0.25) / 0.5, 0, 1)
    got = score_loss(logit, iou, RoITargetConfig())
    np.testing.assert_allclose(float(got), bce(ramp).mean(), rtol=1e-5)
    cfg = RoITargetConfig(score_type="cls", score_lo=0.45, score_hi=0.6)
    counted = (iou.numpy() > 0.6) | (iou.numpy() < 0.45)
    want = bce((iou.numpy() > 0.6).astype(np.float64))[counted].mean()
    np.testing.assert_allclose(float(score_loss(logit, iou, cfg)), want, rtol=1e-5)
    with pytest.raises(ValueError, match="score_type"):
        RoITargetConfig(score_type="iou")


def test_iou_score_target_is_a_clamped_ramp():
    cfg = RoITargetConfig(score_lo=0.25, score_hi=0.75)
    iou = torch.rand(200)
    want = np.clip((iou.numpy() - 0.25) / 0.5, 0, 1)
    np.testing.assert_allclose(iou_score_target(iou, cfg).numpy(), want, atol=1e-6)


def test_refine_loss_falls_when_training_the_head(random_boxes):
    torch.manual_seed(0)
    rng = np.random.default_rng(6)
    gt = random_boxes(rng, 4, 10.0)
    cfg = RoITargetConfig(per_frame=48)
    targets = sample_rois(random_boxes(rng, 60, 10.0), gt, cfg, rng)
    feats = torch.cat([targets.rois, targets.gt - targets.rois], 1)  # (S, 14) informative input
    head = RefineHead(14, [32, 32], dropout=0.0)
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    totals = []
    for _ in range(60):
        losses = refine_loss(*head(feats), targets, cfg)
        total = sum(losses.values())
        opt.zero_grad()
        total.backward()
        opt.step()
        totals.append(float(total.detach()))
    assert totals[-1] < 0.6 * totals[0]
    head.eval()
    logit, deltas = head(feats[:1])
    assert logit.shape == (1,) and deltas.shape == (1, 7)


def test_roi_support_matches_points_in_boxes_and_gates_finalize(random_boxes):
    rng = np.random.default_rng(5)
    rois = random_boxes(rng, 16, spread=6.0)
    xyz = rng.uniform(-8, 8, (300, 3)).astype(np.float32)
    got = roi_support(torch.from_numpy(xyz), torch.from_numpy(rois)).numpy()
    want = points_in_boxes(xyz, rois).any(0)
    np.testing.assert_array_equal(got, want)
    assert 0 < got.sum() < len(rois)
    logit, deltas = torch.full((16,), 3.0), torch.zeros(16, 7)  # every RoI confident, unrefined
    cfg = OutputConfig(nms_iou=1.0)  # no suppression: the support alone decides
    roi_scores = torch.full((16,), 0.5)
    boxes, scores, rcnn = finalize(torch.from_numpy(rois), roi_scores, logit, deltas, cfg, torch.from_numpy(got))
    assert len(boxes) == got.sum() and len(rcnn) == 16
    np.testing.assert_allclose(np.sort(boxes[:, 0].numpy()), np.sort(rois[got, 0]), atol=1e-5)
    assert len(finalize(torch.from_numpy(rois), roi_scores, logit, deltas, cfg)[0]) == 16


def test_final_scores_follow_the_configured_rule(random_boxes):
    rng = np.random.default_rng(6)
    roi_scores, logit = rng.uniform(0, 1, 50).astype(np.float32), rng.normal(0, 3, 50).astype(np.float32)
    confidence = 1 / (1 + np.exp(-logit.astype(np.float64)))
    got = {rule: final_scores(torch.from_numpy(roi_scores), torch.from_numpy(logit), rule).numpy()
           for rule in SCORE_RULES}
    np.testing.assert_allclose(got["rcnn"], confidence, rtol=1e-5)
    np.testing.assert_allclose(got["geometric"], np.sqrt(roi_scores * confidence), rtol=1e-5)
    # finalize ranks and thresholds by the rule's score
    rois = random_boxes(rng, 50, spread=30.0)
    cfg = OutputConfig(nms_iou=1.0, score_thresh=0.3, score="geometric")
    _, scores, _ = finalize(torch.from_numpy(rois), torch.from_numpy(roi_scores), torch.from_numpy(logit),
                            torch.zeros(50, 7), cfg)
    want = np.sort(got["geometric"][got["geometric"] > 0.3])[::-1]
    np.testing.assert_allclose(scores.numpy(), want, rtol=1e-6)
    with pytest.raises(ValueError, match="score must be one of"):
        OutputConfig(score="mean")
