"""BEV visibility: hand-worked occlusion and range, and a shapely ray test on random scenes."""
import numpy as np
import pytest
from shapely.geometry import LineString, Polygon

from harness.core import visibility
from harness.core.boxes import corners_bev

SLOW = np.array([50.0 + 4.75 / 2, 0.0, -0.9, 4.75, 1.83, 1.45, 0.0])


def test_footprint_samples_cover_the_box():
    pts = visibility.footprint_samples(SLOW)
    assert pts.shape == (visibility.GRID_L * visibility.GRID_W, 2)
    assert pts[:, 0].min() > 50.0 and pts[:, 0].max() < 54.75 and np.abs(pts[:, 1]).max() < 1.83 / 2
    assert pts.mean(0) == pytest.approx(SLOW[:2])
    turned = visibility.footprint_samples(np.r_[SLOW[:6], np.pi / 2])
    assert np.ptp(turned[:, 1]) > np.ptp(turned[:, 0])


def test_hidden_half_hidden_and_out_of_range():
    fast = np.array([20.0, 0.0, -0.9, 4.15, 1.78, 1.5, 0.0])  # straight ahead, between the sensor and the slow car
    assert visibility.footprint_shares(SLOW, fast[None])["unoccluded"] == 0.0
    # moved 0.9 m left (it spans y 0.01-1.79 m): it hides the 2 of the 5 sample rows across the width that lie
    # left of the centre line; the rays to the others pass right of it
    half = visibility.footprint_shares(SLOW, np.r_[fast[0], 0.9, fast[2:]][None])
    assert half["unoccluded"] == pytest.approx(3 / 5)
    # a lane over (3.5 m): nothing hidden
    assert visibility.footprint_shares(SLOW, np.r_[fast[0], 3.5, fast[2:]][None])["unoccluded"] == 1.0
    # a box behind the slow car hides nothing
    assert visibility.footprint_shares(SLOW, np.r_[70.0, fast[1:]][None])["visible"] == 1.0
    # 78 m ahead, 4.75 m long: only the samples up to 80 m are in range (the first 5 of 12 along the length)
    far = np.r_[78.0 + 4.75 / 2, SLOW[1:]]
    assert visibility.footprint_shares(far, np.zeros((0, 7)))["in_range"] == pytest.approx(5 / 12)
    assert visibility.footprint_shares(np.r_[90.0, SLOW[1:]], np.zeros((0, 7)))["visible"] == 0.0


def test_segments_cross_boxes_against_shapely():
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = int(rng.integers(1, 8))
        boxes = np.c_[rng.uniform(-20, 40, n), rng.uniform(-15, 15, n), np.zeros(n), rng.uniform(1, 12, n),
                      rng.uniform(0.5, 3, n), np.ones(n), rng.uniform(-np.pi, np.pi, n)]
        ends = np.c_[rng.uniform(-30, 60, 50), rng.uniform(-20, 20, 50)]
        got = visibility.segments_cross_boxes(ends, boxes)
        polys = [Polygon(c) for c in corners_bev(boxes)]
        want = np.array([[LineString([(0, 0), tuple(e)]).intersects(p) for p in polys] for e in ends])
        assert (got == want).all()
    # axis-parallel segments (a zero direction component) and an end inside a box
    box = np.array([[10.0, 0.0, 0, 2.0, 2.0, 1, 0.0]])
    assert visibility.segments_cross_boxes([[20.0, 0.0], [0.0, 5.0], [10.0, 0.5], [20.0, 1.0], [20.0, 2.5]], box)[:, 0].tolist() \
        == [True, False, True, True, False]
    assert visibility.segments_cross_boxes(np.zeros((0, 2)), box).shape == (0, 1)
