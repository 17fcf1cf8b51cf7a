import numpy as np

from harness.core.kitti import kitti_calib, project_boxes_2d
from simulator.labels import (clip_boxes, frame_labels, lidar_boxes, occlusion_level, projected_boxes, truncation,
                               visible_share)
from simulator.lidar import LidarSpec, scan
from simulator.lidar import Pose
from simulator.raycast import STATIC
from simulator.road import RoadConfig, lane_center, road_to_world
from simulator.vehicles import Vehicle
from simulator.weather import WEATHER_PRESETS

ROAD = RoadConfig()
CALIB = kitti_calib()


def _pose() -> Pose:
    x, y, h = road_to_world(ROAD, np.array(150.0), np.array(lane_center(ROAD, 3)))
    return Pose(float(x), float(y), float(h))


def _veh(pose, dx, dy, body="sedan", dims=(4.75, 1.83, 1.45)):
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    return Vehicle(body, dims, "blue", pose.x + c * dx - s * dy, pose.y + s * dx + c * dy, pose.yaw + 0.05, 25.0)


def test_projected_points_of_a_car_fall_in_its_2d_box(highway_scene):
    pose = _pose()
    vehicles = [_veh(pose, 18, -3.5), _veh(pose, 35, 2.0, "suv", (4.7, 1.9, 1.72)), _veh(pose, 9, 3.5)]
    highway_scene.set_vehicles(vehicles)
    pts = scan(highway_scene, LidarSpec(), pose, WEATHER_PRESETS["ClearNoon"], vehicles, np.random.default_rng(0))
    labels, rows = frame_labels(highway_scene, vehicles, pose, 1.73, CALIB)
    dirs = pts[:, :3] / np.linalg.norm(pts[:, :3], axis=1, keepdims=True)
    actor = highway_scene.cast(np.array([pose.x, pose.y, 1.73]), dirs @ pose.rotation().T).actor
    uv, depth = CALIB.project_lidar(pts[:, :3])
    checked = 0
    for k, row in enumerate(rows):
        assert row >= 0 and labels.name[row] == "Car"
        sel = (actor == k) & (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 1242) & (uv[:, 1] >= 0) & (uv[:, 1] < 375)
        l, t, r, b = labels.bbox[row]
        inside = (uv[sel, 0] >= l - 1) & (uv[sel, 0] <= r + 1) & (uv[sel, 1] >= t - 1) & (uv[sel, 1] <= b + 1)
        assert inside.all()
        checked += sel.sum()
    assert checked > 100
    np.testing.assert_allclose(labels.to_lidar(CALIB)[rows], lidar_boxes(vehicles, pose, 1.73), atol=2e-4)


def test_dontcare_rows_come_after_the_objects(highway_scene):
    """KITTI's order, which OpenPCDet's and MMDetection3D's loaders rely on: every object row, by
    distance, then the DontCare rows (here a car beyond the 80 m label distance)."""
    pose = _pose()
    vehicles = [_veh(pose, 30, 0.0), _veh(pose, 95, 3.5), _veh(pose, 60, -3.5), _veh(pose, 12, 3.5)]
    highway_scene.set_vehicles(vehicles)
    labels, rows = frame_labels(highway_scene, vehicles, pose, 1.73, CALIB)
    assert list(labels.name) == ["Car", "Car", "Car", "DontCare"]
    assert rows.tolist() == [1, 3, 2, 0]
    np.testing.assert_allclose(labels.to_lidar(CALIB)[rows], lidar_boxes(vehicles, pose, 1.73), atol=2e-4)


def test_occlusion_rises_behind_a_truck(highway_scene):
    pose = _pose()
    car = _veh(pose, 40, 0)
    truck = _veh(pose, 20, 0, "truck", (11.0, 2.55, 3.8))
    side_truck = _veh(pose, 20, -1.6, "truck", (11.0, 2.55, 3.8))
    levels, shares = [], []
    for vehicles in ([car], [car, side_truck], [car, truck]):
        highway_scene.set_vehicles(vehicles)
        labels, rows = frame_labels(highway_scene, vehicles, pose, 1.73, CALIB)
        bbox = projected_boxes(lidar_boxes(vehicles, pose, 1.73), CALIB)[0][0]
        shares.append(visible_share(highway_scene, 0, np.clip(bbox, 0, [1241, 374, 1241, 374]), CALIB, pose, 1.73, 12))
        levels.append(int(labels.occluded[rows[0]]))
    assert shares[0] > 0.95 and shares[0] > shares[1] > shares[2]
    assert levels[0] == 0 and levels[0] <= levels[1] <= levels[2] and levels[2] >= 2


