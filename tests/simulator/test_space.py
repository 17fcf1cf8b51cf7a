"""The scenario space: design, instances, decision window, sweep weather, reflectance override."""
import math
from dataclasses import replace

import numpy as np
import pytest

import harness.sotif
from harness.core import braking
from harness.core.braking import EGO_DIMS, stopping_distance
from simulator import scenario
from simulator.dataset import GenerateConfig, generate, plan_jobs
from simulator.lidar import LidarSpec, Pose, scan
from simulator.materials import REFLECTIVITY, lidar_tables, paint_id
from simulator.road import RoadConfig, lane_center, road_to_world
from simulator.scenario import SotifConfig, instance_steps, sotif_run, window_length_s
from simulator.space import (CONTINUOUS, FAST_BODIES, SLOW_BODIES, SLOW_PAINTS, STUDY, SWEEP_AXES, ScenarioSpace,
                             SweepPoint, check_space, design, instances, sweep_points, sweep_weather, val_instances)
from simulator.vehicles import Vehicle
from simulator.weather import WEATHER_PRESETS, rain_rate_mmh, road_water_cover

ROAD = RoadConfig()


def test_the_scenario_and_the_verdict_brake_by_the_floors_rule():
    for name in ("T_REACT_S", "DECEL_MPS2", "MARGIN_M", "stopping_distance"):
        assert getattr(harness.sotif, name) is getattr(braking, name)
    assert scenario.stopping_distance is braking.stopping_distance
    assert stopping_distance(10.0) == pytest.approx(10.0 * 1.0 + 100.0 / 8.0 + 2.0)  # 24.5 m
    assert window_length_s(50.0, 10.0, t_react=1.0, decel=4.0) == pytest.approx((50.0 - 24.5) / 10.0)
    assert window_length_s(20.0, 10.0, t_react=1.0, decel=4.0) == 0.0 and window_length_s(20.0, 0.0) == math.inf


def test_design_is_deterministic_per_seed_and_differs_across_seeds():
    space = ScenarioSpace(16)
    a, b, c = design(space, 7), design(space, 7), design(space, 8)
    assert a.shape == (15, 8) and np.array_equal(a, b) and not np.array_equal(a, c)
    assert ((a >= 0) & (a < 1)).all()


def test_design_covers_each_range():
    space = ScenarioSpace(64)
    drawn = instances(space, 3)[1:]
    for name in CONTINUOUS:
        lo, hi = getattr(space, name)
        v = np.array([getattr(inst, name) for inst in drawn])
        assert v.min() >= lo and v.max() <= hi
        assert v.min() - lo < 0.03 * (hi - lo) and hi - v.max() < 0.03 * (hi - lo), name
    assert {i.slow_body for i in drawn} == set(SLOW_BODIES)
    assert {i.slow_paint for i in drawn} == set(SLOW_PAINTS)
    assert {i.fast_body for i in drawn} == set(FAST_BODIES)
    assert all(i.slow_reflectance == SLOW_PAINTS[i.slow_paint][1] for i in drawn)


def test_instance_zero_is_the_study():
    for n in (1, 2, 40):
        assert instances(ScenarioSpace(n), 5)[0] == STUDY
    assert STUDY.sotif_config() == SotifConfig()


def test_reflectances_are_physical():
    assert all(0.0 < r <= 1.0 for _, r in SLOW_PAINTS.values())


def _kinematic_window(inst) -> float:
    sc = inst.sotif_config()
    run = sotif_run(ROAD, 40, np.random.default_rng(0), replace(sc, record_every=1))
    k = int(round(run[0].info["lane_change_time_s"] / sc.dt))
    gap = run[k].info["slow_car_distance_m"] - (sc.slow_body[1][0] + EGO_DIMS[0]) / 2
    return window_length_s(gap, run[k].ego_speed - sc.slow_speed)


def test_a_perfect_detector_can_pass_most_instances():
    """At the lane change, the gap exceeds the stopping distance in >= 75 % of the instances."""
    windows = np.array([_kinematic_window(inst) for inst in instances(ScenarioSpace(64), 0)])
    assert (windows > 0).mean() >= 0.75
    assert _kinematic_window(STUDY) > 3.0  # the study's scenario: seconds to spare


def _first_visible_by_shapely(run) -> int:
    """First step at which a sight line from the LiDAR to some point of the slow car's footprint (a 40 x 10 grid)
    crosses no other vehicle's footprint and the point is within 80 m ahead, 32 m aside."""
    from shapely.geometry import LineString, Polygon

    from simulator.labels import lidar_boxes

    def poly(b):
        c, s_ = np.cos(b[6]), np.sin(b[6])
        return Polygon([(b[0] + c * u - s_ * v, b[1] + s_ * u + c * v)
                        for u, v in ((b[3] / 2, b[4] / 2), (-b[3] / 2, b[4] / 2), (-b[3] / 2, -b[4] / 2),
                                     (b[3] / 2, -b[4] / 2))])
    for k, st in enumerate(run):
        boxes = lidar_boxes(st.vehicles, st.pose, 0.0)
        b, others = boxes[0], [poly(o) for o in boxes[1:]]
        c, s_ = np.cos(b[6]), np.sin(b[6])
        for u in (np.arange(40) + 0.5) / 40 - 0.5:
            for v in (np.arange(10) + 0.5) / 10 - 0.5:
                x, y = b[0] + c * u * b[3] - s_ * v * b[4], b[1] + s_ * u * b[3] + c * v * b[4]
                if 0 <= x <= 80 and abs(y) <= 32 and not any(LineString([(0, 0), (x, y)]).intersects(o) for o in others):
                    return k
    raise AssertionError("never visible")


