import json
import os
import re

import numpy as np
import pytest

from harness.core import kitti
from simulator import generate
from simulator.dataset import GenerateConfig, check_output, plan_jobs
from simulator.lidar import LidarSpec
from simulator.weather import WEATHER_PRESETS

COLUMNS = {"frame_id", "split", "scenario", "weather", "time_of_day", "precipitation_class", "cloudiness",
           "precipitation", "precipitation_deposits", "wetness", "fog_density", "sun_altitude_angle",
           "rain_rate_mmh", "scenario_time_s", "ego_speed_mps", "slow_car_speed_mps", "lane_change_time_s",
           "slow_car_label_index", "fast_car_label_index", "slow_car_distance_m", "n_points"}


@pytest.fixture(scope="module")
def sotif_set(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("sotif"), "sotif", frames=4, weathers=["ClearNoon", "HardRainNight"],
                    seed=3, workers=1, progress=False)


def test_files_parse_with_the_project_reader(sotif_set):
    meta = kitti.read_frames_meta(sotif_set / "meta" / "frames.csv")
    assert COLUMNS <= set(meta.columns) and len(meta) == 4
    assert list(meta["weather"]) == ["ClearNoon"] * 2 + ["HardRainNight"] * 2
    ids = sum((kitti.read_image_set(sotif_set / "ImageSets" / f"{s}.txt") for s in ("train", "val", "test")), [])
    assert sorted(ids) == list(meta["frame_id"])
    for _, row in meta.iterrows():
        fid = row["frame_id"]
        pts = kitti.read_points(kitti.frame_path(sotif_set, "velodyne", fid))
        assert len(pts) == row["n_points"] and (pts[:, 3] >= 0).all() and (pts[:, 3] <= 1).all()
        labels = kitti.read_labels(kitti.frame_path(sotif_set, "label_2", fid))
        dontcare = np.asarray(labels.name) == "DontCare"
        assert not (dontcare[:-1] & ~dontcare[1:]).any()  # as KITTI: DontCare rows after every object row
        calib = kitti.read_calib(kitti.frame_path(sotif_set, "calib", fid))
        assert kitti.read_image(kitti.frame_path(sotif_set, "image_2", fid)).shape == (375, 1242, 3)
        # before the lane change the fast car leads in the ego lane, at the end the slow car does
        lead = row["fast_car_label_index"] if row["scenario_time_s"] < row["lane_change_time_s"] else \
            row["slow_car_label_index"]
        assert 0 <= lead < len(labels) and labels.name[lead] == "Car"
        box = labels.to_lidar(calib)[lead]
        assert 35 < box[0] < 90 and abs(box[1]) < 1.0
    data = json.loads((sotif_set / "meta" / "dataset.json").read_text())
    assert data["seed"] == 3 and data["config"]["lidar"]["name"] == "HDL-64E"
    assert "training/velodyne/000000.bin" in data["files"] and "meta/frames.csv" in data["files"]


def test_same_seed_same_bytes_and_resume(sotif_set, tmp_path):
    again = generate(tmp_path / "b", "sotif", frames=4, weathers=["ClearNoon", "HardRainNight"], seed=3,
                     workers=2, progress=False)
    a = json.loads((sotif_set / "meta" / "dataset.json").read_text())["files"]
    b = json.loads((again / "meta" / "dataset.json").read_text())["files"]
    assert a == b
    lost = kitti.frame_path(again, "velodyne", "000001")
    lost.unlink()
    kitti.frame_path(again, "image_2", "000002").write_bytes(b"garbage")
    kept = kitti.frame_path(again, "velodyne", "000003")
    stamp = kept.stat().st_mtime_ns
    generate(again, "sotif", frames=4, weathers=["ClearNoon", "HardRainNight"], seed=3, workers=1, progress=False)
    assert kept.stat().st_mtime_ns == stamp and lost.exists()
    assert json.loads((again / "meta" / "dataset.json").read_text())["files"] == a