def test_truncation_is_the_share_of_the_volume_out_of_view():
    """Against a Monte Carlo reference (20,000 uniform points per box, projected with the calib's
    matrices): cars ahead, at the image edges, beside and behind the camera."""
    rng = np.random.default_rng(1)
    k = 60
    r, angle = rng.uniform(3, 40, k), rng.choice([-1, 1], k) * rng.normal(0.71, 0.08, k)  # about the image's edges
    angle[:20] = rng.uniform(-np.pi, np.pi, 20)  # anywhere
    boxes = np.c_[r * np.cos(angle), r * np.sin(angle), rng.uniform(-1.2, -0.6, k), rng.uniform(3.5, 5, k),
                  rng.uniform(1.6, 2.0, k), rng.uniform(1.3, 1.8, k), rng.uniform(-np.pi, np.pi, k)]
    share = truncation(boxes, CALIB, 1242, 375)
    p2, velo = CALIB.P2, CALIB.velo_to_rect()
    for box, got in zip(boxes, share):
        u = rng.uniform(-0.5, 0.5, (20000, 3)) * box[3:6]
        c, s = np.cos(box[6]), np.sin(box[6])
        pts = np.c_[u[:, 0] * c - u[:, 1] * s + box[0], u[:, 0] * s + u[:, 1] * c + box[1], u[:, 2] + box[2]]
        uvw = (np.c_[pts, np.ones(len(pts))] @ velo.T)[:, :3] @ p2[:, :3].T + p2[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[:, :2] / uvw[:, 2:]
        seen = (uvw[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] <= 1241) & (uv[:, 1] >= 0) & (uv[:, 1] <= 374)
        assert abs(got - (1 - seen.mean())) < 0.07
    assert (share == 0).sum() > 5 and (share == 1).sum() > 5 and ((share > 0.1) & (share < 0.9)).sum() > 5


def test_clipped_boxes_match_harness_projection():
    rng = np.random.default_rng(2)
    boxes = np.c_[rng.uniform(3, 60, 30), rng.uniform(-15, 15, 30), rng.uniform(-1.5, 0, 30),
                  rng.uniform(3, 6, 30), rng.uniform(1.5, 2.2, 30), rng.uniform(1.3, 2.0, 30), rng.uniform(-3, 3, 30)]
    raw, front = projected_boxes(boxes, CALIB)
    clipped = clip_boxes(raw, 1242, 375)
    np.testing.assert_allclose(clipped[front], project_boxes_2d(boxes, CALIB)[front], atol=1e-6)


def test_occlusion_levels():
    np.testing.assert_array_equal(occlusion_level(np.array([1.0, 0.75, 0.6, 0.4, 0.2, 0.05, 0.01, 0.0])),
                                  [0, 0, 1, 1, 2, 2, 3, 3])
    assert STATIC < 0


def test_sphere_culling_matches_brute_force():
    from simulator.raycast import rays_near_spheres

    rng = np.random.default_rng(3)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = rng.normal(size=3)
    c, r = rng.uniform(-10, 10, (7, 3)), rng.uniform(0.5, 3, 7)
    rel = c - o  # (K, 3)
    along = d @ rel.T  # (N, K)
    perp2 = (rel ** 2).sum(1)[None] - along ** 2
    ref = ((along >= -r) & (perp2 <= r ** 2)).any(1)
    np.testing.assert_array_equal(rays_near_spheres(o, d, c, r), ref)
    origins = rng.normal(size=(3000, 3)) * 5  # one origin per ray
    rel = c[None] - origins[:, None]  # (N, K, 3)
    along = np.einsum("nkc,nc->nk", rel, d)
    ref = ((along >= -r) & ((rel ** 2).sum(2) - along ** 2 <= r ** 2)).any(1)
    np.testing.assert_array_equal(rays_near_spheres(origins, d, c, r), ref)
    assert 50 < ref.sum() < 2950


def test_occluded_matches_first_hits(highway_scene):
    pose = _pose()
    rng = np.random.default_rng(6)
    highway_scene.set_vehicles([_veh(pose, 12, 0), _veh(pose, 25, -3.5, "truck", (11.0, 2.55, 3.8))])
    n = 20000
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    fwd, side = rng.uniform(-5, 60, n), rng.uniform(-8, 8, n)
    origins = np.c_[pose.x + c * fwd - s * side, pose.y + s * fwd + c * side, rng.uniform(0.05, 3, n)]
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) * 0.5
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = np.isfinite(highway_scene.cast(origins, d).t)
    np.testing.assert_array_equal(highway_scene.occluded(origins, d), ref)
    assert 0.1 < ref.mean() < 0.9
    assert (highway_scene.cast(origins, d).actor >= 0).sum() > 100


