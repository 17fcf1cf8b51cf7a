import numpy as np
import pytest

from harness.boxes import points_in_boxes
from simulator.labels import lidar_boxes
from simulator.lidar import LidarSpec, Pose, carla_spec, detection_range, ray_directions, scan
from simulator.road import RoadConfig, lane_center, road_to_world
from simulator.scenario import training_scene
from simulator.vehicles import Vehicle
from simulator.weather import WEATHER_PRESETS

ROAD = RoadConfig()


def _pose(s: float = 200.0, lane: int = 3) -> Pose:
    x, y, h = road_to_world(ROAD, np.array(s), np.array(lane_center(ROAD, lane)))
    return Pose(float(x), float(y), float(h))


def _car(pose: Pose, dx: float, dy: float, body: str = "sedan", dims=(4.75, 1.83, 1.45), paint="white") -> Vehicle:
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    return Vehicle(body, dims, paint, pose.x + c * dx - s * dy, pose.y + s * dx + c * dy, pose.yaw, 25.0)


def test_ray_pattern_matches_spec():
    spec = LidarSpec()
    d = ray_directions(spec)
    assert d.shape == (64 * spec.n_azimuth, 3) and spec.n_azimuth == 2118
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-12)
    el = np.rad2deg(np.arcsin(d[:, 2])).reshape(64, -1)
    np.testing.assert_allclose(el[:, 0], spec.elevations_deg, atol=1e-9)
    assert el.max() == pytest.approx(2.0) and el.min() == pytest.approx(-24.8)
    np.testing.assert_allclose(np.diff(carla_spec().elevations_deg), -26.8 / 63)


def test_boxes_contain_their_vehicles_points(highway_scene):
    rng = np.random.default_rng(0)
    state = training_scene(ROAD, rng)
    highway_scene.set_vehicles(state.vehicles)
    pts = scan(highway_scene, LidarSpec(), state.pose, WEATHER_PRESETS["ClearNoon"], state.vehicles, rng)
    dirs = pts[:, :3] / np.linalg.norm(pts[:, :3], axis=1, keepdims=True)
    hits = highway_scene.cast(np.array([state.pose.x, state.pose.y, 1.73]), dirs @ state.pose.rotation().T)
    boxes = lidar_boxes(state.vehicles, state.pose, 1.73)
    grown = boxes.copy()
    grown[:, 3:6] += 0.15  # range noise sigma 2 cm
    inside = points_in_boxes(pts, grown)
    on_vehicle = hits.actor >= 0
    assert on_vehicle.sum() > 200
    assert inside[np.flatnonzero(on_vehicle), hits.actor[on_vehicle]].mean() > 0.99
    assert points_in_boxes(pts[~on_vehicle & (np.abs(pts[:, 2] + 1.73) > 0.2)], boxes).sum() < 10


def _ranges(pts):
    return np.linalg.norm(pts[:, :3], axis=1)


def test_rain_reduces_points_and_range_monotonically(highway_scene):
    pose = _pose()
    vehicles = [_car(pose, 20, 0), _car(pose, 45, -3.5, paint="black"), _car(pose, 70, 3.5)]
    highway_scene.set_vehicles(vehicles)
    counts, far, reach = [], [], []
    for name in ("ClearNoon", "SoftRainNoon", "MidRainyNoon", "HardRainNoon"):
        pts = scan(highway_scene, LidarSpec(), pose, WEATHER_PRESETS[name], vehicles, np.random.default_rng(1))
        counts.append(len(pts))
        far.append(np.percentile(_ranges(pts), 95))  # range holding 95 % of the returns
        reach.append(detection_range(LidarSpec(), WEATHER_PRESETS[name], 0.02))
    assert counts == sorted(counts, reverse=True) and counts[0] > counts[-1] * 1.02
    assert far == sorted(far, reverse=True) and far[0] > far[-1] + 5
    assert reach[0] > 115 and all(a > b for a, b in zip(reach, reach[1:]))


