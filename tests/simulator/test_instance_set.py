"""Instance mode on disk: meta/frames.csv's instance columns, the 10 Hz window, splits, resume, the sweep's rows."""
import pandas as pd
import pytest

from simulator.dataset import GenerateConfig, generate, plan_jobs
from simulator.frame import INSTANCE_COLUMNS, ROW_COLUMNS, make_frame
from simulator.lidar import LidarSpec
from simulator.space import ScenarioSpace, sweep_points
from tests.simulator.test_golden import digests


@pytest.fixture(scope="module")
def instance_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("inst") / "set"
    return generate(root, preset="sotif", instances=2, weathers="ClearNoon", seed=4, progress=False)


def test_frames_csv_has_the_instance_columns(instance_set):
    df = pd.read_csv(instance_set / "meta" / "frames.csv")
    assert tuple(df.columns) == ROW_COLUMNS + INSTANCE_COLUMNS
    assert set(df["instance_key"]) == {"ClearNoon#0", "ClearNoon#1"}
    assert (df["instance_key"] == df["weather"] + "#" + df["instance"].astype(str)).all()
    assert (df["sweep_axis"] == "preset").all() and (df["fog_mor_m"] == 0).all() and (df["road_water"] == 0).all()
    study = df[df["instance"] == 0]
    assert (study["sc_ego_speed_kmh"] == 90).all() and (study["sc_slow_paint"] == "silver").all()
    assert (study["sc_slow_body"] == "sedan").all() and (study["sc_fast_body"] == "hatchback").all()
    for _, g in df.groupby("instance_key"):
        assert g["sc_cutout_gap_m"].nunique() == 1 and g["lane_change_time_s"].nunique() == 1
        win = g[g["in_window"] == 1]["scenario_time_s"].to_numpy()
        # the window is recorded from 0.5 s before the slow car is first visible, not before the lane change
        t_lc, t_cut = g["lane_change_time_s"].iloc[0], g["cutout_time_s"].iloc[0]
        assert len(win) >= 6 and t_lc - 1e-6 <= win[0] < t_cut
        assert (abs(pd.Series(win).diff().dropna() - 0.1) < 1e-6).all()  # 10 Hz
        before = g[g["scenario_time_s"] < win[0]]
        assert len(before) == 2 and (before["in_window"] == 0).all()
    # whole instances per split: instance 0 test, instance 1 val
    assert df.groupby("instance")["split"].nunique().max() == 1
    assert set(df[df["instance"] == 0]["split"]) == {"test"} and set(df[df["instance"] == 1]["split"]) == {"val"}


def test_same_seed_same_bytes_and_resume_after_a_lost_frame(instance_set, tmp_path):
    want = digests(instance_set)
    frame = sorted((instance_set / "training" / "velodyne").glob("*.bin"))[5]
    frame.unlink()
    (instance_set / "meta" / "dataset.json").unlink()
    generate(instance_set, preset="sotif", instances=2, weathers="ClearNoon", seed=4, progress=False)
    assert digests(instance_set) == want


def test_sweep_rows_carry_their_weather(tmp_path):
    cfg = GenerateConfig("sweep", 0, ("Sweep",), 2, LidarSpec(), space=ScenarioSpace(3, sweep=True))
    jobs = plan_jobs(cfg)
    points = sweep_points(cfg.space, 2)
    for i in range(3):
        job = next(j for j in jobs if j.instance == i and j.in_window)
        row, _ = make_frame(tmp_path, cfg, job)
        p = points[i]
        assert row["weather"] == "Sweep" and row["time_of_day"] == "Noon" and row["sweep_axis"] == p.axis
        assert row["instance_key"] == f"Sweep#{i}"
        if p.axis == "rain":
            assert row["rain_rate_mmh"] == pytest.approx(p.value) and row["precipitation_class"] in ("rain", "dry")
        elif p.axis == "fog":
            assert row["fog_mor_m"] == pytest.approx(p.value, abs=1e-4) and row["rain_rate_mmh"] == 0
        else:
            assert row["road_water"] == pytest.approx(p.value, abs=1e-4) and row["rain_rate_mmh"] == 0
            assert row["precipitation_class"] in ("wet", "dry")
