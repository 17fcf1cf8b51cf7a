"""The KITTI evaluator on cases whose answer can be derived by hand."""
import numpy as np
import pytest

from harness.core.boxes import iou_3d, iou_bev
from harness.core.kitti import Labels, kitti_calib
from harness.eval_kitti import (DIFFICULTIES, Filter, build_eval_set, frame_overlaps, get_thresholds,
                                image_box_overlap,
                                kitti_ap, precision_recall)


def labels(rows, score=None, alpha=None):
    """rows: (name, bbox top, bbox height, x, z, occluded, truncated)."""
    k = len(rows)
    if k == 0:
        return Labels.empty(with_score=score is not None)
    name = [r[0] for r in rows]
    bbox = np.array([[100 + 150 * i, r[1], 200 + 150 * i, r[1] + r[2]] for i, r in enumerate(rows)], float)
    loc = np.array([[r[3], 1.6, r[4]] for r in rows], float)
    return Labels(name=np.array(name, dtype=object), truncated=np.array([r[6] for r in rows], float),
                  occluded=np.array([r[5] for r in rows]), alpha=np.zeros(k) if alpha is None else np.asarray(alpha),
                  bbox=bbox, dimensions=np.tile([1.5, 1.6, 3.9], (k, 1)), location=loc,
                  rotation_y=np.zeros(k), score=None if score is None else np.asarray(score, float))


CAR = ("Car", 150, 60, 0.0, 20.0, 0, 0.0)  # easy


def car(x, z=20.0, height=60, occ=0, trunc=0.0, name="Car"):
    return (name, 150, height, x, z, occ, trunc)


N = 50  # frames are repeated: KITTI samples its 41 recall positions among the matched scores,
# so AP reaches 100 only with at least 41 ground-truth objects


def ap(gt, dt, metric="3d", overlap="0.7", level="moderate", kind="R40"):
    return kitti_ap(build_eval_set(gt * N, dt * N))[metric][overlap][kind][level]


def test_perfect_detections_give_100_and_aos_100():
    gt = [labels([car(-5), car(0), car(5)]), labels([car(2, 30)])]
    dt = [labels([car(-5), car(0), car(5)], score=[0.9, 0.8, 0.7]), labels([car(2, 30)], score=[0.6])]
    res = kitti_ap(build_eval_set(gt * N, dt * N))
    for metric in ("bbox", "bev", "3d", "aos"):
        for key in ("0.7", "0.5", "official_0.5"):
            for kind in ("R11", "R40"):
                assert res[metric][key][kind] == pytest.approx({"easy": 100, "moderate": 100, "hard": 100})


def test_few_objects_follow_the_reference_sampling():
    # 4 objects found perfectly give 4 thresholds: precision 1 at sample positions 0..3, 0 after
    res = kitti_ap(build_eval_set([labels([car(-5), car(0), car(5), car(9)])],
                                  [labels([car(-5), car(0), car(5), car(9)], score=[0.9, 0.8, 0.7, 0.6])]))
    assert res["3d"]["0.7"]["R40"]["moderate"] == pytest.approx(3 / 40 * 100)
    assert res["3d"]["0.7"]["R11"]["moderate"] == pytest.approx(100 / 11)


def test_no_detections_and_no_ground_truth_give_0():
    gt = [labels([car(0)])]
    assert ap(gt, [labels([], score=[])]) == 0.0
    assert ap([labels([])], [labels([car(0)], score=[0.9])]) == 0.0
    assert ap([labels([])], [labels([], score=[])]) == 0.0


def test_only_false_positives_give_0_and_fp_below_tp_keeps_100():
    gt = [labels([car(0)])]
    assert ap(gt, [labels([car(8)], score=[0.9])]) == 0.0
    # a false positive scored below the only true positive does not lower AP
    assert ap(gt, [labels([car(0), car(8)], score=[0.9, 0.1])]) == pytest.approx(100.0)
    # ... scored above it: precision 1/2 at every recall point
    assert ap(gt, [labels([car(0), car(8)], score=[0.1, 0.9])]) == pytest.approx(50.0)
    assert ap(gt, [labels([car(0), car(8)], score=[0.1, 0.9])], kind="R11") == pytest.approx(50.0)


def test_half_recall_r11_and_r40():
    gt = [labels([car(0), car(6)])]
    dt = [labels([car(0)], score=[0.9])]
    # recall 0.5 with precision 1: R40 counts recall points 1/40..20/40 -> 20/40; R11 0,0.1,..,0.5 -> 6/11
    assert ap(gt, dt, kind="R40") == pytest.approx(50.0)
    assert ap(gt, dt, kind="R11") == pytest.approx(600 / 11)


