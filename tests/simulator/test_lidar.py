import numpy as np
import pytest

from harness.core.boxes import points_in_boxes
from simulator.labels import lidar_boxes
from simulator.lidar import LidarSpec, Pose, carla_spec, detection_range, ray_directions, rotate_yaw, scan
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
        reach.append(detection_range(LidarSpec(), WEATHER_PRESETS[name], 0.10))
    assert counts == sorted(counts, reverse=True) and counts[0] > counts[-1] * 1.02
    assert far == sorted(far, reverse=True) and far[0] > far[-1] + 2
    assert reach[0] == pytest.approx(50.0, abs=0.01) and all(a > b for a, b in zip(reach, reach[1:]))


def test_wet_road_loses_far_ground_returns(highway_scene):
    pose = _pose()
    highway_scene.set_vehicles([])
    n = {}
    for name in ("ClearNoon", "WetNoon"):
        pts = scan(highway_scene, LidarSpec(), pose, WEATHER_PRESETS[name], [], np.random.default_rng(2))
        road = (np.abs(pts[:, 2] + 1.73) < 0.1) & (np.abs(pts[:, 1]) < 8)
        r = _ranges(pts)
        n[name] = (road & (r > 14) & (r < 30)).sum(), (road & (r < 10)).sum()  # P_min leaves asphalt to ~17 m
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


def _random_hits(rng, n):
    t = np.where(rng.random(n) < 0.1, np.inf, rng.uniform(0.2, 140, n))
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal *= -np.sign(np.sum(normal * dirs, 1))[:, None]
    return t, dirs, normal, rng.choice([0, 1, 4, 9, 33, 40], n)


def test_hard_returns_match_effect_formulas():
    from simulator import effects
    from simulator.lidar import hard_returns
    from simulator.materials import GROUND, REFLECTIVITY

    rng = np.random.default_rng(5)
    t, dirs, normal, mat = _random_hits(rng, 5000)
    cover, a_rain, a_fog, fog_start, p_min = 0.6, 0.003, 0.002, 5.0, 1.4e-6
    r_out, i_out = hard_returns(t, normal, dirs, mat, REFLECTIVITY.astype(float), GROUND, cover, a_rain, a_fog,
                                fog_start, p_min, 1.0, 120.0)
    cos_i = np.clip(-np.sum(normal * dirs, 1), 1e-3, 1)
    rho = REFLECTIVITY[mat].astype(float)
    rho = np.where(GROUND[mat], effects.wet_reflectivity(rho, cos_i, cover), rho)
    tf = np.where(np.isfinite(t), t, 1e9)
    t2 = effects.two_way_transmission(tf, a_rain, a_fog, fog_start)
    ok = (tf >= 1) & (tf <= 120) & (effects.received_power(rho, cos_i, tf, t2) >= p_min)
    np.testing.assert_array_equal(np.isfinite(r_out), ok)
    np.testing.assert_array_equal(r_out[ok], tf[ok])
    ref_i = np.clip(rho * cos_i * t2 * np.exp(-0.004 * tf), 0, 1)
    np.testing.assert_allclose(i_out[ok], ref_i[ok], rtol=1e-12)
    assert 0.3 < ok.mean() < 0.95


