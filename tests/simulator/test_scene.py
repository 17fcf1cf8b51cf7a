import numpy as np
import pytest

from harness.core.boxes import iou_bev
from harness.core.braking import EGO_DIMS
from harness.core.kitti import kitti_calib
from simulator.camera import camera_rays
from simulator.labels import lidar_boxes
from simulator.lidar import Pose, rotate_yaw
from simulator.road import RoadConfig, centreline, lane_center, road_to_world
from simulator.scenario import SotifConfig, sotif_run, training_scene
from simulator.vehicles import BODY_NAMES, BODY_TYPES, vehicle_mesh

ROAD = RoadConfig()


def test_centreline_is_unit_speed_and_heading_is_tangent():
    s = np.sort(np.random.default_rng(0).uniform(0, ROAD.length, 200))
    x, y, h = centreline(ROAD, s)
    x2, y2, _ = centreline(ROAD, s + 1e-4)
    np.testing.assert_allclose(np.hypot(x2 - x, y2 - y) / 1e-4, 1.0, atol=1e-5)
    np.testing.assert_allclose(np.arctan2(y2 - y, x2 - x), h, atol=1e-4)
    xd, yd, _ = road_to_world(ROAD, s, np.full(200, -5.0))
    np.testing.assert_allclose(np.hypot(xd - x, yd - y), 5.0)
    assert lane_center(ROAD, 1) < lane_center(ROAD, 4) < 0 < lane_center(ROAD, 4, oncoming=True)


def test_rotate_yaw_matches_matrix():
    rng = np.random.default_rng(1)
    v, yaw = rng.normal(size=(100, 3)), rng.uniform(-4, 4)
    np.testing.assert_allclose(rotate_yaw(v, yaw), v @ Pose(0, 0, yaw).rotation().T, atol=1e-12)


def test_camera_rays_reproject_to_their_pixels():
    calib = kitti_calib(width=300, height=90, focal=250.0, cam_in_lidar=(0.4, 0.1, -0.2))
    centre, dirs = camera_rays(calib.lidar2img(), 300, 90, 3)
    depth = np.random.default_rng(2).uniform(2, 80, dirs.shape[:2])
    pts = centre + dirs * depth[..., None]
    uv, d = calib.project_lidar(pts.reshape(-1, 3))
    u = (np.arange(100) + 0.5) * 3 - 0.5
    v = (np.arange(30) + 0.5) * 3 - 0.5
    uu, vv = np.meshgrid(u, v)
    np.testing.assert_allclose(uv, np.c_[uu.ravel(), vv.ravel()], atol=1e-3)
    assert (d > 0).all()
    np.testing.assert_allclose(centre, [0.4, 0.1, -0.2], atol=1e-4)


@pytest.mark.parametrize("body", BODY_NAMES)
def test_vehicle_mesh_spans_its_box(body):
    dims = np.array(BODY_TYPES[body].dims) * 1.03
    tris, mats = vehicle_mesh(body, dims, "red")
    v = tris.reshape(-1, 3)
    np.testing.assert_allclose(v.min(0), [-dims[0] / 2, -dims[1] / 2, -dims[2] / 2], atol=1e-9)
    np.testing.assert_allclose(v.max(0), [dims[0] / 2, dims[1] / 2, dims[2] / 2], atol=1e-9)
    assert len(mats) == len(tris) and len(np.unique(mats)) >= 4


def _lateral(x: float, y: float) -> float:
    """Signed offset from the median by brute-force nearest point on the centreline."""
    s = np.arange(0.0, ROAD.length, 0.01)
    cx, cy, h = centreline(ROAD, s)
    i = np.argmin((cx - x) ** 2 + (cy - y) ** 2)
    return float(-(x - cx[i]) * np.sin(h[i]) + (y - cy[i]) * np.cos(h[i]))


def test_sotif_scenario_kinematics():
    sc = SotifConfig()
    frames = sotif_run(ROAD, 27, np.random.default_rng(0), sc)
    t_lc = frames[0].info["lane_change_time_s"]
    assert 0.5 <= t_lc <= 1.5
    for f in frames:
        slow, fast = f.vehicles[0], f.vehicles[1]
        gap = np.hypot(slow.x - fast.x, slow.y - fast.y) - (slow.dims[0] + fast.dims[0]) / 2
        box = lidar_boxes([slow, fast], f.pose, 1.73)
        if f.time_s <= t_lc - 0.01:
            assert gap > sc.trigger_gap - 1e-6 and abs(box[1, 1]) < 0.05  # fast car still in the ego lane
        assert abs(box[0, 1]) < 0.05  # slow car in the ego lane
        if f.time_s >= t_lc + sc.lane_change_duration:
            assert _lateral(fast.x, fast.y) == pytest.approx(lane_center(ROAD, sc.ego_lane + 1), abs=0.02)
    speeds = [f.ego_speed for f in frames]
    assert speeds[0] == sc.ego_speed and speeds[-1] < sc.slow_speed + 1.0
    assert all(a >= b - 1e-9 for a, b in zip(speeds, speeds[1:]))
    dist = [f.info["slow_car_distance_m"] for f in frames]
    assert 40 < min(dist) and max(dist) < 100  # about 80 m at the cut-out


def _footprint(v):
    from shapely.geometry import Polygon
    c, s_ = np.cos(v.heading), np.sin(v.heading)
    l, w = v.dims[0] / 2, v.dims[1] / 2
    return Polygon([(v.x + c * a - s_ * b, v.y + s_ * a + c * b) for a, b in ((l, w), (-l, w), (-l, -w), (l, -w))])


