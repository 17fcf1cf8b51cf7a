import numpy as np
import pytest
import shapely
from hypothesis import given, settings, strategies as st

from harness.core.boxes import corners_3d, corners_bev, iou_3d, iou_bev, nms_bev, points_in_boxes, wrap_angle


def random_boxes(rng, n, spread=4.0):
    return np.c_[rng.uniform(-spread, spread, (n, 2)), rng.uniform(-1, 1, n),
                 rng.uniform(0.5, 5, n), rng.uniform(0.5, 3, n), rng.uniform(0.5, 2, n),
                 rng.uniform(-np.pi, np.pi, n)]


def shapely_iou_bev(a, b):
    pa = shapely.polygons(corners_bev(a))
    pb = shapely.polygons(corners_bev(b))
    inter = shapely.area(shapely.intersection(pa[:, None], pb[None]))
    union = shapely.area(pa)[:, None] + shapely.area(pb)[None] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def test_iou_bev_matches_shapely_on_random_boxes():
    rng = np.random.default_rng(0)
    a, b = random_boxes(rng, 60), random_boxes(rng, 50)
    np.testing.assert_allclose(iou_bev(a, b), shapely_iou_bev(a, b), atol=1e-9)


def test_iou_3d_matches_shapely_times_height_overlap():
    rng = np.random.default_rng(1)
    a, b = random_boxes(rng, 40), random_boxes(rng, 30)
    pa, pb = shapely.polygons(corners_bev(a)), shapely.polygons(corners_bev(b))
    inter = shapely.area(shapely.intersection(pa[:, None], pb[None]))
    dz = np.clip(np.minimum(a[:, None, 2] + a[:, None, 5] / 2, b[None, :, 2] + b[None, :, 5] / 2)
                 - np.maximum(a[:, None, 2] - a[:, None, 5] / 2, b[None, :, 2] - b[None, :, 5] / 2), 0, None)
    vol = inter * dz
    ref = vol / ((a[:, 3] * a[:, 4] * a[:, 5])[:, None] + (b[:, 3] * b[:, 4] * b[:, 5])[None] - vol)
    np.testing.assert_allclose(iou_3d(a, b), ref, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=7, max_size=7), st.lists(st.floats(-3, 3), min_size=7, max_size=7))
def test_iou_bev_matches_shapely_hypothesis(u, v):
    a = np.array([[u[0], u[1], u[2], abs(u[3]) + 0.1, abs(u[4]) + 0.1, 1.0, u[6]]])
    b = np.array([[v[0], v[1], v[2], abs(v[3]) + 0.1, abs(v[4]) + 0.1, 1.0, v[6]]])
    np.testing.assert_allclose(iou_bev(a, b), shapely_iou_bev(a, b), atol=1e-7)


def test_special_cases_identical_nested_touching_degenerate():
    box = np.array([[0, 0, 0, 4, 2, 1.5, 0.3]])
    assert iou_bev(box, box)[0, 0] == pytest.approx(1.0)
    assert iou_3d(box, box)[0, 0] == pytest.approx(1.0)
    inner = np.array([[0, 0, 0, 2, 1, 1.5, 0.3]])
    assert iou_bev(box, inner)[0, 0] == pytest.approx(0.25)
    touching = np.array([[0, 0, 0, 2, 2, 1, 0], [2, 0, 0, 2, 2, 1, 0]])
    assert iou_bev(touching[:1], touching[1:])[0, 0] == pytest.approx(0.0, abs=1e-12)
    flat = np.array([[0, 0, 0, 4, 0, 1.5, 0.3]])
    assert iou_bev(flat, box)[0, 0] == 0.0 and iou_bev(box, flat)[0, 0] == 0.0
    assert iou_bev(flat, flat)[0, 0] == 0.0
    stacked = np.array([[0, 0, 2.0, 4, 2, 1.0, 0.3]])  # same footprint, no height overlap
    assert iou_3d(box, stacked)[0, 0] == 0.0
    assert iou_bev(box, np.zeros((0, 7))).shape == (1, 0)
    rotated = box.copy()
    rotated[0, 6] += np.pi  # a box turned by pi covers the same area
    assert iou_bev(box, rotated)[0, 0] == pytest.approx(1.0)


def test_corners_and_wrap():
    box = np.array([[1, 2, 3, 4, 2, 1, np.pi / 2]])
    c = corners_3d(box)[0]
    np.testing.assert_allclose(c.mean(axis=0), [1, 2, 3])
    np.testing.assert_allclose(np.ptp(c, axis=0), [2, 4, 1], atol=1e-12)  # l along +y at yaw=pi/2
    assert wrap_angle(np.pi) == pytest.approx(-np.pi)
    a = np.random.default_rng(0).uniform(-20, 20, 1000)
    w = wrap_angle(a)
    assert ((w >= -np.pi) & (w < np.pi)).all()
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-9)


def test_nms_bev_against_brute_force():
    rng = np.random.default_rng(2)
    boxes, scores = random_boxes(rng, 80, spread=3), rng.uniform(size=80)
    keep = nms_bev(boxes, scores, 0.3)
    iou = shapely_iou_bev(boxes, boxes)
    order, ref = np.argsort(-scores), []
    for i in order:
        if all(iou[i, j] <= 0.3 for j in ref):
            ref.append(i)
    assert keep.tolist() == ref


def test_points_in_boxes_brute_force():
    rng = np.random.default_rng(3)
    boxes, pts = random_boxes(rng, 10), rng.uniform(-6, 6, (500, 3))
    inside = points_in_boxes(pts, boxes)
    for k, b in enumerate(boxes):
        poly = shapely.polygons(corners_bev(b[None]))[0]
        ref = shapely.contains_xy(poly, pts[:, 0], pts[:, 1]) & (np.abs(pts[:, 2] - b[2]) <= b[5] / 2)
        assert (inside[:, k] == ref).all()