def test_van_and_dontcare_are_ignored():
    gt = [labels([car(0), car(6, name="Van")])]
    dt = [labels([car(0), car(6)], score=[0.9, 0.95])]
    assert ap(gt, dt) == pytest.approx(100.0)  # detection on a Van: neither TP nor FP
    gt = [labels([car(0), car(6, name="DontCare")])]
    dt = [labels([car(0), car(6)], score=[0.9, 0.95])]
    assert ap(gt, dt, metric="bbox") == pytest.approx(100.0)  # DontCare absorbs the 2D FP
    assert ap(gt, dt, metric="3d") == pytest.approx(50.0)  # ... only in the 2D metric, as in KITTI


def test_difficulty_boundaries():
    # height exactly 40 px is not easy (<= 40 ignored), 41 px is; occlusion 1 is moderate; trunc 0.3 ok for moderate
    gt = [labels([car(0, height=40), car(6, height=41)])]
    dt = [labels([car(0, height=40), car(6, height=41)], score=[0.9, 0.8])]
    assert ap(gt, dt, level="easy") == pytest.approx(100.0)
    gt = [labels([car(0, occ=1, trunc=0.3)])]
    res = kitti_ap(build_eval_set(gt * N, [labels([], score=[])] * N))["3d"]["0.7"]["R40"]
    assert res["moderate"] == 0.0 and res["hard"] == 0.0
    found = [labels([car(0, occ=1, trunc=0.3)], score=[0.5])]
    missed = kitti_ap(build_eval_set(gt * N, found * N))["3d"]["0.7"]["R40"]
    assert missed == pytest.approx({"easy": 0.0, "moderate": 100.0, "hard": 100.0})
    # a detection smaller than 25 px is ignored, not a false positive
    gt = [labels([car(0)])]
    dt = [labels([car(0), car(9, height=20)], score=[0.5, 0.9])]
    assert ap(gt, dt) == pytest.approx(100.0)


def test_heading_flipped_by_pi_halves_nothing_but_aos():
    gt = [labels([car(0), car(6)])]
    dt = [labels([car(0), car(6)], score=[0.9, 0.8], alpha=[np.pi, 0.0])]
    res = kitti_ap(build_eval_set(gt * N, dt * N))
    assert res["bbox"]["0.7"]["R40"]["moderate"] == pytest.approx(100.0)
    # precision 1 everywhere; similarity (1+cos(pi))/2 = 0 for the first TP, 1 for the second:
    # at recall 1/2 the cumulative similarity is 0/1, at recall 1 it is 1/2, interpolated to the right -> 50
    assert res["aos"]["0.7"]["R40"]["moderate"] == pytest.approx(50.0)


def test_3d_overlap_threshold_is_strict():
    gt = [labels([car(0)])]
    shifted = labels([car(0)], score=[0.9])
    # shift along the length (rotation_y = 0: length along camera x): IoU = (3.9 - d) / (3.9 + d)
    d = 3.9 * 0.3 / 1.7  # IoU exactly 0.7 -> not a match (overlap must be > 0.7)
    shifted.location[0, 0] += d + 1e-6
    assert ap(gt, [shifted]) == 0.0
    shifted.location[0, 0] -= 2e-6
    assert ap(gt, [shifted]) == pytest.approx(100.0)


def test_distance_filter_and_height_off():
    far = car(0, z=55.0, height=20)  # a far car is below 25 px: every KITTI difficulty ignores it
    gt = [labels([far, car(3)])]
    dt = [labels([car(3)], score=[0.9])]
    es = build_eval_set(gt * N, dt * N)
    assert kitti_ap(es)["3d"]["0.7"]["R40"]["hard"] == pytest.approx(100.0)
    all_cars = Filter("all")
    assert kitti_ap(es, filters=[all_cars])["3d"]["0.7"]["R40"]["all"] == pytest.approx(50.0)
    near, mid = Filter("0-30", min_distance=0, max_distance=30), Filter("50-80", min_distance=50, max_distance=80)
    res = kitti_ap(es, filters=[near, mid])["3d"]["0.7"]["R40"]
    assert res == pytest.approx({"0-30": 100.0, "50-80": 0.0})