@pytest.mark.parametrize("cover", [0.0, 0.8])
def test_first_returns_equal_merge_then_hard_returns(cover):
    """The pass over Embree's raw output equals raycast.merge_hits followed by hard_returns; then the noise."""
    from simulator.lidar import add_range_noise, first_returns, hard_returns
    from simulator.materials import GROUND, REFLECTIVITY
    from simulator.raycast import merge_hits

    rng = np.random.default_rng(11)
    n, n_static, n_dyn = 6000, 300, 80
    t, dirs, _, _ = _random_hits(rng, n)
    t_s = np.where(np.isfinite(t), t, 1e37).astype(np.float32)
    prim_s = np.where(np.isfinite(t), rng.integers(0, n_static, n), -1).astype(np.int32)
    ng_s = (rng.normal(size=(n, 3)) * rng.uniform(0.1, 5, (n, 1))).astype(np.float32)
    ng_s[rng.random(n) < 0.01] = 0.0  # degenerate triangles
    near = np.flatnonzero(rng.random(n) < 0.3)
    t_d = rng.uniform(0.5, 150, len(near)).astype(np.float32)
    prim_d = np.where(rng.random(len(near)) < 0.5, rng.integers(0, n_dyn, len(near)), -1).astype(np.int32)
    ng_d = rng.normal(size=(len(near), 3)).astype(np.float32)
    mat_s, mat_d = rng.choice([0, 1, 2, 4, 13], n_static), rng.choice([9, 10, 33, 40], n_dyn)
    refl = REFLECTIVITY.astype(np.float64)
    weather = (cover, 0.004, 0.003, 0.75, 1.4e-6, 1.0, 120.0)
    r, i, detected, path, power = first_returns(t_s, prim_s, ng_s, mat_s, near, t_d, prim_d, ng_d, mat_d, dirs, refl,
                                                GROUND, *weather)
    t_ref, normal32, mat_ref, actor = merge_hits(t_s, prim_s, ng_s, mat_s, near, t_d, prim_d, ng_d, mat_d,
                                                 np.zeros(n_dyn, np.int64), dirs)
    ng = ng_s.astype(np.float64)  # the chosen triangle's normal in float64 (merge_hits' is float32-exact)
    dyn = near[actor[near] >= 0]
    ng[dyn] = ng_d[actor[near] >= 0]
    norm = np.linalg.norm(ng, axis=1, keepdims=True)
    normal = np.where(norm > 0, ng / np.where(norm > 0, norm, 1), 0) * -np.sign(np.sum(ng * dirs, 1))[:, None]
    hit = actor != -1  # raycast.MISS
    np.testing.assert_allclose(normal[hit], normal32[hit], atol=1e-6)
    t_inf = np.where(t_ref >= 1e37, np.inf, t_ref)
    r_ref, i_ref = hard_returns(t_inf, normal, dirs, mat_ref, refl, GROUND, *weather)
    ok = np.isfinite(r_ref)
    np.testing.assert_array_equal(detected, np.flatnonzero(ok))
    assert ok.sum() > n // 4
    np.testing.assert_array_equal(r, r_ref)  # NaN where lost
    np.testing.assert_allclose(i, i_ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(path, np.where(hit, np.minimum(t_inf, 120.0), 120.0))  # the surface blocks drops
    # the received power of the detected rays: the intensity without CARLA's exp(-0.004 r), over r^2
    ref_p = np.exp(0.004 * r_ref[ok]) * i_ref[ok] / r_ref[ok] ** 2
    unclipped = i_ref[ok] < 1
    np.testing.assert_allclose(power[ok][unclipped], ref_p[unclipped], rtol=1e-9)
    assert (power[ok] >= weather[4]).all() and np.isnan(power[~ok]).all()
    z = rng.standard_normal(len(detected))
    add_range_noise(r, detected, z, power, 1.4e-6, 0.02, 0.04)
    noisy = r_ref[ok] + z * np.sqrt(0.02 ** 2 + 0.04 ** 2 / (2 * power[ok] / 1.4e-6))  # LISA: dR / sqrt(2 SNR)
    np.testing.assert_allclose(r[ok], noisy, rtol=1e-14)
    assert np.isnan(r[~ok]).all()


def test_pattern_culling_matches_brute_force():
    from simulator.lidar import pattern_rays_near_spheres, world_rays
    from simulator.raycast import rays_near_spheres

    spec = LidarSpec()
    rng = np.random.default_rng(12)
    for trial in range(6):
        yaw = rng.uniform(-4, 4)
        origin = rng.uniform(-50, 50, 3)
        wd, o32 = world_rays(ray_directions(spec), yaw, origin)
        np.testing.assert_array_equal(wd, rotate_yaw(ray_directions(spec), yaw).astype(np.float32))
        assert (o32 == origin.astype(np.float32)).all()
        centres = origin + rng.uniform(-40, 40, (9, 3)) * [1, 1, 0.1]
        centres[0] = origin + [rng.uniform(-1, 1), 0.5, 0.2]  # sphere around the sensor: every column
        centres[1] = origin + [30.0, -0.3, 0.0]  # straddles the azimuth wrap at yaw
        centres[1, :2] = origin[:2] + 30 * np.array([np.cos(yaw), np.sin(yaw)]) + [0.0, -0.3]
        radii = rng.uniform(0.5, 4, 9)
        got = pattern_rays_near_spheres(origin, wd, spec.n_azimuth, yaw, centres, radii)
        np.testing.assert_array_equal(got, rays_near_spheres(origin, wd, centres, radii))
        assert got.sum() > 1000


def test_points_match_numpy():
    from simulator.lidar import points_from_returns

    rng = np.random.default_rng(13)
    n = 3000
    r = np.where(rng.random(n) < 0.2, np.nan, rng.uniform(0.5, 130, n))
    dirs = rng.normal(size=(n, 3))
    inten = rng.random(n)
    pts = points_from_returns(dirs, r, inten, 1.0, 120.0)
    keep = (r >= 1.0) & (r <= 120.0)
    np.testing.assert_array_equal(pts, np.c_[dirs[keep] * r[keep, None], inten[keep]].astype(np.float32))


def test_spray_clusters_land_on_their_nearest_ray():
    from simulator.lidar import spray_ranges

    pose = _pose()
    spec = LidarSpec()
    car = _car(pose, 15, 0)
    idx, r = spray_ranges(spec, pose, [car], 1.0, np.random.default_rng(7))
    assert len(idx) > 0 and (np.diff(idx) > 0).all()
    pts = ray_directions(spec)[idx] * r[:, None]  # LiDAR frame
    assert (pts[:, 0] < 15 - 4.75 / 2 + 0.1).all() and (pts[:, 0] > 15 - 4.75 / 2 - 4.6).all()
    assert (np.abs(pts[:, 1]) < 2.5).all() and (pts[:, 2] > -1.73).all()
    assert len(spray_ranges(spec, pose, [car], 0.0, np.random.default_rng(7))[0]) == 0
