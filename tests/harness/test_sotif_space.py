import math

import numpy as np
import pandas as pd
import pytest

from harness import sotif_space
from harness.conditions import condition_labels
from harness.core import kitti
from tests.harness.test_sotif import OTHER, SLOW, _write_frame

FRONT = 4.7 / 2 + 4.75 / 2  # LiDAR to the ego's bumper plus half the slow car: rear gap = x - FRONT
FAR = 20.0  # a prediction shift that leaves no overlap
T_LC = 1.0  # s, lane change
TIMES = [0.0, 0.5] + [round(1.0 + 0.1 * j, 1) for j in range(10)]  # 2 Hz before the lane change, 10 Hz after


def make_instances(root, instances):
    """An instance-mode data set: ``instances`` maps (weather, instance) -> (ego m/s, slow m/s, hits after the
    lane change); every instance has frames at TIMES, the slow car's rear 50 m ahead at the lane change."""
    pred_dir = root / "pred"
    pred_dir.mkdir(parents=True)
    rows, fid_no = [], 0
    for (weather, inst), (ego, slow, hits) in instances.items():
        for t in TIMES:
            fid = f"{fid_no:06d}"
            fid_no += 1
            box = SLOW.copy()
            box[0] = 50.0 + FRONT - (ego - slow) * (t - T_LC)
            j = round((t - T_LC) * 10)
            hit = hits[j] if j >= 0 else 1  # a hit before the lane change never counts
            shifted = box.copy()
            shifted[0] += 0.0 if hit else FAR
            _write_frame(root, fid, np.stack([OTHER, box]), shifted, [0.9], pred_dir)
            rows.append({"frame_id": fid, "split": "test", "weather": weather, "instance": inst,
                         "instance_key": f"{weather}#{inst}", "sweep_axis": "preset", "scenario_time_s": t,
                         "lane_change_time_s": T_LC, "slow_car_label_index": 1, "ego_speed_mps": ego,
                         "slow_car_speed_mps": slow, "in_window": int(t >= T_LC), "rain_rate_mmh": 0.0,
                         "fog_mor_m": 0.0, "road_water": 0.0, "precipitation_class": "dry",
                         "sc_slow_reflectance": 0.1 + 0.1 * inst, "sc_slow_body": "car"})
    kitti.write_image_set(root / "ImageSets" / "test.txt", [r["frame_id"] for r in rows])
    kitti.write_frames_meta(root / "meta" / "frames.csv", pd.DataFrame(rows))
    return root, pred_dir


def wilson_reference(k, n, z=1.959963984540054):
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def test_wilson_interval_against_the_formula():
    rng = np.random.default_rng(1)
    for _ in range(100):
        n = int(rng.integers(1, 200))
        k = int(rng.integers(0, n + 1))
        assert sotif_space.wilson_interval(k, n) == pytest.approx(wilson_reference(k, n), abs=1e-9)
    assert all(math.isnan(v) for v in sotif_space.wilson_interval(0, 0))


def test_pass_rates_per_bin_mark_too_few():
    inst = pd.DataFrame({"weather": ["A"] * 6 + ["B"] * 2, "pass": [True, True, False, True, True, True, False, False],
                         "sc_ego_speed_kmh": np.linspace(80, 130, 8)})
    rates = sotif_space.pass_rates(inst, "weather").set_index("bin")
    assert rates.loc["A", "n"] == 6 and rates.loc["A", "n_pass"] == 5 and not rates.loc["A", "too_few"]
    assert (rates.loc["A", "lo"], rates.loc["A", "hi"]) == pytest.approx(wilson_reference(5, 6))
    assert rates.loc["B", "rate"] == 0.0 and rates.loc["B", "too_few"]
    assert sotif_space.pass_rates(inst, "fog_mor_m").empty  # a column the data set does not have
    assert sotif_space.pass_rates(inst.assign(fog_mor_m=0.0), "fog_mor_m").empty  # one value tells nothing


def test_pass_rates_count_feasible_instances_and_keep_five_per_bin():
    rng = np.random.default_rng(3)
    inst = pd.DataFrame({"rain_rate_mmh": rng.uniform(0, 100, 23), "pass": rng.uniform(size=23) < 0.5,
                         "feasible": rng.uniform(size=23) < 0.8})
    rates = sotif_space.pass_rates(inst, "rain_rate_mmh")
    assert len(rates) == 4 and (rates["n"] + rates["n_infeasible"] >= 5).all()  # 23 // 5 = 4 bins
    assert rates["bin"].iloc[0].startswith("[" + f"{inst.rain_rate_mmh.min():.3g}")  # from the lowest up
    assert rates["n_infeasible"].sum() == (~inst.feasible).sum()
    assert rates["n_pass"].sum() == (inst["pass"] & inst.feasible).sum()  # only feasible instances count
    assert len(sotif_space.pass_rates(inst.iloc[:12], "rain_rate_mmh")) == 2  # 12 instances: two bins of 6


def test_boundary_grid_against_a_loop():
    rng = np.random.default_rng(2)
    frames = pd.DataFrame({"distance_m": rng.uniform(0, 100, 200), "rain_rate_mmh": rng.uniform(0, 55, 200),
                           "hit": rng.uniform(size=200) < 0.6})
    x_edges, y_edges = [0, 25, 50, 75, 100], [0, 10, 30, 60, 100]  # no frame above 55 mm/h: an empty row
    hits, counts = sotif_space.boundary_grid(frames, "rain_rate_mmh", x_edges, y_edges)
    assert counts.shape == (4, 4) and (counts[3] == 0).all() and counts.sum() == 200
    for i in range(4):
        for j in range(4):
            inside = ((frames.rain_rate_mmh >= y_edges[i]) & (frames.rain_rate_mmh < y_edges[i + 1])
                      & (frames.distance_m >= x_edges[j]) & (frames.distance_m < x_edges[j + 1]))
            assert counts[i, j] == inside.sum() and hits[i, j] == (inside & frames.hit).sum()


def test_condition_labels_bin_only_many_numeric_values():
    few = pd.Series([0.0, 4.5, 4.5, 18.0])
    assert condition_labels(few).tolist() == ["0.0", "4.5", "4.5", "18.0"]  # as str(value), as grouping did
    assert condition_labels(pd.Series(["car", "van"])).tolist() == ["car", "van"]
    many = pd.Series(np.arange(20, dtype=float))
    labels = condition_labels(many)
    assert labels.nunique() == 4 and labels.iloc[0] == "[0, 4.75)" and labels.iloc[-1] == "[14.2, 19]"
    for value, label in zip(many, labels):
        lo, hi = (float(v) for v in label.strip("[])").split(", "))
        assert lo <= value <= hi