def test_get_thresholds_and_image_overlap():
    np.testing.assert_allclose(get_thresholds(np.array([0.9, 0.5, 0.7]), 3), [0.9, 0.7, 0.5])
    assert len(get_thresholds(np.linspace(0, 1, 200), 200)) == 41
    a = np.array([[0, 0, 10, 10]])
    b = np.array([[5, 0, 15, 10]])
    assert image_box_overlap(a, b)[0, 0] == pytest.approx(50 / 150)
    assert image_box_overlap(a, b, 0)[0, 0] == pytest.approx(0.5)


def test_frame_subsets_equal_separate_sets():
    rng = np.random.default_rng(0)
    gts, dts = [], []
    for _ in range(12):
        n = rng.integers(0, 4)
        xs = rng.uniform(-8, 8, n)
        gts.append(labels([car(x) for x in xs]))
        found = xs[rng.uniform(size=n) < 0.7]
        keep = found + rng.normal(0, 0.3, len(found))
        dts.append(labels([car(x) for x in keep], score=rng.uniform(size=len(keep))))
    es = build_eval_set(gts, dts)
    sub = [1, 3, 5, 7]
    a = kitti_ap(es, frames=sub)
    b = kitti_ap(build_eval_set([gts[i] for i in sub], [dts[i] for i in sub]))
    assert a == b
    pr = precision_recall(es, "bev", DIFFICULTIES[1], 0.7)
    assert (np.diff(pr["precision"]) <= 1e-12).all()  # interpolated precision never rises


def _reference_corners(x, z, l, w, ry):
    """kitti_object_eval_python's rbbox_to_corners: the (l, w) rectangle turned by
    [[cos, sin], [-sin, cos]] in the camera's (x, z) plane."""
    c, s = np.cos(ry), np.sin(ry)
    cx = np.array([-l, -l, l, l]) / 2
    cz = np.array([-w, w, w, -w]) / 2
    return np.c_[c * cx + s * cz + x, -s * cx + c * cz + z]


def _reference_overlaps(dt: Labels, gt: Labels):
    """BEV and 3D IoU as the reference computes them (shapely for the polygon intersection)."""
    from shapely.geometry import Polygon
    def poly(lab, i):
        return Polygon(_reference_corners(lab.location[i, 0], lab.location[i, 2], lab.dimensions[i, 2],
                                          lab.dimensions[i, 1], lab.rotation_y[i]))
    bev, d3 = np.zeros((len(dt), len(gt))), np.zeros((len(dt), len(gt)))
    for i in range(len(dt)):
        for j in range(len(gt)):
            inter = poly(dt, i).intersection(poly(gt, j)).area
            (hd, wd, ld), (hg, wg, lg) = dt.dimensions[i], gt.dimensions[j]
            bev[i, j] = inter / (ld * wd + lg * wg - inter)
            # camera y points down: a box spans [y - h, y]
            dy = min(dt.location[i, 1], gt.location[j, 1]) - max(dt.location[i, 1] - hd, gt.location[j, 1] - hg)
            inc = inter * max(dy, 0.0)
            d3[i, j] = inc / (ld * wd * hd + lg * wg * hg - inc)
    return bev, d3


def test_overlaps_of_turned_boxes_follow_the_reference_and_the_lidar_frame():
    """BEV and 3D IoU of cars at random headings, 0.3-1.5 m apart: the evaluator's camera-frame
    overlaps equal the reference's corner formula and the LiDAR-frame IoU of the same boxes."""
    rng = np.random.default_rng(7)
    k = 40
    gt_lidar = np.c_[rng.uniform(5, 60, k), rng.uniform(-10, 10, k), rng.uniform(-1.2, -0.6, k),
                     rng.uniform(3.5, 4.8, k), rng.uniform(1.6, 2.0, k), rng.uniform(1.3, 1.8, k),
                     rng.uniform(-np.pi, np.pi, k)]
    dt_lidar = gt_lidar + np.c_[rng.uniform(-1, 1, (k, 3)), rng.uniform(-0.3, 0.3, (k, 3)),
                                rng.uniform(-0.4, 0.4, k)]
    calib = kitti_calib()
    gt = Labels.from_lidar(gt_lidar, calib, ["Car"] * k)
    dt = Labels.from_lidar(dt_lidar, calib, ["Car"] * k, score=np.ones(k))
    ov = frame_overlaps(dt, gt)
    bev, d3 = _reference_overlaps(dt, gt)
    assert (np.diag(bev) > 0.2).sum() > k // 2 and (np.abs(gt.rotation_y % (np.pi / 2)) > 0.05).sum() > k // 2
    np.testing.assert_allclose(ov["bev"], bev, atol=1e-9)
    np.testing.assert_allclose(ov["3d"], d3, atol=1e-9)
    np.testing.assert_allclose(ov["bev"], iou_bev(dt_lidar, gt_lidar), atol=1e-9)
    np.testing.assert_allclose(ov["3d"], iou_3d(dt_lidar, gt_lidar), atol=1e-9)


