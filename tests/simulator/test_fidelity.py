"""Graded response of the public output to rain: the same scenario frames under five weathers, counted
from the written .bin and label files with plain numpy (not the simulator's own columns)."""
import math

import numpy as np
import pytest

from harness.core import kitti
from simulator import effects, generate

WEATHERS = ("ClearNoon", "ClearNight", "SoftRainNoon", "MidRainyNoon", "HardRainNoon")


def _in_box(points, box, margin):
    """Points inside a LiDAR-frame box [x, y, z, l, w, h, yaw] grown by `margin` on every side."""
    c, s = math.cos(box[6]), math.sin(box[6])
    d = points[:, :3].astype(np.float64) - box[:3]
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)
    return (np.abs(local) <= np.asarray(box[3:6]) / 2 + margin).all(1)


@pytest.fixture(scope="module")
def rain_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("rain")
    generate(root, preset="sotif", frames=4 * len(WEATHERS), weathers=list(WEATHERS), seed=0, progress=False)
    meta = kitti.read_frames_meta(root / "meta" / "frames.csv")
    return root, meta


def _counts(root, meta):
    """Per (weather, scenario step): returns on the slow car, smeared around it, air returns near the sensor."""
    out = {}
    for _, row in meta.iterrows():
        pts = kitti.read_points(kitti.frame_path(root, "velodyne", row.frame_id))
        calib = kitti.read_calib(kitti.frame_path(root, "calib", row.frame_id))
        boxes = kitti.read_labels(kitti.frame_path(root, "label_2", row.frame_id)).to_lidar(calib)
        r = np.linalg.norm(pts[:, :3], axis=1)
        in_any = np.zeros(len(pts), bool)
        for b in boxes:
            in_any |= _in_box(pts, b, 0.5)
        air = int(((r < 8.0) & (pts[:, 2] > -1.73 + 0.3) & ~in_any).sum())  # nothing solid stands there
        car = smeared = None
        if row.slow_car_label_index >= 0 and row.slow_car_distance_m < 65:
            box = boxes[int(row.slow_car_label_index)]
            on = _in_box(pts, box, 0.15)
            near = _in_box(pts, box, 1.5) & (pts[:, 2] > box[2] - box[5] / 2 + 0.3)
            car, smeared = int(on.sum()), int((near & ~on).sum())
            assert car == row.slow_car_returns  # the meta column counts the same points
        out[row.weather, row.scenario_time_s] = car, smeared, air, row.slow_car_t2
    return out


def test_rain_grades_the_slow_cars_returns_as_extinction_predicts(rain_set):
    root, meta = rain_set
    counts = _counts(root, meta)
    steps = sorted({t for (w, t), v in counts.items() if w == "ClearNoon" and v[0]})
    assert len(steps) >= 2
    total = {w: sum(counts[w, t][0] for t in steps) for w in WEATHERS}
    assert total["ClearNoon"] >= 40
    rain = ("SoftRainNoon", "MidRainyNoon", "HardRainNoon")
    for t in steps:  # rain never adds returns on the car; which ones a drop takes is random, so per frame only this
        assert all(counts[w, t][0] <= counts["ClearNoon", t][0] for w in rain), t
    seq = [total[w] for w in ("ClearNoon",) + rain]
    assert seq == sorted(seq, reverse=True), seq  # over the scenario, never more with more rain
    assert total["SoftRainNoon"] >= 0.8 * total["ClearNoon"]
    assert total["ClearNight"] == total["ClearNoon"]  # night changes nothing the LiDAR sees
    for w in WEATHERS:  # smeared returns stay at the clear-weather level
        assert sum(counts[w, t][1] for t in steps) <= sum(counts["ClearNoon", t][1] for t in steps) + 0.1 * total["ClearNoon"]
    # the meta's T^2 is the Marshall-Palmer two-way transmission at the car's range, computed here from N(D)
    for (w, t), (car, _, _, t2) in counts.items():
        if car is not None:
            rate = {"ClearNoon": 0, "ClearNight": 0, "SoftRainNoon": 4.5, "MidRainyNoon": 18.0, "HardRainNoon": 50.0}[w]
            r = float(meta.loc[(meta.weather == w) & (meta.scenario_time_s == t), "slow_car_range_m"].iloc[0])
            alpha = effects.marshall_palmer_extinction(rate)
            assert t2 == pytest.approx(math.exp(-2 * alpha * r), abs=1e-5)


def test_phantom_returns_grow_with_rain_and_not_at_night(rain_set):
    root, meta = rain_set
    counts = _counts(root, meta)
    air = {w: sum(v[2] for (ww, _), v in counts.items() if ww == w) for w in WEATHERS}
    assert abs(air["ClearNight"] - air["ClearNoon"]) <= 3 + 0.1 * air["ClearNoon"]
    assert air["ClearNoon"] < air["SoftRainNoon"] < air["MidRainyNoon"] < air["HardRainNoon"]
    cols = meta.groupby("weather")["air_returns"].sum()
    assert cols["ClearNight"] <= cols["ClearNoon"] + 3 and cols["SoftRainNoon"] < cols["HardRainNoon"]