def test_the_fast_car_never_touches_the_slow_car_and_clears_it_at_the_cutout_gap():
    """Over the scenario space's corners (short gap, high closing speed, slow lane change, slow car offset
    towards the fast car's lane), the two bodies never overlap; once the fast car is CLEARANCE_M to the side of
    the slow car the bumper gap is the instance's cut-out gap (within one step's closing)."""
    from dataclasses import replace

    from simulator.scenario import CLEARANCE_M
    from simulator.space import STUDY
    cases = [(STUDY, 0.0), (replace(STUDY, ego_speed_kmh=130.0, slow_speed_kmh=30.0, cutout_gap_m=5.0,
                                    lane_change_s=5.0, slow_body="truck"), 0.5),
             (replace(STUDY, ego_speed_kmh=120.0, cutout_gap_m=5.0, lane_change_s=2.5, fast_body="van"), -0.5)]
    for inst, offset in cases:
        sc = replace(inst.sotif_config(), record_every=1)
        run = sotif_run(ROAD, 80, np.random.default_rng(0), sc, slow_offset=offset)
        closing = sc.ego_speed - sc.slow_speed
        cleared = None
        for f in run:
            slow, fast = _footprint(f.vehicles[0]), _footprint(f.vehicles[1])
            assert slow.intersection(fast).area == 0.0, (inst, f.time_s)
            side = abs(_lateral(f.vehicles[1].x, f.vehicles[1].y) - _lateral(f.vehicles[0].x, f.vehicles[0].y))
            if cleared is None and side >= (f.vehicles[0].dims[1] + f.vehicles[1].dims[1]) / 2 + CLEARANCE_M:
                cleared = f
        assert cleared is not None
        gap = np.hypot(cleared.vehicles[0].x - cleared.vehicles[1].x, cleared.vehicles[0].y - cleared.vehicles[1].y) \
            - (cleared.vehicles[0].dims[0] + cleared.vehicles[1].dims[0]) / 2
        assert sc.trigger_gap - closing * sc.dt - 0.05 <= gap <= sc.trigger_gap + 0.05


def test_training_scenes_do_not_overlap():
    for seed in range(5):
        state = training_scene(ROAD, np.random.default_rng(seed))
        boxes = lidar_boxes(state.vehicles, state.pose, 1.73)
        ego = np.array([[0.0, 0.0, 0.0, *EGO_DIMS, 0.0]])
        iou = iou_bev(np.r_[ego, boxes], np.r_[ego, boxes])
        np.fill_diagonal(iou, 0)
        assert iou.max() == 0 and len(boxes) >= 3
        assert (boxes[:, 0] > -50).all() and (boxes[:, 0] < 105).all()


def test_camera_brightness_follows_weather_and_cars_show_in_their_box(highway_scene):
    from simulator.camera import CameraSpec, render
    from simulator.labels import projected_boxes
    from simulator.vehicles import Vehicle
    from simulator.weather import WEATHER_PRESETS

    spec = CameraSpec(width=300, height=90, downsample=2)
    calib = kitti_calib(width=300, height=90, focal=175.0)
    x, y, h = road_to_world(ROAD, np.array(150.0), np.array(lane_center(ROAD, 3)))
    pose = Pose(float(x), float(y), float(h))
    car = Vehicle("sedan", (4.75, 1.83, 1.45), "red", pose.x + 15 * np.cos(h), pose.y + 15 * np.sin(h), float(h), 25.0)
    imgs = {}
    for vehicles in ([], [car]):
        highway_scene.set_vehicles(vehicles)
        for name in ("ClearNoon", "HardRainNoon", "ClearNight"):
            imgs[name, len(vehicles)] = render(highway_scene, calib.lidar2img(), pose, 1.73, WEATHER_PRESETS[name],
                                               np.random.default_rng(0), spec).astype(float)
    mean = {k: v.mean() for k, v in imgs.items()}
    assert mean["ClearNoon", 0] > mean["HardRainNoon", 0] > mean["ClearNight", 0]
    l, t, r, b = projected_boxes(lidar_boxes([car], pose, 1.73), calib)[0][0].astype(int)
    inside = np.abs(imgs["ClearNoon", 1] - imgs["ClearNoon", 0])[t:b, l:r].mean()
    outside = np.abs(imgs["ClearNoon", 1] - imgs["ClearNoon", 0])[:, :max(l - 10, 1)].mean()
    assert inside > 20 and outside < 1
    assert imgs["ClearNoon", 1][t:b, l:r, 0].mean() > imgs["ClearNoon", 1][t:b, l:r, 2].mean()  # red paint


_POKE_DURING_IMPORT = """
import importlib.abc, os, signal, sys
# Python's own handler, whatever the test run inherited (a background job started without job
# control, as by nohup or `make test &` in a script, ignores SIGINT, and so would this child)
signal.signal(signal.SIGINT, signal.default_int_handler)
class Poke(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "trimesh.voxel":  # imported inside trimesh's `except BaseException`
            os.kill(os.getpid(), signal.SIGINT)
        return None
sys.meta_path.insert(0, Poke())
try:
    import simulator.prims
except KeyboardInterrupt:
    sys.exit(3)
sys.exit(0)
"""


def test_a_ctrl_c_during_the_trimesh_import_is_not_swallowed():
    import subprocess
    import sys
    res = subprocess.run([sys.executable, "-c", _POKE_DURING_IMPORT], capture_output=True, text=True, timeout=120)
    assert res.returncode == 3, res.stderr