def test_instance_steps_window_is_at_10_hz():
    """Every step (10 Hz) from the lane change to the latest passing confirmation plus slack, capped."""
    sc = SotifConfig()
    run = sotif_run(ROAD, 100, np.random.default_rng(0), SotifConfig(record_every=1))
    k_lc = int(round(run[0].info["lane_change_time_s"] / sc.dt))
    gap = run[k_lc].info["slow_car_distance_m"] - (sc.slow_body[1][0] + EGO_DIMS[0]) / 2
    end_s = window_length_s(gap, run[k_lc].ego_speed - sc.slow_speed) + 0.3  # the study's: 8.8 s + slack
    clear_s = run[0].info["cutout_time_s"] - run[0].info["lane_change_time_s"]  # the cut-out 1.7 s later
    steps = instance_steps(run, sc, lead_in=2, slack_s=0.3, window_max_s=7.5)
    window = [k for k, w in steps if w]
    lead = [k for k, w in steps if k < window[0]]
    # 10 Hz from 0.5 s before any of the slow car is visible (by the shapely check below), 2 Hz lead-in before
    first = _first_visible_by_shapely(run)
    assert k_lc < first and window[0] == first - 5
    assert lead == [window[0] - 10, window[0] - 5] and np.all(np.diff(window) == 1)
    assert [k for k, w in steps if not w] == lead  # no 2 Hz tail
    assert 1.5 < clear_s < 2.0 and 8.5 < end_s < clear_s + 7.5 and window[-1] == k_lc + round(end_s / sc.dt)
    capped = instance_steps(run, sc, lead_in=2, slack_s=0.3, window_max_s=2.5)
    assert [k for k, w in capped if w][-1] == k_lc + round((clear_s + 2.5) / sc.dt)


def test_window_length_is_the_latest_passing_confirmation():
    # 60 m gap closing at 10 m/s: stopping 10 * 0.35 + 100 / 12 + 2 = 13.83 m -> (60 - 13.83) / 10 s
    assert window_length_s(60.0, 10.0) == pytest.approx((60.0 - 3.5 - 100.0 / 12.0 - 2.0) / 10.0)
    assert window_length_s(60.0, 10.0, t_react=1.0, decel=4.0) == pytest.approx((60.0 - 10.0 - 12.5 - 2.0) / 10.0)
    assert window_length_s(5.0, 10.0) == 0.0 and window_length_s(5.0, 0.0) == math.inf


def test_val_instances_are_whole_and_never_the_study():
    assert val_instances(1, 0.1) == set()
    assert val_instances(4, 0.1) == {1}
    v = val_instances(40, 0.1)
    assert len(v) == 4 and 0 not in v


def test_sweep_points_cover_their_axes():
    space = ScenarioSpace(60, sweep=True)
    pts = sweep_points(space, 2)
    assert [p.axis for p in pts[:6]] == list(SWEEP_AXES) * 2
    for axis, (lo, hi) in (("rain", space.rain_mmh), ("fog", space.fog_mor_m), ("water", space.road_water)):
        v = np.array([p.value for p in pts if p.axis == axis])
        assert v.min() >= lo and v.max() <= hi and len(v) == 20
    fog = np.log(np.array([p.value for p in pts if p.axis == "fog"]) / 50.0) / np.log(40.0)  # log-uniform
    assert fog.min() < 0.15 and fog.max() > 0.85
    assert instances(space, 2)[0] != STUDY and len(instances(space, 2)) == 60


def test_sweep_weather_is_physical_and_presets_unchanged():
    rain = sweep_weather(SweepPoint("rain", 100.0))
    assert rain_rate_mmh(rain) == 100.0 and road_water_cover(rain) == 1.0
    assert rain_rate_mmh(sweep_weather(SweepPoint("rain", 12.5))) == 12.5
    assert road_water_cover(sweep_weather(SweepPoint("rain", 12.5))) == pytest.approx(0.5)  # the slider of 12.5 mm/h
    fog = sweep_weather(SweepPoint("fog", 200.0))
    assert fog.lidar_fog_mor_m == 200.0 and rain_rate_mmh(fog) == 0.0 and fog.fog_distance == 0.0
    water = sweep_weather(SweepPoint("water", 0.4))
    assert road_water_cover(water) == pytest.approx(0.4) and rain_rate_mmh(water) == 0.0
    assert rain_rate_mmh(WEATHER_PRESETS["HardRainNoon"]) == 50.0
    assert all(p.rain_rate_override_mmh is None for p in WEATHER_PRESETS.values())