def test_training_scenes_with_another_sensor(tmp_path):
    vlp16 = LidarSpec(name="VLP-16-like", elevations_deg=tuple(np.linspace(15.0, -15.0, 16)), azimuth_step_deg=0.2,
                      max_range=100.0)
    out = generate(tmp_path / "t", "train", frames=2, seed=1, progress=False, lidar_spec=vlp16)
    assert json.loads((out / "meta" / "dataset.json").read_text())["sensors"]["lidar"]["name"] == "VLP-16-like"
    pts = kitti.read_points(kitti.frame_path(out, "velodyne", "000000"))
    elevation = np.rad2deg(np.arctan2(pts[:, 2], np.linalg.norm(pts[:, :2], axis=1)))
    assert np.abs(elevation[:, None] - np.linspace(15.0, -15.0, 16)[None]).min(1).max() < 0.5
    assert np.linalg.norm(pts[:, :3], axis=1).max() <= 100.0
    meta = kitti.read_frames_meta(out / "meta" / "frames.csv")
    assert set(meta["weather"]) <= {"ClearNoon", "CloudyNoon"} and set(meta["scenario"]) == {"train"}
    assert meta["lane_change_time_s"].isna().all() and (meta["slow_car_label_index"] == -1).all()
    assert kitti.read_image_set(out / "ImageSets" / "test.txt") == []


def test_fewer_frames_forced_into_the_same_folder_remove_the_extra_ones(tmp_path):
    """Frames an earlier, longer generation made go (their files and records); files of no record stay."""
    spec = LidarSpec(name="VLP-16-like", elevations_deg=tuple(np.linspace(15.0, -15.0, 16)), azimuth_step_deg=0.4)
    out = generate(tmp_path / "t", "train", frames=3, seed=1, progress=False, lidar_spec=spec)
    mine = out / "training" / "velodyne" / "000007.bin"
    mine.write_bytes(b"\0" * 16)
    generate(out, "train", frames=2, seed=1, progress=False, lidar_spec=spec, force=True)
    for kind in ("velodyne", "image_2", "calib", "label_2"):
        assert sorted(p.stem for p in (out / "training" / kind).iterdir()) == ["000000", "000001"] + (
            ["000007"] if kind == "velodyne" else [])
    assert sorted(p.stem for p in (out / "meta" / "frames").iterdir()) == ["000000", "000001"]
    assert mine.read_bytes() == b"\0" * 16
    files = json.loads((out / "meta" / "dataset.json").read_text())["files"]
    assert not any("000002" in f for f in files)


SMALL = LidarSpec(name="VLP-16-like", elevations_deg=tuple(np.linspace(15.0, -15.0, 16)), azimuth_step_deg=0.4)


def _snapshot(root):
    """Every path under ``root`` with its bytes (a link: its target), to compare before and after."""
    return {str(p.relative_to(root)): os.readlink(p) if p.is_symlink() else p.read_bytes() if p.is_file() else None
            for p in root.rglob("*")}


def test_a_data_set_of_another_configuration_is_refused_unless_forced(tmp_path):
    out = generate(tmp_path / "t", "train", frames=2, seed=1, progress=False, lidar_spec=SMALL)
    before = _snapshot(out)
    for change, named in (({"seed": 2}, "seed 1 (asked 2)"), ({"frames": 1}, "frames 2 (asked 1)"),
                          ({"preset": "sotif", "weathers": ["ClearNoon"]}, "preset train (asked sotif)")):
        with pytest.raises(ValueError, match=rf"{out}: holds a data set simulated with another configuration "
                                             rf"\(.*{re.escape(named)}.*--force"):
            generate(out, **{"preset": "train", "frames": 2, "seed": 1, "progress": False, "lidar_spec": SMALL,
                             **change})
        assert _snapshot(out) == before
    (out / "meta" / "dataset.json").unlink()  # a partial data set: its frame records name the configuration
    with pytest.raises(ValueError, match="another configuration"):
        generate(out, "train", frames=2, seed=2, progress=False, lidar_spec=SMALL)
    generate(out, "train", frames=1, seed=2, progress=False, lidar_spec=SMALL, force=True)
    data = json.loads((out / "meta" / "dataset.json").read_text())
    assert data["seed"] == 2 and data["n_frames"] == 1
    assert sorted(p.name for p in (out / "training" / "velodyne").iterdir()) == ["000000.bin"]