def test_wet_road_loses_far_ground_returns(highway_scene):
    pose = _pose()
    highway_scene.set_vehicles([])
    n = {}
    for name in ("ClearNoon", "WetNoon"):
        pts = scan(highway_scene, LidarSpec(), pose, WEATHER_PRESETS[name], [], np.random.default_rng(2))
        road = (np.abs(pts[:, 2] + 1.73) < 0.1) & (np.abs(pts[:, 1]) < 8)
        n[name] = (road & (_ranges(pts) > 30)).sum(), (road & (_ranges(pts) < 10)).sum()
    assert n["WetNoon"][0] < 0.6 * n["ClearNoon"][0]
    assert n["WetNoon"][1] > 0.95 * n["ClearNoon"][1]


def test_carla_mode_ignores_weather(highway_scene):
    pose = _pose()
    vehicles = [_car(pose, 25, 0)]
    highway_scene.set_vehicles(vehicles)
    scans = [scan(highway_scene, carla_spec(), pose, WEATHER_PRESETS[n], vehicles, np.random.default_rng(3))
             for n in ("ClearNoon", "HardRainNight", "WetCloudySunset")]
    assert all(np.array_equal(scans[0], s) for s in scans[1:])
    d = _ranges(scans[0])
    np.testing.assert_allclose(scans[0][:, 3], np.exp(-0.004 * d), rtol=1e-5)
    physics = scan(highway_scene, LidarSpec(), pose, WEATHER_PRESETS["ClearNoon"], vehicles, np.random.default_rng(3))
    assert 0.4 < len(scans[0]) / len(physics) < 0.75  # CARLA drops ~45 % at random plus weak returns


def test_fused_hard_returns_match_effect_formulas():
    from simulator import effects
    from simulator.lidar import hard_returns
    from simulator.materials import GROUND, REFLECTIVITY

    rng = np.random.default_rng(5)
    n = 5000
    t = np.where(rng.random(n) < 0.1, np.inf, rng.uniform(0.2, 140, n))
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal *= -np.sign(np.sum(normal * dirs, 1))[:, None]
    mat = rng.choice([0, 1, 4, 9, 33, 40], n)
    noise = rng.standard_normal(n)
    cover, a_rain, a_fog, fog_start, p_min, k = 0.6, 0.003, 0.002, 5.0, 1.4e-6, 0.015
    r_out, i_out = hard_returns(t, normal, dirs, mat, REFLECTIVITY.astype(float), GROUND, cover, a_rain, a_fog,
                                fog_start, p_min, 1.0, 120.0, 0.02, k, noise)
    cos_i = np.clip(-np.sum(normal * dirs, 1), 1e-3, 1)
    rho = REFLECTIVITY[mat].astype(float)
    rho = np.where(GROUND[mat], effects.wet_reflectivity(rho, cos_i, cover), rho)
    tf = np.where(np.isfinite(t), t, 1e9)
    t2 = effects.two_way_transmission(tf, a_rain, a_fog, fog_start)
    ok = (tf >= 1) & (tf <= 120) & (effects.received_power(rho, cos_i, tf, t2) >= p_min)
    np.testing.assert_array_equal(np.isfinite(r_out), ok)
    np.testing.assert_allclose(r_out[ok], (tf + noise * np.hypot(0.02, k * tf))[ok], rtol=1e-12)
    ref_i = np.clip(rho * cos_i * t2 * np.exp(-0.004 * tf), 0, 1)
    np.testing.assert_allclose(i_out[ok], ref_i[ok], rtol=1e-12)
    assert 0.3 < ok.mean() < 0.95


def test_spray_clusters_land_on_their_nearest_ray():
    from simulator.lidar import spray_ranges

    pose = _pose()
    spec = LidarSpec()
    car = _car(pose, 15, 0)
    r = spray_ranges(ray_directions(spec), spec, pose, [car], 1.0, np.random.default_rng(7))
    hit = np.flatnonzero(np.isfinite(r))
    assert len(hit) > 0
    pts = ray_directions(spec)[hit] * r[hit, None]  # LiDAR frame
    assert (pts[:, 0] < 15 - 4.75 / 2 + 0.1).all() and (pts[:, 0] > 15 - 4.75 / 2 - 4.6).all()
    assert (np.abs(pts[:, 1]) < 2.5).all() and (pts[:, 2] > -1.73).all()
    assert np.isnan(spray_ranges(ray_directions(spec), spec, pose, [car], 0.0, np.random.default_rng(7))).all()