@pytest.mark.parametrize("kwargs, word", [
    (dict(preset="sotif", instances=0), "instances"), (dict(preset="sotif", instances=-2), "instances"),
    (dict(preset="sotif", instances=True), "instances"), (dict(preset="train", instances=3), "train"),
    (dict(preset="sotif", instances=3, frames=5), "frames"), (dict(preset="sweep", weathers="ClearNoon"), "weathers"),
    (dict(preset="sweeps"), "preset")])
def test_bad_input_is_refused(tmp_path, kwargs, word):
    with pytest.raises(ValueError, match=word):
        generate(tmp_path / "x", progress=False, **kwargs)
    assert not (tmp_path / "x").exists()


def test_bad_space_is_refused():
    with pytest.raises(ValueError, match="cutout_gap_m"):
        check_space(ScenarioSpace(4, cutout_gap_m=(20.0, 5.0)))
    with pytest.raises(ValueError, match="slow_speed_kmh"):
        check_space(ScenarioSpace(4, slow_speed_kmh=(30.0, 100.0)))


def test_reflectance_override_moves_only_that_paint():
    v = [Vehicle("sedan", (4.75, 1.83, 1.45), "black", 0, 0, 0, 20.0),
         Vehicle("sedan", (4.75, 1.83, 1.45), "black", 9, 0, 0, 20.0, "slow", 0.6)]
    mat = np.array([paint_id("black"), 3, paint_id("black"), paint_id("black"), 3])
    actor = np.array([0, 0, 1, 1, 1])
    lm, refl, ground = lidar_tables(mat, actor, v)
    assert lm.tolist() == [paint_id("black"), 3, len(REFLECTIVITY), len(REFLECTIVITY), 3]
    assert refl[len(REFLECTIVITY)] == 0.6 and not ground[len(REFLECTIVITY)] and np.array_equal(refl[:-1], REFLECTIVITY)
    same, r2, _ = lidar_tables(mat, actor, v[:1])
    assert same is mat and r2.dtype == np.float64


def _slow_car_points(scene, reflectance):
    """(points, returns on the car) of a black sedan 40 m ahead in lane 3 (override ``reflectance``)."""
    d = lane_center(ROAD, 3)
    xe, ye, he = road_to_world(ROAD, np.array(300.0), np.array(d))
    xc, yc, hc = road_to_world(ROAD, np.array(340.0), np.array(d))
    car = Vehicle("sedan", (4.75, 1.83, 1.45), "black", float(xc), float(yc), float(hc), 20.0, "slow", reflectance)
    pose = Pose(float(xe), float(ye), float(he))
    scene.set_vehicles([car])
    pts = scan(scene, LidarSpec(), pose, WEATHER_PRESETS["ClearNoon"], [car], np.random.default_rng(0))
    on_car = (np.abs(pts[:, 0] - 40.0) < 3.0) & (np.abs(pts[:, 1]) < 1.5) & (pts[:, 2] > -1.6)
    return pts, int(on_car.sum())


def test_override_equal_to_the_table_changes_nothing(highway_scene):
    """Reference: an override with the paint table's own value scans byte for byte like no override; a darker
    one loses returns."""
    table = float(REFLECTIVITY[paint_id("black")])
    a, n_a = _slow_car_points(highway_scene, None)
    b, _ = _slow_car_points(highway_scene, table)
    assert np.array_equal(a, b)
    _, n_dark = _slow_car_points(highway_scene, 0.01)
    _, n_bright = _slow_car_points(highway_scene, 0.9)
    assert n_dark < n_a <= n_bright


def test_plan_is_deterministic():
    cfg = GenerateConfig("sotif", 0, ("ClearNoon", "WetNoon"), 1, LidarSpec(), space=ScenarioSpace(5))
    jobs = plan_jobs(cfg)
    assert jobs == plan_jobs(cfg)
    keys = {(j.weather, j.instance) for j in jobs}
    assert keys == {(w, i) for w in ("ClearNoon", "WetNoon") for i in range(5)}
    assert {j.instance for j in jobs if j.split == "val"} == val_instances(5, 0.1)


@pytest.mark.parametrize("argv, word", [(["--preset", "sotif", "--instances", "0"], "instances"),
                                        (["--preset", "train", "--instances", "2"], "train"),
                                        (["--preset", "sweep", "--weathers", "ClearNoon"], "weathers")])
def test_cli_refuses_bad_instances(tmp_path, capsys, argv, word):
    from harness.cli import main
    assert main(["--quiet", "simulate", "--out", str(tmp_path / "x"), *argv]) == 2
    assert word in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_cli_refuses_an_unknown_preset(tmp_path):
    from harness.cli import main
    with pytest.raises(SystemExit) as e:
        main(["simulate", "--preset", "sweeps", "--out", str(tmp_path / "x")])
    assert e.value.code == 2