def test_unit_normals_facing_matches_numpy():
    from simulator.raycast import unit_normals_facing

    rng = np.random.default_rng(4)
    ng, d = rng.normal(size=(500, 3)).astype(np.float32), rng.normal(size=(500, 3))
    ref = ng / np.linalg.norm(ng, axis=1, keepdims=True)
    ref *= np.where(np.sum(ref * d, 1) > 0, -1.0, 1.0)[:, None]
    np.testing.assert_allclose(unit_normals_facing(ng, d), ref, rtol=1e-6)


def test_merged_hits_match_brute_force_nearest_triangle():
    from simulator.prims import UNIT_BOX, place
    from simulator.raycast import MISS, STATIC, RayScene
    from simulator.vehicles import world_triangles
    from simulator.world import World

    rng = np.random.default_rng(5)
    ground = place(UNIT_BOX, np.array([[0.0, 0.0, -0.5]]), np.array([200.0, 200.0, 1.0]), np.zeros(1))
    world = World(ground.astype(np.float32), np.zeros(len(ground), np.uint8), None)
    scene = RayScene(world)
    cars = [Vehicle("sedan", (4.75, 1.83, 1.45), "red", float(x), float(y), float(a), 20.0)
            for x, y, a in zip(rng.uniform(5, 30, 4), rng.uniform(-10, 10, 4), rng.uniform(-3, 3, 4))]
    scene.set_vehicles(cars)
    d = rng.normal(size=(4000, 3))
    d[:, 2] = -np.abs(d[:, 2]) * 0.3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.array([0.0, 0.0, 1.7])
    hits = scene.cast(o, d)
    from simulator.raycast import first_hit_distance
    t_ground = first_hit_distance(ground, np.broadcast_to(o, d.shape), d)
    t_cars = np.stack([first_hit_distance(world_triangles(c)[0], np.broadcast_to(o, d.shape), d) for c in cars], 1)
    ref_t = np.minimum(t_ground, t_cars.min(1))
    ref_actor = np.where(t_cars.min(1) < t_ground, t_cars.argmin(1), np.where(np.isfinite(t_ground), STATIC, MISS))
    np.testing.assert_allclose(hits.t, ref_t, rtol=1e-5)
    np.testing.assert_array_equal(hits.actor, ref_actor)
    assert (hits.actor >= 0).sum() > 50
    assert np.allclose(np.linalg.norm(hits.normal[np.isfinite(hits.t)], axis=1), 1.0, atol=1e-5)


def test_brute_force_triangle_hits_match_embree():
    from simulator.raycast import first_hit_distance, rays_hit_triangles
    from simulator.vehicles import world_triangles

    rng = np.random.default_rng(7)
    for body, dims in (("sedan", (4.75, 1.83, 1.45)), ("truck", (11.0, 2.55, 3.8))):
        car = Vehicle(body, dims, "red", 20.0, 3.0, rng.uniform(-3, 3), 20.0)
        tris = world_triangles(car)[0]
        origin = np.array([0.0, 0.0, 1.7])
        d = np.array([20.0, 3.0, 0.7]) + rng.normal(size=(3000, 3)) * [1.0, 3.0, 1.0] - origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        ref = np.isfinite(first_hit_distance(tris, np.broadcast_to(origin, d.shape), d))
        np.testing.assert_array_equal(rays_hit_triangles(origin, d, tris), ref)
        assert 0.2 < ref.mean() < 0.9
        assert not rays_hit_triangles(origin, -d, tris).any()  # behind the origin
