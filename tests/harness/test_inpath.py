"""In-path hits and phantom boxes: hand-worked cases and brute-force references on random boxes."""
import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from harness import inpath
from harness.core.boxes import corners_bev

TRUCK = np.array([40.0 + 11.5 / 2, 0.0, -0.2, 11.5, 2.55, 3.8, 0.0])  # rear face 40 m ahead of the sensor


def _car(rear_m, y=0.0, yaw=0.0):
    return np.array([rear_m + 4.5 / 2, y, -0.9, 4.5, 1.9, 1.5, yaw])


def test_car_box_on_a_trucks_rear_face_is_a_hit():
    # the 4.5 x 1.9 m box spans 40-44.5 m: inside the truck's footprint, rear faces equal (BEV IoU 8.55 / 29.3 = 0.29)
    assert inpath.inpath_hits(_car(40.0), TRUCK).tolist() == [True]
    # 0.9 m short is within max(1 m, 3 % of 40 m = 1.2 m): still a hit; 3 m short is not, though it overlaps
    assert inpath.inpath_hits(_car(39.1), TRUCK).tolist() == [True]
    assert inpath.inpath_hits(_car(37.0), TRUCK).tolist() == [False]
    # a box in the next lane (3.5 m left, centres 3.5 m apart > 2 m, footprints apart) is not on the truck
    assert inpath.inpath_hits(_car(40.0, y=3.5), TRUCK).tolist() == [False]
    # a box whose heading is flipped (yaw pi) has the same rear face
    assert inpath.inpath_hits(_car(40.0, yaw=np.pi), TRUCK).tolist() == [True]


def test_rear_tolerance_and_rear_face_by_hand():
    assert inpath.rear_tolerance(20.0) == 1.0 and inpath.rear_tolerance(60.0) == pytest.approx(1.8)
    # a box turned 90 degrees: its rear face is its centre less half its width along the lane
    box = np.array([30.0, 0.0, 0.0, 4.0, 2.0, 1.5, np.pi / 2])
    assert inpath.rear_face(box, 0.0)[0] == pytest.approx(29.0)
    # along a lane turned 30 degrees, an aligned box's rear face is its centre's projection less l / 2
    yaw = np.pi / 6
    box = np.array([20 * np.cos(yaw), 20 * np.sin(yaw), 0, 4.0, 2.0, 1.5, yaw])
    assert inpath.rear_face(box, yaw)[0] == pytest.approx(18.0)


def test_rear_face_against_corner_projection(rng=np.random.default_rng(0)):
    for _ in range(200):
        b = np.r_[rng.uniform(-50, 50, 2), 0, rng.uniform(1, 12), rng.uniform(1, 3), 1.5, rng.uniform(-np.pi, np.pi)]
        lane = rng.uniform(-np.pi, np.pi)
        want = (corners_bev(b)[0] @ np.array([np.cos(lane), np.sin(lane)])).min()
        assert inpath.rear_face(b, lane)[0] == pytest.approx(want)


def _random_boxes(rng, n):
    return np.c_[rng.uniform(0, 30, n), rng.uniform(-6, 6, n), np.zeros(n), rng.uniform(1, 8, n),
                 rng.uniform(0.5, 3, n), np.ones(n), rng.uniform(-np.pi, np.pi, n)]


def test_on_objects_against_shapely():
    rng = np.random.default_rng(1)
    a, b = _random_boxes(rng, 40), _random_boxes(rng, 30)
    got = inpath.on_objects(a, b)
    for i in range(len(a)):
        for j in range(len(b)):
            pa, pb = Polygon(corners_bev(a[i])[0]), Polygon(corners_bev(b[j])[0])
            near = np.hypot(*(a[i, :2] - b[j, :2])) <= 2.0
            assert got[i, j] == (near or pa.intersection(pb).area > 0), (i, j)
    assert inpath.on_objects(np.zeros((0, 7)), b).shape == (0, 30)


def test_lane_curvature_and_offset_by_hand():
    # a lane bending left with radius 1000 m: the arc through the origin along +x, at x = 60 m rising 1.8 m
    r, x = 1000.0, 60.0
    y, heading = r - np.sqrt(r * r - x * x), np.arcsin(x / r)
    slow = np.array([x, y, 0, 4.7, 1.9, 1.5, heading])
    assert inpath.lane_curvature(slow) == pytest.approx(1 / r)
    left = [x - np.sin(heading), y + np.cos(heading)]  # 1 m to the left of the lane, across it
    assert inpath.lane_offset([left, [0.0, -0.5]], 1 / r) == pytest.approx([1.0, -0.5], abs=1e-6)
    # a slow car 0.4 m left of its lane centre on a straight lane: the lane is the x axis
    assert inpath.lane_curvature(np.array([50.0, 0.4, 0, 4.7, 1.9, 1.5, 0.0]), 0.4) == pytest.approx(0.0)
    assert inpath.lane_offset([[10.0, 1.0]], 0.0).tolist() == [1.0]


def test_lane_offset_against_distance_to_the_circle():
    """|offset| is the distance to the arc's circle; positive on the side of its left normal (inside a left bend,
    outside a right one)."""
    rng = np.random.default_rng(2)
    for k in rng.uniform(-0.01, 0.01, 50):
        p = np.c_[rng.uniform(0, 80, 20), rng.uniform(-10, 10, 20)]
        disc = Point(0, 1 / k).buffer(abs(1 / k), 4096)
        dist = np.array([disc.exterior.distance(Point(*q)) for q in p])
        side = np.array([1.0 if disc.contains(Point(*q)) else -1.0 for q in p]) * np.sign(k)
        got = inpath.lane_offset(p, k)
        assert np.allclose(np.abs(got), dist, atol=2e-3)
        clear = dist > 1e-2
        assert np.all(np.sign(got[clear]) == side[clear])


def test_phantoms_by_hand():
    objects = np.stack([TRUCK, _car(20.0, y=3.5)])
    ghosts = np.stack([_car(15.0), _car(15.0, y=3.5), _car(40.0), _car(21.0, y=3.5), _car(85.0), _car(-1.0)])
    # in the lane on nothing; next lane; on the truck; on the car; beyond 80 m; behind the ego's bumper
    assert inpath.phantoms(ghosts, objects, 0.0).tolist() == [True, False, False, False, False, False]
    assert inpath.phantoms(np.zeros((0, 7)), objects, 0.0).tolist() == []
    assert inpath.phantoms(ghosts[:1], np.zeros((0, 7)), 0.0).tolist() == [True]


def test_lane_curvature_recovers_random_arcs():
    """A slow car placed on the arc of curvature k (heading along it, offset o to the left of its lane centre)
    gives back k."""
    rng = np.random.default_rng(4)
    for k, s, o in zip(rng.uniform(-0.004, 0.004, 100), rng.uniform(10, 80, 100), rng.uniform(-0.5, 0.5, 100)):
        theta = k * s  # heading after an arc length s from the origin along +x
        centre = np.array([np.sin(theta) / k, (1 - np.cos(theta)) / k]) if abs(k) > 1e-12 else np.array([s, 0.0])
        left = np.array([-np.sin(theta), np.cos(theta)])
        x, y = centre + o * left
        assert inpath.lane_curvature(np.array([x, y, 0, 4.7, 1.9, 1.5, theta]), o) == pytest.approx(k, abs=1e-9)
