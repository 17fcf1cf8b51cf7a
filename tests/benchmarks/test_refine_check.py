"""benchmarks/refine_check.py: per-value errors of proposals and refined boxes near labelled cars."""
import math

import numpy as np

from benchmarks.refine_check import box_errors, matched_errors


def test_box_errors_against_a_loop():
    rng = np.random.default_rng(0)
    boxes = rng.normal(size=(20, 7))
    boxes[:, 6] = rng.uniform(-4, 4, 20)
    gt = rng.normal(size=(1, 7))
    got = box_errors(boxes.copy(), gt)
    for b, row in zip(boxes, got):
        np.testing.assert_allclose(row[:6], np.abs(b[:6] - gt[0, :6]))
        # the yaw error is the smallest angle between the two headings, either way round
        want = min(abs(b[6] - gt[0, 6] - k * math.pi) for k in range(-4, 5))
        assert abs(row[6] - want) < 1e-12
        assert 0 <= row[6] <= math.pi / 2 + 1e-12


def test_matched_errors_pairs_each_proposal_with_its_refined_row():
    cars = np.array([[10.0, 0, -1, 4, 1.8, 1.5, 0], [30.0, 5, -1, 4, 1.8, 1.5, 0]])
    rois = np.array([[10.4, 0.2, -0.9, 4.2, 1.8, 1.4, 0.1],   # near car 0
                     [12.0, 0.0, -1.0, 4.0, 1.8, 1.5, 0.0],   # 2 m away: left out
                     [30.0, 5.5, -1.2, 4.0, 1.8, 1.5, math.pi]])  # near car 1, heading flipped
    refined = rois.copy()
    refined[:, 0] -= 0.3
    at_roi, at_rcnn, ious = matched_errors(rois, refined, cars)
    assert at_roi.shape == at_rcnn.shape == (2, 7) and ious.shape == (2, 3)
    np.testing.assert_allclose(at_roi[:, 0], [0.4, 0.0], atol=1e-12)
    np.testing.assert_allclose(at_rcnn[:, 0], [0.1, 0.3], atol=1e-12)
    np.testing.assert_allclose(at_roi[:, 2], [0.1, 0.2], atol=1e-12)
    np.testing.assert_allclose(at_roi[:, 6], [0.1, 0.0], atol=1e-12)
    none = matched_errors(rois, refined, np.zeros((0, 7)))
    assert none[0].shape == (0, 7) and none[2].shape == (0, 3)


def test_ious_against_the_height_overlap_by_hand():
    # aligned boxes with the same footprint: the 3D IoU is the height overlap over the union
    car = np.array([[10.0, 0, -1.0, 4, 2, 1.5, 0]])
    roi = np.array([[10.0, 0, -0.8, 4, 2, 1.3, 0]])  # z 0.2 m up, 0.2 m lower
    refined = np.array([[10.0, 0, -1.0, 4, 2, 1.4, 0]])
    _, _, ious = matched_errors(roi, refined, car)
    # roi spans [-1.45, -0.15], car [-1.75, -0.25]: overlap 1.2, union 1.3 + 1.5 - 1.2 = 1.6
    np.testing.assert_allclose(ious[0], [1.2 / 1.6, 1.0, 1.4 / 1.5], atol=1e-9)


def test_ranked_by_iou_scores_each_box_by_its_best_car_then_suppresses():
    from benchmarks.refine_check import ranked_by_iou
    cars = np.array([[10.0, 0, -1.0, 4, 2, 1.5, 0], [30.0, 5, -1.0, 4, 2, 1.5, 0]])
    boxes = np.array([[10.0, 0, -0.8, 4, 2, 1.3, 0],     # car 0, 0.2 m high and 0.2 m short: 1.2 / 1.6
                      [10.0, 0, -1.0, 4, 2, 1.5, 0],     # car 0 exactly: 1.0, suppresses the one above
                      [31.0, 5, -1.0, 4, 2, 1.5, 0],     # car 1, 1 m along x: 3 / 5 of the footprint
                      [50.0, -9, -1.0, 4, 2, 1.5, 0]])   # no car: dropped
    kept, scores = ranked_by_iou(boxes, cars)
    np.testing.assert_allclose(kept, boxes[[1, 2]], atol=1e-6)
    np.testing.assert_allclose(scores, [1.0, 3.0 / 5.0], atol=1e-6)
    assert ranked_by_iou(boxes, np.zeros((0, 7)))[0].shape == (0, 7)
    assert ranked_by_iou(np.zeros((0, 7)), cars)[1].shape == (0,)