def test_the_same_configuration_resumes_a_partial_data_set_and_keeps_a_whole_one(tmp_path):
    out = generate(tmp_path / "t", "train", frames=2, seed=1, progress=False, lidar_spec=SMALL)
    whole = _snapshot(out)
    generate(out, "train", frames=2, seed=1, progress=False, lidar_spec=SMALL)
    assert _snapshot(out) == whole
    (out / "meta" / "dataset.json").unlink()  # cut short after its first frame
    (out / "meta" / "frames" / "000001.json").unlink()
    kitti.frame_path(out, "velodyne", "000001").unlink()
    generate(out, "train", frames=2, seed=1, progress=False, lidar_spec=SMALL)
    assert _snapshot(out) == whole


def test_a_generation_cut_short_before_its_first_frame_record_resumes(tmp_path):
    cfg = GenerateConfig("train", 2, ("ClearNoon",), 1, SMALL)
    (tmp_path / "meta" / "frames").mkdir(parents=True)
    (tmp_path / "meta" / "frames" / ".000000.json.abcd1234.tmp").write_bytes(b"{")
    kitti.frame_path(tmp_path, "velodyne", "000000").parent.mkdir(parents=True)
    kitti.frame_path(tmp_path, "velodyne", "000000").write_bytes(b"\0" * 16)
    kitti.frame_path(tmp_path, "velodyne", "000001").with_name(".000001.bin.abcd1234.tmp").write_bytes(b"")
    check_output(tmp_path, cfg, {"000000", "000001"})
    check_output(tmp_path / "new", cfg, {"000000", "000001"})


@pytest.mark.parametrize("files, named", [
    ({"notes.txt": b"mine"}, "notes.txt"),
    ({"ImageSets/train.txt": b"000000\n", "training/velodyne/000000.bin": b"\0" * 16,
      "training/velodyne/000005.bin": b"\0" * 16}, "ImageSets"),  # a KITTI folder of another source
    ({"training/velodyne/000005.bin": b"\0" * 16}, "training/velodyne/000005.bin"),
    ({"meta/frames.csv": b"frame_id\n"}, "meta/frames.csv")])
def test_a_folder_of_other_files_is_refused_and_left_as_it_is(tmp_path, files, named):
    for rel, data in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(data)
    before = _snapshot(tmp_path)
    with pytest.raises(ValueError, match=rf"{tmp_path}: is not empty and holds no data set of this configuration "
                                         rf"\(it has {re.escape(named)}\).*--force"):
        generate(tmp_path, "train", frames=2, seed=1, progress=False, lidar_spec=SMALL)
    assert _snapshot(tmp_path) == before


def test_frame_counts():
    from simulator.dataset import default_frames, max_frames

    assert default_frames("sotif", 21) == 547 and default_frames("sotif", 2) == 52
    assert max_frames("sotif", 21) == 547 and default_frames("train", 6) == 400 and max_frames("train", 1) > 1e9