def _brute_force_pr(gt_x, dt_x, dt_score):
    """Precision and recall at each distinct score of a matched detection, by counting: frames of cars
    at distinct x (5 m apart) and detections exactly on a car (a hit) or 2.5 m from every car (IoU 0),
    so a car is found at threshold t when one of its detections scores >= t, and every other kept
    detection (a miss or a second one on a found car) is a false positive."""
    n_gt = sum(len(g) for g in gt_x)
    best = [max((s for x, s in zip(dx, ds) if x == car_x), default=None)  # each car's best score
            for gx, dx, ds in zip(gt_x, dt_x, dt_score) for car_x in gx]
    matched = sorted({b for b in best if b is not None}, reverse=True)
    all_scores = np.concatenate([np.asarray(s, float) for s in dt_score])
    prec, rec = [], []
    for t in matched:
        tp = sum(b is not None and b >= t for b in best)
        prec.append(tp / (all_scores >= t).sum())
        rec.append(tp / n_gt)
    return np.array(matched), np.array(prec), np.array(rec)


def test_score_pr_curve_against_brute_force_counting():
    from harness.eval_kitti import score_pr_curve
    rng = np.random.default_rng(7)
    for _ in range(5):
        gt_x, dt_x, dt_score = [], [], []
        for _ in range(rng.integers(1, 6)):
            cars = sorted(rng.choice(np.arange(-10, 11, 5), rng.integers(0, 4), replace=False).tolist())
            dets = [x for x in cars if rng.random() < 0.8] + [x for x in cars if rng.random() < 0.3]  # hits, doubles
            dets += (rng.choice(np.arange(-10, 11, 5), rng.integers(0, 3)) + 2.5).tolist()  # misses
            gt_x.append(cars)
            dt_x.append(dets)
            dt_score.append(np.round(rng.uniform(0, 1, len(dets)), 2).tolist())  # ties happen
        es = build_eval_set([labels([car(x) for x in g]) for g in gt_x],
                            [labels([car(x) for x in d], score=s) for d, s in zip(dt_x, dt_score)])
        got = score_pr_curve(es, "3d", Filter("all"), 0.7)
        score, prec, rec = _brute_force_pr(gt_x, dt_x, dt_score)
        assert np.allclose(got["score"], score) and np.allclose(got["precision"], prec)
        assert np.allclose(got["recall"], rec)


def test_score_pr_curve_of_a_perfect_detector_reaches_recall_1_at_precision_1():
    from harness.eval_kitti import score_pr_curve
    gt = [labels([car(-5), car(0), car(5)]), labels([car(2, 30)])]
    dt = [labels([car(-5), car(0), car(5)], score=[0.9, 0.8, 0.7]), labels([car(2, 30)], score=[0.6])]
    got = score_pr_curve(build_eval_set(gt, dt), "3d", Filter("all"), 0.7)
    assert got["score"].tolist() == [0.9, 0.8, 0.7, 0.6] and got["recall"].tolist() == [0.25, 0.5, 0.75, 1.0]
    assert got["precision"].tolist() == [1.0] * 4
    empty = score_pr_curve(build_eval_set([labels([car(0)])], [labels([], score=[])]), "3d", Filter("all"), 0.7)
    assert all(len(v) == 0 for v in empty.values())


def test_score_pr_curve_keeps_at_most_max_points_and_both_ends():
    from harness.eval_kitti import score_pr_curve
    xs = np.arange(-20, 21, 5)
    gt = [labels([car(x) for x in xs])] * 40  # 360 cars, each found once with its own score
    scores = np.linspace(0.99, 0.01, 360).reshape(40, len(xs))
    es = build_eval_set(gt, [labels([car(x) for x in xs], score=s) for s in scores])
    full, thin = score_pr_curve(es, "3d", Filter("all"), 0.7, max_points=1000), score_pr_curve(es, "3d", Filter("all"), 0.7)
    assert len(full["score"]) == 360 and len(thin["score"]) == 200
    assert thin["score"][0] == full["score"][0] and thin["score"][-1] == full["score"][-1] and thin["recall"][-1] == 1.0
    idx = np.searchsorted(-full["score"], -thin["score"])  # every kept point is a point of the full curve
    assert np.array_equal(full["recall"][idx], thin["recall"]) and np.array_equal(full["precision"][idx], thin["precision"])