def test_split_plans():
    cfg = GenerateConfig("sotif", 547, tuple(WEATHER_PRESETS), 0, LidarSpec())
    jobs = plan_jobs(cfg)
    splits = [j.split for j in jobs]
    assert splits.count("test") == 492 and splits.count("val") == 55
    per = np.unique([j.weather for j in jobs], return_counts=True)[1]
    assert per.min() == 26 and per.max() == 27 and len(per) == 21
    assert [j.step for j in jobs if j.weather == "ClearNoon"] == list(range(27))
    capped = plan_jobs(GenerateConfig("sotif", 42, tuple(WEATHER_PRESETS), 0, LidarSpec()))
    assert [j.step for j in capped if j.weather == "HardRainNight"] == [0, 25]
    train = plan_jobs(GenerateConfig("train", 400, ("ClearNoon", "ClearNight"), 0, LidarSpec()))
    assert [j.split for j in train].count("val") == 60 and len(train) == 400


@pytest.mark.parametrize("kwargs, message", [
    ({"preset": "city"}, "preset"), ({"weathers": ["Sunny"]}, "Sunny"), ({"lidar_model": "ouster"}, "lidar model"),
    ({"frames": 0}, "frames"), ({"workers": 0}, "workers"), ({"seed": -1}, "seed")])
def test_invalid_arguments(tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=message):
        generate(tmp_path / "x", **{"progress": False, **kwargs})


def test_ply_export_and_preview(sotif_set, tmp_path):
    from simulator.export import export_ply, preview

    ply = export_ply(sotif_set, "000001", tmp_path / "f.ply").read_text().splitlines()
    meta = kitti.read_frames_meta(sotif_set / "meta" / "frames.csv")
    n_labels = len(kitti.read_labels(kitti.frame_path(sotif_set, "label_2", "000001")))
    assert f"element vertex {meta['n_points'][1] + 8 * n_labels}" in ply
    assert len(ply) == ply.index("end_header") + 1 + meta["n_points"][1] + 8 * n_labels + 12 * n_labels
    assert preview(sotif_set, "000001", tmp_path / "p.png").stat().st_size > 10000


def test_carla_mode_scans_do_not_depend_on_weather(tmp_path):
    out = generate(tmp_path / "c", "sotif", frames=2, weathers=["ClearNoon", "HardRainNight"], seed=2,
                   lidar_model="carla", progress=False)
    a, b = (kitti.frame_path(out, "velodyne", f).read_bytes() for f in ("000000", "000001"))
    assert a == b and len(a) > 0
    assert kitti.frame_path(out, "image_2", "000000").read_bytes() != kitti.frame_path(out, "image_2", "000001").read_bytes()


def test_a_resumed_simulation_removes_the_temp_files_a_kill_left(tmp_path):
    from harness.core.files import folder_lock
    from simulator.dataset import generate
    out = generate(tmp_path / "d", preset="train", frames=2, seed=3, progress=False)
    scan = out / "training" / "velodyne" / "000001.bin"
    stale = scan.parent / ".000001.bin.7eif5tqt.tmp"  # a write cut off by Ctrl-C
    stale.write_bytes(scan.read_bytes()[:100])
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p != stale}
    generate(out, preset="train", frames=2, seed=3, progress=False)
    assert not stale.exists()
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    with folder_lock(out, "simulate"):  # another simulate is writing there
        with pytest.raises(ValueError, match=r"d: another sotif-bench simulate is writing to this folder"):
            generate(out, preset="train", frames=2, seed=3, progress=False)


def test_workers_are_spawned_from_a_process_running_other_threads(monkeypatch):
    """A worker forked beside other threads can inherit a held lock and hang (the boundary searches' simulation
    in a run did); only a process with no other thread and no torch or onnxruntime forks them."""
    import sys

    from simulator import dataset
    monkeypatch.setattr(dataset.threading, "active_count", lambda: 1)
    for name in ("torch", "onnxruntime"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    assert dataset.start_method() == "fork"
    monkeypatch.setattr(dataset.threading, "active_count", lambda: 2)
    assert dataset.start_method() == "spawn"
    monkeypatch.setattr(dataset.threading, "active_count", lambda: 1)
    monkeypatch.setitem(sys.modules, "onnxruntime", object())
    assert dataset.start_method() == "spawn"
